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
from calib_cli.io.h5 import atomic_path, open_checked, write_calibration_groups, write_provenance

_STR = h5py.string_dtype()


def write_diagnosis(path, summary: dict, bins: dict, residuals: dict, noise_sigma: dict,
                    inputs=(), serial=None, calibration=None) -> None:
    """summary: the JSON-able dict; bins: time/segment/count arrays;
    residuals: {stage: {sensor: (M, n)}}; calibration: the final model's
    CalibrationResult (written in the calibration layout)."""
    with atomic_path(path) as tmp, h5py.File(tmp, "w") as h5:
        extra = {"method": summary["method"]}
        if calibration is not None:
            extra["raw_units"] = json.dumps(calibration.raw_units)
        write_provenance(h5, "diagnosis", inputs, serial, extra)
        if calibration is not None:
            write_calibration_groups(h5, calibration, residuals=False)
        h5.create_dataset("summary", data=json.dumps(summary), dtype=_STR)
        b = h5.create_group("bins")
        for k, v in bins.items():
            b[k] = np.asarray(v)
        r = h5.create_group("residuals")
        for stage, per in residuals.items():
            g = r.create_group(stage)
            for s, v in per.items():
                g[s] = np.asarray(v, float)
        n = h5.create_group("noise_sigma")
        for s, v in noise_sigma.items():
            n[s] = np.asarray(v, float)


def read_diagnosis(path) -> dict:
    """The summary JSON object of a diagnosis file."""
    p = str(path)
    with open_checked(p, "diagnosis") as h5:
        try:
            raw = h5["summary"][()]
        except KeyError:
            raise InputError("missing field /summary", p) from None
    try:
        return json.loads(raw.decode() if isinstance(raw, bytes) else str(raw))
    except json.JSONDecodeError as exc:
        raise InputError(f"/summary is not valid JSON ({exc})", p) from None


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
