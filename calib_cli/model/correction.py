"""Invert a sensor model: from outputs back to physical inputs.

The inverse is numerical, through ``ImuModel.predict`` itself, so the
correction can never disagree with the forward model: x <- x + T^-1 (y -
predict(x)), with T the transfer matrix (exact in one step for the linear
bias + K model, a few steps with small nonlinear terms).
"""

from __future__ import annotations

import numpy as np

from calib_cli.model.effects import INPUT
from calib_cli.model.imu_model import ImuModel
from calib_cli.model.kinematics import Kinematics


def _transfer(model: ImuModel, params: dict, sensor: str) -> np.ndarray:
    key = f"{sensor}_K"
    if key in params:
        return np.asarray(params[key], dtype=float)
    return np.eye(3)


def correct(model: ImuModel, params: dict, sensor: str, y: np.ndarray,
            other: np.ndarray | None = None, iterations: int = 4,
            temp: np.ndarray | None = None) -> np.ndarray:
    """Physical input (N, 3) that makes the model output ``y`` (N, 3), triad.

    sensor "accel": returns specific force; "gyro": angular rate, with
    ``other`` the corrected specific force (for g-sensitivity; zero if None).
    Rate-dependent input effects (lever arms) are not inverted here: the
    result is at the triad's reference point, as the contract's correction.
    temp: (N,) degC for temperature-dependent effects (None: none apply).
    """
    y = np.asarray(y, dtype=float)
    n = len(y)
    # the rate-dependent input effects add nothing at the zero rates evaluated here
    model = ImuModel(tuple(e for e in model.effects if e.stage != INPUT), model.layout)
    T = _transfer(model, params, sensor)
    Tinv = np.linalg.inv(T)
    zeros = np.zeros((n, 3))
    x = (y - np.asarray(params.get(f"{sensor}_bias", 0.0))) @ Tinv.T
    for _ in range(iterations + (4 if temp is not None else 0)):
        if sensor == "accel":
            kin = Kinematics(np.zeros(n), x, zeros, zeros, temp=temp)
        else:
            kin = Kinematics(np.zeros(n), zeros if other is None else other, x, zeros, temp=temp)
        pred = model.predict(params, kin, sensors=(sensor,))[sensor]
        step = (y - pred) @ Tinv.T
        x = x + step
        if np.max(np.abs(step)) <= 1e-13 * (np.max(np.abs(x)) + 1e-300):
            break
    return x
