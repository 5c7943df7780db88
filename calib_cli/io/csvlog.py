"""CSV logs (CONTRACT.md section 4): read, segment, write.

Columns: ``time`` (s); a triad ``ax ay az`` (m/s^2) and ``gx gy gz`` (rad/s),
a redundant unit ``a0 .. a{n-1}`` and ``g0 .. g{n-1}``; optional ``temp``
(degC), ``table_angle`` (rad), ``table_rate`` (rad/s), ``segment`` (index
into the plan's segments, -1 between segments). Lines starting with ``#``
are comments; the first other line names the columns.
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from calib_cli.data import Recording
from calib_cli.errors import InputError, num
from calib_cli.geometry import Layout
from calib_cli.io.log_segments import (  # noqa: F401  (re-exported: the CSV's segments)
    TIME_MAX,
    Chunk,
    check_time_range,
    plan_cycles,
    segments_from_column,
    segments_from_detection,
)
from calib_cli.io.plan import Plan
from calib_cli.io.sniff import not_a_text_log
from calib_cli.methods.static_detect import detect_static
from calib_cli.plan import plan_layout

OPTIONAL = ("temp", "table_angle", "table_rate")
SEG_MAX = 2**31  # a segment index beyond this is no index (and would overflow an int)


def _read_table(path: str):
    """(header names, float array (N, k)) with errors that name row and column."""
    try:
        text = Path(path).read_text(encoding="utf-8")
    except FileNotFoundError:
        raise InputError("no such file", path) from None
    except UnicodeDecodeError as exc:
        raise InputError(not_a_text_log(path, exc), path) from None
    except OSError as exc:
        raise InputError(f"cannot read: {exc}", path) from None
    lines = text.splitlines()
    body_start, header = None, None
    for i, line in enumerate(lines):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        header = [c.strip() for c in s.split(",")]
        body_start = i + 1
        break
    if header is None:
        raise InputError("empty file (no header line)", path)
    if len(set(header)) != len(header):
        raise InputError(f"duplicate column names in header: {header}", path)
    rows = [(i + 1, ln) for i, ln in enumerate(lines[body_start:], start=body_start)
            if ln.strip() and not ln.lstrip().startswith("#")]
    if not rows:
        raise InputError("no data rows after the header", path)
    try:
        data = np.loadtxt(io.StringIO("\n".join(r for _, r in rows)), delimiter=",", ndmin=2)
        if data.shape[1] != len(header):
            raise ValueError
    except ValueError:
        for lineno, r in rows:  # find the exact cell, for the message
            cells = r.split(",")
            if len(cells) != len(header):
                raise InputError(f"line {lineno}: {len(cells)} cells, header has "
                                 f"{len(header)}", path) from None
            for name, c in zip(header, cells):
                try:
                    float(c)
                except ValueError:
                    raise InputError(f"line {lineno}, column {name!r}: not a number: "
                                     f"{c.strip()!r}", path) from None
        raise InputError("unreadable numeric data", path) from None
    bad = ~np.isfinite(data)
    if bad.any():
        r, c = np.argwhere(bad)[0]
        raise InputError(f"line {rows[r][0]}, column {header[c]!r}: {num(data[r, c])} (NaN or "
                         "infinite values are not allowed)", path)
    return header, data


def read_columns(path: str, layout: Layout):
    """Time, accel, gyro, optional columns and segment index from a contract CSV."""
    header, data = _read_table(path)
    it, ia, ig, iopt, iseg = _layout_columns(header, layout, path)
    t = data[:, it]
    check_time_range(t, path)
    if len(t) > 1 and np.any(np.diff(t) <= 0):
        i = int(np.flatnonzero(np.diff(t) <= 0)[0])
        raise InputError(f"time is not increasing at data row {i + 2} "
                         f"({num(t[i])} then {num(t[i + 1])})", path)
    accel = data[:, ia]
    gyro = None if ig is None else data[:, ig]
    opt = {k: data[:, iopt[k]] if k in iopt else None for k in OPTIONAL}
    seg = None if iseg is None else data[:, iseg]
    if seg is not None and np.any(seg != np.round(seg)):
        raise InputError("column 'segment' must hold integers", path)
    if seg is not None and np.any(np.abs(seg) > SEG_MAX):
        v = seg[np.flatnonzero(np.abs(seg) > SEG_MAX)[0]]
        raise InputError(f"segment index {num(v)} out of range: segment indices are 0..N-1 "
                         "for the plan's N segments (-1 between segments)", path)
    return t, accel, gyro, opt, None if seg is None else seg.astype(int)


def import_csv(path, plan: Plan, window_s: float = 1.0, multiplier: float = 3.0,
               min_static_s: float = 1.0, units: dict | None = None) -> Recording:
    """A contract CSV and its plan -> Recording. Raises InputError naming the file."""
    path = str(path)
    layout = plan_layout(plan)
    t, accel, gyro, opt, seg = read_columns(path, layout)
    if seg is not None:
        segments = segments_from_column(seg, plan, path)
    else:
        report = detect_static(t, accel, gyro, window_s, multiplier, min_static_s)
        cycles = plan_cycles(plan, t, gyro, opt.get("table_rate"))
        segments = segments_from_detection(report, plan, len(t), path, cycles)
    if not segments:
        raise InputError("no segments found in the data", path)
    n_cycles = sum(1 for s in segments if s.kind == "rotating")
    layout = Layout(layout.n, layout.el0, layout.az0, n_cycles)
    return Recording(time=t, accel=accel, gyro=gyro, segments=tuple(segments), site=plan.site,
                     plan_kind=plan.kind, plan_text=plan.text, serial=plan.serial,
                     units=units or {"accel": "m/s^2", "gyro": "rad/s"}, layout=layout,
                     temp=opt["temp"], table_angle=opt["table_angle"],
                     table_rate=opt["table_rate"])


def write_csv(path, rec: Recording) -> None:
    """The contract's CSV columns, with the segment index of each sample."""
    from calib_cli.io.h5 import atomic_path

    n = len(rec)
    seg = np.full(n, -1)
    for s in rec.segments:
        seg[s.start:s.stop] = s.plan_index
    if rec.layout.redundant:
        names = [f"a{i}" for i in range(rec.layout.n)] + [f"g{i}" for i in range(rec.layout.n)]
    else:
        names = ["ax", "ay", "az", "gx", "gy", "gz"]
    cols = [rec.time, rec.accel, rec.gyro]
    for k in OPTIONAL:
        v = getattr(rec, k)
        if v is not None:
            names.append(k)
            cols.append(np.nan_to_num(v))
    names.append("segment")
    cols.append(seg)
    table = np.column_stack([np.asarray(c, dtype=float).reshape(n, -1) for c in cols])
    with atomic_path(path) as tmp:
        with open(tmp, "w", encoding="utf-8") as fh:
            fh.write(f"# calib simulated log; plan kind {rec.plan_kind}; serial {rec.serial or ''}\n")
            fh.write(",".join(["time"] + names) + "\n")
            fmt = ["%.6f"] + ["%.12g"] * (table.shape[1] - 2) + ["%d"]
            np.savetxt(fh, table, delimiter=",", fmt=fmt)


