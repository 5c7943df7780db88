"""Turn a least-squares fit into a CalibrationResult with contract keys."""

from __future__ import annotations

import numpy as np

from calib_cli.data import CalibrationResult
from calib_cli.methods.lsq import LsqFit
from calib_cli.model.imu_model import ImuModel, Packing
from calib_cli.model.truth import describe_effect

_COUNT_UNITS = {
    "accel_bias": "count", "accel_K": "count/(m/s^2)",
    "gyro_bias": "count", "gyro_K": "count/(rad/s)", "gyro_D": "count/(m/s^2)",
}


def param_units(model: ImuModel, raw_units: dict) -> dict[str, str]:
    """Unit of every parameter key: SI, or counts-based when the data was in counts."""
    out = {}
    for s in model.specs():
        sensor = s.key.split("_")[0]
        if raw_units.get(sensor) == "count" and s.key in _COUNT_UNITS:
            out[s.key] = _COUNT_UNITS[s.key]
        else:
            out[s.key] = s.unit
    return out


def entry_name(key: str, shape: tuple, flat: int) -> str:
    if not shape:
        return key
    idx = np.unravel_index(flat, shape)
    return f"{key}[{','.join(str(int(i)) for i in idx)}]"


def build_result(method: str, model: ImuModel, packing: Packing, fit: LsqFit, base: dict,
                 raw_units: dict, stats: dict, serial=None, residuals=None, tables=None,
                 keys=None, extra_unobservable=()) -> CalibrationResult:
    """Params, sigma (0 fixed by convention, NaN unobservable), covariance in
    contract order, and stats.unobservable naming each entry the data cannot fix."""
    params = packing.unpack(fit.theta, base)
    sig = packing.sigma_arrays(np.diag(fit.cov))
    keys = keys or [s.key for s in packing.specs]
    labels = packing.labels()
    unobs = [entry_name(k, model.spec(k).shape, i) for (k, i), u in zip(labels, fit.unobservable)
             if u] + list(extra_unobservable)
    st = dict(stats)
    st["unobservable"] = unobs
    units = param_units(model, raw_units)
    return CalibrationResult(
        method=method,
        params={k: np.asarray(params[k]) for k in keys},
        sigma={k: sig[k] for k in keys},
        units={k: units[k] for k in keys},
        covariance=fit.cov, cov_order=labels, stats=st,
        residuals=residuals or {}, tables=tables or {},
        model=[describe_effect(e) for e in model.effects],
        raw_units=dict(raw_units), layout=model.layout, serial=serial)
