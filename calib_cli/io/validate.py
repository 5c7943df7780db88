"""Validation of HDF5 content before use (issue 15; docs/file-formats.md).

One place for the checks every reader makes; the readers in io/h5.py (and
the chunked readers of apply and allan) call these. Every failure is an
InputError (exit 3) naming the file and the dataset.

Policy:

- format version: an integer attribute 1..FORMAT_VERSION (a string such as
  "abc" or a future version is refused, with the version this calib reads).
- declared sizes: a dataset whose declared size (shape x item size) is far
  beyond what the file can hold (uncompressed: more than twice the file size
  plus 1 MiB; compressed: 1000 times) is refused before anything is read or
  allocated.
- raw/corrected recordings: ``samples/time`` one-dimensional, finite and
  increasing (never going back; repeated values are allowed because a
  host-clock recorder stamps a batch of frames with one time);
  ``accel``/``gyro`` two-dimensional with one row per time and all values
  finite (every command: a NaN would silently spread into every estimate);
  ``temp``/``table_angle``/``table_rate`` one value per time, NaN allowed
  there (not measured) but not +-inf; the segment arrays all of one length,
  start <= stop within the samples.
- calibrations: a non-empty ``params`` group, finite values, the shapes of the
  method's model (3 / 3x3 for a triad, n for a redundant unit), every K
  invertible (condition number below 1e10), a square covariance matrix.
- a dataset whose Fletcher-32 checksum fails (files written since this
  check) is "damaged data" naming the dataset; files written before carry no
  checksum and are still read.
"""

from __future__ import annotations

import os

import h5py
import numpy as np

from calib_cli.errors import DamagedInput, InputError

_SLACK = 1 << 20
MAX_COND = 1e10


def format_version(h5: h5py.File, path: str, current: int) -> int:
    ver = h5.attrs.get("format_version")
    try:
        if isinstance(ver, bytes):
            ver = ver.decode()
        if isinstance(ver, np.ndarray):
            ver = ver.item() if ver.size == 1 else None
        v = int(ver)
        if isinstance(ver, (float, np.floating)) and v != ver:
            raise ValueError
    except (TypeError, ValueError, OverflowError):
        raise InputError(f"format version {ver!r} is not a number (this calib reads version "
                         f"1 to {current})", path) from None
    if v < 1 or v > current:
        hint = " (written by a newer calib: update calib)" if v > current else ""
        raise InputError(f"unsupported format version {v} (this calib reads version 1 to "
                         f"{current}){hint}", path)
    return v


def check_declared_sizes(h5: h5py.File, path: str) -> None:
    """Refuse a file whose datasets declare far more data than it can hold."""
    try:
        size = os.path.getsize(path)
    except OSError:
        return
    bad = []

    def visit(name, obj):
        if bad or not isinstance(obj, h5py.Dataset):
            return
        try:
            shape = obj.shape
            if shape is None:
                return
            n = int(np.prod(shape, dtype=float)) if shape else 1
            nbytes = float(n) * obj.dtype.itemsize
            limit = (1000.0 if obj.compression else 2.0) * size + _SLACK
        except Exception:  # an unreadable header: the read will say so
            return
        if nbytes > limit:
            bad.append((name, shape, nbytes))

    try:
        h5.visititems(visit)
    except (RuntimeError, OSError, KeyError, ValueError):
        raise DamagedInput("damaged HDF5 structure", path) from None
    if bad:
        name, shape, nbytes = bad[0]
        raise InputError(f"dataset /{name} declares {shape} ({nbytes / 1e9:.3g} GB), far more "
                         f"than the file's {size} bytes can hold: damaged or forged file",
                         path)


def load(ds, path: str) -> np.ndarray:
    """Read a whole dataset; a failed checksum or a damaged chunk is exit 3."""
    try:
        return ds[()]
    except OSError as exc:
        msg = str(exc).lower()
        what = ("checksum mismatch (Fletcher-32): the file was altered or damaged"
                if "letcher" in msg or "checksum" in msg or "filter" in msg
                else "unreadable data")
        raise DamagedInput(f"damaged data in {ds.name}: {what}", path) from None


def check_time(time, path: str, name: str = "/samples/time") -> None:
    t = np.asarray(time)
    if t.ndim != 1:
        raise InputError(f"{name} must be one-dimensional, has shape {t.shape}", path)
    if t.dtype.kind not in "fiu":
        raise InputError(f"{name} is not numeric", path)
    if t.size and not np.all(np.isfinite(t)):
        i = int(np.flatnonzero(~np.isfinite(t))[0])
        raise DamagedInput(f"{name} holds a non-finite value at sample {i}", path)
    if t.size > 1:
        d = np.diff(t)
        if not np.all(d >= 0):
            i = int(np.flatnonzero(d < 0)[0])
            raise InputError(f"{name} goes back in time (sample {i + 1}: "
                             f"{float(t[i + 1]):g} s after {float(t[i]):g} s)", path)
        if t[-1] <= t[0]:
            raise InputError(f"{name} does not advance (every sample at {float(t[0]):g} s)",
                             path)


