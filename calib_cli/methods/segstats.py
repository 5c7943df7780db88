"""Per-segment means and noise of the static positions: what static methods fit."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calib_cli.data import Recording, Segment


@dataclass(frozen=True)
class StaticStats:
    """Means over each static segment.

    means: (M, n) in the recording's units. counts: (M,) samples.
    sigma: (n,) pooled within-segment standard deviation per channel (one
    sample), so the mean of segment k has variance sigma^2 / counts[k] for
    white noise.
    """

    segments: tuple[Segment, ...]
    means: np.ndarray
    counts: np.ndarray
    sigma: np.ndarray

    @property
    def labels(self) -> list[str]:
        return [s.label for s in self.segments]

    def mean_cov(self) -> np.ndarray:
        """(M, n, n) covariance of each segment mean from white sample noise."""
        return np.einsum("k,ij->kij", 1.0 / self.counts, np.diag(self.sigma**2))


def static_stats(rec: Recording, sensor: str = "accel", segments=None) -> StaticStats:
    segs = tuple(rec.static_segments() if segments is None else segments)
    data = rec.accel if sensor == "accel" else rec.gyro
    means, counts, ss, dof = [], [], 0.0, 0
    for s in segs:
        x = data[s.slice]
        m = x.mean(axis=0)
        means.append(m)
        counts.append(len(x))
        ss = ss + ((x - m) ** 2).sum(axis=0)
        dof += len(x) - 1
    n = data.shape[1]
    sigma = np.sqrt(ss / dof) if dof > 0 else np.full(n, np.nan)
    return StaticStats(segs, np.array(means).reshape(-1, n), np.array(counts, dtype=float), sigma)
