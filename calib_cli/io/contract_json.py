"""The contract's JSON objects (CONTRACT.md, JSON outputs): what ``calib show --json``
prints for a calibration and what the batch's export step writes."""

from __future__ import annotations

import math

import numpy as np


def to_jsonable(x):
    """numpy arrays -> nested lists, NaN/inf -> None (JSON null)."""
    if isinstance(x, dict):
        return {str(k): to_jsonable(v) for k, v in x.items()}
    if isinstance(x, (list, tuple)):
        return [to_jsonable(v) for v in x]
    if isinstance(x, np.ndarray):
        return to_jsonable(x.tolist())
    if isinstance(x, (np.floating, float)):
        v = float(x)
        return None if not math.isfinite(v) else v
    if isinstance(x, np.integer):
        return int(x)
    if isinstance(x, np.bool_):
        return bool(x)
    return x


def calibration_json(path, covariance: bool = False) -> dict:
    """The contract's JSON object for a calibration file."""
    from calib_cli.io.h5 import read_calibration  # h5py only when a file is read

    c = read_calibration(path)
    obj = {"method": c.method, "unit": {"serial": c.serial},
           "params": c.params, "sigma": c.sigma, "units": c.units, "stats": c.stats}
    if covariance:
        obj["covariance"] = {"order": [[k, i] for k, i in c.cov_order],
                             "matrix": c.covariance}
    return obj
