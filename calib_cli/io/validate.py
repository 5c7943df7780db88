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
    if not isinstance(ds, h5py.Dataset):
        raise InputError(f"{getattr(ds, 'name', ds)} is not a dataset", path)
    try:
        return ds[()]
    except (OSError, RuntimeError, ValueError, TypeError, UnicodeDecodeError) as exc:
        raise DamagedInput(f"damaged data in {ds.name}: {_why(exc)}", path) from None


def _why(exc) -> str:
    msg = str(exc).lower()
    return ("checksum mismatch (Fletcher-32): the file was altered or damaged"
            if "letcher" in msg or "checksum" in msg or "filter" in msg
            else "unreadable data (damaged or of a type calib does not read)")


def _has_vlen(h5) -> bool:
    """Whether any attribute or dataset of the file holds variable-length data
    (types only, from the object headers: nothing of a heap is read)."""
    found = []

    def vlen(dt) -> bool:
        return h5py.check_vlen_dtype(dt) is not None or bool(
            dt.names and any(vlen(dt.fields[n][0]) for n in dt.names))

    def visit(_name, obj):
        if not found and isinstance(obj, h5py.Dataset) and vlen(obj.dtype):
            found.append(obj)
        if not found and any(vlen(obj.attrs.get_id(n).dtype) for n in obj.attrs):
            found.append(obj)

    visit("/", h5)
    if not found:
        h5.visititems(visit)
    return bool(found)


_GCOL = b"GCOL\x01"


