"""Sample inputs shared by the issue-9 tests (report, export, show A B)."""

from __future__ import annotations

import numpy as np

from calib_cli.data import CalibrationResult
from calib_cli.model.effects import Bias, GSensitivity, ScaleMisalignment
from calib_cli.model.imu_model import ImuModel
from calib_cli.model.truth import describe_effect

PLAN = """
name = "six"
kind = "static"
sample_rate_hz = 50.0
[site]
latitude_deg = 50.45
[unit]
serial = "SN-42"
""" + "".join(f"""
[[segment]]
label = "{lab}"
attitude_deg = {att}
duration_s = 4
""" for lab, att in [("z-up", [0, 0, 0]), ("z-down", [180, 0, 0]), ("x-up", [0, -90, 0]),
                     ("x-down", [0, 90, 0]), ("y-up", [90, 0, 0]), ("y-down", [-90, 0, 0])])


def triad_calibration(seed=0) -> CalibrationResult:
    """A full triad calibration (accel b, K; gyro d, G, D) with awkward numbers."""
    rng = np.random.default_rng(seed)
    effects = (Bias("accel"), ScaleMisalignment("accel", "full"), Bias("gyro"),
               ScaleMisalignment("gyro", "full"), GSensitivity("gyro"))
    params = {"accel_bias": rng.normal(0, 0.05, 3),
              "accel_K": np.eye(3) + rng.normal(0, 3e-3, (3, 3)),
              "gyro_bias": rng.normal(0, 1e-3, 3),
              "gyro_K": np.eye(3) + rng.normal(0, 3e-3, (3, 3)),
              "gyro_D": rng.normal(0, 1e-4, (3, 3))}
    sigma = {k: np.full(np.shape(v), 1e-6) for k, v in params.items()}
    units = {"accel_bias": "m/s^2", "accel_K": "-", "gyro_bias": "rad/s", "gyro_K": "-",
             "gyro_D": "(rad/s)/(m/s^2)"}
    model = ImuModel(effects)
    return CalibrationResult(method="vector", params=params, sigma=sigma, units=units,
                             covariance=np.eye(1), cov_order=[("accel_bias", 0)],
                             stats={"unobservable": []},
                             model=[describe_effect(e) for e in model.effects], serial="SN-42")
