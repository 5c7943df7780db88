"""Apply a calibration to sensor outputs (pure; the CLI feeds it chunks)."""

from __future__ import annotations

import numpy as np

from calib_cli.data import CalibrationResult
from calib_cli.errors import InputError
from calib_cli.model.correction import correct
from calib_cli.model.imu_model import ImuModel
from calib_cli.sim.truth import effect_from_description


def model_of(cal: CalibrationResult) -> ImuModel:
    return ImuModel(tuple(effect_from_description(d) for d in cal.model), cal.layout)


def check_units(cal: CalibrationResult, rec_units: dict, path: str) -> None:
    """Refuse data in other units than the calibration was fitted on."""
    for sensor in ("accel", "gyro"):
        if f"{sensor}_bias" in cal.params or f"{sensor}_K" in cal.params:
            want, got = cal.raw_units.get(sensor), rec_units.get(sensor)
            if want and got and want != got:
                raise InputError(f"{sensor} data is in {got!r} but the calibration was fitted "
                                 f"on {want!r}", path)


def corrected_channels(cal: CalibrationResult) -> list[str]:
    return [s for s in ("accel", "gyro") if f"{s}_K" in cal.params or f"{s}_bias" in cal.params]


def apply_triad(cal: CalibrationResult, accel: np.ndarray, gyro: np.ndarray | None,
                accel_si: bool = True):
    """Corrected (accel, gyro) for a chunk: f = K^-1 (A - b), w = G^-1 (W - d - D f).
    Channels the calibration does not cover pass through unchanged. For a
    gyro-only calibration with g-sensitivity, f is the raw accelerometer
    output when that is in SI (``accel_si``), else zero."""
    model = model_of(cal)
    params = {k: np.asarray(v, dtype=float) for k, v in cal.params.items()}
    chans = corrected_channels(cal)
    f = correct(model, params, "accel", accel) if "accel" in chans else accel
    w = gyro
    if gyro is not None and "gyro" in chans:
        other = f if "accel" in chans else (accel if accel_si else None)
        w = correct(model, params, "gyro", gyro, other=other)
    return f, w
