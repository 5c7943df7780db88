"""Per-segment means and noise of the static positions: what static methods fit."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calib_cli.data import Recording, Segment
from calib_cli.methods.noise import pooled_within


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
    pooled = pooled_within((data[s.slice] for s in segs), data.shape[1])
    return StaticStats(segs, pooled.means, pooled.counts, pooled.sigma)