# ---------------------------------------------------------------------------
# streaming import (docs/import.md): the log is read block by block into the
# raw file; memory does not grow with the log's length.

STREAM_ROWS = 65536  # rows per block of the pure-Python reader
ARROW_BLOCK = 1 << 20  # bytes per block of the pyarrow reader (its default; larger blocks
# are no faster and its readahead then holds hundreds of MB)
USE_THREADS = True


class _Fallback(Exception):
    """The fast reader met something it does not handle exactly as the
    reference reader does: start again with the reference reader."""


def _stream_header(path: str):
    """(column names, byte offset of the line after the header, header bytes)."""
    try:
        fh = open(path, "rb")
    except FileNotFoundError:
        raise InputError("no such file", path) from None
    except OSError as exc:
        raise InputError(f"cannot read: {exc}", path) from None
    with fh:
        consumed = b""
        while True:
            raw = fh.readline()
            if not raw:
                raise InputError("empty file (no header line)", path)
            consumed += raw
            try:
                s = raw.decode("utf-8").strip()
            except UnicodeDecodeError as exc:
                raise InputError(not_a_text_log(path, exc), path) from None
            if not s or s.startswith("#"):
                continue
            header = [c.strip() for c in s.split(",")]
            if len(set(header)) != len(header):
                raise InputError(f"duplicate column names in header: {header}", path)
            return header, len(consumed), consumed


