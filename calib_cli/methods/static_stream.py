"""Static-interval detection over a record that does not fit in memory.

The same rule as ``static_detect.detect_static`` (docs/import.md), fed block
by block: ``blocks()`` returns a fresh iterator over consecutive
``(t, accel, gyro_or_None)`` blocks of the record (from the HDF5 file being
written, for instance), and the detector makes a few passes over it, keeping
only a decimated moving-std series and a bracket of values around the
quantiles it needs:

1. the sample period ``dt``: the exact median of ``diff(t)`` (time only);
2. the noise floor of every axis: the exact 10th percentile of the moving
   standard deviation, bracketed from a decimated series of it and then
   selected exactly (values inside the bracket are kept, the rest counted);
3. the quiet masks for every threshold multiplier, as runs.

Memory is bounded by the block size, the decimated series (at most
``SAMPLE_ROWS`` rows) and the bracket (at most ``BRACKET_CAP`` values per
axis; a wider bracket is narrowed by a histogram pass first), not by the
record's length. The intervals are those of ``detect_static`` on the whole
record (the moving sums are accumulated per block instead of over the whole
record, a difference of rounding only: tests/test_import_stream.py checks
the boundaries are identical).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Iterator

import numpy as np

from calib_cli.methods.static_detect import (
    DEFAULT_MULTIPLIER,
    FLOOR_QUANTILE,
    MULTIPLIERS,
    DetectionReport,
)

SAMPLE_ROWS = 100_000  # decimated series kept for the bracket
BRACKET_CAP = 1_000_000  # values per axis kept inside a bracket
HIST_BINS = 65536
SUB_ROWS = 65536  # rows per moving-std step of StreamDetector.feed (bounds its buffers)
ONLINE_PAD = 0.10  # OnlineFloors: its first bracket, +- this fraction of the first block's ranks
NARROW_PAD = 0.02  # OnlineFloors: a narrowed bracket, +- this fraction of the rows seen
AMBIGUOUS_CAP = 500_000  # OnlineFloors: rows kept whose level the bracket leaves open
RUNS_CAP = 2_000_000  # OnlineFloors: runs of the level bounds

Blocks = Callable[[], Iterable[tuple]]


class MovingStd:
    """``static_detect.moving_std`` fed block by block: ``feed(x)`` returns the
    rows whose window is complete, ``finish(n)`` the rest (the last windows are
    clipped to the record's end, so they wait for its length).

    The rows come as (m, k) arrays in column-major (Fortran) order: every
    axis's values contiguous, as the passes over them read them. The buffer
    is (k, rows) complex: x - ref in the real part, its square in the
    imaginary part, so that one complex cumulative sum along each row gives
    both moving sums (two independent additions per element in one pass:
    half the time of two real cumulative sums, and the same values)."""

    def __init__(self, w: int):
        self.w = w
        self.buf = None
        self.buf_start = 0
        self.next_out = 0
        self.ref = None

    def _emit(self, i_max, w, n):
        out = _window_std(self.buf, self.buf_start, self.next_out, i_max, w, w // 2, n)
        self.next_out = i_max
        keep = min(max(i_max - w, 0), n - w)  # the last windows reach back to n - w
        self.buf = self.buf[:, keep - self.buf_start:]
        self.buf_start = keep
        return out

    def feed(self, x: np.ndarray, x2: np.ndarray | None = None) -> np.ndarray | None:
        """``x2``: more columns of the same rows (the gyro beside the accelerometer)."""
        parts = [np.asarray(x, dtype=float)] + ([] if x2 is None else [np.asarray(x2, float)])
        parts = [p[:, None] if p.ndim == 1 else p for p in parts]
        m = len(parts[0])
        k = sum(p.shape[1] for p in parts)
        if self.ref is None:
            self.ref = np.concatenate([p.mean(axis=0) for p in parts])  # conditioning
        old = 0 if self.buf is None else self.buf.shape[1]
        buf = np.empty((k, old + m), dtype=complex)
        if old:
            buf[:, :old] = self.buf
        new = buf[:, old:].view(float).reshape(k, m, 2)
        re = new[:, :, 0]
        j = 0
        for p in parts:  # the reference subtracted straight into the buffer, axis by axis
            for c in range(p.shape[1]):
                np.subtract(p[:, c], self.ref[j], out=re[j])
                j += 1
        np.multiply(re, re, out=new[:, :, 1])
        self.buf = buf
        avail = self.buf_start + buf.shape[1]
        w, h = self.w, self.w // 2
        if avail < w:
            return None  # not one full window yet
        i_max = avail - w + h + 1  # windows [i - h, i - h + w) inside what we have
        if i_max <= self.next_out:
            return None
        return self._emit(i_max, w, 10**18)

    def finish(self, n: int) -> np.ndarray | None:
        if self.buf is None or self.next_out >= n:
            return None
        w = max(2, min(self.w, n))
        if w != self.w:  # shorter than one window: nothing was emitted yet
            self.buf_start = 0
        return self._emit(n, w, n)


def moving_std_blocks(xs: Iterable[np.ndarray], w: int, n: int) -> Iterator[np.ndarray]:
    """``static_detect.moving_std`` of the concatenation of ``xs`` (n rows in
    all), yielded block by block."""
    ms = MovingStd(max(2, min(w, n)))
    for x in xs:
        out = ms.feed(x)
        if out is not None and len(out):
            yield out
    out = ms.finish(n)
    if out is not None and len(out):
        yield out


def _window_std(buf, buf_start, i0, i1, w, h, n):
    """Moving standard deviation of the rows [i0, i1) from ``buf`` ((k, rows)
    complex: x - ref and its square), a new (i1 - i0, k) array in column-major
    order."""
    lo = np.clip(np.arange(i0, i1) - h, 0, n - w) - buf_start
    a, b = int(lo[0]), int(lo[-1]) + w
    seg = buf[:, a:b]
    c = np.empty((seg.shape[0], seg.shape[1] + 1), dtype=complex)
    c[:, 0] = 0.0
    np.cumsum(seg, axis=1, out=c[:, 1:])
    lo = lo - a
    if lo[-1] - lo[0] == len(lo) - 1:  # contiguous windows: slices, not gathers (in place)
        j0, j1 = int(lo[0]), int(lo[-1]) + 1
        s = c[:, j0 + w:j1 + w]
        s -= c[:, j0:j1]
    else:
        s = c[:, lo + w] - c[:, lo]
    # var = (s2 - s1^2 / w) / (w - 1) with s1, s2 the moving sums of x and x^2, into a
    # new contiguous array
    out = np.multiply(s.real, s.real)
    out *= 1.0 / w
    np.subtract(s.imag, out, out=out)
    out *= 1.0 / (w - 1)
    np.maximum(out, 0.0, out=out)
    return np.sqrt(out, out=out).T


def _lerp(a, b, t):
    """numpy's percentile interpolation (``numpy.lib._function_base_impl._lerp``)."""
    d = b - a
    out = a + d * t
    return np.where(t >= 0.5, b - d * (1 - t), out)


def stream_percentile(values: Callable[[], Iterable[np.ndarray]], n: int, q: float,
                      sample: np.ndarray | None = None) -> np.ndarray:
    """``np.percentile(X, q, axis=0)`` (linear) of the (n, k) array whose rows
    ``values()`` yields in blocks, with memory bounded by the bracket.

    ``sample``: rows of X (any subset) that bracket the quantile; without it
    one pass takes a decimated series."""
    v = q / 100.0 * (n - 1)
    r0 = int(math.floor(v))
    r1 = min(r0 + 1, n - 1)
    frac = v - r0
    if sample is None:
        step = max(1, n // SAMPLE_ROWS)
        parts, off = [], 0
        for blk in values():
            first = (-off) % step
            parts.append(blk[first::step].copy())  # a copy: a view would keep the block
            off += len(blk)
        sample = np.concatenate(parts)
    sample = np.asarray(sample, dtype=float)
    m, k = sample.shape
    # a bracket of +-3 percentage points (at least 50 sample ranks) around the quantile
    pad = max(50, int(0.03 * m))
    p = q / 100.0 * (m - 1)
    lo_i, hi_i = int(p) - pad, int(p) + 1 + pad
    kth = [i for i in (lo_i, hi_i) if 0 <= i < m]
    if kth:
        sample = np.partition(sample, kth, axis=0)
    lo = np.array([sample[lo_i, j] if lo_i >= 0 else -np.inf for j in range(k)])
    hi = np.array([sample[hi_i, j] if hi_i < m else np.inf for j in range(k)])
    result = np.empty(k)
    todo = list(range(k))
    for _ in range(40):
        lo_t, hi_t = lo[todo], hi[todo]
        below = np.zeros(len(todo), dtype=np.int64)
        inside = np.zeros(len(todo), dtype=np.int64)
        imin = np.full(len(todo), np.inf)
        imax = np.full(len(todo), -np.inf)
        kept: list[list[np.ndarray]] | None = [[] for _ in todo]
        for blk in values():
            # one column at a time, contiguous (no copy of a column-major block)
            xt = np.asarray(blk).T
            xt = np.ascontiguousarray(xt if len(todo) == len(xt) else xt[todo])
            for j, c in enumerate(xt):
                nb = np.count_nonzero(c < lo_t[j])
                below[j] += nb
                le = c <= hi_t[j]  # below the bracket or in it (lo <= hi)
                cnt = np.count_nonzero(le) - nb
                if not cnt:
                    continue
                inside[j] += cnt
                xj = c[le]
                xj = xj[xj >= lo_t[j]]
                imin[j] = min(imin[j], xj.min())
                imax[j] = max(imax[j], xj.max())
                if kept is not None:
                    kept[j].append(xj)
            if kept is not None and np.any(inside > BRACKET_CAP):
                kept = None  # too many values in the bracket: narrow it first
        done = []
        for j, ax in enumerate(todo):
            c = int(below[j])
            if c > r0:
                lo[ax] = -np.inf
                continue
            if c + int(inside[j]) <= r1:
                hi[ax] = np.inf
                continue
            if imin[j] == imax[j]:  # every value in the bracket is the same
                result[ax] = imin[j]
                done.append(ax)
                continue
            if kept is None:
                continue
            vals = np.concatenate(kept[j])
            vals = np.partition(vals, sorted({r0 - c, r1 - c}))
            a, b = vals[r0 - c], vals[r1 - c]
            result[ax] = _lerp(np.float64(a), np.float64(b), np.float64(frac))
            done.append(ax)
        todo = [ax for ax in todo if ax not in done]
        if not todo:
            return result
        if kept is None:
            lo, hi = _narrow(values, todo, lo, hi, r0, r1)
    raise RuntimeError("percentile bracket did not converge")


def _widen(x, sign):
    if not np.isfinite(x):
        return x
    return -np.inf if sign < 0 else np.inf


def _narrow(values, todo, lo, hi, r0, r1):
    """One histogram pass over the bracket of each axis in ``todo``: the
    bracket becomes the bins that hold ranks r0 and r1."""
    lo, hi = lo.copy(), hi.copy()
    below = np.zeros(len(todo), dtype=np.int64)
    hists = [np.zeros(HIST_BINS, dtype=np.int64) for _ in todo]
    # infinite bracket ends: use the finite range of the data
    mn = np.full(len(todo), np.inf)
    mx = np.full(len(todo), -np.inf)
    if not (np.all(np.isfinite(lo[todo])) and np.all(np.isfinite(hi[todo]))):
        for blk in values():
            x = blk[:, todo]
            mn = np.minimum(mn, x.min(axis=0))
            mx = np.maximum(mx, x.max(axis=0))
    a = np.where(np.isfinite(lo[todo]), lo[todo], mn)
    b = np.where(np.isfinite(hi[todo]), hi[todo], mx)
    width = np.where(b > a, b - a, 1.0)
    for blk in values():
        x = blk[:, todo]
        below += np.sum(x < a, axis=0)
        for j in range(len(todo)):
            xj = x[:, j]
            xj = xj[(xj >= a[j]) & (xj <= b[j])]
            idx = np.minimum(((xj - a[j]) / width[j] * HIST_BINS).astype(np.int64), HIST_BINS - 1)
            hists[j] += np.bincount(idx, minlength=HIST_BINS)
    for j, ax in enumerate(todo):
        cum = below[j] + np.cumsum(hists[j])
        i0 = int(np.searchsorted(cum, r0 + 1))  # bin holding rank r0
        i1 = int(np.searchsorted(cum, r1 + 1))
        lo[ax] = a[j] + width[j] * max(i0 - 1, 0) / HIST_BINS
        hi[ax] = a[j] + width[j] * min(i1 + 2, HIST_BINS) / HIST_BINS
    return lo, hi


def stream_median_diff(times: Callable[[], Iterable[np.ndarray]], n: int,
                       sample: np.ndarray | None = None) -> float:
    """``np.median(np.diff(t))`` of the concatenated time blocks."""
    if n < 2:
        return 1.0

    def diffs():
        last = None
        for t in times():
            t = np.asarray(t, dtype=float)
            if len(t) == 0:
                continue
            d = np.diff(t) if last is None else np.diff(np.concatenate([[last], t]))
            last = t[-1]
            yield d[:, None]

    return float(stream_percentile(diffs, n - 1, 50.0, sample)[0])


class _RunTracker:
    """[start, stop) runs of True over consecutive boolean blocks."""

    def __init__(self):
        self.starts, self.stops = [], []
        self.off = 0
        self.prev = False

    def feed(self, f: np.ndarray) -> None:
        if len(f) == 0:
            return
        d = np.diff(np.concatenate([[self.prev], f]).astype(np.int8))
        self.starts.append(np.flatnonzero(d == 1) + self.off)
        self.stops.append(np.flatnonzero(d == -1) + self.off)
        self.prev = bool(f[-1])
        self.off += len(f)

    def result(self) -> tuple[np.ndarray, np.ndarray]:
        stops = self.stops + ([np.array([self.off])] if self.prev else [])

        def cat(xs):
            return np.concatenate(xs).astype(np.int64) if xs else np.empty(0, np.int64)

        return cat(self.starts), cat(stops)


def take_sorted(times: Callable[[], Iterable[np.ndarray]], idx: np.ndarray) -> np.ndarray:
    """t[idx] for indices into the concatenated time blocks."""
    idx = np.asarray(idx, dtype=np.int64)
    order = np.argsort(idx, kind="stable")
    srt = idx[order]
    out_sorted = np.empty(len(srt))
    off, j = 0, 0
    for t in times():
        end = off + len(t)
        k = int(np.searchsorted(srt, end))
        if k > j:
            out_sorted[j:k] = np.asarray(t)[srt[j:k] - off]
            j = k
        off = end
        if j == len(srt):
            break
    out = np.empty(len(srt))
    out[order] = out_sorted
    return out


class Decimator:
    """Every ``stride``-th row of a stream (from row 0), the stride doubling
    whenever more than ``2 * limit`` rows are kept: a decimated series of
    bounded size."""

    def __init__(self, limit: int = SAMPLE_ROWS):
        self.limit = limit
        self.stride = 1
        self.buf: np.ndarray | None = None  # the kept rows, then room: filled in place
        self.kept = 0
        self.off = 0

    def feed(self, x: np.ndarray) -> None:
        x = np.asarray(x)
        first = (-self.off) % self.stride
        part = x[first::self.stride]
        p = len(part)
        self.off += len(x)
        if self.buf is None or self.kept + p > len(self.buf):
            grown = np.empty((max(2 * self.limit + p, 2 * (self.kept + p)),) + x.shape[1:],
                             dtype=x.dtype)
            if self.kept:
                grown[:self.kept] = self.buf[:self.kept]
            self.buf = grown
        self.buf[self.kept:self.kept + p] = part
        self.kept += p
        if self.kept > 2 * self.limit:  # every other kept row, in place
            half = self.buf[:self.kept:2]
            self.kept = len(half)
            self.buf[:self.kept] = half
            self.stride *= 2

    def series(self) -> np.ndarray | None:
        return None if self.buf is None else self.buf[:self.kept].copy()


def _median(x: np.ndarray) -> float:
    """``np.median`` of a finite 1-d array (np.median's first call imports
    numpy.ma, about 20 ms of an import's start-up)."""
    m = len(x)
    k = m // 2
    if m % 2:
        return float(np.partition(x, k)[k])
    p = np.partition(x, [k - 1, k])
    return float((p[k - 1] + p[k]) / 2.0)


class StreamDetector:
    """Static detection fed during the import, block by block.

    It keeps a decimated series of ``diff(t)`` and of the moving standard
    deviation (window from the first block's sample period) and hands the
    full moving std to ``store`` (``write(array)``, ``blocks()``), so that the
    final passes read it back instead of computing it again. ``result``
    checks the window against the exact median sample period and computes
    the moving std again from the samples only when it differs."""

    def __init__(self, window_s: float = 1.0, store=None):
        self.window_s = window_s
        self.store = store
        self.ms = None
        self.w_est = None
        self.t_last = None
        self.diffs = Decimator()
        self.stds = Decimator()
        self.n = 0
        self.axes = None  # (accelerometer axes, has a gyro), from the first block

    def feed(self, t, accel, gyro=None) -> None:
        t = np.asarray(t, dtype=float)
        if not len(t):
            return
        if self.ms is None:
            dt = _median(np.diff(t)) if len(t) > 1 else 1.0
            self.w_est = max(3, int(round(self.window_s / dt))) if dt > 0 else 3
            self.ms = MovingStd(self.w_est)
        d = np.diff(t) if self.t_last is None else np.diff(np.concatenate([[self.t_last], t]))
        self.t_last = t[-1]
        self.axes = (np.shape(accel)[1], gyro is not None)
        self.diffs.feed(d[:, None])
        # the moving std in steps of at most SUB_ROWS rows: its buffers stay small
        # whatever the source's block size (the same values: MovingStd is exact across feeds)
        for i in range(0, len(t), SUB_ROWS):
            self._out(self.ms.feed(accel[i:i + SUB_ROWS],
                                   None if gyro is None else gyro[i:i + SUB_ROWS]))
        self.n += len(t)

    def _out(self, s):
        if s is not None and len(s):
            if not isinstance(self.store, OnlineFloors):  # the others' bracket
                self.stds.feed(s)
            if self.store is not None:
                self.store.write(s)

    def result(self, blocks: Blocks, multiplier: float = DEFAULT_MULTIPLIER,
               min_duration_s: float = 1.0, times=None) -> DetectionReport:
        """``times``: a fresh iterator of the time blocks alone (cheaper to read
        than ``blocks``); taken from ``blocks`` when not given."""
        n = self.n
        if self.ms is not None:
            self._out(self.ms.finish(n))

        if times is None:
            def times():
                for t, _, _ in blocks():
                    yield t

        dt = stream_median_diff(times, n, self.diffs.series()) if n > 1 else 1.0
        w = max(3, int(round(self.window_s / dt)))
        online = self.store if isinstance(self.store, OnlineFloors) else None
        got = online.result(n, multiplier) if online is not None and w == self.w_est else None
        if got is not None:
            floors, levels = got
            na, has_g = self.axes
            fa = np.maximum(floors[:na], 1e-300)
            fg = np.maximum(floors[na:], 1e-300) if has_g else None
            return _report(levels, times, n, dt, w, self.window_s, multiplier, min_duration_s,
                           fa, fg)
        if w == self.w_est and self.store is not None and online is None:
            stds, sample = self.store.blocks, self.stds.series()
        else:  # the moving std again, from the samples
            stds, sample = _std_source(blocks, w, n), None
        return _detect(blocks, times, stds, sample, n, dt, w, self.window_s, multiplier,
                       min_duration_s, self.axes)


class OnlineFloors:
    """A store for ``StreamDetector`` that keeps no moving std: the passes
    after the feed are done during it, against a bracket of the noise floor.

    The bracket of every axis's floor [lo, hi] is taken from the first block
    (+- ``ONLINE_PAD`` of its ranks around the quantile); then for every
    block it counts the values below lo and keeps those inside (the exact
    floor is selected from them at the end, as ``stream_percentile`` does;
    when more than ``BRACKET_CAP`` are kept, the bracket is narrowed to
    +- ``NARROW_PAD`` of the rows seen around the quantile of those rows),
    and bounds every row's level between its values for the floors hi and lo
    of the first bracket
    (the ratio max_j s_j / f_j is monotonic in every f_j, rounding included),
    kept as runs; the rows whose two bounds differ are kept with their moving
    std and get their exact level once the floors are known. The result is
    exactly that of the passes over the whole series (``_detect``), or None
    when the bracket did not hold the floor (a first block unlike the rest)
    or a cap was reached: the detector then computes the moving std again from
    the samples. Memory: the values in the bracket, the ambiguous rows and
    the runs, each capped."""

    def __init__(self, multiplier: float = DEFAULT_MULTIPLIER):
        self.multiplier = multiplier
        self.ks = _multipliers(multiplier)
        self.lo = self.hi = None
        self.off = 0
        self.failed = False
        self.last = None
        self.starts: list[np.ndarray] = []
        self.codes: list[np.ndarray] = []
        self.n_runs = 0
        self.amb_idx: list[np.ndarray] = []
        self.amb_s: list[np.ndarray] = []
        self.n_amb = 0

    def _bracket(self, s):
        m, k = s.shape
        p = FLOOR_QUANTILE / 100.0 * (m - 1)
        pad = max(50, int(ONLINE_PAD * m))
        lo_i, hi_i = int(p) - pad, int(p) + 1 + pad
        kth = [i for i in (lo_i, hi_i) if 0 <= i < m]
        part = np.partition(s, kth, axis=0) if kth else s
        self.lo = part[lo_i].copy() if lo_i >= 0 else np.full(k, -np.inf)
        self.hi = part[hi_i].copy() if hi_i < m else np.full(k, np.inf)
        # the floors are clipped at 1e-300 (_detect); the level bounds from the clipped ends
        self.lo0, self.hi0 = np.maximum(self.lo, 1e-300), np.maximum(self.hi, 1e-300)
        self.inv_min = 1.0 / self.hi0
        self.inv_max = 1.0 / self.lo0
        self.below = np.zeros(k, dtype=np.int64)
        self.kept: list[list[np.ndarray]] = [[] for _ in range(k)]
        self.n_kept = np.zeros(k, dtype=np.int64)

    def _narrow(self, j, seen):
        """Axis j's bracket narrowed around the quantile of the ``seen`` rows."""
        vals = np.concatenate(self.kept[j])
        p = FLOOR_QUANTILE / 100.0 * (seen - 1) - self.below[j]
        # at most a quarter of the cap a side: a pad growing with the rows seen would
        # outgrow the cap past ~25 M rows and give the store up (the exact floor is
        # still checked against the bracket at the end)
        pad = max(50, min(int(NARROW_PAD * seen), BRACKET_CAP // 4))
        i_lo, i_hi = int(p) - pad, int(p) + 1 + pad
        kth = [i for i in (i_lo, i_hi) if 0 <= i < len(vals)]
        if kth:
            vals = np.partition(vals, kth)
        # (a quantile outside the kept values leaves the bracket as it is: too many values
        # stay in it, and the store gives up)
        if 0 < i_lo < len(vals):
            self.lo[j] = vals[i_lo]
        if 0 <= i_hi < len(vals) - 1:
            self.hi[j] = vals[i_hi]
        below = vals < self.lo[j]
        self.below[j] += np.count_nonzero(below)
        vals = vals[~below & (vals <= self.hi[j])]
        self.kept[j] = [vals]
        self.n_kept[j] = len(vals)

    def _fail(self):
        self.failed = True
        self.kept = self.starts = self.codes = self.amb_idx = self.amb_s = []

    def write(self, s):
        s = np.asarray(s, dtype=float)
        m = len(s)
        if not m:
            return
        if self.failed:
            self.off += m
            return
        if self.lo is None:
            self._bracket(s)
        for j, c in enumerate(s.T):  # contiguous columns of a column-major block
            nb = np.count_nonzero(c < self.lo[j])
            self.below[j] += nb
            le = c <= self.hi[j]  # below the bracket or in it (lo <= hi)
            cnt = np.count_nonzero(le) - nb
            if cnt:
                xj = c[le]
                self.kept[j].append(xj[xj >= self.lo[j]])
                self.n_kept[j] += cnt
        for j in np.flatnonzero(self.n_kept > BRACKET_CAP):
            self._narrow(j, self.off + m)
        low = _levels(s, self.inv_min, self.ks)
        high = _levels(s, self.inv_max, self.ks)
        amb = np.flatnonzero(low != high)
        self.n_amb += len(amb)
        code = low.astype(np.int16) * 16 + high
        ch = np.flatnonzero(code[1:] != code[:-1]) + 1
        if self.last is None or code[0] != self.last:
            ch = np.concatenate([[0], ch])
        self.n_runs += len(ch)
        if self.n_kept.max() > BRACKET_CAP or self.n_amb > AMBIGUOUS_CAP \
                or self.n_runs > RUNS_CAP:
            self._fail()
            self.off += m
            return
        if len(amb):
            self.amb_idx.append(amb + self.off)
            self.amb_s.append(s[amb])
        self.starts.append(ch + self.off)
        self.codes.append(code[ch])
        self.last = code[-1]
        self.off += m

    def result(self, n: int, multiplier: float, rows: int = 65536):
        """(floors, iterator of level blocks) or None (see the class doc)."""
        if self.failed or self.lo is None or multiplier != self.multiplier or self.off != n:
            return None
        v = FLOOR_QUANTILE / 100.0 * (n - 1)
        r0 = int(math.floor(v))
        r1 = min(r0 + 1, n - 1)
        frac = v - r0
        k = len(self.lo)
        floors = np.empty(k)
        for j in range(k):
            c = int(self.below[j])
            if c > r0 or c + int(self.n_kept[j]) <= r1:
                return None  # the floor is outside the bracket
            vals = np.partition(np.concatenate(self.kept[j]), sorted({r0 - c, r1 - c}))
            floors[j] = _lerp(np.float64(vals[r0 - c]), np.float64(vals[r1 - c]),
                              np.float64(frac))
        f_all = np.maximum(floors, 1e-300)
        if np.any(f_all < self.lo0) or np.any(f_all > self.hi0):  # the level bounds' bracket
            return None
        inv = 1.0 / f_all
        ks = self.ks
        starts = np.concatenate(self.starts)
        low = (np.concatenate(self.codes) // 16).astype(np.int8)
        ends = np.append(starts[1:], n)
        amb_idx = np.concatenate(self.amb_idx) if self.amb_idx else np.empty(0, np.int64)
        amb_lvl = _levels(np.concatenate(self.amb_s), inv, ks) if self.amb_s \
            else np.empty(0, np.int8)

        def levels():
            for b0 in range(0, n, rows):
                b1 = min(n, b0 + rows)
                i0 = int(np.searchsorted(starts, b0, "right")) - 1
                i1 = int(np.searchsorted(starts, b1, "left"))
                lengths = np.minimum(ends[i0:i1], b1) - np.maximum(starts[i0:i1], b0)
                lvl = np.repeat(low[i0:i1], lengths)
                a0, a1 = np.searchsorted(amb_idx, [b0, b1])
                lvl[amb_idx[a0:a1] - b0] = amb_lvl[a0:a1]
                yield lvl

        return floors, levels()


class ListStore:
    """An in-memory store for ``StreamDetector`` (a record that is in memory
    anyway, e.g. ``import text``)."""

    def __init__(self):
        self.parts: list[np.ndarray] = []

    def write(self, arr):
        self.parts.append(np.array(arr))

    def blocks(self):
        return iter(self.parts)


def detect_static_arrays(t, accel, gyro=None, window_s: float = 1.0,
                         multiplier: float = DEFAULT_MULTIPLIER, min_duration_s: float = 1.0,
                         rows: int = 65536) -> DetectionReport:
    """``detect_static`` of in-memory arrays through the block detector (one
    moving-std computation instead of one per threshold)."""
    t = np.asarray(t, dtype=float)
    det = StreamDetector(window_s, ListStore())
    for i in range(0, len(t), rows):
        det.feed(t[i:i + rows], accel[i:i + rows], None if gyro is None else gyro[i:i + rows])

    def blocks():
        for i in range(0, len(t), rows):
            yield t[i:i + rows], accel[i:i + rows], None if gyro is None else gyro[i:i + rows]

    def times():
        for i in range(0, len(t), rows):
            yield t[i:i + rows]

    return det.result(blocks, multiplier, min_duration_s, times=times)


def _std_source(blocks, w, n):
    def sensors():
        for _, a, g in blocks():
            yield a if g is None else np.concatenate([a, g], axis=1)

    return lambda: moving_std_blocks(sensors(), w, n)


def detect_static_stream(blocks: Blocks, n: int, window_s: float = 1.0,
                         multiplier: float = DEFAULT_MULTIPLIER,
                         min_duration_s: float = 1.0) -> DetectionReport:
    """``detect_static`` over a record given as blocks (see the module doc)."""

    def times():
        for t, _, _ in blocks():
            yield t

    dt = stream_median_diff(times, n) if n > 1 else 1.0
    w = max(3, int(round(window_s / dt)))
    return _detect(blocks, times, _std_source(blocks, w, n), None, n, dt, w, window_s,
                   multiplier, min_duration_s)


def _detect(blocks, times, stds, sample, n, dt, w, window_s, multiplier, min_duration_s,
            axes=None):
    """``axes``: (accelerometer axes, has a gyro) when known; else read from
    the first block."""
    floors = stream_percentile(stds, n, FLOOR_QUANTILE, sample)
    if axes is None:
        first = next(iter(blocks()))
        axes = (first[1].shape[1], first[2] is not None)
    na, has_g = axes
    fa = np.maximum(floors[:na], 1e-300)
    fg = np.maximum(floors[na:], 1e-300) if has_g else None
    f_all = floors.copy()
    f_all[:na] = fa
    if has_g:
        f_all[na:] = fg

    ks = _multipliers(multiplier)
    inv = 1.0 / f_all
    levels = (_levels(s, inv, ks) for s in stds())  # one pass over the moving std
    return _report(levels, times, n, dt, w, window_s, multiplier, min_duration_s, fa, fg)


def _multipliers(multiplier):
    return sorted(set(MULTIPLIERS) | {multiplier})


def _ratio(s, inv):
    """r = max_j s_j inv_j per row: s_j < k f_j for every axis j <=> r < k."""
    r = s[:, 0] * inv[0]
    for j in range(1, s.shape[1]):
        np.maximum(r, s[:, j] * inv[j], out=r)
    return r


def _levels(s, inv, ks):
    """Level per row: how many multipliers r reaches (quiet at k <=> level <=
    index of k)."""
    r = _ratio(s, inv)
    lvl = np.zeros(len(r), dtype=np.int8)
    for k in ks:
        lvl += r >= k
    return lvl


def _report(levels, times, n, dt, w, window_s, multiplier, min_duration_s, fa, fg):
    """The detection report from the level of every row (blocks in order)."""
    ks = _multipliers(multiplier)
    trackers = {k: _RunTracker() for k in ks}
    n_quiet = 0
    i_mult = ks.index(multiplier)
    prev = None  # level of the last row of the previous block
    off = 0
    for lvl in levels:  # quiet masks for every multiplier, kept as runs
        if not len(lvl):
            continue
        n_quiet += int(np.count_nonzero(lvl <= i_mult))
        # the masks change only where the level does: the runs of every multiplier from
        # those rows alone
        ch = np.flatnonzero(lvl[1:] != lvl[:-1]) + 1
        if prev is None:
            idx = np.concatenate([[0], ch])
            before = np.full(1 + len(ch), len(ks), dtype=np.int8)  # "not quiet" before row 0
            before[1:] = lvl[ch - 1]
        else:
            idx = np.concatenate([[0], ch])
            before = np.empty(1 + len(ch), dtype=np.int8)
            before[0] = prev
            before[1:] = lvl[ch - 1]
        after = lvl[idx]
        for i, k in enumerate(ks):
            qb, qa = before <= i, after <= i
            trackers[k].starts.append(idx[qa & ~qb] + off)
            trackers[k].stops.append(idx[qb & ~qa] + off)
            trackers[k].prev = bool(lvl[-1] <= i)
        prev = lvl[-1]
        off += len(lvl)
    for k in ks:
        trackers[k].off = off
    run_pairs = {k: trackers[k].result() for k in ks}
    half = w // 2
    # the times the interval rule needs, read in one pass
    need = []
    for a, b in run_pairs.values():
        need += [a, b - 1, a + half, np.maximum(b - half - 1, 0)]
    need_idx = np.sort(np.clip(np.concatenate(need) if need else np.empty(0, np.int64),
                               0, max(n - 1, 0)))
    # np.unique without its first call's import of numpy.ma (20 ms of an import)
    need_idx = need_idx[np.concatenate([[True], need_idx[1:] != need_idx[:-1]])] \
        if len(need_idx) else need_idx
    tv = take_sorted(times, need_idx) if len(need_idx) else np.empty(0)
    tmap = dict(zip(need_idx.tolist(), tv.tolist()))

    def find(k, short=None):
        out = []
        a_arr, b_arr = run_pairs[k]
        for a, b in zip(a_arr.tolist(), b_arr.tolist()):
            a2, b2 = a + half, b - half
            span = (tmap[b2 - 1] - tmap[a2]) + dt if b2 > a2 else 0.0
            if b2 > a2 and span >= min_duration_s:
                out.append((int(a2), int(b2)))
            elif short is not None:
                short.append(float((tmap[b - 1] - tmap[a]) + dt - 2 * half * dt))
        return out

    counts = {k: len(find(k)) for k in ks}
    short: list[float] = []
    intervals = find(multiplier, short)
    short = [x for x in short if x > 0]
    return DetectionReport(intervals, multiplier, window_s, min_duration_s, fa, fg, counts,
                           short_runs=len(short), longest_short_s=max(short, default=0.0),
                           static_fraction=n_quiet / n if n else float("nan"))
