"""HDF5 layouts, version 1 (documented in docs/file-formats.md).

Every file carries provenance root attributes (CONTRACT.md section 6). The
readers check kind and version and name the file and the field on any
problem (InputError, exit 3).
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import sys
from datetime import datetime, timezone
from pathlib import Path

import h5py
import numpy as np

from calib_cli import __version__
from calib_cli.data import SAMPLE_KINDS, CalibrationResult, Recording, Segment
from calib_cli.errors import DamagedInput, InputError
from calib_cli.geometry import Layout
from calib_cli.io import validate
from calib_cli.io.escape import line_text
from calib_cli.io.h5file import h5_output, put, set_attrs, set_text
from calib_cli.model.earth import Site
from calib_cli.plan import KINDS as PLAN_KINDS

FORMAT_VERSION = 1
KINDS = ("raw", "calibration", "corrected", "diagnosis", "allan")
_STR = h5py.string_dtype()


# ---------------------------------------------------------------------------
# provenance, atomic output, checked opening


def sha256_file(path) -> str:
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def write_provenance(h5: h5py.File, kind: str, inputs=(), serial: str | None = None,
                     extra: dict | None = None) -> None:
    """Root attributes: kind, version, tool, command, UTC time, serial, input hashes."""
    set_text(h5, "kind", kind)
    h5.attrs["format_version"] = FORMAT_VERSION
    set_text(h5, "tool", "calib")
    set_text(h5, "tool_version", __version__)
    set_text(h5, "command", " ".join([Path(sys.argv[0]).name] + sys.argv[1:]))
    set_text(h5, "created_utc", datetime.now(timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ"))
    set_text(h5, "unit_serial", serial or "")
    hashes = {str(p): sha256_file(p) for p in inputs if p and Path(p).is_file()}
    set_text(h5, "input_sha256", json.dumps(hashes))
    set_attrs(h5, extra or {})
    if kind in ("calibration", "diagnosis"):  # a fit carries its data's origin on
        copy_source(h5, inputs)


# ---------------------------------------------------------------------------
# the samples' origin: /source (docs/file-formats.md; io/imu_logs.py fills it)

SOURCE_JSON = ("parameters", "parameters_changed", "device_ids")


def write_source(h5, source: dict) -> None:
    """/source: where the samples come from and whether the device had already
    corrected them ("samples": "raw", "corrected" or "unknown") and by which
    parameters; dicts and lists as JSON text (long text checksummed, io/h5file.py)."""
    g = h5.require_group("source")
    set_attrs(g, {k: json.dumps(v) if isinstance(v, (dict, list, tuple)) else v
                  for k, v in source.items() if v is not None})


def _read_source_group(g, path: str) -> dict:
    out = {}
    names = list(g.attrs) + [n for n in g if isinstance(g[n], h5py.Dataset)]  # long text
    for k in names:
        v = g.attrs[k] if k in g.attrs else None
        if v is None or isinstance(v, (bytes, str, np.bytes_)) or (
                isinstance(v, np.ndarray) and v.dtype.kind in "SUO"):
            v = validate.text(g, k, path)
        elif isinstance(v, np.generic):
            v = v.item()
        if k in SOURCE_JSON and isinstance(v, str):
            try:
                v = json.loads(v)
            except ValueError:
                raise InputError(f"/source/{k} is not valid JSON", path) from None
        out[k] = v
    return out


def read_source(path) -> dict:
    """The /source of a raw, calibration or diagnosis file ({} when it has none:
    a CSV import, a simulation)."""
    p = str(path)
    with h5py.File(p, "r") as h5:
        return _read_source_group(h5["source"], p) if "source" in h5 else {}


def copy_source(h5, inputs) -> None:
    """The /source of the first input that has one (the fitted raw file)."""
    for p in inputs:
        try:
            if not (p and Path(p).is_file() and h5py.is_hdf5(p)):
                continue
            with h5py.File(p, "r") as src:
                if "source" in src:
                    write_source(h5, _read_source_group(src["source"], str(p)))
                    return
        except OSError:
            continue


@contextlib.contextmanager
def atomic_path(path):
    """Yield a temporary path beside ``path``; rename onto it on success,
    delete it on any failure, so a failed command leaves nothing behind
    (calib_cli/io/outpath.py: umask, stale temp files, OS errors -> exit 2)."""
    from calib_cli.io.outpath import atomic_file

    with atomic_file(path) as tmp:
        yield tmp


def open_checked(path, kinds) -> h5py.File:
    """Open an HDF5 file for reading and check its kind and format version."""
    p = str(path)
    if isinstance(kinds, str):
        kinds = (kinds,)
    if not Path(p).exists():
        raise InputError("no such file", p)
    try:
        h5 = h5py.File(p, "r")
    except OSError:
        from calib_cli.io.sniff import hint_for_non_hdf5

        raise InputError(f"not an HDF5 file (or damaged){hint_for_non_hdf5(p)}", p) from None
    try:
        # before any text is read: HDF5 loops forever on some damaged string heaps
        validate.check_global_heaps(h5, p)
        kind = attr_str(h5, "kind")
    except (KeyError, RuntimeError, OSError, ValueError, TypeError) as exc:
        h5.close()
        raise _structure(exc, p) from None
    except BaseException:
        h5.close()
        raise
    if kind not in kinds:
        h5.close()
        what = f"a {kind!r} file" if kind else "not a calib file (no 'kind' attribute)"
        raise InputError(f"{what}; expected {' or '.join(repr(k) for k in kinds)}", p)
    try:
        check_untrusted_h5(h5, p)
        # calib_cli/io/validate.py (issue 15): version parsed, each dataset's declared size
        validate.format_version(h5, p, FORMAT_VERSION)
        validate.check_declared_sizes(h5, p)
        validate.check_root_text(h5, p)  # issue 37: provenance text decodes as UTF-8
    except (KeyError, RuntimeError, OSError, ValueError, TypeError) as exc:
        h5.close()  # HDF5 refuses its own damaged metadata this way: bad input, not a bug
        raise _structure(exc, p) from None
    except BaseException:
        h5.close()
        raise
    return h5


# ---------------------------------------------------------------------------
# trust boundary: what one HDF5 input may reach and cost (docs/security.md)

# the data an input declares (sum over its datasets of elements x item size)
# may exceed its size on disk by this factor, or reach MIN_BUDGET, no more:
# calib writes uncompressed files (factor ~1); noisy sensor data does not
# compress 100x; a file of unallocated chunks or a compression bomb does.
MAX_EXPANSION = 100
MIN_BUDGET = 64 << 20


def _human(n: float) -> str:
    for unit, f in (("GB", 1e9), ("MB", 1e6), ("kB", 1e3)):
        if n >= f:
            return f"{n / f:.3g} {unit}"
    return f"{int(n)} B"


def _has_reference(dt) -> bool:
    if h5py.check_dtype(ref=dt) is not None:
        return True
    if dt.names:
        return any(_has_reference(dt.fields[n][0]) for n in dt.names)
    if dt.subdtype is not None:
        return _has_reference(dt.subdtype[0])
    base = h5py.check_dtype(vlen=dt)
    return base is not None and not isinstance(base, type) and _has_reference(np.dtype(base))


def _ref_attrs(obj, where: str, p: str) -> None:
    for name in obj.attrs:
        if _has_reference(obj.attrs.get_id(name).dtype):
            raise InputError(f"attribute {name!r} of {line_text(where)} holds HDF5 object or region "
                             "references; calib does not follow references (docs/security.md)", p)


def _structure(exc, path) -> DamagedInput:
    """HDF5 refusing its own damaged metadata: bad input (exit 3), not a bug."""
    return DamagedInput(f"damaged HDF5 structure ({str(exc).split('(')[0].strip()})", path)


def check_untrusted_h5(h5: h5py.File, path: str) -> None:
    """Refuse what would make reading an input reach outside it or cost more
    than it is worth, before anything is read (exit 3 naming the object):

    - external links, and user-defined links (another file through a link);
    - virtual datasets and datasets with external raw storage (data in other
      files: they would be read and not hashed into the provenance);
    - object and region references, in datasets and attributes;
    - declared data (all datasets, and any one chunk) beyond
      max(MIN_BUDGET, MAX_EXPANSION x the file's size on disk).
    """
    budget = max(MIN_BUDGET, MAX_EXPANSION * os.path.getsize(path))
    groups, datasets = [h5], []

    def visit(name, obj):
        (groups if isinstance(obj, h5py.Group) else datasets).append(obj)

    h5.visititems(visit)  # objects reached by hard links, each once
    for g in groups:
        _ref_attrs(g, g.name, path)
        for name in g:
            link = g.get(name, getlink=True)
            full = line_text(f"{g.name.rstrip('/')}/{name}")
            if isinstance(link, h5py.ExternalLink):
                raise InputError(f"{full} is an external link to "
                                 f"{line_text(link.filename)}:{line_text(link.path)}; "
                                 "calib does not follow links out of a file (docs/security.md)",
                                 path)
            if not isinstance(link, (h5py.HardLink, h5py.SoftLink)):
                raise InputError(f"{full} is a user-defined link; refused (docs/security.md)",
                                 path)
            if isinstance(link, h5py.SoftLink):  # must lead to an object of this file
                try:
                    ok = g.get(name) is not None
                except (RuntimeError, KeyError, OSError, ValueError):
                    ok = False
                if not ok:
                    raise InputError(f"{full} is a soft link to {line_text(link.path)} that "
                                     "leads nowhere (dangling, or a cycle of links)", path)
    declared = 0
    for ds in datasets:
        if not isinstance(ds, h5py.Dataset):
            continue  # a committed datatype
        _ref_attrs(ds, ds.name, path)
        if ds.is_virtual:
            files = sorted({line_text(m.file_name) for m in ds.virtual_sources()})
            raise InputError(f"{line_text(ds.name)} is a virtual dataset (mapped from {', '.join(files)}); "
                             "calib does not read data from other files (docs/security.md)", path)
        if ds.id.get_create_plist().get_external_count() > 0:
            raise InputError(f"{line_text(ds.name)} keeps its data in an external file; calib does not read "
                             "data from other files (docs/security.md)", path)
        if _has_reference(ds.dtype):
            raise InputError(f"{line_text(ds.name)} holds HDF5 object or region references; calib does not "
                             "follow references (docs/security.md)", path)
        item = ds.dtype.itemsize
        size = int(np.prod(ds.shape, dtype=object)) * item if ds.shape else item
        chunk = int(np.prod(ds.chunks, dtype=object)) * item if ds.chunks else 0
        declared += size
        if declared > budget or chunk > budget:
            raise InputError(f"{line_text(ds.name)} declares {_human(size)} of data (chunks of "
                             f"{_human(chunk)}) in a file of {_human(os.path.getsize(path))}; "
                             f"one input may declare at most {_human(budget)} "
                             f"(max({MIN_BUDGET >> 20} MiB, {MAX_EXPANSION}x its size on disk), "
                             "docs/security.md)", path)


def file_kind(path) -> str:
    """The kind attribute of a calib HDF5 file (checked)."""
    with open_checked(path, KINDS) as h5:
        return attr_str(h5, "kind")


def attr_str(h5, name, default=""):
    """A text attribute, decoded (io/validate.py: exit 3 naming it when it is not text)."""
    return validate.text(h5, name, h5.file.filename, default)


def provenance(path) -> dict:
    """Root attributes of a calib file as a dict of plain values (text decoded,
    long text read from its dataset, io/h5file.py)."""
    p = str(path)
    with open_checked(p, KINDS) as h5:
        out = {}
        for k in h5.attrs:
            try:
                v = h5.attrs[k]
            except (OSError, RuntimeError, ValueError, TypeError, UnicodeDecodeError):
                v = None
            if isinstance(v, (bytes, np.bytes_, str)) or v is None:
                v = validate.text(h5, k, p)
            elif isinstance(v, np.generic):
                v = v.item()
            out[k] = v
        for k in ("command", "input_sha256", "plan_kind", "unit_serial"):
            if k not in out and k in h5:
                out[k] = validate.text(h5, k, p)
        return out


def _need(h5, name, path):
    if name not in h5:
        raise InputError(f"missing field /{name}", path)
    return h5[name]


def _opt_vec(arr):
    return None if arr is None or np.all(np.isnan(arr)) else np.asarray(arr, dtype=float)


def _opt_num(x):
    return None if np.isnan(x) else float(x)


def _vec_or_nan(v, n=3):
    return np.full(n, np.nan) if v is None else np.asarray(v, dtype=float)


# ---------------------------------------------------------------------------
# raw recordings

SAMPLE_FIELDS = ("temp", "table_angle", "table_rate")


def write_segments(h5, segments) -> None:
    g = h5.create_group("segments")
    put(g, "label", [s.label for s in segments], dtype=_STR)
    put(g, "kind", [s.kind for s in segments], dtype=_STR)
    put(g, "start", np.array([s.start for s in segments], dtype=np.int64))
    put(g, "stop", np.array([s.stop for s in segments], dtype=np.int64))
    put(g, "plan_index", np.array([s.plan_index for s in segments], dtype=np.int64))
    for name in ("attitude", "table_axis_enu", "lever_arm", "rotation_axis_body"):
        put(g, name, np.array([_vec_or_nan(getattr(s, name)) for s in segments],
                              dtype=float).reshape(-1, 3))
    for name in ("attitude_sigma", "table_rate", "rotation_angle"):
        put(g, name, np.array([np.nan if getattr(s, name) is None else getattr(s, name)
                               for s in segments], dtype=float))


def read_segments(h5, path, n: int | None = None) -> tuple[Segment, ...]:
    """The segments, checked (io/validate.py: types, spans within the ``n``
    samples, NaN only as a whole unknown vector)."""
    g = _need(h5, "segments", path)
    if n is None:
        smp = h5.get("samples")
        t = smp.get("time") if isinstance(smp, h5py.Group) else None
        n = t.shape[0] if isinstance(t, h5py.Dataset) and t.shape else 0
    cols = validate.segment_columns(g, path, n)
    out = []
    for i, label in enumerate(cols["label"]):
        out.append(Segment(label=label, kind=cols["kind"][i], start=int(cols["start"][i]),
                           stop=int(cols["stop"][i]), plan_index=int(cols["plan_index"][i]),
                           attitude=_opt_vec(cols["attitude"][i]),
                           attitude_sigma=_opt_num(cols["attitude_sigma"][i]),
                           table_axis_enu=_opt_vec(cols["table_axis_enu"][i]),
                           table_rate=_opt_num(cols["table_rate"][i]),
                           lever_arm=_opt_vec(cols["lever_arm"][i]),
                           rotation_axis_body=_opt_vec(cols["rotation_axis_body"][i]),
                           rotation_angle=_opt_num(cols["rotation_angle"][i])))
    return tuple(out)


def _write_params_group(h5, name, params: dict) -> None:
    g = h5.create_group(name)
    for k, v in params.items():
        put(g, k, np.asarray(v, dtype=float))


def _read_params_group(g) -> dict:
    p = g.file.filename
    if not isinstance(g, h5py.Group):
        raise InputError(f"{g.name} is not a group", p)
    out = {}
    for k in g:
        v = validate.load(g[k], p)
        if not isinstance(v, np.ndarray) and not isinstance(v, (float, int, np.number)) \
                or np.asarray(v).dtype.kind not in "fiu":
            raise InputError(f"{g.name}/{k} must hold numbers, holds "
                             f"{getattr(v, 'dtype', type(v).__name__)}", p)
        out[k] = np.asarray(v, dtype=float)
    return out


def write_site_layout(h5, site: Site, layout: Layout) -> None:
    s = h5.create_group("site")
    s.attrs["latitude"] = site.latitude
    s.attrs["height"] = site.height
    s.attrs["g"] = np.nan if site.g is None else site.g
    s.attrs["gravity_used"] = site.gravity
    lay = h5.create_group("layout")
    lay.attrs["n"] = layout.n
    lay.attrs["n_cycles"] = layout.n_cycles
    if layout.redundant:
        put(lay, "el0", np.asarray(layout.el0, dtype=float))
        put(lay, "az0", np.asarray(layout.az0, dtype=float))


def read_site_layout(h5, path) -> tuple[Site, Layout]:
    _need(h5, "site", path)
    sv = validate.site_values(h5, path)
    site = Site(latitude=sv["latitude"], height=sv["height"],
                g=None if np.isnan(sv["g"]) else sv["g"])
    lv = validate.layout_values(h5, path)
    return site, Layout(n=lv["n"], el0=lv["el0"], az0=lv["az0"], n_cycles=lv["n_cycles"])


def write_raw(path, rec: Recording, inputs=(), kind: str = "raw") -> None:
    """Write a recording atomically (kind "raw", or "corrected" for apply's output).
    Its content is validated first (io/validate.py): a NaN, a time going back
    is an error naming the input it came from."""
    validate.check_recording(rec, str(inputs[0]) if inputs else str(path))
    with h5_output(path) as h5:
        write_provenance(h5, kind, inputs, rec.serial, {"plan_kind": rec.plan_kind})
        smp = h5.create_group("samples")
        chunks = (min(len(rec.time), 65536),) if len(rec.time) else None
        ck = chunks is not None  # Fletcher-32 checksums on every chunked dataset
        smp.create_dataset("time", data=rec.time, chunks=chunks, fletcher32=ck)
        for name in ("accel", "gyro"):
            arr = getattr(rec, name)
            if arr is not None:
                smp.create_dataset(name, data=arr, chunks=(chunks[0], arr.shape[1])
                                   if chunks else None, fletcher32=ck)
        for name in SAMPLE_FIELDS:
            arr = getattr(rec, name)
            if arr is not None:
                smp.create_dataset(name, data=arr, chunks=chunks, fletcher32=ck)
        set_attrs(smp, {"accel_units": rec.units.get("accel", "m/s^2"),
                        "gyro_units": rec.units.get("gyro", "rad/s"),
                        "sample_kind": rec.sample_kind})
        write_segments(h5, rec.segments)
        write_site_layout(h5, rec.site, rec.layout)
        set_text(h5.create_group("plan"), "text", rec.plan_text)
        if rec.counters:
            set_attrs(h5.create_group("counters"), rec.counters)
        if rec.truth is not None:
            t = h5.create_group("truth")
            _write_params_group(t, "params", rec.truth.get("params", {}))
            for k, v in rec.truth.get("noise", {}).items():
                t.attrs["noise_" + k] = np.asarray(v, dtype=float)
            if rec.truth.get("attitudes") is not None:
                put(t, "attitudes", np.asarray(rec.truth["attitudes"], dtype=float))
            set_text(t, "effects", json.dumps(rec.truth.get("effects", [])))


def check_raw_header(h5, p: str):
    """The checks of a recording's structure, nothing of the samples read (the
    chunked readers of apply and allan call it too): (n, units, site, layout)."""
    try:
        smp = _need(h5, "samples", p)
        n = validate.check_samples_layout(smp, p)
        units = validate.sample_units(smp, p)
        site, layout = read_site_layout(h5, p)
        validate.check_sample_types(smp, p, units, layout.n)
        validate.check_segments_layout(h5, p, n)
    except (RuntimeError, OSError) as exc:  # HDF5 refusing its own structure
        raise _structure(exc, p) from None
    return n, units, site, layout


def read_raw(path, kinds=("raw", "corrected")) -> Recording:
    """Read a raw (or corrected) recording, fully into memory, every field
    checked (io/validate.py)."""
    p = str(path)
    with open_checked(p, kinds) as h5:
        try:
            n, units, site, layout = check_raw_header(h5, p)
            smp = h5["samples"]
            time = np.asarray(validate.load(smp["time"], p), dtype=float)
            accel = np.asarray(validate.load(smp["accel"], p), dtype=float)
            gyro = (np.asarray(validate.load(smp["gyro"], p), dtype=float) if "gyro" in smp
                    else None)
            opt = {k: np.asarray(validate.load(smp[k], p), dtype=float) if k in smp else None
                   for k in SAMPLE_FIELDS}
            sample_kind = attr_str(smp, "sample_kind", "instant")
            if sample_kind not in SAMPLE_KINDS:
                raise InputError(f"unknown sample kind {sample_kind!r} (expected "
                                 f"{' or '.join(SAMPLE_KINDS)})", p)
            segments = read_segments(h5, p, n)
            plan_text = attr_str(h5["plan"], "text") if "plan" in h5 else ""
            plan_kind = attr_str(h5, "plan_kind", "static")
            if plan_kind not in PLAN_KINDS:
                raise InputError(f"attribute 'plan_kind' of / is {plan_kind!r}; expected "
                                 f"{', '.join(PLAN_KINDS)}", p)
            counters = {}
            if "counters" in h5:
                for k in h5["counters"].attrs:
                    v = h5["counters"].attrs[k]
                    counters[k] = (attr_str(h5["counters"], k) if isinstance(v, (bytes, str))
                                   else v.item() if isinstance(v, np.generic) else v)
            truth = None
            if "truth" in h5:
                t = h5["truth"]
                truth = {"params": _read_params_group(t["params"]) if "params" in t else {},
                         "noise": {k[6:]: np.asarray(v, dtype=float) for k, v in t.attrs.items()
                                   if k.startswith("noise_")},
                         "attitudes": (np.asarray(validate.load(t["attitudes"], p), dtype=float)
                                       if "attitudes" in t else None),
                         "effects": json.loads(attr_str(t, "effects", "[]"))}
        except (KeyError, ValueError, TypeError, IndexError, OverflowError) as exc:
            raise InputError(f"malformed raw file: {exc}", p) from None
        except (RuntimeError, OSError) as exc:  # HDF5 refusing its own structure
            raise _structure(exc, p) from None
        rec = Recording(time=time, accel=accel, gyro=gyro, segments=segments, site=site,
                         plan_kind=plan_kind, plan_text=plan_text,
                         serial=attr_str(h5, "unit_serial") or None, units=units,
                         layout=layout, truth=truth, counters=counters,
                         sample_kind=sample_kind, **opt)
    validate.check_recording(rec, p)
    return rec


# ---------------------------------------------------------------------------
# calibrations


def write_calibration(path, res: CalibrationResult, inputs=()) -> None:
    with h5_output(path) as h5:
        write_provenance(h5, "calibration", inputs, res.serial,
                         {"method": res.method, "raw_units": json.dumps(res.raw_units)})
        write_calibration_groups(h5, res)


def write_calibration_groups(h5, res: CalibrationResult, residuals: bool = True) -> None:
    """The groups of a calibration (params, sigma, units, covariance, stats, residuals,
    tables, model, site/layout) into an open file: a calibration file, or a
    diagnosis file (its final model, docs/diagnose.md)."""
    _write_params_group(h5, "params", res.params)
    _write_params_group(h5, "sigma", res.sigma)
    set_attrs(h5.create_group("units"), {k: str(v) for k, v in res.units.items()})
    c = h5.create_group("covariance")
    put(c, "matrix", np.asarray(res.covariance, dtype=float))
    put(c, "order_key", [k for k, _ in res.cov_order], dtype=_STR)
    put(c, "order_index", np.array([i for _, i in res.cov_order], dtype=np.int64))
    set_text(h5.create_group("stats"), "json", json.dumps(res.stats))
    if residuals:  # (a diagnosis file's /residuals are its stages)
        _write_params_group(h5, "residuals", res.residuals)
    tables = h5.create_group("tables")
    for k, v in res.tables.items():
        if isinstance(v, (list, tuple)) and v and isinstance(v[0], str):
            put(tables, k, list(v), dtype=_STR)
        else:
            put(tables, k, np.asarray(v))
    set_text(h5.create_group("model"), "effects", json.dumps(res.model))
    write_site_layout(h5, _site_placeholder(), res.layout)


def _site_placeholder():
    return Site()


CAL_KINDS = ("calibration", "diagnosis")  # a diagnosis file holds its final model's calibration


def read_calibration(path) -> CalibrationResult:
    """Read a calibration (or a diagnosis file's final model), every field
    checked (io/validate.py ``check_calibration``: the model's effects known,
    each parameter they need present, finite and of its shape, K invertible)."""
    p = str(path)
    with open_checked(p, CAL_KINDS) as h5:
        if attr_str(h5, "kind") == "diagnosis" and "params" not in h5:
            raise InputError("a diagnosis file without a calibration of its final model (written "
                             "by an older calib): run calib diagnose again", p)
        try:
            params = _read_params_group(_need(h5, "params", p))
            sigma = _read_params_group(_need(h5, "sigma", p))
            ug = _need(h5, "units", p)
            units = {k: attr_str(ug, k) for k in ug.attrs}
            c = _need(h5, "covariance", p)
            keys = validate.strings(_need(c, "order_key", p), p)
            idx = validate.numeric(validate.load(_need(c, "order_index", p), p),
                                    "/covariance/order_index", p, integer=True)
            if len(keys) != len(idx) or idx.ndim != 1:
                raise InputError("/covariance/order_key and order_index differ in length", p)
            order = [(k, int(i)) for k, i in zip(keys, idx)]
            stats = json.loads(attr_str(_need(h5, "stats", p), "json", "{}"))
            residuals = (_read_params_group(h5["residuals"]) if "residuals" in h5
                         and attr_str(h5, "kind") == "calibration" else {})
            tables = {}
            if "tables" in h5:
                for k, d in h5["tables"].items():
                    if isinstance(d, h5py.Dataset) and d.dtype.kind in "OS":
                        tables[k] = validate.strings(d, p)
                    else:
                        tables[k] = validate.load(d, p)
            model = json.loads(attr_str(h5["model"], "effects", "[]")) if "model" in h5 else []
            _, layout = read_site_layout(h5, p) if "site" in h5 else (None, Layout())
            raw_units = json.loads(attr_str(h5, "raw_units", "{}")) or {
                "accel": "m/s^2", "gyro": "rad/s"}
            cov = validate.load(_need(c, "matrix", p), p)
            method = attr_str(h5, "method")
            serial = attr_str(h5, "unit_serial") or None
        except (KeyError, ValueError, TypeError, IndexError, OverflowError) as exc:
            raise InputError(f"malformed calibration file: {exc}", p) from None
        except (RuntimeError, OSError) as exc:  # HDF5 refusing its own structure
            raise _structure(exc, p) from None
    res = CalibrationResult(method=method, params=params, sigma=sigma, units=units,
                            covariance=cov, cov_order=order, stats=stats, residuals=residuals,
                            tables=tables, model=model, raw_units=raw_units, layout=layout,
                            serial=serial)
    validate.check_calibration(res, p)
    return res
