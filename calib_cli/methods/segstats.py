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


# |mean f| of a static position, in units of g, that a fit can still explain: the
# scale factors it accepts are 0.5..2 (methods/gross.py); a little beyond for the bias
GRAVITY_SEEN = (0.4, 2.5)


def check_gravity_seen(rec: Recording, path: str | None = None) -> None:
    """Each static position of an SI triad record must measure about g (issue
    37): all-zero, constant or mislabelled data (g stored as m/s^2) are refused
    with exit 3 before a fit meets a singular matrix."""
    from calib_cli.errors import InputError

    if rec.accel is None or rec.layout.redundant or rec.in_counts("accel"):
        return
    g = rec.site.gravity
    for s in rec.static_segments():
        if s.stop <= s.start:
            continue
        f = float(np.linalg.norm(rec.accel[s.slice].mean(axis=0)))
        if not GRAVITY_SEEN[0] * g <= f <= GRAVITY_SEEN[1] * g:
            raise InputError(f"static segment {s.label!r} measures |f| = {f:.4g} m/s^2, not about "
                             f"g ({g:.4g} m/s^2): the accelerometer data are not specific force "
                             "in m/s^2 (zero, stuck, or in another unit: see the import's "
                             "--accel-units)", path)
