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
from calib_cli.errors import InputError
from calib_cli.geometry import Layout
from calib_cli.io import validate
from calib_cli.io.escape import line_text
from calib_cli.model.earth import Site

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
    h5.attrs["kind"] = kind
    h5.attrs["format_version"] = FORMAT_VERSION
    h5.attrs["tool"] = "calib"
    h5.attrs["tool_version"] = __version__
    h5.attrs["command"] = " ".join([Path(sys.argv[0]).name] + sys.argv[1:])
    h5.attrs["created_utc"] = datetime.now(timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")
    h5.attrs["unit_serial"] = serial or ""
    hashes = {str(p): sha256_file(p) for p in inputs if p and Path(p).is_file()}
    h5.attrs["input_sha256"] = json.dumps(hashes)
    for k, v in (extra or {}).items():
        h5.attrs[k] = v
    if kind in ("calibration", "diagnosis"):  # a fit carries its data's origin on
        copy_source(h5, inputs)


# ---------------------------------------------------------------------------
# the samples' origin: /source (docs/file-formats.md; io/imu_logs.py fills it)

SOURCE_JSON = ("parameters", "parameters_changed", "device_ids")


def write_source(h5, source: dict) -> None:
    """/source: where the samples come from and whether the device had already
    corrected them ("samples": "raw", "corrected" or "unknown") and by which
    parameters; dicts and lists as JSON text."""
    g = h5.require_group("source")
    for k, v in source.items():
        if v is None:
            continue
        g.attrs[k] = json.dumps(v) if isinstance(v, (dict, list, tuple)) else v


def _read_source_group(g) -> dict:
    out = {}
    for k, v in g.attrs.items():
        v = v.decode() if isinstance(v, bytes) else (v.item() if isinstance(v, np.generic) else v)
        if k in SOURCE_JSON and isinstance(v, str):
            try:
                v = json.loads(v)
            except ValueError:
                raise InputError(f"/source/{k} is not valid JSON", g.file.filename) from None
        out[k] = v
    return out


def read_source(path) -> dict:
    """The /source of a raw, calibration or diagnosis file ({} when it has none:
    a CSV import, a simulation)."""
    p = str(path)
    with h5py.File(p, "r") as h5:
        return _read_source_group(h5["source"]) if "source" in h5 else {}


def copy_source(h5, inputs) -> None:
    """The /source of the first input that has one (the fitted raw file)."""
    for p in inputs:
        try:
            if not (p and Path(p).is_file() and h5py.is_hdf5(p)):
                continue
            with h5py.File(p, "r") as src:
                if "source" in src:
                    write_source(h5, _read_source_group(src["source"]))
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
    kind = _attr_str(h5, "kind")
    if kind not in kinds:
        h5.close()
        what = f"a {kind!r} file" if kind else "not a calib file (no 'kind' attribute)"
        raise InputError(f"{what}; expected {' or '.join(repr(k) for k in kinds)}", p)
    try:
        check_untrusted_h5(h5, p)
        # calib_cli/io/validate.py (issue 15): version parsed, each dataset's declared size
        validate.format_version(h5, p, FORMAT_VERSION)
        validate.check_declared_sizes(h5, p)
    except (KeyError, RuntimeError, OSError, ValueError, TypeError) as exc:
        h5.close()  # HDF5 refuses its own damaged metadata this way: bad input, not a bug
        raise InputError(f"damaged HDF5 structure ({str(exc).split('(')[0].strip()})",
                         p) from None
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
        return _attr_str(h5, "kind")


def _attr_str(h5, name, default=""):
    v = h5.attrs.get(name, default)
    return v.decode() if isinstance(v, bytes) else str(v)


def provenance(path) -> dict:
    """Root attributes of a calib file as a dict of plain values."""
    with open_checked(path, KINDS) as h5:
        out = {}
        for k, v in h5.attrs.items():
            if isinstance(v, bytes):
                v = v.decode()
            elif isinstance(v, np.generic):
                v = v.item()
            out[k] = v
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
    g.create_dataset("label", data=[s.label for s in segments], dtype=_STR)
    g.create_dataset("kind", data=[s.kind for s in segments], dtype=_STR)
    g["start"] = np.array([s.start for s in segments], dtype=np.int64)
    g["stop"] = np.array([s.stop for s in segments], dtype=np.int64)
    g["plan_index"] = np.array([s.plan_index for s in segments], dtype=np.int64)
    for name in ("attitude", "table_axis_enu", "lever_arm", "rotation_axis_body"):
        g[name] = np.array([_vec_or_nan(getattr(s, name)) for s in segments]).reshape(-1, 3)
    for name in ("attitude_sigma", "table_rate", "rotation_angle"):
        g[name] = np.array([np.nan if getattr(s, name) is None else getattr(s, name)
                            for s in segments], dtype=float)


def read_segments(h5, path) -> tuple[Segment, ...]:
    g = _need(h5, "segments", path)
    try:
        labels = [x.decode() if isinstance(x, bytes) else x for x in g["label"][()]]
        kinds = [x.decode() if isinstance(x, bytes) else x for x in g["kind"][()]]
        cols = {k: g[k][()] for k in ("start", "stop", "plan_index", "attitude", "table_axis_enu",
                                      "lever_arm", "rotation_axis_body", "attitude_sigma",
                                      "table_rate", "rotation_angle")}
    except KeyError as exc:
        raise InputError(f"missing field /segments/{exc.args[0]}", path) from None
    out = []
    for i, label in enumerate(labels):
        out.append(Segment(label=label, kind=kinds[i], start=int(cols["start"][i]),
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
        v = np.asarray(v, dtype=float)
        g.create_dataset(k, data=v, fletcher32=bool(v.ndim and v.size))


def _read_params_group(g) -> dict:
    return {k: np.asarray(validate.load(g[k], g.file.filename), dtype=float) for k in g}


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
        lay["el0"] = layout.el0
        lay["az0"] = layout.az0


def read_site_layout(h5, path) -> tuple[Site, Layout]:
    s = _need(h5, "site", path)
    g = float(s.attrs.get("g", np.nan))
    site = Site(latitude=float(s.attrs.get("latitude", 0.0)),
                height=float(s.attrs.get("height", 0.0)), g=None if np.isnan(g) else g)
    lay = h5.get("layout")
    if lay is None:
        return site, Layout()
    el0 = lay["el0"][()] if "el0" in lay else None
    az0 = lay["az0"][()] if "az0" in lay else None
    return site, Layout(n=int(lay.attrs.get("n", 3)), el0=el0, az0=az0,
                        n_cycles=int(lay.attrs.get("n_cycles", 0)))


def write_raw(path, rec: Recording, inputs=(), kind: str = "raw") -> None:
    """Write a recording atomically (kind "raw", or "corrected" for apply's output).
    Its content is validated first (io/validate.py): a NaN, a time going back
    is an error naming the input it came from."""
    validate.check_recording(rec, str(inputs[0]) if inputs else str(path))
    with atomic_path(path) as tmp, h5py.File(tmp, "w") as h5:
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
        smp.attrs["accel_units"] = rec.units.get("accel", "m/s^2")
        smp.attrs["gyro_units"] = rec.units.get("gyro", "rad/s")
        smp.attrs["sample_kind"] = rec.sample_kind
        write_segments(h5, rec.segments)
        write_site_layout(h5, rec.site, rec.layout)
        h5.create_group("plan").attrs["text"] = rec.plan_text
        if rec.counters:
            c = h5.create_group("counters")
            for k, v in rec.counters.items():
                c.attrs[k] = v
        if rec.truth is not None:
            t = h5.create_group("truth")
            _write_params_group(t, "params", rec.truth.get("params", {}))
            for k, v in rec.truth.get("noise", {}).items():
                t.attrs["noise_" + k] = np.asarray(v, dtype=float)
            if rec.truth.get("attitudes") is not None:
                t["attitudes"] = np.asarray(rec.truth["attitudes"], dtype=float)
            t.attrs["effects"] = json.dumps(rec.truth.get("effects", []))


def read_raw(path, kinds=("raw", "corrected")) -> Recording:
    """Read a raw (or corrected) recording, fully into memory."""
    p = str(path)
    with open_checked(p, kinds) as h5:
        try:
            smp = _need(h5, "samples", p)
            n = validate.check_samples_layout(smp, p)
            validate.check_segments_layout(h5, p, n)
            time = np.asarray(validate.load(smp["time"], p), dtype=float)
            accel = np.asarray(validate.load(smp["accel"], p), dtype=float)
            gyro = (np.asarray(validate.load(smp["gyro"], p), dtype=float) if "gyro" in smp
                    else None)
            opt = {k: np.asarray(validate.load(smp[k], p), dtype=float) if k in smp else None
                   for k in SAMPLE_FIELDS}
            units = {"accel": _attr_str(smp, "accel_units", "m/s^2"),
                     "gyro": _attr_str(smp, "gyro_units", "rad/s")}
            sample_kind = _attr_str(smp, "sample_kind", "instant")
            if sample_kind not in SAMPLE_KINDS:
                raise InputError(f"unknown sample kind {sample_kind!r} (expected "
                                 f"{' or '.join(SAMPLE_KINDS)})", p)
            segments = read_segments(h5, p)
            site, layout = read_site_layout(h5, p)
            plan_text = _attr_str(h5["plan"], "text") if "plan" in h5 else ""
            counters = {k: (v.item() if isinstance(v, np.generic) else v)
                        for k, v in h5["counters"].attrs.items()} if "counters" in h5 else {}
            truth = None
            if "truth" in h5:
                t = h5["truth"]
                truth = {"params": _read_params_group(t["params"]) if "params" in t else {},
                         "noise": {k[6:]: np.asarray(v) for k, v in t.attrs.items()
                                   if k.startswith("noise_")},
                         "attitudes": t["attitudes"][()] if "attitudes" in t else None,
                         "effects": json.loads(_attr_str(t, "effects", "[]"))}
        except (KeyError, ValueError, TypeError, IndexError, OverflowError) as exc:
            raise InputError(f"malformed raw file: {exc}", p) from None
        n = len(time)
        if accel.ndim != 2 or accel.shape[0] != n or (gyro is not None and gyro.shape[0] != n):
            raise InputError("samples/accel and samples/gyro must have one row per time", p)
        for s in segments:
            if not (0 <= s.start <= s.stop <= n):
                raise InputError(f"segment {s.label!r} points outside the samples", p)
        rec = Recording(time=time, accel=accel, gyro=gyro, segments=segments, site=site,
                         plan_kind=_attr_str(h5, "plan_kind", "static"), plan_text=plan_text,
                         serial=_attr_str(h5, "unit_serial") or None, units=units,
                         layout=layout, truth=truth, counters=counters,
                         sample_kind=sample_kind, **opt)
    validate.check_recording(rec, p)
    return rec


# ---------------------------------------------------------------------------
# calibrations


def write_calibration(path, res: CalibrationResult, inputs=()) -> None:
    with atomic_path(path) as tmp, h5py.File(tmp, "w") as h5:
        write_provenance(h5, "calibration", inputs, res.serial,
                         {"method": res.method, "raw_units": json.dumps(res.raw_units)})
        write_calibration_groups(h5, res)


def write_calibration_groups(h5, res: CalibrationResult, residuals: bool = True) -> None:
    """The groups of a calibration (params, sigma, units, covariance, stats, residuals,
    tables, model, site/layout) into an open file: a calibration file, or a
    diagnosis file (its final model, docs/diagnose.md)."""
    _write_params_group(h5, "params", res.params)
    _write_params_group(h5, "sigma", res.sigma)
    u = h5.create_group("units")
    for k, v in res.units.items():
        u.attrs[k] = v
    c = h5.create_group("covariance")
    c["matrix"] = np.asarray(res.covariance, dtype=float)
    c.create_dataset("order_key", data=[k for k, _ in res.cov_order], dtype=_STR)
    c["order_index"] = np.array([i for _, i in res.cov_order], dtype=np.int64)
    h5.create_group("stats").attrs["json"] = json.dumps(res.stats)
    if residuals:  # (a diagnosis file's /residuals are its stages)
        _write_params_group(h5, "residuals", res.residuals)
    tables = h5.create_group("tables")
    for k, v in res.tables.items():
        if isinstance(v, (list, tuple)) and v and isinstance(v[0], str):
            tables.create_dataset(k, data=list(v), dtype=_STR)
        else:
            tables[k] = np.asarray(v)
    h5.create_group("model").attrs["effects"] = json.dumps(res.model)
    write_site_layout(h5, _site_placeholder(), res.layout)


def _site_placeholder():
    return Site()


CAL_KINDS = ("calibration", "diagnosis")  # a diagnosis file holds its final model's calibration


def read_calibration(path) -> CalibrationResult:
    p = str(path)
    with open_checked(p, CAL_KINDS) as h5:
        if _attr_str(h5, "kind") == "diagnosis" and "params" not in h5:
            raise InputError("a diagnosis file without a calibration of its final model (written "
                             "by an older calib): run calib diagnose again", p)
        try:
            params = _read_params_group(_need(h5, "params", p))
            sigma = _read_params_group(_need(h5, "sigma", p))
            units = {k: (v.decode() if isinstance(v, bytes) else str(v))
                     for k, v in _need(h5, "units", p).attrs.items()}
            c = _need(h5, "covariance", p)
            order = [(k.decode() if isinstance(k, bytes) else k, int(i))
                     for k, i in zip(c["order_key"][()], c["order_index"][()])]
            stats = json.loads(_attr_str(_need(h5, "stats", p), "json", "{}"))
            residuals = (_read_params_group(h5["residuals"]) if "residuals" in h5
                         and _attr_str(h5, "kind") == "calibration" else {})
            tables = {}
            if "tables" in h5:
                for k, d in h5["tables"].items():
                    v = d[()]
                    if d.dtype.kind in "OS":
                        v = [x.decode() if isinstance(x, bytes) else x for x in v]
                    tables[k] = v
            model = json.loads(_attr_str(h5["model"], "effects", "[]")) if "model" in h5 else []
            _, layout = read_site_layout(h5, p) if "site" in h5 else (None, Layout())
            raw_units = json.loads(_attr_str(h5, "raw_units", "{}")) or {
                "accel": "m/s^2", "gyro": "rad/s"}
            cov = validate.load(_need(c, "matrix", p), p)
        except (KeyError, ValueError, TypeError, IndexError, OverflowError) as exc:
            raise InputError(f"malformed calibration file: {exc}", p) from None
        return CalibrationResult(method=_attr_str(h5, "method"), params=params, sigma=sigma,
                                 units=units, covariance=cov, cov_order=order,
                                 stats=stats, residuals=residuals, tables=tables, model=model,
                                 raw_units=raw_units, layout=layout,
                                 serial=_attr_str(h5, "unit_serial") or None)