def _layout_columns(header, layout: Layout, path: str):
    """Column indices of time, accel, gyro (None), optional, segment; the
    missing-column errors of ``read_columns``."""
    idx = {name: i for i, name in enumerate(header)}
    if "time" not in idx:
        raise InputError("missing column 'time'", path)
    if layout.redundant:
        an = [f"a{i}" for i in range(layout.n)]
        gn = [f"g{i}" for i in range(layout.n)]
    else:
        an, gn = ["ax", "ay", "az"], ["gx", "gy", "gz"]
    missing = [c for c in an if c not in idx]
    if missing:
        raise InputError(f"missing column{'s' * (len(missing) > 1)} {', '.join(missing)}", path)
    gmiss = [c for c in gn if c not in idx]
    if gmiss and len(gmiss) < len(gn):
        raise InputError(f"missing column{'s' * (len(gmiss) > 1)} {', '.join(gmiss)}", path)
    return (idx["time"], [idx[c] for c in an], None if gmiss else [idx[c] for c in gn],
            {k: idx[k] for k in OPTIONAL if k in idx}, idx.get("segment"))


def _chunk(data_cols, cols):
    ti, ai, gi, oi, si = cols
    return Chunk(time=data_cols[ti], accel=np.column_stack([data_cols[i] for i in ai]),
                 gyro=None if gi is None else np.column_stack([data_cols[i] for i in gi]),
                 opt={k: data_cols[i] for k, i in oi.items()},
                 segment=None if si is None else data_cols[si])


class CommentFilter:
    """A read-only byte stream over the log from the line after the header,
    without comment lines (first non-blank character ``#``) and blank lines;
    it hashes every byte of the file on the way (the provenance's SHA-256)."""

    def __init__(self, path, offset, head, hasher):
        self.fh = open(path, "rb")
        self.fh.seek(offset)
        self.hasher = hasher
        hasher.update(head)
        self.tail = b""
        self.closed = False
        self.removed = 0  # lines dropped (comments, blank lines)

    def readable(self):
        return True

    def seekable(self):
        return False

    def writable(self):
        return False

    def read(self, size=-1):
        while True:
            chunk = self.fh.read(size if size and size > 0 else ARROW_BLOCK)
            if not chunk:
                out, self.tail = self.tail, b""
                return self._filter(out) if out else b""
            self.hasher.update(chunk)
            data = self.tail + chunk
            cut = data.rfind(b"\n") + 1
            if cut == 0:  # no complete line yet
                self.tail = data
                continue
            out, self.tail = data[:cut], data[cut:]
            out = self._filter(out)
            if out:
                return out

    def _filter(self, data: bytes) -> bytes:
        if b"#" not in data and b"\n\n" not in data and not data.startswith(b"\n"):
            return data
        lines = data.split(b"\n")
        if not lines[-1]:
            lines.pop()
        keep = [ln for ln in lines if ln.strip() and not ln.lstrip().startswith(b"#")]
        self.removed += len(lines) - len(keep)
        return b"\n".join(keep) + b"\n" if keep else b""

    def close(self):
        self.fh.close()
        self.closed = True


SEGMENT = 4 << 20  # bytes of the log per pyarrow reader on the direct path