def check_finite(arr, path: str, name: str, offset: int = 0) -> None:
    a = np.asarray(arr)
    if a.dtype.kind not in "fiu":
        raise InputError(f"{name} is not numeric", path)
    if a.size and a.dtype.kind == "f" and not np.all(np.isfinite(a)):
        i = int(np.flatnonzero(~np.all(np.isfinite(a.reshape(len(a), -1)), axis=1))[0])
        raise DamagedInput(f"{name} holds a NaN or infinite value at sample {offset + i}; "
                         "repair or re-import the recording", path)


def check_samples_layout(smp, path: str) -> int:
    """Shapes of the samples group (from the headers, nothing read). Returns n."""
    if not isinstance(smp, h5py.Group):
        raise InputError("/samples is not a group", path)
    for name in ("time", "accel"):
        if name not in smp or not isinstance(smp[name], h5py.Dataset):
            raise InputError(f"missing dataset /samples/{name} (is this a recording? "
                             "a calibration goes to apply/show, a recording to fit)", path)
    t = smp["time"]
    if len(t.shape or ()) != 1:
        raise InputError(f"/samples/time must be one-dimensional, has shape {t.shape}", path)
    n = t.shape[0]
    for name in ("accel", "gyro"):
        if name in smp:
            s = smp[name].shape or ()
            if len(s) != 2 or s[0] != n or s[1] < 1:
                raise InputError(f"/samples/{name} has shape {s}, expected ({n}, channels): "
                                 "one row per time", path)
    for name in ("temp", "table_angle", "table_rate"):
        if name in smp:
            s = smp[name].shape or ()
            if s != (n,):
                raise InputError(f"/samples/{name} has shape {s}, expected ({n},)", path)
    return n


def check_segments_layout(h5, path: str, n: int) -> None:
    g = h5.get("segments")
    if g is None or not isinstance(g, h5py.Group):
        return
    lengths = {k: (g[k].shape or (0,))[0] for k in g if isinstance(g[k], h5py.Dataset)
               and g[k].shape}
    if len(set(lengths.values())) > 1:
        raise InputError("the /segments arrays have different lengths ("
                         + ", ".join(f"{k} {v}" for k, v in sorted(lengths.items())) + ")",
                         path)


def check_recording(rec, path: str) -> None:
    """Values of a recording read into memory (see the policy above)."""
    n = len(rec.time)
    check_time(rec.time, path)
    for name in ("accel", "gyro"):
        a = getattr(rec, name)
        if a is not None:
            if a.ndim != 2 or a.shape[0] != n:
                raise InputError(f"/samples/{name} has shape {a.shape}, expected ({n}, "
                                 "channels)", path)
            check_finite(a, path, f"/samples/{name}")
    for name in ("temp", "table_angle", "table_rate"):
        a = getattr(rec, name)
        if a is not None:
            if a.shape != (n,):
                raise InputError(f"/samples/{name} has shape {a.shape}, expected ({n},)", path)
            if np.any(np.isinf(a)):
                raise DamagedInput(f"/samples/{name} holds an infinite value", path)
    for i, s in enumerate(rec.segments):
        if not (0 <= s.start <= s.stop <= n):
            raise InputError(f"segment {i} ({s.label!r}) points outside the samples "
                             f"({s.start}..{s.stop} of {n})", path)


def _expected_shapes(key: str, n: int, redundant: bool):
    if redundant:
        return {(n,)}
    if key.endswith("_K") or key.endswith("_D") or key == "proof_mass_offsets":
        return {(3, 3)}
    if key.endswith("_bias") or key == "attitude":
        return {(3,)}
    return None  # any shape (thermal terms, lever arms, ...)


def _spec_shapes(c) -> dict:
    """Parameter shapes from the calibration's own model (the effect catalogue's specs:
    a temperature polynomial of order N has (3, N)); empty where the model cannot be
    built (the heuristic shapes apply then)."""
    try:
        from calib_cli.methods.apply import model_of

        return {sp.key: tuple(sp.shape) for sp in model_of(c).specs()}
    except Exception:  # a malformed model description: checked by the heuristic below
        return {}


def check_calibration(c, path: str) -> None:
    """A calibration's parameters before apply or export use them."""
    if not c.params:
        raise InputError("the calibration holds no parameters (empty /params)", path)
    n = c.layout.n if c.layout is not None else 3
    redundant = bool(c.layout is not None and c.layout.redundant)
    specs = _spec_shapes(c)
    for k, v in c.params.items():
        v = np.asarray(v, dtype=float)
        if not np.all(np.isfinite(v)):
            raise InputError(f"parameter {k} holds a NaN or infinite value", path)
        want = (None if k == "lever_arm" else  # one row per rotating cycle of the fit
                {specs[k]} if k in specs else
                _expected_shapes(k, n, redundant and not k.endswith("_K")))
        if want is not None and v.shape not in want:
            raise InputError(f"parameter {k} has shape {v.shape}, expected "
                             f"{' or '.join(str(w) for w in sorted(want))}", path)
        if k.endswith("_K") and not redundant:
            cond = np.linalg.cond(v) if v.size else np.inf
            if not np.isfinite(cond) or cond > MAX_COND:
                raise InputError(f"parameter {k} is singular (not invertible)", path)
    cov = np.asarray(c.covariance, dtype=float)
    if cov.ndim != 2 or cov.shape[0] != cov.shape[1]:
        raise InputError(f"the covariance matrix has shape {cov.shape}, expected square", path)
