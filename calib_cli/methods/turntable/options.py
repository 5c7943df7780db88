"""The rotating-table fit's options and prior widths (docs/turntable.md)."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class TurntableOptions:
    """lever_arm: "off" (no lever-arm terms), "known" (each cycle's plan ``lever_arm_m``),
    "estimate". proof_mass: "auto" (estimated; entries the record cannot determine are
    reported with sigma null and listed in stats.unobservable), "estimate" (the same),
    "off" (held at 0, reported with sigma null). tangential: include dw/dt x r. block_s:
    measurement block (s). passes: the most Gauss-Newton passes over the whole record
    after the start (exit 4 naming what still moves when they do not converge);
    converge_sigma: converged when a pass moves no parameter by more than this many of its
    sigma. axis_sigma: how well the table axis stays fixed (rad, 1-sigma per block; None:
    estimated). runout_sigma: prior of the bearing's twice-per-revolution rocking (rad; 0:
    not modelled). table_tilt_sigma: prior of each table axis's tilt from the plan (rad).
    mount_sigma: how well a cycle's mounting (the table axis in body axes) is known where
    the plan gives no ``attitude_sigma_deg`` (rad; a default, not information: what it
    alone holds is reported unobservable). effects: further catalogue effects fitted
    (``calib fit turntable --with``), [(name, sensor)]. noise: {"accel": (3,), "gyro":
    (3,)} per-sample sigma (else estimated from the data). table_encoder: the table's
    channels used ("auto": those the log has that pass the checks; "angle", "rate",
    "both", "off"). The channel priors: the rate channel's scale error and offset, the
    angle encoder's once-per-revolution error and scale (an encoder's counts per
    revolution are exact: a channel whose angle is off in scale fails its checks).
    grade / priors: the prior widths (GRADES)."""

    lever_arm: str = "estimate"
    proof_mass: str = "auto"
    g_sensitivity: bool = True  # the gyros' D (off: reported 0, sigma 0; diagnose's base)
    base_structure: str = "full"  # "diagonal": K and G diagonal (diagnose --base diagonal)
    tangential: bool = True
    block_s: float = 0.2
    passes: int = 8
    converge_sigma: float = 0.1
    runout_sigma: float = 5e-4
    axis_sigma: float | None = None
    table_tilt_sigma: float = float(np.radians(0.05))
    mount_sigma: float = float(np.radians(3.0))
    accel_skip: float = 0.02  # rad/s^2: with tangential off, blocks accelerating faster are skipped
    history_every: float = 2.0
    effects: tuple = ()
    noise: dict | None = None
    table_encoder: str = "auto"
    rate_scale_sigma: float = 0.01
    rate_bias_sigma: float = float(np.radians(0.1))
    encoder_sigma: float | None = None
    encoder_opr_sigma: float = 2e-3
    encoder_scale_sigma: float = 1e-5
    grade: str = "mems"
    priors: dict | None = None


# A-priori 1-sigma of each parameter group (SI) per grade of unit: weakly informative
# around a neutral unit. "mems" are about ten times the catalogue's typical MEMS sizes;
# "navigation" is the rough-stand paper's setting (gyro drift 0.1 deg/h, accelerometer
# bias 6e-4 g, lever arms 0.1 m, proof-mass offsets 0.02 m).
GRADES = {
    "mems": {"accel_bias": 1.0, "accel_K": 0.05, "gyro_bias": 0.05, "gyro_K": 0.05,
             "gyro_D": 2e-3, "lever_arm": 0.5, "proof_mass_offsets": 0.05},
    "tactical": {"accel_bias": 0.02, "accel_K": 5e-3, "gyro_bias": float(np.radians(10 / 3600)),
                 "gyro_K": 5e-3, "gyro_D": 2e-4, "lever_arm": 0.2, "proof_mass_offsets": 0.02},
    "navigation": {"accel_bias": 6e-4 * 9.80665, "accel_K": 1e-3,
                   "gyro_bias": float(np.radians(0.1 / 3600)), "gyro_K": 1e-3, "gyro_D": 2e-5,
                   "lever_arm": 0.1, "proof_mass_offsets": 0.02},
}
PRIOR_KEYS = tuple(GRADES["mems"])
ENCODER_MODES = ("auto", "angle", "rate", "both", "off")
