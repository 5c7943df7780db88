"""Find the rotation cycles of a turntable record that has no ``segment`` column.

A rotating segment (CONTRACT.md section 3: a plan segment with
``table_axis_enu``) is one mounting of the unit on the table: the table axis
stays fixed in body axes while the table turns, stops and reverses as its
controller likes. So a cycle is found as a run of turning that keeps one
rotation axis in body axes (up to sign); the next cycle starts where the
axis seen by the gyros changes by more than ``axis_tol`` (the unit was
remounted). Holds at zero rate inside a cycle stay inside it. A short burst of
turning (a remount, a hand slew) of less than ``min_turn`` in total is not a
cycle. Where the table's own rate channel is recorded, it says when the table
turns; the axis always comes from the gyros.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class CycleDetection:
    """Detected cycles as sample spans [start, stop), and what was rejected."""

    cycles: list[tuple[int, int]]
    axes_body: list[np.ndarray]  # mean rotation axis of each cycle, body axes (sign: first turn)
    short_runs: list[tuple[float, float, float]]  # (t_start, t_stop, turned deg) left out

    def explain(self, expected: int) -> str:
        """One sentence on why the count may differ from the plan's."""
        msg = (f"found {len(self.cycles)} rotation cycles (runs of turning about one body axis, "
               f"split where that axis changes by more than 10 deg)")
        if self.short_runs:
            msg += (f"; {len(self.short_runs)} shorter runs of turning were taken as remounts "
                    "(less than one revolution)")
        if len(self.cycles) != expected:
            msg += "; give the CSV a 'segment' column to state the cycles"
        return msg


def detect_cycles(t: np.ndarray, gyro: np.ndarray, table_rate: np.ndarray | None = None,
                  window_s: float = 0.5, min_rate: float = np.radians(5.0),
                  axis_tol: float = np.radians(10.0), min_turn: float = 2 * np.pi,
                  preroll_s: float = 2.0) -> CycleDetection:
    """Cycles of a turntable record. t (N,) s; gyro (N, 3) rad/s; table_rate (N,) rad/s
    or None. A window of ``window_s`` turns when its mean rate exceeds ``min_rate``.
    Each cycle is extended by up to ``preroll_s`` into the quiet time around it (the
    fit starts a cycle's attitude from the table at rest)."""
    n = len(t)
    fs = 1.0 / float(np.median(np.diff(t))) if n > 1 else 1.0
    m = max(1, int(round(window_s * fs)))
    nw = n // m
    if nw < 2:
        return CycleDetection([], [], [])
    wm = gyro[: nw * m].reshape(nw, m, 3).mean(axis=1)
    speed = np.linalg.norm(wm, axis=1)
    if table_rate is not None and np.all(np.isfinite(table_rate)):
        moving = np.abs(table_rate[: nw * m].reshape(nw, m).mean(axis=1)) > min_rate
    else:
        moving = speed > min_rate
    quiet = speed < 0.5 * min_rate
    cos_tol = np.cos(axis_tol)
    runs: list[list[int]] = []  # window indices of each run of one axis
    axes: list[np.ndarray] = []
    for k in np.flatnonzero(moving):
        if speed[k] < 1e-12:
            continue
        u = wm[k] / speed[k]
        if runs and abs(u @ axes[-1]) >= cos_tol:
            runs[-1].append(k)
            a = axes[-1] * (len(runs[-1]) - 1) + np.sign(u @ axes[-1]) * u
            axes[-1] = a / np.linalg.norm(a)
        else:
            runs.append([k])
            axes.append(u)
    cycles, cyc_axes, short = [], [], []
    for run, a in zip(runs, axes):
        turned = float(speed[run].sum() * m / fs)
        if turned < min_turn:
            short.append((float(t[run[0] * m]), float(t[min(n - 1, (run[-1] + 1) * m - 1)]),
                          float(np.degrees(turned))))
            continue
        cycles.append([run[0], run[-1] + 1])
        cyc_axes.append(a)
    # extend into the quiet time around each cycle, never into a neighbour
    pre = int(round(preroll_s / window_s))
    spans = []
    for c, (w0, w1) in enumerate(cycles):
        lo = cycles[c - 1][1] if c > 0 else 0
        hi = cycles[c + 1][0] if c + 1 < len(cycles) else nw
        a = w0
        while a > lo and w0 - a < pre and quiet[a - 1]:
            a -= 1
        b = w1
        while b < hi and b - w1 < pre and quiet[b]:
            b += 1
        spans.append((a * m, min(n, b * m)))
    return CycleDetection(spans, cyc_axes, short)


def trim_intervals(intervals, spans, min_len: int) -> list[tuple[int, int]]:
    """Static intervals with the cycle spans cut out (holds inside a cycle are
    not static positions); the longest remaining piece of each is kept where it
    still has ``min_len`` samples."""
    out = []
    for a, b in intervals:
        pieces = [(a, b)]
        for s0, s1 in spans:
            nxt = []
            for p0, p1 in pieces:
                if s1 <= p0 or s0 >= p1:
                    nxt.append((p0, p1))
                    continue
                if s0 > p0:
                    nxt.append((p0, s0))
                if s1 < p1:
                    nxt.append((s1, p1))
            pieces = nxt
        if pieces:
            best = max(pieces, key=lambda p: p[1] - p[0])
            if best[1] - best[0] >= min_len:
                out.append((int(best[0]), int(best[1])))
    return out
