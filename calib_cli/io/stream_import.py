"""The import pipeline every log format shares: blocks of samples in, a raw
HDF5 file out, with memory bounded by the block size (docs/import.md).

A *source* is an iterable of ``Chunk`` (time, accel, gyro, optional columns,
segment index) in time order. ``import_to_raw`` writes the samples into
chunked, resizable datasets as they come, then finds the segments (from the
segment column's runs, or by the streaming static detection fed as it
writes, whose passes are done on the way, ``methods.static_stream.OnlineFloors``:
nothing is stored per row, and the moving std is computed again from the file
only when its bracket missed a floor) and matches them to the plan exactly
as ``import csv`` always has (``csvlog.segments_from_detection``). CSV, text,
bag, ULog and DataFlash imports all go through here.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field, replace
from pathlib import Path

import h5py
import numpy as np

from calib_cli.data import Segment
from calib_cli.errors import InputError
from calib_cli.geometry import Layout
from calib_cli.io import validate
from calib_cli.io.h5 import (
    sha256_file,
    write_provenance,
    write_segments,
    write_site_layout,
    write_source,
)
from calib_cli.io.h5file import h5_output, set_attrs, set_text
from calib_cli.io.log_segments import (
    Chunk,
    check_time_range,
    convert_units,
    plan_cycles,
    segments_from_column,
    segments_from_detection,
)
from calib_cli.methods.static_stream import OnlineFloors, StreamDetector
from calib_cli.plan import Plan, plan_layout  # noqa: F401  (plan_layout re-exported)

CHUNK_ROWS = 65536
READ_ROWS = 1 << 18
OPTIONAL = ("temp", "table_angle", "table_rate")


@dataclass
class ImportSummary:
    n: int
    segments: tuple[Segment, ...]
    units: dict
    counters: dict = field(default_factory=dict)


class _Sink:
    """Resizable chunked datasets in /samples, appended block by block.

    Rows are written in whole HDF5 chunks (``CHUNK_ROWS``): a partial chunk
    waits for the next block, so no chunk is written, read back through its
    checksum and written again; ``flush()`` writes the last partial chunk."""

    def __init__(self, smp: h5py.Group):
        self.smp = smp
        self.ds: dict[str, h5py.Dataset] = {}
        self.tail: dict[str, np.ndarray] = {}
        self.n = 0

    def _ds(self, name, width):
        if name not in self.ds:
            shape = (0,) if width is None else (0, width)
            maxshape = (None,) if width is None else (None, width)
            chunks = (CHUNK_ROWS,) if width is None else (CHUNK_ROWS, width)
            # Fletcher-32 on every chunk: a damaged file is an error, not data (issue 15)
            self.ds[name] = self.smp.create_dataset(name, shape=shape, maxshape=maxshape,
                                                    chunks=chunks, dtype="f8", fletcher32=True)
        return self.ds[name]

    def append(self, name, arr):
        arr = np.asarray(arr, dtype=float)
        d = self._ds(name, None if arr.ndim == 1 else arr.shape[1])
        tail = self.tail.pop(name, None)
        have = d.shape[0] + (0 if tail is None else len(tail))
        if have < self.n:  # a column absent from earlier blocks: zeros there, as resize gives
            gap = np.zeros((self.n - have,) + arr.shape[1:])
            tail = gap if tail is None else np.concatenate([tail, gap])
        if tail is not None:
            arr = np.concatenate([tail, arr])
        m = len(arr) // CHUNK_ROWS * CHUNK_ROWS
        if m < len(arr):
            self.tail[name] = np.array(arr[m:])
        if m:
            self._write(d, arr[:m])

    @staticmethod
    def _write(d, arr):
        k = d.shape[0]
        d.resize(k + len(arr), axis=0)
        d[k:k + len(arr)] = arr

    def flush(self):
        for name, arr in self.tail.items():
            self._write(self.ds[name], arr)
        self.tail.clear()

    def times(self, rows=READ_ROWS):
        """Fresh iterator of the time blocks alone: views of one buffer that
        the next block overwrites (no fresh memory per block)."""
        t = self.ds["time"]
        buf = np.empty(min(rows, self.n))
        for i in range(0, self.n, rows):
            out = buf[:min(self.n, i + rows) - i]
            t.read_direct(out, np.s_[i:i + len(out)])
            yield out

    def blocks(self, rows=READ_ROWS):
        """Fresh iterator of (t, accel, gyro) blocks of what was written."""
        t, a = self.ds["time"], self.ds["accel"]
        g = self.ds.get("gyro")
        for i in range(0, self.n, rows):
            j = min(self.n, i + rows)
            yield t[i:j], a[i:j], (g[i:j] if g is not None else None)


class _SegRuns:
    """Runs of the segment column, block by block."""

    def __init__(self):
        self.vals, self.starts = [], []
        self.last = None

    def feed(self, seg, off):
        seg = np.asarray(seg)
        if not len(seg):
            return
        starts = np.concatenate([[0], np.flatnonzero(np.diff(seg)) + 1])
        for s in starts.tolist():
            v = int(seg[s])
            if s == 0 and self.last == v:
                continue  # the run goes on from the previous block
            self.vals.append(v)
            self.starts.append(int(off + s))
        self.last = int(seg[-1])


def prefetch(source: Iterable[Chunk], depth: int = 3) -> Iterator[Chunk]:
    """``source`` iterated by a background thread, at most ``depth`` chunks
    ahead: a reader that releases the GIL (pyarrow's) parses the next blocks
    while this thread writes and detects (memory: ``depth`` chunks more).
    Its exceptions are raised here, in order; closing this iterator (or an
    exception here) stops the thread and closes ``source`` there."""
    import queue
    import threading

    q: queue.Queue = queue.Queue(maxsize=depth)
    stop = threading.Event()
    end = object()

    def put(item):
        while not stop.is_set():
            try:
                q.put(item, timeout=0.1)
                return True
            except queue.Full:
                continue
        return False

    def run():
        it = iter(source)
        try:
            for ch in it:
                if not put((ch, None)):
                    break
            else:
                put((end, None))
        except BaseException as exc:  # handed over to the consumer
            put((None, exc))
        finally:
            close = getattr(it, "close", None)
            if close is not None:
                close()

    th = threading.Thread(target=run, name="calib-import-reader", daemon=True)
    th.start()
    try:
        while True:
            item, exc = q.get()
            if exc is not None:
                raise exc
            if item is end:
                return
            yield item
    finally:
        stop.set()
        th.join()


def segments_from_runs(vals, starts, n, plan: Plan, path: str):
    """csvlog.segments_from_column, from the runs of the column."""
    if not vals:
        return []
    vals = np.asarray(vals)
    starts = np.asarray(starts)
    stops = np.concatenate([starts[1:], [n]])
    # one entry per run: segments_from_column checks the indices and makes the labels
    segs = segments_from_column(vals, plan, path)
    runs = [(int(a), int(b)) for v, a, b in zip(vals, starts, stops) if v >= 0]
    out = [replace(s, start=a, stop=b) for s, (a, b) in zip(segs, runs)]
    return out


_ALLOCATOR_TUNED = False


def keep_freed_memory() -> None:
    """On glibc, keep freed memory in the process for reuse (``mallopt``):
    every block of the import allocates and frees the same few arrays of a
    few MB, and by default glibc maps them fresh (or trims the heap and
    grows it again) each time, so that the kernel zeroes every page again:
    about half the page faults of an import. Peak memory is unchanged (the
    freed blocks are those the next block reuses). Elsewhere: nothing."""
    global _ALLOCATOR_TUNED
    if _ALLOCATOR_TUNED:
        return
    _ALLOCATOR_TUNED = True
    import sys

    if not sys.platform.startswith("linux"):
        return
    try:
        import ctypes

        libc = ctypes.CDLL("libc.so.6")
        M_TRIM_THRESHOLD, M_MMAP_THRESHOLD = -1, -3
        libc.mallopt(M_MMAP_THRESHOLD, 64 << 20)
        libc.mallopt(M_TRIM_THRESHOLD, 256 << 20)
    except (OSError, AttributeError):  # not glibc (musl, ...)
        pass


def import_to_raw(out, source: Iterable[Chunk], plan: Plan, path: str, inputs=(),
                  window_s: float = 1.0, multiplier: float = 3.0, min_static_s: float = 1.0,
                  accel_units: str = "m/s^2", gyro_units: str = "rad/s",
                  hashes: Callable[[], dict] | None = None, counters: dict | None = None,
                  check: Callable[[_Sink, list], None] | None = None,
                  sample_kind: str = "instant", provenance: dict | None = None) -> ImportSummary:
    """Stream ``source`` into the raw file ``out`` (written atomically).

    ``path`` names the log in error messages; ``inputs`` are hashed into the
    provenance (``hashes()`` may supply hashes already computed while
    streaming); ``check(sink, segments)`` may veto the segments (gap checks) and returns
    counters to record. ``source`` is closed on return (a generator's ``close``).
    ``counters`` and ``provenance`` (the samples' origin, /source: h5.write_source)
    are written as they are once ``source`` is exhausted (a reader fills them in).
    """
    keep_freed_memory()
    try:
        return _import_to_raw(out, source, plan, path, inputs, window_s, multiplier,
                              min_static_s, accel_units, gyro_units, hashes, counters, check,
                              sample_kind, provenance)
    finally:
        close = getattr(source, "close", None)
        if close is not None:  # a reader thread (``prefetch``) stops now, not at exit
            close()


def _import_to_raw(out, source, plan, path, inputs, window_s, multiplier, min_static_s,
                   accel_units, gyro_units, hashes, counters, check, sample_kind,
                   provenance=None):

    layout = plan_layout(plan)
    units = convert_units(np.zeros((1, 3)), np.zeros((1, 3)), accel_units, gyro_units, path)[2]
    with h5_output(out) as h5:
        smp = h5.create_group("samples")
        sink = _Sink(smp)
        runs = None
        # the detection's passes over the moving std done while it is computed (no spill)
        det = StreamDetector(window_s, OnlineFloors(multiplier))
        for ch in source:
            m = len(ch.time)
            if not m:
                continue
            if (accel_units, gyro_units) == ("m/s^2", "rad/s"):
                a, g = ch.accel, ch.gyro  # SI already: no copy
            else:
                a, g, _ = convert_units(ch.accel, ch.gyro, accel_units, gyro_units, path)
            check_time_range(ch.time, path)  # 1e20 s: one line, exit 3 (issue 15)
            # a cell of 1e300 is no sample: exit 3 naming it (issue 37)
            validate.check_magnitudes(np.asarray(a), "accel", units["accel"], path, sink.n)
            if g is not None:
                validate.check_magnitudes(np.asarray(g), "gyro", units["gyro"], path, sink.n)
            sink.append("time", ch.time)
            sink.append("accel", a)
            if runs is None and ch.segment is None:
                det.feed(ch.time, a, g)
            if g is not None:
                sink.append("gyro", g)
            for k in OPTIONAL:
                if ch.opt.get(k) is not None:
                    sink.append(k, ch.opt[k])
            if ch.segment is not None:
                runs = runs or _SegRuns()
                runs.feed(ch.segment, sink.n)
            sink.n += m
        sink.flush()
        n = sink.n
        if n == 0:
            raise InputError("no samples", path)
        if runs is not None:
            segments = segments_from_runs(runs.vals, runs.starts, n, plan, path)
        else:
            report = det.result(sink.blocks, multiplier, min_static_s, times=sink.times)
            cycles = None
            if "gyro" in sink.ds and any(s.kind == "rotating" for s in plan.segments):
                # rotation cycles (methods/cycle_detect.py) work on the whole record: a
                # turntable plan without a segment column reads time and gyro back in full
                tr = sink.ds["table_rate"][()] if "table_rate" in sink.ds else None
                cycles = plan_cycles(plan, sink.ds["time"][()], sink.ds["gyro"][()], tr)
            segments = segments_from_detection(report, plan, n, path, cycles)
        if not segments:
            raise InputError("no segments found in the data", path)
        counters = dict(counters or {})
        if check is not None:
            counters.update(check(sink, segments) or {})
        n_cycles = sum(1 for s in segments if s.kind == "rotating")
        layout = Layout(layout.n, layout.el0, layout.az0, n_cycles)
        write_provenance(h5, "raw", [], plan.serial, {"plan_kind": plan.kind})
        known = hashes() if hashes else {}
        set_text(h5, "input_sha256", json.dumps(
            {str(p): known.get(str(p)) or sha256_file(p) for p in inputs if p and Path(p).is_file()}))
        set_attrs(smp, {"accel_units": units["accel"], "gyro_units": units["gyro"],
                        "sample_kind": sample_kind})
        write_segments(h5, segments)
        write_site_layout(h5, plan.site, layout)
        set_text(h5.create_group("plan"), "text", plan.text)
        if counters:
            set_attrs(h5.create_group("counters"), counters)
        if provenance:
            write_source(h5, provenance)
    return ImportSummary(n, tuple(segments), units, counters)