def _segments(path, offset, hasher):
    """The log's body after ``offset`` in pieces of at most ``SEGMENT`` bytes,
    each cut after a newline (the last one at the end of the file), as
    memoryviews of one reused buffer: a piece is valid until the next is asked
    for. Every byte of the file goes through ``hasher`` (the provenance's
    SHA-256) on the way: the file is read once, into memory that is reused
    (pyarrow's own reading thread would read it into fresh buffers, and a
    hashing thread would read it again)."""
    buf = bytearray(SEGMENT)
    mv = memoryview(buf)
    with open(path, "rb", buffering=0) as fh:
        head = b""
        while len(head) < offset:
            more = fh.read(offset - len(head))
            if not more:
                break
            head += more
        hasher.update(head)
        carry = 0
        while True:
            k = fh.readinto(mv[carry:]) if carry < SEGMENT else 0
            if k:
                hasher.update(mv[carry:carry + k])
            tot = carry + k
            if not tot:
                return
            cut = buf.rfind(b"\n", 0, tot) + 1 if k else tot
            if not cut:
                if tot < SEGMENT:  # a short read: read on
                    carry = tot
                    continue
                raise _Fallback("a line longer than a segment")
            yield mv[:cut]
            rest = tot - cut
            buf[:rest] = buf[cut:tot]
            carry = rest
            if not k:
                return


class Assembler:
    """pyarrow's record batches (about 1 MB of text each) regrouped into chunks
    of exactly ``CHUNK_ROWS`` rows (the raw file's HDF5 chunk: whole chunks are
    written once, never read back and rewritten), one copy per value."""

    def __init__(self, cols):
        self.cols = cols  # (time, accel, gyro, optional, segment) column indices
        self.pending: list[list[np.ndarray]] = []
        self.n = 0

    def add(self, data):
        self.pending.append(data)
        self.n += len(data[0])

    def take(self, m):
        """A chunk of the first m pending rows."""
        ti, ai, gi, oi, si = self.cols
        t = np.empty(m)
        acc = np.empty((m, len(ai)))
        gyr = None if gi is None else np.empty((m, len(gi)))
        opt = {k: np.empty(m) for k in oi}
        seg = None if si is None else np.empty(m)
        off = 0
        while off < m:
            data = self.pending[0]
            k = min(len(data[0]), m - off)
            sl = slice(off, off + k)
            t[sl] = data[ti][:k]
            for j, i in enumerate(ai):
                acc[sl, j] = data[i][:k]
            if gi is not None:
                for j, i in enumerate(gi):
                    gyr[sl, j] = data[i][:k]
            for name, i in oi.items():
                opt[name][sl] = data[i][:k]
            if si is not None:
                seg[sl] = data[si][:k]
            if k == len(data[0]):
                self.pending.pop(0)
            else:
                self.pending[0] = [c[k:] for c in data]
            off += k
        self.n -= m
        return Chunk(time=t, accel=acc, gyro=gyr, opt=opt, segment=seg)


class FileHash:
    """SHA-256 of a whole file, computed by a background thread while the
    import reads it (hashlib releases the GIL on large blocks)."""

    def __init__(self, path):
        import hashlib
        import threading

        self.h = hashlib.sha256()
        self.err = None
        self.th = threading.Thread(target=self._run, args=(path,), daemon=True)
        self.th.start()

    def _run(self, path):
        try:
            with open(path, "rb") as fh:
                for block in iter(lambda: fh.read(1 << 20), b""):
                    self.h.update(block)
        except OSError as exc:  # pragma: no cover - the file vanished mid-import
            self.err = exc

    def hexdigest(self):
        self.th.join()
        return None if self.err else self.h.hexdigest()


def _arrow_batches(stream, header):
    """The record batches of one pyarrow reader over ``stream`` (none for an
    empty one); _Fallback on anything else it does not take."""
    import pyarrow as pa
    import pyarrow.csv as pacsv

    try:
        reader = pacsv.open_csv(
            stream,
            read_options=pacsv.ReadOptions(column_names=header, block_size=ARROW_BLOCK,
                                           use_threads=USE_THREADS),
            parse_options=pacsv.ParseOptions(delimiter=",", quote_char=False),
            convert_options=pacsv.ConvertOptions(
                column_types={h: pa.float64() for h in header}, strings_can_be_null=False,
                quoted_strings_can_be_null=False, null_values=[]))
    except pa.ArrowInvalid as exc:
        if "Empty CSV file" in str(exc):
            return
        raise _Fallback(str(exc)) from None
    while True:
        try:
            batch = reader.read_next_batch()
        except StopIteration:
            return
        except (pa.ArrowInvalid, pa.ArrowTypeError) as exc:
            raise _Fallback(str(exc)) from None
        yield batch


