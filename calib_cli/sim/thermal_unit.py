"""A random unit with temperature drift: the default truth of `calib emulate --chamber`
and of the thermal validation scenarios (calib_cli/validation/thermal_cases.py)."""

from __future__ import annotations

import numpy as np

from calib_cli.model.effects import ThermalLag, make_effect
from calib_cli.model.imu_model import ImuModel
from calib_cli.model.truth import Truth, default_truth


def thermal_truth(rng, order: int = 2, lag_tau: float | None = None,
                  bias_mg: float = 5.0, scale_ppm: float = 300.0, temp_ref: float = 25.0) -> Truth:
    """A random MEMS unit (bias, K for both sensors) with temperature drift:
    per axis, accel bias moving by about bias_mg over -40..85 degC (linear and
    quadratic parts), scale by about scale_ppm, gyro bias by ~ 50 deg/h."""
    from calib_cli.model.effects import Layout

    base = default_truth(Layout(), rng)
    g0 = 9.80665
    lo, hi = -40.0 - temp_ref, 85.0 - temp_ref
    span2 = max(lo * lo, hi * hi)

    def drift(total):
        c1 = rng.choice([-1, 1], 3) * rng.uniform(0.3, 0.6, 3) * total / (hi - lo)
        c2 = rng.choice([-1, 1], 3) * rng.uniform(0.3, 0.6, 3) * total / span2
        return np.column_stack([c1, c2])[:, :order]

    params = dict(base.params)
    params["accel_temp_bias"] = drift(bias_mg * 1e-3 * g0)
    params["accel_temp_scale"] = drift(scale_ppm * 1e-6)
    params["gyro_temp_bias"] = drift(50.0 / 3600 * np.pi / 180)
    params["gyro_temp_scale"] = np.zeros((3, order))
    if order == 1:
        for k in ("accel_temp_bias", "accel_temp_scale", "gyro_temp_bias", "gyro_temp_scale"):
            params[k] = params[k][:, 0]
    effects = base.model.effects + (
        make_effect("temperature_drift", "accel", order=order, temp_ref=temp_ref),
        make_effect("temperature_drift", "gyro", order=order, temp_ref=temp_ref))
    if lag_tau:
        effects = effects + (ThermalLag(),)
        params["thermal_lag_tau"] = np.array(float(lag_tau))
    noise = {"accel_white": 1e-3, "gyro_white": 3e-4}  # per sample at 10 Hz
    return Truth(ImuModel(effects, base.model.layout), params, noise)
