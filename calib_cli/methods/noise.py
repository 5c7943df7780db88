"""White-noise estimators, one per shape of data. Every fit and diagnose takes
its per-sample noise sigma from here (none writes its own).

Which suits what:

- ``pooled_within(pieces)``: pieces of data whose truth is constant within each
  piece (static positions, possibly after subtracting a known time-varying
  prediction such as the turning earth rate). The scatter about each piece's
  own mean, pooled over pieces with N_k - 1 degrees of freedom each: the
  unbiased white-noise variance, and the same numbers the segment means are
  fitted with. Slow wander within a piece inflates it (which is what a fit of
  the means wants: the means carry that wander too).
- ``difference_sigma(x, order, parts)``: a continuous record whose truth moves
  (drifting temperature, a turning table, the bins of diagnose). The d-th
  differences of white noise of sigma have variance C(2d, d) sigma^2 (2, 6, 20
  for d = 1, 2, 3) and remove a polynomial truth of degree d - 1 over the few
  samples they span: order 1 for slow trends (thermal soaks), order 2 for
  straight ramps and slopes (segments of constant rate), order 3 for
  accelerating motion (table cycles). Higher orders follow faster motion but
  waste more of the noise's high-frequency content on nothing; use the lowest
  order the motion allows. ``robust``: "mad" (median absolute deviation:
  insensitive to the few differences spanning a corner or a spike), "std"
  (plain standard deviation), or "auto" (MAD, falling back to the standard
  deviation where the data are quantised so coarsely that the MAD collapses).

Units: those of the data. Arrays: samples along axis 0.
"""

from __future__ import annotations

from dataclasses import dataclass
from math import comb

import numpy as np

MAD_TO_SIGMA = 1.4826  # sigma of a normal distribution per median absolute deviation


@dataclass(frozen=True)
class PooledNoise:
    """``pooled_within``'s result. means (M, n): each piece's mean; counts (M,):
    samples per piece; sigma (n,): the pooled per-sample standard deviation per
    channel (NaN when no piece has two samples); dof: its degrees of freedom."""

    means: np.ndarray
    counts: np.ndarray
    sigma: np.ndarray
    dof: int


def pooled_within(pieces, n_channels: int | None = None) -> PooledNoise:
    """Pooled within-piece noise of pieces (N_k, n) of data whose truth is constant
    within each piece. ``n_channels`` sizes the result when there is no piece."""
    means, counts, ss, dof = [], [], 0.0, 0
    n = n_channels
    for x in pieces:
        x = np.asarray(x, dtype=float)
        n = x.shape[1]
        m = x.mean(axis=0)
        means.append(m)
        counts.append(len(x))
        ss = ss + ((x - m) ** 2).sum(axis=0)
        dof += len(x) - 1
    n = n or 0
    sigma = np.sqrt(ss / dof) * np.ones(n) if dof > 0 else np.full(n, np.nan)
    return PooledNoise(np.array(means, dtype=float).reshape(-1, n),
                       np.array(counts, dtype=float), sigma, int(max(dof, 0)))


def difference_sigma(x: np.ndarray, order: int, parts=None, robust: str = "auto") -> np.ndarray:
    """Per-column white-noise sigma (n,) of x (N, n) from its ``order``-th differences,
    taken within each (start, stop) of ``parts`` (default: the whole record) so that
    no difference spans a gap or a segment boundary. See the module docstring for
    which order and which ``robust`` suits what."""
    x = np.asarray(x, dtype=float)
    if x.ndim == 1:
        x = x[:, None]
    parts = [(0, len(x))] if parts is None else parts
    d = [np.diff(x[a:b], order, axis=0) for a, b in parts if b - a > order]
    d = np.concatenate(d) if d else np.zeros((0, x.shape[1]))
    if len(d) == 0:
        return np.full(x.shape[1], np.nan)
    scale = np.sqrt(float(comb(2 * order, order)))
    if robust == "std":
        return d.std(axis=0) / scale
    mad = MAD_TO_SIGMA * np.median(np.abs(d - np.median(d, axis=0)), axis=0) / scale
    if robust == "mad":
        return mad
    sd = d.std(axis=0) / scale
    # quantised data (counts) can have a MAD of zero: fall back to the standard deviation
    return np.where(mad > 0.3 * sd, mad, sd)
