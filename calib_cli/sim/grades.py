"""Default truth units by grade for the simulator: the navigation-grade unit that
``calib simulate`` uses for plans of kind align (docs/align.md). The MEMS default
is ``model.truth.default_truth``; the table default ``sim.turntable_plans.turntable_truth``."""

from __future__ import annotations

import numpy as np

from calib_cli.model.effects import Bias, Layout, ScaleMisalignment
from calib_cli.model.imu_model import ImuModel
from calib_cli.model.truth import Truth
from calib_cli.units import G0, SUFFIXES

UG = G0 * 1e-6
DPH = SUFFIXES["_dph"]
K_PRIOR = 30e-6  # 1-sigma of each gyro K entry (scale factor ppm, misalignment rad)
ACCEL_NOISE = 20.0 * UG  # m/s^2/sqrt(Hz)
ARW = 0.002 * SUFFIXES["_dpsqrth"]  # rad/sqrt(s)


def nav_truth(rng: np.random.Generator, k_prior: float = K_PRIOR,
              accel_noise: float = ACCEL_NOISE, arw: float = ARW) -> Truth:
    """A navigation-grade unit: accel bias 50-200 micro-g, gyro bias 0.01-0.05
    deg/h (random signs), gyro K = I + N(0, k_prior^2) per entry."""
    sign = rng.choice([-1.0, 1.0], size=(2, 3))
    ab = sign[0] * rng.uniform(50, 200, 3) * UG
    gb = sign[1] * rng.uniform(0.01, 0.05, 3) * DPH
    K = np.eye(3) + rng.standard_normal((3, 3)) * k_prior
    model = ImuModel((Bias("accel"), Bias("gyro"), ScaleMisalignment("gyro")), Layout())
    return Truth(model, {"accel_bias": ab, "gyro_bias": gb, "gyro_K": K},
                 {"accel_white_density": np.full(3, accel_noise),
                  "gyro_white_density": np.full(3, arw)})
