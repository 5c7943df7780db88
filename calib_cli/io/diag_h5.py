"""The "diagnosis" HDF5 kind (format version 1; docs/diagnose.md).

    / (attrs)              provenance (io.h5.write_provenance) + method
    /summary               str: the JSON object of `calib diagnose --json`
    /bins/time             (M,) s, mean time of each bin
    /bins/segment          (M,) raw segment index
    /bins/count            (M,) samples per bin
    /residuals/<stage>/<sensor>   (M, n) bin residual, data - model, in noise
                           units; stage "initial" (base model), "step1", ...
    /noise_sigma/<sensor>  (n,) per-sample white-noise sigma (data units)
    /params, /sigma, /units, /covariance, /stats, /model, ...
                           the final model as a calibration, in the layout of a
                           calibration file (io.h5.write_calibration_groups):
                           every command that reads a calibration reads it
                           (its /residuals are the stages above)
"""

from __future__ import annotations

import json

import h5py
import numpy as np

from calib_cli.errors import InputError
from calib_cli.io.h5 import open_checked, write_calibration_groups, write_provenance
from calib_cli.io.h5file import h5_output, put

_STR = h5py.string_dtype()


def write_diagnosis(path, summary: dict, bins: dict, residuals: dict, noise_sigma: dict,
                    inputs=(), serial=None, calibration=None) -> None:
    """summary: the JSON-able dict; bins: time/segment/count arrays;
    residuals: {stage: {sensor: (M, n)}}; calibration: the final model's
    CalibrationResult (written in the calibration layout)."""
    with h5_output(path) as h5:
        extra = {"method": summary["method"]}
        if calibration is not None:
            extra["raw_units"] = json.dumps(calibration.raw_units)
        write_provenance(h5, "diagnosis", inputs, serial, extra)
        if calibration is not None:
            write_calibration_groups(h5, calibration, residuals=False)
        put(h5, "summary", [json.dumps(summary)], dtype=_STR)  # (1,): checksummed
        b = h5.create_group("bins")
        for k, v in bins.items():
            put(b, k, np.asarray(v))
        r = h5.create_group("residuals")
        for stage, per in residuals.items():
            g = r.create_group(stage)
            for s, v in per.items():
                put(g, s, np.asarray(v, float))
        n = h5.create_group("noise_sigma")
        for s, v in noise_sigma.items():
            put(n, s, np.asarray(v, float))


def read_diagnosis(path) -> dict:
    """The summary JSON object of a diagnosis file."""
    p = str(path)
    from calib_cli.io import validate

    with open_checked(p, "diagnosis") as h5:
        if "summary" not in h5:
            raise InputError("missing field /summary", p)
        ds = h5["summary"]
        if not isinstance(ds, h5py.Dataset):
            raise InputError("/summary is not a dataset", p)
        if ds.shape == ():  # written before issue 37: a scalar string
            raw = validate.decode(validate.load(ds, p), "/summary", p)
        else:  # (1,) fixed-length text, checksummed
            texts = validate.strings(ds, p)
            if len(texts) != 1:
                raise InputError(f"/summary holds {len(texts)} texts, expected 1", p)
            raw = texts[0]
    try:
        obj = json.loads(raw)
    except json.JSONDecodeError as exc:
        raise InputError(f"/summary is not valid JSON ({exc})", p) from None
    if not isinstance(obj, dict):
        raise InputError("/summary is not a JSON object", p)
    return obj


def read_diagnosis_arrays(path) -> dict:
    """{"bins": {time, segment, count}, "residuals": {stage: {name: (M, n)}}} of a
    diagnosis file: the residuals (noise units) of the base model ("initial") and
    after each step, for reports."""
    p = str(path)
    out: dict = {"bins": {}, "residuals": {}}
    with open_checked(p, "diagnosis") as h5:
        for k in ("time", "segment", "count"):
            if f"bins/{k}" in h5:
                out["bins"][k] = np.asarray(h5[f"bins/{k}"][()])
        if "residuals" in h5:
            for stage in h5["residuals"]:
                grp = h5["residuals"][stage]
                if isinstance(grp, h5py.Group):
                    out["residuals"][stage] = {n: np.asarray(grp[n][()], float) for n in grp
                                               if isinstance(grp[n], h5py.Dataset)}
    return out