def _arrow_chunks(path, header, offset, head, cols, hasher, direct=False):
    """The pyarrow reader: yields chunks; raises _Fallback on anything unusual.

    ``direct``: the body of the log, from the line after the header, read in
    pieces (``_segments``, hashed on the way) that pyarrow parses from
    memory; any comment or blank-only line in the body is a parse error,
    hence a _Fallback to the filtering stream (``CommentFilter``)."""
    if direct:
        import pyarrow as pa

        def batches():
            for piece in _segments(path, offset, hasher):
                yield from _arrow_batches(pa.BufferReader(pa.py_buffer(piece)), header)
                del piece  # the reader is done with the buffer before it is reused

        stream = None
        source = batches()
    else:
        stream = CommentFilter(path, offset, head, hasher)
        source = _arrow_batches(stream, header)
    t_last = None
    ti, si = cols[0], cols[4]
    asm = Assembler(cols)
    rows = 0
    try:
        for batch in source:
            data = [batch.column(i).to_numpy(zero_copy_only=False) for i in range(len(header))]
            if not len(data[0]):
                continue
            # one reduction per column; the exact test only when the sums are not finite
            # (NaN or inf anywhere, or an overflow of the sum)
            if not np.isfinite(sum(float(np.add.reduce(c)) for c in data)) and \
                    not all(np.isfinite(c).all() for c in data):
                raise _Fallback("non-finite")
            t = data[ti]
            if (t_last is not None and t[0] <= t_last) or np.any(t[1:] <= t[:-1]):
                raise _Fallback("time")
            if si is not None and np.any(data[si] != np.round(data[si])):
                raise _Fallback("segment")
            t_last = t[-1]
            rows += len(t)
            asm.add(data)
            while asm.n >= STREAM_ROWS:  # pyarrow's blocks are small: write in larger ones
                yield asm.take(STREAM_ROWS)
        if asm.n:
            yield asm.take(asm.n)
        if not rows:
            raise InputError("no data rows after the header", path)
    finally:
        source.close()
        if stream is not None:
            stream.close()


def _text_chunks(path, header, cols_or_error, hasher=None):
    """The reference reader, streamed: every error exactly as ``_read_table``
    and ``read_columns`` give it, in the same order of precedence."""
    try:
        fh = open(path, encoding="utf-8", newline=None)
    except OSError as exc:
        raise InputError(f"cannot read: {exc}", path) from None
    k = len(header)
    nonfinite = None  # first NaN/inf cell (an unreadable cell anywhere takes precedence)
    time_err = seg_err = None
    t_last, n_rows = None, 0
    seen_header = False
    rows: list[tuple[int, str]] = []

    def parse(rows):
        try:
            data = np.loadtxt(io.StringIO("\n".join(r for _, r in rows)), delimiter=",", ndmin=2)
            if data.shape[1] != k:
                raise ValueError
        except ValueError:
            for lineno, r in rows:
                cells = r.split(",")
                if len(cells) != k:
                    raise InputError(f"line {lineno}: {len(cells)} cells, header has {k}",
                                     path) from None
                for name, c in zip(header, cells):
                    try:
                        float(c)
                    except ValueError:
                        raise InputError(f"line {lineno}, column {name!r}: not a number: "
                                         f"{c.strip()!r}", path) from None
            raise InputError("unreadable numeric data", path) from None
        return data

    def block(rows):
        nonlocal nonfinite, time_err, seg_err, t_last, n_rows
        data = parse(rows)
        bad = ~np.isfinite(data)
        if bad.any() and nonfinite is None:
            r, c = np.argwhere(bad)[0]
            nonfinite = (f"line {rows[r][0]}, column {header[c]!r}: {num(data[r, c])} (NaN or "
                         "infinite values are not allowed)")
        if nonfinite is None and not isinstance(cols_or_error, InputError):
            ti, si = cols_or_error[0], cols_or_error[4]
            t = data[:, ti]
            tt = t if t_last is None else np.concatenate([[t_last], t])
            if time_err is None and len(tt) > 1 and np.any(np.diff(tt) <= 0):
                i = int(np.flatnonzero(np.diff(tt) <= 0)[0])
                gi = n_rows + i - (t_last is not None)
                time_err = (f"time is not increasing at data row {gi + 2} "
                            f"({num(tt[i])} then {num(tt[i + 1])})")
            t_last = t[-1]
            if si is not None and seg_err is None and np.any(data[:, si] != np.round(data[:, si])):
                seg_err = "column 'segment' must hold integers"
        n_rows += len(data)
        return data

    with fh:
        try:
            for i, line in enumerate(fh):
                if hasher is not None:
                    hasher.update(line.encode("utf-8"))
                s = line.strip()
                if not seen_header:
                    if s and not s.startswith("#"):
                        seen_header = True
                    continue
                if not s or line.lstrip().startswith("#"):
                    continue
                rows.append((i + 1, line.rstrip("\n")))
                if len(rows) >= STREAM_ROWS:
                    data = block(rows)
                    rows = []
                    if not (nonfinite or time_err or seg_err
                            or isinstance(cols_or_error, InputError)):
                        yield _chunk([data[:, j] for j in range(k)], cols_or_error)
        except UnicodeDecodeError as exc:
            raise InputError(not_a_text_log(path, exc), path) from None
        if rows:
            data = block(rows)
            if not (nonfinite or time_err or seg_err or isinstance(cols_or_error, InputError)):
                yield _chunk([data[:, j] for j in range(k)], cols_or_error)
    if n_rows == 0:
        raise InputError("no data rows after the header", path)
    for err in (nonfinite, cols_or_error if isinstance(cols_or_error, InputError) else None,
                time_err, seg_err):
        if err is not None:
            raise err if isinstance(err, InputError) else InputError(err, path)


