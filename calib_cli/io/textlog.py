"""Foreign-layout text logs: whitespace or CSV, with or without a header, a
column map, declared units, and separate accelerometer and gyro files that
share timestamps (docs/import.md).

Units declared at import: the accelerometer in ``count``, ``m/s^2`` or ``g``
(1 g = 9.80665 m/s^2, standard gravity, not the site's g), the gyro in
``count``, ``rad/s`` or ``deg/s``. Data in g or deg/s is converted to SI
here; counts stay counts (the fit then reports K in counts per SI unit and
biases in counts).
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from calib_cli.data import Recording
from calib_cli.errors import InputError, num
from calib_cli.geometry import Layout
from calib_cli.io.log_segments import (  # noqa: F401  (units re-exported)
    ACCEL_UNITS,
    G0,
    GYRO_UNITS,
    check_time_range,
    convert_units,
    plan_cycles,
    segments_from_column,
    segments_from_detection,
)
from calib_cli.io.plan import Plan
from calib_cli.methods.static_stream import detect_static_arrays

TIME_UNITS = {"s": 1.0, "ms": 1e-3, "us": 1e-6, "ns": 1e-9, "sample": None}
SAMPLE_COUNTERS = ("samples", "n_samples", "sample", "index")
FIELDS = ("time", "ax", "ay", "az", "gx", "gy", "gz", "temp", "segment")
ALIASES = {
    "time": ("time", "t", "timestamp", "time_s"),
    "ax": ("ax", "acc_x", "accx", "accel_x"), "ay": ("ay", "acc_y", "accy", "accel_y"),
    "az": ("az", "acc_z", "accz", "accel_z"),
    "gx": ("gx", "gyr_x", "gyro_x", "gyrx"), "gy": ("gy", "gyr_y", "gyro_y", "gyry"),
    "gz": ("gz", "gyr_z", "gyro_z", "gyrz"),
    "temp": ("temp", "temperature"), "segment": ("segment", "part"),
}


def _sniff(path: str, delimiter: str, header: str):
    """The first data-or-header line of a delimited text log, for the pyarrow
    readers: (separator, column count, names or None, data offset in bytes, line
    number of the first data row), or None when the file needs the reference reader
    (unreadable, empty, not UTF-8, whitespace-separated, repeated column names)."""
    try:
        fh = open(path, "rb")
    except OSError:
        return None
    with fh:
        offset, lineno = 0, 0
        while True:
            raw = fh.readline()
            if not raw:
                return None
            lineno += 1
            try:
                first = raw.decode("utf-8").strip()
            except UnicodeDecodeError:
                return None
            if first and not first.startswith(("#", "%")):
                break
            offset += len(raw)
    seps = {"comma": ",", "semicolon": ";", "tab": "\t", "whitespace": None}
    if delimiter == "auto":
        sep = next((s for s in (",", ";", "\t") if s in first), None)
    else:
        sep = seps.get(delimiter)
    if sep is None:
        return None
    cells0 = [c.strip() for c in first.split(sep)]
    has_header = any(not _is_number(c) for c in cells0) if header == "auto" else header == "yes"
    names = cells0 if has_header else None
    if names is not None and len(set(names)) != len(names):
        return None
    if has_header:
        return sep, len(cells0), names, offset + len(raw), lineno + 1
    return sep, len(cells0), names, offset, lineno


def _read_text_arrow(path: str, delimiter: str, header: str):
    """read_text with pyarrow's reader: (names, cells (N, k) float, line
    numbers), or None whenever the file needs the reference reader (no
    pyarrow, whitespace-separated, comment or blank lines in the body, a cell
    that is not a number, NaN): that reader then gives the data or the exact
    error message."""
    from calib_cli.io.csvlog import CommentFilter, have_pyarrow

    if not have_pyarrow():
        return None
    import pyarrow as pa
    import pyarrow.csv as pacsv

    sniff = _sniff(path, delimiter, header)
    if sniff is None:
        return None
    sep, k, names, start, body_line = sniff

    class _NoHash:
        def update(self, b):
            pass

    stream = CommentFilter(path, start, b"", _NoHash())
    cols = [f"c{i}" for i in range(k)]
    try:
        table = pacsv.read_csv(
            stream, read_options=pacsv.ReadOptions(column_names=cols, block_size=8 << 20),
            parse_options=pacsv.ParseOptions(delimiter=sep, quote_char=False),
            convert_options=pacsv.ConvertOptions(column_types={c: pa.float64() for c in cols},
                                                 strings_can_be_null=False, null_values=[],
                                                 quoted_strings_can_be_null=False))
    except (pa.ArrowInvalid, pa.ArrowTypeError):
        return None
    finally:
        stream.close()
    if stream.removed or table.num_rows == 0:
        return None
    cells = np.column_stack([table.column(i).to_numpy() for i in range(len(cols))])
    if not np.isfinite(cells).all():
        return None
    return names, cells, np.arange(len(cells)) + body_line


def read_text(path: str, delimiter: str = "auto", header: str = "auto", fast: bool = True):
    """(column names or None, cells (N, k) array of str, line numbers (N,)).

    delimiter: auto (comma, semicolon or tab if the first data line has one,
    else whitespace), comma, semicolon, tab, whitespace. header: auto (the
    first non-comment line is a header when any cell is not a number), yes, no.
    ``fast``: try pyarrow's reader first (cells then float, not str).
    """
    if fast:
        got = _read_text_arrow(path, delimiter, header)
        if got is not None:
            return got
    try:
        text = Path(path).read_text(encoding="utf-8")
    except FileNotFoundError:
        raise InputError("no such file", path) from None
    except UnicodeDecodeError as exc:
        from calib_cli.io.sniff import not_a_text_log

        raise InputError(not_a_text_log(path, exc), path) from None
    except OSError as exc:
        raise InputError(f"cannot read: {exc}", path) from None
    lines = [(i + 1, ln.strip()) for i, ln in enumerate(text.splitlines())]
    lines = [(i, ln) for i, ln in lines if ln and not ln.startswith(("#", "%"))]
    if not lines:
        raise InputError("no data lines", path)
    first = lines[0][1]
    seps = {"comma": ",", "semicolon": ";", "tab": "\t", "whitespace": None}
    if delimiter == "auto":
        sep = next((s for s in (",", ";", "\t") if s in first), None)
    elif delimiter in seps:
        sep = seps[delimiter]
    else:
        raise InputError(f"unknown delimiter {delimiter!r}; use auto, comma, semicolon, tab "
                         "or whitespace", path)

    def split(ln):
        return [c.strip() for c in ln.split(sep)] if sep else ln.split()

    cells0 = split(first)
    if header == "auto":
        has_header = any(not _is_number(c) for c in cells0)
    else:
        has_header = header == "yes"
    names = cells0 if has_header else None
    body = lines[1:] if has_header else lines
    if not body:
        raise InputError("no data rows", path)
    k = len(cells0)
    rows = []
    for lineno, ln in body:
        c = split(ln)
        if len(c) != k:
            raise InputError(f"line {lineno}: {len(c)} cells, expected {k}", path)
        rows.append(c)
    if names is not None and len(set(names)) != len(names):
        raise InputError(f"duplicate column names in header: {names}", path)
    return names, np.array(rows, dtype=object), np.array([i for i, _ in body])


def _is_number(s: str) -> bool:
    try:
        float(s)
        return True
    except ValueError:
        return False


def parse_column_map(spec: str | None, path: str = "") -> dict:
    """"time=t,ax=acc_x,ay=3" -> {"time": "t", "ax": "acc_x", "ay": 3}; a
    number is a column position counting from 1."""
    out = {}
    if not spec:
        return out
    for part in spec.split(","):
        if not part.strip():
            continue
        if "=" not in part:
            raise InputError(f"column map entry {part.strip()!r} must be FIELD=COLUMN "
                             f"(fields: {', '.join(FIELDS)})", path)
        key, val = (x.strip() for x in part.split("=", 1))
        if key not in FIELDS:
            raise InputError(f"unknown field {key!r} in the column map; fields: "
                             f"{', '.join(FIELDS)}", path)
        out[key] = int(val) if val.isdigit() else val
    return out


def _default_map(names, k: int, role: str) -> dict:
    """Field -> column for a file without a column map."""
    if names is not None:
        low = [n.lower() for n in names]
        out = {}
        for field, al in ALIASES.items():
            hit = next((a for a in al if a in low), None)
            if hit is not None:
                out[field] = names[low.index(hit)]
        if "time" not in out:  # a sample counter: time = counter / --rate
            hit = next((a for a in SAMPLE_COUNTERS if a in low), None)
            if hit is not None:
                out["time"] = names[low.index(hit)]
                out["_time_unit"] = "sample"
        if role in ("accel", "gyro") and not any(f in out for f in ("ax", "gx")):
            # a separate file with generic names: time + three axes
            pre = "a" if role == "accel" else "g"
            rest = [n for n in names if n != out.get("time")]
            if len(rest) == 3:
                out.update({pre + ax: n for ax, n in zip("xyz", rest, strict=False)})
        return out
    layouts = {
        "both": {7: ("time", "ax", "ay", "az", "gx", "gy", "gz"),
                 6: ("ax", "ay", "az", "gx", "gy", "gz"),
                 4: ("time", "ax", "ay", "az"), 3: ("ax", "ay", "az")},
        "accel": {4: ("time", "ax", "ay", "az"), 3: ("ax", "ay", "az")},
        "gyro": {4: ("time", "gx", "gy", "gz"), 3: ("gx", "gy", "gz")},
    }[role]
    if k not in layouts:
        return {}
    return {f: i + 1 for i, f in enumerate(layouts[k])}


def _column(names, cells, lines, ref, field, path, numeric=True):
    if isinstance(ref, int):
        if not 1 <= ref <= cells.shape[1]:
            raise InputError(f"column {ref} for {field!r} does not exist: the file has "
                             f"{cells.shape[1]} columns", path)
        j = ref - 1
    else:
        if names is None or ref not in names:
            have = f"columns: {', '.join(names)}" if names else "the file has no header"
            raise InputError(f"no column {ref!r} for {field!r} ({have})", path)
        j = names.index(ref)
    col = cells[:, j]
    if not numeric:
        return col
    try:
        out = col.astype(float)
    except ValueError:
        for i, c in enumerate(col):
            if not _is_number(c):
                raise InputError(f"line {lines[i]}, column {ref!r}: not a number: {c!r}",
                                 path) from None
        raise
    if not np.all(np.isfinite(out)):
        i = int(np.flatnonzero(~np.isfinite(out))[0])
        raise InputError(f"line {lines[i]}, column {ref!r}: {col[i]} (NaN or infinite values "
                         "are not allowed)", path)
    return out


def read_segments_json(path: str, plan: Plan, n: int) -> np.ndarray:
    """Per-sample plan segment index from {label: {"start": i, "end": j}} or
    {label: [i, j]} (sample indices, end exclusive; imucal's session lists)."""
    try:
        raw = json.loads(Path(path).read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InputError("no such file", path) from None
    except (OSError, ValueError) as exc:
        raise InputError(f"cannot read segment list: {exc}", path) from None
    labels = [s.label for s in plan.segments]
    seg = np.full(n, -1)
    if not isinstance(raw, dict):
        raise InputError("segment list must be a JSON object {label: {start, end}}", path)
    for label, v in raw.items():
        if label not in labels:
            raise InputError(f"segment {label!r} is not in the plan (plan labels: "
                             f"{', '.join(labels)})", path)
        try:
            a, b = (v["start"], v["end"]) if isinstance(v, dict) else v
            a, b = int(a), int(b)
        except (KeyError, TypeError, ValueError):
            raise InputError(f"segment {label!r}: expected {{\"start\": i, \"end\": j}}",
                             path) from None
        if not 0 <= a < b <= n:
            raise InputError(f"segment {label!r}: [{a}, {b}) outside the {n} samples", path)
        seg[a:b] = labels.index(label)
    return seg


def import_text(acc_path, plan: Plan, gyro_path=None, columns: str | None = None,
                gyro_columns: str | None = None, accel_units: str = "m/s^2",
                gyro_units: str = "rad/s", rate: float | None = None, time_unit: str = "s",
                delimiter: str = "auto", header: str = "auto", sort: bool = False,
                segments_json: str | None = None, window_s: float = 1.0,
                multiplier: float = 3.0, min_static_s: float = 1.0) -> Recording:
    """A foreign-layout text log (one file, or accelerometer + gyro files) -> Recording."""
    acc_path = str(acc_path)
    from calib_cli.plan import plan_layout

    layout = plan_layout(plan)
    if layout.redundant:
        raise InputError("text import handles triads; a redundant unit needs the contract CSV",
                         acc_path)
    if time_unit not in TIME_UNITS:
        raise InputError(f"unknown time unit {time_unit!r}; use one of {', '.join(TIME_UNITS)}",
                         acc_path)
    names, cells, lines = read_text(acc_path, delimiter, header)
    cmap = parse_column_map(columns, acc_path) or _default_map(
        names, cells.shape[1], "accel" if gyro_path else "both")
    if "segment" in cmap and cells.dtype != object:  # labels or indices: the text reader
        names, cells, lines = read_text(acc_path, delimiter, header, fast=False)
    if not all(f in cmap for f in ("ax", "ay", "az")):
        raise InputError(f"cannot tell which columns hold ax, ay, az ({cells.shape[1]} columns"
                         f"{', header ' + ' '.join(names) if names else ', no header'}): give "
                         "--columns, e.g. time=1,ax=2,ay=3,az=4", acc_path)
    if cmap.pop("_time_unit", None) == "sample" and time_unit == "s":
        time_unit = "sample"  # the default map found a sample counter, not a time
    n = len(cells)

    def get(f, **kw):
        return _column(names, cells, lines, cmap[f], f, acc_path, **kw) if f in cmap else None

    accel = np.column_stack([get(f) for f in ("ax", "ay", "az")])
    t = get("time")
    temp = get("temp")
    seg_col = get("segment", numeric=False)
    gyro = None
    if all(f in cmap for f in ("gx", "gy", "gz")):
        gyro = np.column_stack([get(f) for f in ("gx", "gy", "gz")])
    if gyro_path is not None:
        gyro_path = str(gyro_path)
        gnames, gcells, glines = read_text(gyro_path, delimiter, header)
        gmap = parse_column_map(gyro_columns, gyro_path) or _default_map(
            gnames, gcells.shape[1], "gyro")
        if not all(f in gmap for f in ("gx", "gy", "gz")):
            raise InputError("cannot tell which columns hold gx, gy, gz: give --gyro-columns, "
                             "e.g. time=1,gx=2,gy=3,gz=4", gyro_path)
        if len(gcells) != n:
            raise InputError(f"{len(gcells)} rows, but the accelerometer file {acc_path} has {n}: "
                             "separate files must share their timestamps row by row", gyro_path)
        gyro = np.column_stack([_column(gnames, gcells, glines, gmap[f], f, gyro_path)
                                for f in ("gx", "gy", "gz")])
        if "time" in gmap and t is not None:
            gt = _column(gnames, gcells, glines, gmap["time"], "time", gyro_path)
            tol = 1e-6 * max(1.0, float(np.max(np.abs(t))))
            bad = np.flatnonzero(np.abs(gt - t) > tol)
            if len(bad):
                i = int(bad[0])
                raise InputError(f"line {glines[i]}: time {num(gt[i])} differs from the "
                                 f"accelerometer file's {num(t[i])}: the files must share "
                                 "timestamps", gyro_path)
    # time in seconds
    scale = TIME_UNITS[time_unit]
    if t is None or scale is None:
        if not rate or rate <= 0:
            what = "no time column" if t is None else "time in samples"
            raise InputError(f"{what}: give the sample rate with --rate HZ", acc_path)
        t = (np.arange(n, dtype=float) if t is None else t) / rate
    else:
        t = t * scale
    check_time_range(t, acc_path, "; give the clock's unit with --time-unit (s, ms, us, ns)")
    if n > 1 and np.any(np.diff(t) <= 0):
        if sort:
            order = np.argsort(t, kind="stable")
            t, accel = t[order], accel[order]
            gyro = None if gyro is None else gyro[order]
            temp = None if temp is None else temp[order]
            seg_col = None if seg_col is None else seg_col[order]
            lines = lines[order]
        if np.any(np.diff(t) <= 0):
            i = int(np.flatnonzero(np.diff(t) <= 0)[0])
            hint = "" if sort else " (--sort orders the rows by time)"
            raise InputError(f"time is not increasing at line {lines[i + 1]} ({num(t[i])} then "
                             f"{num(t[i + 1])}){hint}", acc_path)
    accel, gyro, units = convert_units(accel, gyro, accel_units, gyro_units, acc_path)

    if segments_json is not None:
        seg = read_segments_json(str(segments_json), plan, n)
        segments = segments_from_column(seg, plan, str(segments_json))
    elif seg_col is not None:
        segments = segments_from_column(_segment_indices(seg_col, plan, lines, acc_path), plan,
                                        acc_path)
    else:
        report = detect_static_arrays(t, accel, gyro, window_s, multiplier, min_static_s)
        cycles = plan_cycles(plan, t, gyro, None)
        segments = segments_from_detection(report, plan, n, acc_path, cycles)
    if not segments:
        raise InputError("no segments found in the data", acc_path)
    return Recording(time=t, accel=accel, gyro=gyro, segments=tuple(segments), site=plan.site,
                     plan_kind=plan.kind, plan_text=plan.text, serial=plan.serial, units=units,
                     layout=Layout(), temp=temp)


def _segment_indices(col, plan: Plan, lines, path) -> np.ndarray:
    """A segment column of plan indices or plan labels (empty or -1: between)."""
    labels = {s.label: i for i, s in enumerate(plan.segments)}
    out = np.empty(len(col), dtype=int)
    for i, c in enumerate(col):
        if c in labels:
            out[i] = labels[c]
        elif c in ("", "-1"):
            out[i] = -1
        else:
            try:
                out[i] = int(c)
            except ValueError:
                raise InputError(f"line {lines[i]}: segment {c!r} is neither a plan label nor "
                                 f"an index (plan labels: {', '.join(labels)})", path) from None
    return out


# ---------------------------------------------------------------------------
# streaming (issue 19): the common layout goes block by block into the raw
# file (io/stream_import.py); anything else, and every error, takes the
# in-memory path above, which gives the data or the exact message.


class _NotStreamable(Exception):
    """The streamed reader does not take this file or these options."""


def _text_stream_plan(path: str, columns, delimiter: str, header: str, rate, time_unit: str):
    """(separator, data offset, column names, field -> column index, time unit,
    rate) for pyarrow's streaming reader, or _NotStreamable."""
    sniff = _sniff(path, delimiter, header)
    if sniff is None:
        raise _NotStreamable
    sep, k, names, start, _line = sniff
    try:  # a bad column map: the in-memory path gives its error after the file's own
        cmap = parse_column_map(columns, path) or _default_map(names, k, "both")
    except InputError:
        raise _NotStreamable from None
    if "segment" in cmap or not all(f in cmap for f in ("ax", "ay", "az")):
        raise _NotStreamable
    if cmap.pop("_time_unit", None) == "sample" and time_unit == "s":
        time_unit = "sample"
    idx = {}
    for f, ref in cmap.items():
        if isinstance(ref, int):
            if not 1 <= ref <= k:
                raise _NotStreamable
            idx[f] = ref - 1
        else:
            if names is None or ref not in names:
                raise _NotStreamable
            idx[f] = names.index(ref)
    scale = TIME_UNITS.get(time_unit, 0.0)
    if (scale is None or "time" not in idx) and (not rate or rate <= 0):
        raise _NotStreamable  # the in-memory path asks for --rate
    return sep, start, k, idx, scale


def _text_chunks_arrow(path, sep, start, k, idx, scale, rate):
    """Chunks of a delimited text log through pyarrow; _NotStreamable on
    anything unusual (a comment or blank-only line in the body, a cell that is
    not a number, NaN, time not increasing)."""
    import pyarrow as pa
    import pyarrow.csv as pacsv

    from calib_cli.io.csvlog import ARROW_BLOCK, STREAM_ROWS, USE_THREADS, Assembler

    names = [f"c{i}" for i in range(k)]
    stream = pa.OSFile(path)
    stream.seek(start)
    try:
        reader = pacsv.open_csv(
            stream, read_options=pacsv.ReadOptions(column_names=names, block_size=ARROW_BLOCK,
                                                   use_threads=USE_THREADS),
            parse_options=pacsv.ParseOptions(delimiter=sep, quote_char=False),
            convert_options=pacsv.ConvertOptions(column_types={c: pa.float64() for c in names},
                                                 strings_can_be_null=False, null_values=[],
                                                 quoted_strings_can_be_null=False))
    except (pa.ArrowInvalid, pa.ArrowTypeError):
        stream.close()
        raise _NotStreamable from None
    # the chunk layout of csvlog: (time, accel, gyro, optional, segment) column indices;
    # a time column computed from the row number is appended as column k
    ti = idx.get("time", k)
    gi = [idx[f] for f in ("gx", "gy", "gz")] if all(f in idx for f in ("gx", "gy", "gz")) \
        else None
    cols = (ti, [idx[f] for f in ("ax", "ay", "az")], gi,
            {"temp": idx["temp"]} if "temp" in idx else {}, None)
    asm = Assembler(cols)
    t_last, n = None, 0
    try:
        while True:
            try:
                batch = reader.read_next_batch()
            except StopIteration:
                break
            except (pa.ArrowInvalid, pa.ArrowTypeError):
                raise _NotStreamable from None
            data = [batch.column(i).to_numpy(zero_copy_only=False) for i in range(k)]
            m = len(data[0])
            if not m:
                continue
            if not all(np.isfinite(c).all() for c in data):
                raise _NotStreamable
            # time in seconds, as import_text computes it
            if "time" not in idx:
                t = np.arange(n, n + m, dtype=float) / rate
            elif scale is None:
                t = data[ti] / rate
            else:
                t = data[ti] * scale
            if (t_last is not None and t[0] <= t_last) or np.any(t[1:] <= t[:-1]):
                raise _NotStreamable  # the in-memory path: the error, or --sort
            data.append(t)
            if ti != k:
                data[ti] = t
            t_last = t[-1]
            n += m
            asm.add(data)
            while asm.n >= STREAM_ROWS:
                yield asm.take(STREAM_ROWS)
        if n == 0:
            raise _NotStreamable  # "no data rows", from the in-memory path
        if asm.n:
            yield asm.take(asm.n)
    finally:
        stream.close()


def import_text_to_raw(out, acc_path, plan: Plan, gyro_path=None, columns: str | None = None,
                       gyro_columns: str | None = None, accel_units: str = "m/s^2",
                       gyro_units: str = "rad/s", rate: float | None = None,
                       time_unit: str = "s", delimiter: str = "auto", header: str = "auto",
                       sort: bool = False, segments_json: str | None = None,
                       window_s: float = 1.0, multiplier: float = 3.0,
                       min_static_s: float = 1.0, inputs=(), sample_kind: str = "instant"):
    """``import_text`` written to the raw file ``out``: (samples, units,
    segments). A single delimited file without --sort, --segments or a
    segment column is streamed block by block (memory independent of its
    length) when pyarrow is installed; anything else, and any problem in the
    file, goes through ``import_text`` in memory, which gives the same data
    or the exact error message (line numbers included)."""
    from calib_cli.io.csvlog import have_pyarrow

    acc_path = str(acc_path)
    streamable = (gyro_path is None and not sort and segments_json is None and have_pyarrow()
                  and time_unit in TIME_UNITS and not plan_is_redundant(plan))
    if streamable:
        from calib_cli.io.csvlog import FileHash
        from calib_cli.io.stream_import import import_to_raw, prefetch

        try:
            sep, start, k, idx, scale = _text_stream_plan(acc_path, columns, delimiter, header,
                                                          rate, time_unit)
            fh = FileHash(acc_path)  # the provenance's SHA-256, by a thread meanwhile
            res = import_to_raw(out, prefetch(_text_chunks_arrow(acc_path, sep, start, k, idx,
                                                                 scale, rate)),
                                plan, acc_path, inputs, window_s, multiplier, min_static_s,
                                accel_units, gyro_units, sample_kind=sample_kind,
                                hashes=lambda: {acc_path: fh.hexdigest()})
            return res.n, res.units, res.segments
        except _NotStreamable:
            pass
    from calib_cli.io.h5 import write_raw

    rec = import_text(acc_path, plan, gyro_path, columns, gyro_columns, accel_units, gyro_units,
                      rate, time_unit, delimiter, header, sort, segments_json, window_s,
                      multiplier, min_static_s)
    rec = rec.with_(sample_kind=sample_kind)
    write_raw(out, rec, inputs)
    return len(rec), rec.units, rec.segments


def plan_is_redundant(plan: Plan) -> bool:
    from calib_cli.plan import plan_layout

    return plan_layout(plan).redundant
