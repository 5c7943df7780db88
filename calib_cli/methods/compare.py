"""Compare two calibrations of one unit (e.g. two dates): parameter
differences in units of their combined sigma. Pure."""

from __future__ import annotations

import numpy as np

from calib_cli.data import CalibrationResult
from calib_cli.errors import InputError


def compare(a: CalibrationResult, b: CalibrationResult, path_b: str = "<B>") -> dict:
    """diff = B - A, sigma = sqrt(sA^2 + sB^2) (the two fits are independent),
    z = diff / sigma per entry. Entries fixed in both (sigma 0) get z 0 when
    equal; an unobservable entry (sigma NaN) gets z NaN. Keys with different
    units raise InputError; keys with different shapes or present in one
    file only are listed, not compared."""
    out = {"params": {}, "sigma": {}, "z": {}, "units": {}, "a": {}, "b": {},
           "only_in_a": sorted(set(a.params) - set(b.params)),
           "only_in_b": sorted(set(b.params) - set(a.params)), "incomparable": []}
    worst, worst_z = None, 0.0
    for k in a.params:
        if k not in b.params:
            continue
        ua, ub = a.units.get(k, ""), b.units.get(k, "")
        if ua != ub:
            raise InputError(f"{k} is in {ub!r} here but in {ua!r} in the first file: "
                             "a comparison needs the same units", path_b)
        va, vb = np.asarray(a.params[k], float), np.asarray(b.params[k], float)
        if va.shape != vb.shape:
            out["incomparable"].append(k)
            continue
        sa = np.asarray(a.sigma.get(k, np.full(va.shape, np.nan)), float)
        sb = np.asarray(b.sigma.get(k, np.full(vb.shape, np.nan)), float)
        d = vb - va
        s = np.sqrt(sa**2 + sb**2)
        with np.errstate(divide="ignore", invalid="ignore"):
            z = np.where(s > 0, d / s, np.where(d == 0, 0.0, np.inf))
        z = np.where(np.isnan(s), np.nan, z)
        out["params"][k], out["sigma"][k], out["z"][k] = d, s, z
        out["units"][k], out["a"][k], out["b"][k] = ua, va, vb
        if np.any(np.isfinite(np.abs(z)) | np.isinf(z)):
            zz = np.where(np.isnan(z), -1.0, np.abs(z))
            i = int(np.argmax(zz))
            if zz.flat[i] > worst_z or worst is None:
                idx = np.unravel_index(i, z.shape) if z.ndim else ()
                worst = f"{k}[{','.join(map(str, idx))}]" if z.ndim else k
                worst_z = float(zz.flat[i])
    out["max_abs_z"] = worst_z if worst is not None else None
    out["worst"] = worst
    return out
