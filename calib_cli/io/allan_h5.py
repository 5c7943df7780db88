"""The "allan" HDF5 kind (format version 1; docs/allan.md).

    / (attrs)            provenance (io.h5.write_provenance) + source_kind,
                         segment, start, stop, tau0, n_samples, stride_div,
                         confidence
    /channels            (n_ch,) str   e.g. accel_x ... gyro_z
    /units               (n_ch,) str   unit of each channel (m/s^2, rad/s, count)
    /curve/tau           (n_tau,) s, octave spaced
    /curve/adev          (n_tau, n_ch) overlapping Allan deviation
    /curve/adev_lo, adev_hi   (n_tau, n_ch) confidence interval
    /curve/clusters      (n_tau,) independent clusters
    /terms/<name>/value, lo, hi, tau, clusters   (n_ch,) for name in
                         random_walk, bias_instability, rate_random_walk
    /averaging/target, time, tau_min, min_time   (n_ch,)  (min_time: from the
                         quantisation term; absent in files of older versions)
"""

from __future__ import annotations

import h5py
import numpy as np

from calib_cli.errors import InputError
from calib_cli.io.h5 import attr_str, open_checked, write_provenance
from calib_cli.io.h5file import h5_output, put
from calib_cli.methods.allan import CONFIDENCE, TERM_NAMES, AllanResult

_STR = h5py.string_dtype()


def write_allan(path, res: AllanResult, inputs=(), serial=None) -> None:
    with h5_output(path) as h5:
        meta = {k: v for k, v in res.meta.items() if v is not None and k != "serial"}
        write_provenance(h5, "allan", inputs, serial,
                         {**meta, "tau0": res.tau0, "n_samples": res.n_samples,
                          "stride_div": res.stride_div, "confidence": CONFIDENCE})
        put(h5, "channels", list(res.channels), dtype=_STR)
        put(h5, "units", list(res.units), dtype=_STR)
        c = h5.create_group("curve")
        for k in ("tau", "adev", "adev_lo", "adev_hi"):
            put(c, k, np.asarray(getattr(res, k)))
        put(c, "clusters", np.asarray(res.clusters, dtype=np.int64))
        t = h5.create_group("terms")
        for name, d in res.terms.items():
            g = t.create_group(name)
            for k, v in d.items():
                put(g, k, np.asarray(v))
        a = h5.create_group("averaging")
        put(a, "target", np.asarray(res.target))
        put(a, "time", np.asarray(res.averaging_time))
        put(a, "tau_min", np.asarray(res.tau_min))
        put(a, "min_time", np.asarray(res.min_avg()))


def _strs(d):
    return [x.decode() if isinstance(x, bytes) else str(x) for x in d[()]]


def read_allan(path) -> AllanResult:
    p = str(path)
    with open_checked(p, "allan") as h5:
        try:
            c, t, a = h5["curve"], h5["terms"], h5["averaging"]
            terms = {name: {k: t[name][k][()] for k in t[name]} for name in TERM_NAMES
                     if name in t}
            meta = {k: (attr_str(h5, k)) for k in ("source_kind", "segment")
                    if k in h5.attrs}
            for k in ("start", "stop"):
                if k in h5.attrs:
                    meta[k] = int(h5.attrs[k])
            return AllanResult(
                channels=_strs(h5["channels"]), units=_strs(h5["units"]),
                tau0=float(h5.attrs["tau0"]), n_samples=int(h5.attrs["n_samples"]),
                tau=c["tau"][()], adev=c["adev"][()], clusters=c["clusters"][()],
                adev_lo=c["adev_lo"][()], adev_hi=c["adev_hi"][()], terms=terms,
                tau_min=a["tau_min"][()], averaging_time=a["time"][()], target=a["target"][()],
                stride_div=int(h5.attrs.get("stride_div", 16)), meta=meta,
                min_averaging_time=a["min_time"][()] if "min_time" in a else None)
        except (KeyError, ValueError, TypeError) as exc:
            raise InputError(f"malformed allan file: missing or bad field {exc}", p) from None