def check_global_heaps(h5, path: str) -> None:
    """Walk every global heap collection of a file that holds variable-length
    data (calib's files before issue 37, other tools' files) as HDF5 will, and
    refuse one HDF5 would loop on forever or read past (a free-space object of
    size 0, an object beyond its collection): exit 3 instead of a hang. Files
    without variable-length data (calib's own since issue 37) are not read."""
    import mmap

    if not _has_vlen(h5):
        return
    try:
        with open(path, "rb") as fh, mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ) as m:
            n = len(m)
            pos = m.find(_GCOL)
            while pos != -1:
                size = int.from_bytes(m[pos + 8:pos + 16], "little")
                end = pos + size
                bad = size < 32 or end > n
                p = pos + 16
                while not bad and p < end:
                    if p + 16 > end:  # a tail too small for a header: free space
                        break
                    idx = int.from_bytes(m[p:p + 2], "little")
                    osize = int.from_bytes(m[p + 8:p + 16], "little")
                    need = 16 + ((osize + 7) // 8) * 8 if idx else osize
                    bad = need < 16 or p + need > end
                    p += need
                if bad:
                    raise DamagedInput(f"damaged string heap at byte {pos} (a text of the file "
                                       "cannot be read)", path)
                pos = m.find(_GCOL, pos + 4)
    except (OSError, ValueError):  # an empty or unreadable file: HDF5 says so on opening
        return


def rows(ds, a: int, b: int, path: str) -> np.ndarray:
    """Rows a..b of a dataset (chunked readers); a failed checksum is exit 3."""
    try:
        return ds[a:b]
    except (OSError, RuntimeError, ValueError, TypeError) as exc:
        raise DamagedInput(f"damaged data in {ds.name} (samples {a}..{b}): {_why(exc)}",
                           path) from None


def decode(v, where: str, path: str) -> str:
    """A text value read from HDF5 (bytes or str) as UTF-8; exit 3 naming it."""
    if isinstance(v, np.ndarray) and v.size == 1 and v.dtype.kind in "SUO":
        v = v.reshape(-1)[0]
    if isinstance(v, (bytes, np.bytes_)):
        try:
            return bytes(v).decode("utf-8")
        except UnicodeDecodeError as exc:
            raise DamagedInput(f"{where} is not UTF-8 text (byte 0x{bytes(v)[exc.start]:02x} at "
                               f"position {exc.start})", path) from None
    if isinstance(v, str):
        return v
    raise InputError(f"{where} must be text, holds {type(v).__name__}", path)


def text(obj, name: str, path: str, default: str = "") -> str:
    """A text attribute of ``obj`` (or the long-text dataset of that name that
    io/h5file.py writes beside), decoded as UTF-8; exit 3 naming it otherwise."""
    where = f"attribute {name!r} of {obj.name}"
    try:
        if name in obj.attrs:
            v = obj.attrs[name]
        elif isinstance(obj, h5py.Group) and isinstance(obj.get(name, getlink=True), h5py.HardLink) \
                and isinstance(obj[name], h5py.Dataset) and obj[name].dtype.kind in "SO":
            where = f"{obj[name].name}"
            v = load(obj[name], path)
        else:
            return default
    except UnicodeDecodeError as exc:
        raise DamagedInput(f"{where} is not UTF-8 text ({exc.reason} at position {exc.start})",
                           path) from None
    except (OSError, RuntimeError, KeyError, ValueError, TypeError) as exc:
        raise DamagedInput(f"{where} cannot be read ({str(exc).split('(')[0].strip()})",
                           path) from None
    return decode(v, where, path)


def check_root_text(h5, path: str) -> None:
    """Every text attribute of the root (the provenance) decodes as UTF-8."""
    for name in h5.attrs:
        try:
            v = h5.attrs[name]
        except (OSError, RuntimeError, ValueError, TypeError, UnicodeDecodeError):
            v = b""  # text() below names it
        if isinstance(v, (bytes, str)) or (isinstance(v, np.ndarray) and v.dtype.kind in "SO"):
            text(h5, name, path)


def strings(ds, path: str) -> list[str]:
    """A dataset of text (fixed or variable length), each decoded as UTF-8."""
    arr = load(ds, path)
    if not isinstance(arr, np.ndarray) or arr.ndim != 1 or arr.dtype.kind not in "SO":
        raise InputError(f"{ds.name} must be a list of text, has shape "
                         f"{getattr(arr, 'shape', ())} of {getattr(arr, 'dtype', type(arr))}",
                         path)
    return [decode(x, f"{ds.name}[{i}]", path) for i, x in enumerate(arr)]


def number(obj, name: str, path: str, default=None, lo=-np.inf, hi=np.inf,
           integer: bool = False, nan_ok: bool = False):
    """A numeric attribute: a number (not text, not a bool), finite unless
    ``nan_ok`` (NaN: unknown), within [lo, hi]; exit 3 naming it otherwise."""
    where = f"attribute {name!r} of {obj.name}"
    try:
        if name not in obj.attrs:
            return default
        v = obj.attrs[name]
    except (OSError, RuntimeError, KeyError, ValueError, TypeError, UnicodeDecodeError):
        raise DamagedInput(f"{where} cannot be read", path) from None
    if isinstance(v, np.ndarray) and v.size == 1:
        v = v.reshape(-1)[0]
    if isinstance(v, (bool, np.bool_)) or not isinstance(v, (int, float, np.integer, np.floating)):
        raise InputError(f"{where} must be a number, holds {v!r}", path)
    v = v.item() if isinstance(v, np.generic) else v
    if isinstance(v, float) and np.isnan(v) and nan_ok:
        return v
    if not np.isfinite(v) or not lo <= v <= hi:
        raise InputError(f"{where} is {v!r}, outside {lo:g}..{hi:g}", path)
    if integer:
        if v != int(v):
            raise InputError(f"{where} must be a whole number, holds {v!r}", path)
        return int(v)
    return float(v)


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
            check_magnitudes(a, name, (rec.units or {}).get(name, UNITS[name][0]), path)
    check_rate(rec.time, path)
    for name, lim in (("temp", (-273.15, 1000.0)), ("table_angle", (-1e9, 1e9)),
                      ("table_rate", (-1e4, 1e4))):
        a = getattr(rec, name)
        if a is not None:
            if a.shape != (n,):
                raise InputError(f"/samples/{name} has shape {a.shape}, expected ({n},)", path)
            if np.any(np.isinf(a)):
                raise DamagedInput(f"/samples/{name} holds an infinite value", path)
            bad = ~np.isnan(a) & ((a < lim[0]) | (a > lim[1]))
            if np.any(bad):
                i = int(np.flatnonzero(bad)[0])
                raise DamagedInput(f"/samples/{name} holds {float(a[i]):.6g} at sample {i}, "
                                   f"outside {lim[0]:g}..{lim[1]:g}", path)
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


def model_specs(c, path: str) -> dict:
    """{param key: shape} the calibration's model needs (noise terms aside):
    every effect named in /model known to this calib, with valid options, and
    fitting the layout; exit 3 naming what is not."""
    from calib_cli.model.effects import CATALOGUE, STOCHASTIC
    from calib_cli.model.imu_model import ImuModel
    from calib_cli.model.truth import effect_from_description

    model = c.model
    if not isinstance(model, list) or not model:
        raise InputError("the calibration names no model (attribute 'effects' of /model is "
                         "missing or empty): calib cannot tell which parameters it needs", path)
    effects = []
    for i, d in enumerate(model):
        if not isinstance(d, dict) or not isinstance(d.get("name"), str):
            raise InputError(f"entry {i} of the model (/model effects) is not an effect "
                             f"description: {d!r}", path)
        if d["name"] not in CATALOGUE:
            raise InputError(f"the model names an unknown effect {d['name']!r} (/model "
                             f"effects); this calib knows {', '.join(sorted(CATALOGUE))}", path)
        if d.get("sensor") not in (None, "", "accel", "gyro"):  # "": no sensor (time_offset)
            raise InputError(f"effect {d['name']!r} of the model has sensor {d.get('sensor')!r}"
                             "; expected 'accel' or 'gyro'", path)
        try:
            effects.append(effect_from_description(d))
        except (TypeError, ValueError, KeyError, AttributeError) as exc:
            raise InputError(f"effect {d['name']!r} of the model has options calib does not "
                             f"take ({exc})", path) from None
    try:
        specs = ImuModel(tuple(effects), c.layout).specs()
    except Exception as exc:  # an effect that does not fit the layout
        raise InputError(f"the model's effects do not fit the unit's layout ({exc})",
                         path) from None
    stoch = {k for e in effects if e.stage == STOCHASTIC for k in
             (sp.key for sp in e.specs(c.layout))}
    return {sp.key: tuple(sp.shape) for sp in specs if sp.key not in stoch}


def _check_stats(stats, path: str) -> None:
    """The statistics other commands use: typed (a range is two numbers)."""
    if not isinstance(stats, dict):
        raise InputError("/stats json is not an object", path)

    def num(v):
        return isinstance(v, (int, float)) and not isinstance(v, bool) and np.isfinite(v)

    rng = stats.get("temp_range_degC")
    if rng is not None and not (isinstance(rng, list) and len(rng) == 2 and all(map(num, rng))
                                and rng[0] <= rng[1]):
        raise InputError(f"stats temp_range_degC must be two temperatures [low, high] in degC, "
                         f"holds {rng!r}", path)
    ref = stats.get("temp_ref_degC")
    if ref is not None and not num(ref):
        raise InputError(f"stats temp_ref_degC must be a number (degC), holds {ref!r}", path)
    for k in ("g_error_rms_before", "g_error_rms_after", "g_error_floor",
              "accel_residual_rms", "gyro_residual_rms"):
        v = stats.get(k)
        if v is not None and not (isinstance(v, (int, float)) and not isinstance(v, bool)):
            raise InputError(f"stats {k} must be a number or null, holds {v!r}", path)
    un = stats.get("unobservable")
    if un is not None and not (isinstance(un, list) and all(isinstance(x, str) for x in un)):
        raise InputError(f"stats unobservable must be a list of names, holds {un!r}", path)
    nm = stats.get("noise_model")
    if nm is not None and not isinstance(nm, (dict, list)):
        raise InputError(f"stats noise_model must be a table, holds {nm!r}", path)


def check_calibration(c, path: str) -> None:
    """A calibration's content before anything uses it (read_calibration calls
    it): its model known and complete (a missing K is refused, never taken as
    the identity), finite values of the model's shapes, K invertible, sigma
    >= 0 (NaN: not determined), a square covariance of the order's size,
    statistics of their types."""
    if not c.params:
        raise InputError("the calibration holds no parameters (empty /params)", path)
    n = c.layout.n if c.layout is not None else 3
    redundant = bool(c.layout is not None and c.layout.redundant)
    specs = model_specs(c, path)
    missing = [k for k in specs if k not in c.params]
    if missing:
        raise InputError(f"the calibration's model needs {', '.join(missing)} but /params has "
                         f"no {' and no '.join(missing)} (calib never takes a missing K as "
                         "the identity)", path)
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
            cond = np.linalg.cond(v) if v.size and v.ndim == 2 else np.inf
            if not np.isfinite(cond) or cond > MAX_COND:
                raise InputError(f"parameter {k} is singular (not invertible)", path)
    for k, v in (c.sigma or {}).items():
        v = np.asarray(v, dtype=float)
        if np.any(np.isinf(v)) or np.any(v[~np.isnan(v)] < 0):
            raise InputError(f"sigma of {k} holds a negative or infinite value", path)
        if k in c.params and v.shape != np.shape(c.params[k]):
            raise InputError(f"sigma of {k} has shape {v.shape}, the parameter "
                             f"{np.shape(c.params[k])}", path)
    cov = np.asarray(c.covariance, dtype=float)
    if cov.ndim != 2 or cov.shape[0] != cov.shape[1]:
        raise InputError(f"the covariance matrix has shape {cov.shape}, expected square", path)
    if np.any(np.isinf(cov)):
        raise InputError("the covariance matrix holds an infinite value", path)
    if len(c.cov_order) != cov.shape[0]:
        raise InputError(f"the covariance matrix is {cov.shape[0]} x {cov.shape[0]} but its "
                         f"order names {len(c.cov_order)} entries", path)
    for k, i in c.cov_order:
        if k not in c.params or not 0 <= i < np.size(c.params[k]):
            raise InputError(f"the covariance order names {k}[{i}], which /params does not "
                             "hold", path)
    _check_stats(c.stats, path)


# ---------------------------------------------------------------------------
# issue 37: every field a reader uses, typed and in its physical range

G_RANGE = (9.7, 9.9)  # m/s^2: |g| anywhere a bench stands (docs/file-formats.md)
# beyond any sensor calib calibrates (SI; counts: the 53-bit integers a float holds)
ACCEL_MAX = 1e5  # m/s^2, about 10,000 g
GYRO_MAX = 1e3  # rad/s, about 57,000 deg/s
COUNT_MAX = 2.0 ** 53
RATE_MAX = 1e6  # Hz, as sample_rate_hz of a plan
UNITS = {"accel": ("m/s^2", "count"), "gyro": ("rad/s", "count")}
SEGMENT_KINDS = ("static", "turn", "rotating")


def numeric(arr, where: str, path: str, integer: bool = False) -> np.ndarray:
    a = np.asarray(arr)
    if a.dtype.kind not in ("iu" if integer else "fiu"):
        if integer and a.dtype.kind == "f" and np.all(np.isfinite(a)) and np.all(a == np.round(a)):
            return a.astype(np.int64)
        raise InputError(f"{where} must hold {'whole numbers' if integer else 'numbers'}, holds "
                         f"{a.dtype}", path)
    return a


def allow_any_g(h5) -> bool:
    """Whether the recording's plan says ``[site] allow_any_g = true``."""
    try:
        import tomllib

        t = text(h5["plan"], "text", "") if "plan" in h5 else ""
        return tomllib.loads(t).get("site", {}).get("allow_any_g") is True
    except Exception:  # an unreadable plan text grants nothing
        return False


def site_values(h5, path: str) -> dict:
    """/site: latitude (rad), height (m), g (m/s^2 or NaN: normal gravity)."""
    s = h5["site"]
    if not isinstance(s, h5py.Group):
        raise InputError("/site is not a group", path)
    lat = number(s, "latitude", path, 0.0, -np.pi / 2, np.pi / 2)
    height = number(s, "height", path, 0.0, -1e3, 1e4)
    g = number(s, "g", path, np.nan, nan_ok=True)
    if not np.isnan(g) and not (g > 0 and (G_RANGE[0] <= g <= G_RANGE[1] or allow_any_g(h5))):
        raise InputError(f"attribute 'g' of /site is {g:g} m/s^2, outside {G_RANGE[0]}-"
                         f"{G_RANGE[1]} m/s^2 (Earth's gravity; a plan with [site] allow_any_g "
                         "= true allows other positive values)", path)
    return {"latitude": lat, "height": height, "g": g}


def layout_values(h5, path: str) -> dict:
    lay = h5.get("layout")
    if lay is None:
        return {"n": 3, "el0": None, "az0": None, "n_cycles": 0}
    if not isinstance(lay, h5py.Group):
        raise InputError("/layout is not a group", path)
    n = number(lay, "n", path, 3, 1, 4096, integer=True)
    n_cycles = number(lay, "n_cycles", path, 0, 0, 1e7, integer=True)
    geo = {}
    for k in ("el0", "az0"):
        if k in lay:
            v = numeric(load(lay[k], path), f"/layout/{k}", path).astype(float)
            if v.shape != (n,) or not np.all(np.isfinite(v)):
                raise InputError(f"/layout/{k} must be {n} finite angles, has shape {v.shape}",
                                 path)
            geo[k] = v
    if len(geo) == 1:
        raise InputError("/layout has only one of el0 and az0", path)
    if not geo and n != 3:
        raise InputError(f"/layout says {n} channels but gives no el0/az0 (a triad has 3)", path)
    return {"n": n, "el0": geo.get("el0"), "az0": geo.get("az0"), "n_cycles": n_cycles}


def sample_units(smp, path: str) -> dict:
    out = {}
    for s, (si, _) in UNITS.items():
        u = text(smp, f"{s}_units", path, si)
        if u not in UNITS[s]:
            raise InputError(f"attribute '{s}_units' of /samples is {u!r}; calib writes "
                             f"{' or '.join(repr(x) for x in UNITS[s])}", path)
        out[s] = u
    return out


def check_sample_types(smp, path: str, units: dict, n_channels: int) -> None:
    """Types and channel counts of /samples (headers only, nothing read)."""
    for name in ("time", "accel", "gyro", "temp", "table_angle", "table_rate"):
        if name not in smp:
            continue
        ds = smp[name]
        if not isinstance(ds, h5py.Dataset):
            raise InputError(f"/samples/{name} is not a dataset", path)
        k = ds.dtype.kind
        counts = units.get(name) == "count"
        if k != "f" and not (k in "iu" and (counts or name == "time")):
            raise InputError(f"/samples/{name} is stored as {ds.dtype} "
                             f"({'text' if k in 'SUO' else 'not floating point'}); calib "
                             "writes float64" + (" (integers only for data in counts)"
                                                 if name in ("accel", "gyro") else ""), path)
        if name in ("accel", "gyro") and ds.shape[1] != n_channels:
            raise InputError(f"/samples/{name} has {ds.shape[1]} channels, the layout "
                             f"{n_channels} (a triad: 3)", path)


def check_magnitudes(a: np.ndarray, sensor: str, unit: str, path: str, offset: int = 0) -> None:
    """Values no sensor of this kind gives (1e300 in one cell): exit 3 naming the sample."""
    lim = COUNT_MAX if unit == "count" else ACCEL_MAX if sensor == "accel" else GYRO_MAX
    if a.size and a.dtype.kind in "fiu":
        big = np.abs(a.reshape(len(a), -1)) > lim
        if np.any(big):
            i, j = (int(x[0]) for x in np.nonzero(big))
            raise DamagedInput(f"/samples/{sensor} holds {float(a[i].reshape(-1)[j]):.6g} {unit} "
                               f"at sample {offset + i}, beyond any {sensor}erometer"
                               .replace("gyroerometer", "gyro") + f" (|x| <= {lim:g} {unit})",
                               path)


def check_rate(time: np.ndarray, path: str) -> None:
    if len(time) > 1:
        span = float(time[-1] - time[0])
        rate = (len(time) - 1) / span if span > 0 else np.inf
        if rate > RATE_MAX:
            raise InputError(f"/samples/time gives {rate:.3g} samples per second (more than "
                             f"{RATE_MAX:g} Hz): times in the wrong unit?", path)


_SEG_VECTORS = {"attitude": 100.0, "table_axis_enu": None, "lever_arm": 100.0,
                "rotation_axis_body": None}  # bound of |x|; None: a unit vector
_SEG_SCALARS = {"attitude_sigma": (0.0, np.pi), "table_rate": (-1e4, 1e4),
                "rotation_angle": (-1e6, 1e6)}


def segment_columns(g, path: str, n: int) -> dict:
    """/segments read and checked: text labels and kinds, whole-number spans
    within the n samples, each vector all NaN (unknown) or finite (unit
    vectors of norm 1), each scalar NaN or finite within its range."""
    if not isinstance(g, h5py.Group):
        raise InputError("/segments is not a group", path)
    need = ("label", "kind", "start", "stop", "plan_index", *_SEG_VECTORS, *_SEG_SCALARS)
    for k in need:
        if k not in g:
            raise InputError(f"missing field /segments/{k}", path)
    out = {"label": strings(g["label"], path), "kind": strings(g["kind"], path)}
    m = len(out["label"])
    for k in ("start", "stop", "plan_index"):
        out[k] = numeric(load(g[k], path), f"/segments/{k}", path, integer=True)
    for k, lim in _SEG_VECTORS.items():
        v = numeric(load(g[k], path), f"/segments/{k}", path).astype(float)
        if v.shape != (m, 3):
            raise InputError(f"/segments/{k} has shape {v.shape}, expected ({m}, 3)", path)
        nan = np.isnan(v)
        for i in range(m):
            row = v[i]
            if nan[i].all():
                continue
            bad = (nan[i].any() or not np.all(np.isfinite(row))
                   or (lim is not None and np.max(np.abs(row)) > lim)
                   or (lim is None and abs(float(np.linalg.norm(row)) - 1.0) > 1e-3))
            if bad:
                what = ("a unit vector" if lim is None else f"finite, |x| <= {lim:g}")
                raise InputError(f"/segments/{k} of segment {i} ({out['label'][i]!r}) is "
                                 f"{row.tolist()}: expected all NaN (unknown) or {what}", path)
        out[k] = v
    for k, (lo, hi) in _SEG_SCALARS.items():
        v = numeric(load(g[k], path), f"/segments/{k}", path).astype(float)
        if v.shape != (m,):
            raise InputError(f"/segments/{k} has shape {v.shape}, expected ({m},)", path)
        bad = ~np.isnan(v) & ~((v >= lo) & (v <= hi))
        if np.any(bad):
            i = int(np.flatnonzero(bad)[0])
            raise InputError(f"/segments/{k} of segment {i} ({out['label'][i]!r}) is "
                             f"{v[i]:g}: expected NaN (unknown) or {lo:g}..{hi:g}", path)
        out[k] = v
    for k in ("kind", "start", "stop", "plan_index"):
        if len(out[k]) != m:
            raise InputError(f"/segments/{k} has {len(out[k])} entries, /segments/label {m}",
                             path)
    for i in range(m):
        kind, a, b = out["kind"][i], int(out["start"][i]), int(out["stop"][i])
        where = f"segment {i} ({out['label'][i]!r})"
        if kind not in SEGMENT_KINDS:
            raise InputError(f"{where} has kind {kind!r}; expected "
                             f"{', '.join(SEGMENT_KINDS)}", path)
        if not 0 <= a <= b <= n:
            raise InputError(f"{where} points outside the samples ({a}..{b} of {n})", path)
        if out["plan_index"][i] < -1:
            raise InputError(f"{where} has plan_index {int(out['plan_index'][i])}", path)
    return out