def have_pyarrow() -> bool:
    try:
        import pyarrow.csv  # noqa: F401
    except ImportError:
        return False
    return True


def import_csv_stream(path, plan: Plan, out, inputs=(), window_s: float = 1.0,
                      multiplier: float = 3.0, min_static_s: float = 1.0,
                      accel_units: str = "m/s^2", gyro_units: str = "rad/s",
                      fast: bool | None = None, sample_kind: str = "instant", progress=None):
    """A contract CSV and its plan -> raw file ``out``, streamed (pyarrow's
    reader when installed, ``calib-cli[fast]``, else the pure-Python one; the
    same data and the same error messages either way). Returns ImportSummary.
    progress: optional callback ``progress(chunks_read)`` after each chunk."""
    import hashlib

    from calib_cli.io.stream_import import import_to_raw, prefetch

    path = str(path)
    layout = plan_layout(plan)
    header, offset, head = _stream_header(path)
    try:
        cols = _layout_columns(header, layout, path)
    except InputError as exc:
        cols = exc
    use_fast = have_pyarrow() if fast is None else fast
    kw = dict(window_s=window_s, multiplier=multiplier, min_static_s=min_static_s,
              accel_units=accel_units, gyro_units=gyro_units, sample_kind=sample_kind)
    if use_fast and not isinstance(cols, InputError):
        # pyarrow parsing the log read in pieces (_segments); on a comment line (or
        # anything else it does not take exactly as the reference reader does) through
        # the comment filter; then the reference reader
        hasher = hashlib.sha256()
        try:
            return import_to_raw(out, _counted(prefetch(_arrow_chunks(path, header, offset, head,
                                                                      cols, hasher, direct=True)),
                                               progress),
                                 plan, path, inputs, hashes=lambda: {path: hasher.hexdigest()},
                                 **kw)
        except _Fallback:
            pass
        hasher = hashlib.sha256()
        try:
            return import_to_raw(out, _counted(prefetch(_arrow_chunks(path, header, offset, head, cols,
                                                             hasher)), progress),
                                 plan, path, inputs,
                                 hashes=lambda: {path: hasher.hexdigest()}, **kw)
        except _Fallback:
            pass
    return import_to_raw(out, _counted(_text_chunks(path, header, cols), progress), plan, path,
                         inputs, **kw)


def _counted(chunks, progress):
    """The chunks, calling progress(number read so far) after each."""
    if progress is None:
        yield from chunks
        return
    for i, c in enumerate(chunks, 1):
        yield c
        progress(i)
