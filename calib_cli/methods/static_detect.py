"""Static-interval detection that explains itself.

Rule (docs/import.md): the moving standard deviation of each accelerometer
axis (and gyro axis, when present) over a window of ``window_s`` (default
1 s) is compared with the noise floor of that axis, estimated as the 10th
percentile of the moving standard deviation over the whole record (robust as
long as at least ~10 % of the record is static). A sample is static when every
axis is below ``multiplier`` times its floor (default 3). Runs of static
samples at least ``min_duration_s`` long (default 1 s), trimmed by half a
window at each end (the window smears the motion), are the intervals.

The gyro test matters: a turn about the vertical leaves the accelerometers
unchanged, so accelerometers alone would merge the positions on either side.

When the count is not what the plan expects, ``DetectionReport.explain``
says how many intervals other multipliers would find.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

FLOOR_QUANTILE = 10.0  # percent
DEFAULT_MULTIPLIER = 3.0
MULTIPLIERS = (1.5, 2.0, 3.0, 4.0, 6.0, 8.0, 12.0, 20.0)


@dataclass(frozen=True)
class DetectionReport:
    intervals: list[tuple[int, int]]  # [start, stop) sample indices
    multiplier: float
    window_s: float
    min_duration_s: float
    floor_accel: np.ndarray  # per-axis noise floor (std), data units
    floor_gyro: np.ndarray | None
    counts: dict  # multiplier -> number of intervals it would find
    short_runs: int = 0  # quiet runs at this threshold rejected as shorter than min_duration_s
    longest_short_s: float = 0.0  # the longest of them, s
    static_fraction: float = float("nan")  # share of samples below the threshold

    def explain(self, expected: int | None = None, at_least: bool = False) -> str:
        """Why this many intervals, and which threshold would find the expected
        number (``at_least``: that many or more)."""
        n = len(self.intervals)
        parts = [f"found {n} static interval{'s' * (n != 1)} of >= {self.min_duration_s:g} s "
                 f"(window {self.window_s:g} s, threshold {self.multiplier:g} x the noise floor)"]
        if self.short_runs:
            parts.append(f"{self.short_runs} more quiet span{'s' * (self.short_runs != 1)} "
                         f"{'were' if self.short_runs != 1 else 'was'} shorter than --min-static "
                         f"{self.min_duration_s:g} s (longest {self.longest_short_s:.2f} s)")
        if np.isfinite(self.static_fraction) and self.static_fraction < 0.15:
            parts.append(f"only {100 * self.static_fraction:.0f} % of the samples are quiet: the "
                         "noise floor (10th percentile of the moving std) needs >= ~10 % of the "
                         "record static")
        alts = ", ".join(f"{k:g}x: {c}" for k, c in sorted(self.counts.items()))
        parts.append(f"other thresholds would find {alts}")
        if expected is not None:
            ok = [k for k, c in sorted(self.counts.items())
                  if (c >= expected if at_least else c == expected)]
            if ok:
                best = min(ok, key=lambda k: abs(k - self.multiplier))
                parts.append(f"--threshold {best:g} finds {self.counts[best]}")
            else:
                more = [k for k, c in sorted(self.counts.items()) if c > n]
                hint = f"--threshold {more[0]:g} finds {self.counts[more[0]]}; " if more else ""
                parts.append(f"no threshold finds {'that many' if not at_least else expected}: "
                             f"{hint}check --min-static (shorter positions), --window, or the "
                             "plan's segment count")
        elif n == 0 or any(c > n for c in self.counts.values()):
            more = [(k, c) for k, c in sorted(self.counts.items()) if c > n]
            if more:
                k, c = max(more, key=lambda kc: kc[1])
                parts.append(f"--threshold {k:g} finds the most ({c})")
        return "; ".join(parts)


def moving_std(x: np.ndarray, w: int) -> np.ndarray:
    """Centred moving standard deviation over w samples, per column (N, k)."""
    x = np.asarray(x, dtype=float)
    n = len(x)
    w = max(2, min(w, n))
    x = x - x.mean(axis=0)  # conditioning for the cumulative sums
    c1 = np.vstack([np.zeros(x.shape[1]), np.cumsum(x, axis=0)])
    c2 = np.vstack([np.zeros(x.shape[1]), np.cumsum(x * x, axis=0)])
    lo = np.clip(np.arange(n) - w // 2, 0, n - w)
    s1 = c1[lo + w] - c1[lo]
    s2 = c2[lo + w] - c2[lo]
    var = np.maximum(s2 / w - (s1 / w) ** 2, 0.0) * w / (w - 1)
    return np.sqrt(var)


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    d = np.diff(np.concatenate([[0], mask.astype(np.int8), [0]]))
    return list(zip(np.flatnonzero(d == 1), np.flatnonzero(d == -1)))


def detect_static(t, accel, gyro=None, window_s: float = 1.0, multiplier: float = DEFAULT_MULTIPLIER,
                  min_duration_s: float = 1.0) -> DetectionReport:
    t = np.asarray(t, dtype=float)
    dt = float(np.median(np.diff(t))) if len(t) > 1 else 1.0
    w = max(3, int(round(window_s / dt)))
    sa = moving_std(accel, w)
    fa = np.maximum(np.percentile(sa, FLOOR_QUANTILE, axis=0), 1e-300)
    sg = fg = None
    if gyro is not None:
        sg = moving_std(gyro, w)
        fg = np.maximum(np.percentile(sg, FLOOR_QUANTILE, axis=0), 1e-300)

    def quiet(k):
        ok = np.all(sa < k * fa, axis=1)
        if sg is not None:
            ok &= np.all(sg < k * fg, axis=1)
        return ok

    def find(k, short=None):
        out = []
        half = w // 2
        for a, b in _runs(quiet(k)):
            a2, b2 = a + half, b - half
            span = (t[b2 - 1] - t[a2]) + dt if b2 > a2 else 0.0
            if b2 > a2 and span >= min_duration_s:
                out.append((int(a2), int(b2)))
            elif short is not None:
                short.append(float((t[b - 1] - t[a]) + dt - 2 * half * dt))
        return out

    counts = {k: len(find(k)) for k in sorted(set(MULTIPLIERS) | {multiplier})}
    short: list[float] = []
    intervals = find(multiplier, short)
    short = [x for x in short if x > 0]
    return DetectionReport(intervals, multiplier, window_s, min_duration_s, fa, fg, counts,
                           short_runs=len(short), longest_short_s=max(short, default=0.0),
                           static_fraction=float(np.mean(quiet(multiplier))) if len(t) else
                           float("nan"))


def too_few_hint(rec, needed: int) -> str:
    """For an estimator that has too few static positions: what the detector
    finds in this recording and which threshold would find ``needed`` or more
    (import with --threshold/--min-static, or `calib detect RAW`)."""
    if rec is None or len(rec.time) < 3:
        return ""
    counters = getattr(rec, "counters", None) or {}
    if "plan_finished" in counters:  # made by calib record: its segments are the plan's
        planned = ""
        try:
            import tomllib

            n_plan = len(tomllib.loads(rec.plan_text or "").get("segment", []))
            planned = f" ({len(rec.segments)} of the plan's {n_plan} segments are in it)"
        except Exception:  # noqa: BLE001 - the count is a courtesy
            pass
        if not counters.get("plan_finished"):
            return (f" (this recording was stopped before its plan ended{planned}: record "
                    "the plan again with calib record; a recorded file's segments come from "
                    "its plan, not from static detection)")
        return (f" (recorded by calib record{planned}: its segments come from its plan; "
                "check the plan's positions with calib plan check)")
    try:
        rep = detect_static(rec.time, rec.accel, rec.gyro)
    except (ValueError, FloatingPointError):
        return ""
    return (f" (static detection with the defaults on this recording: "
            f"{rep.explain(needed, at_least=True)}; re-import with those options, or see "
            "`calib detect RAW`)")
