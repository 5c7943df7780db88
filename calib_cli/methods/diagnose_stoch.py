"""The bias random walk as a ``diagnose`` candidate.

A bias that integrates white noise of density q (the catalogue's
``bias_random_walk``; rate random walk for gyros) makes the bin residuals of a
channel e_b = B(t_b) + w_b with B a random walk and w the white noise of the
bin mean (variance v_b). A Kalman filter over the bins in time order gives
the innovations nu_b with variance S_b, so

    log L(q) = -1/2 sum_b (log S_b + nu_b^2 / S_b)       (first bin: diffuse start)

and nu_b / sqrt(S_b) are the whitened residuals a generalised least-squares
refit minimises. The candidate's evidence comes from the wander *within*
segments only: q (per channel, on a logarithmic grid) and the score
2 (log L(q) - log L(0)) use a walk that restarts at every segment, because
offsets between positions visited one after the other are what any
position-dependent misfit (attitude errors, an effect in a form the
catalogue lacks) also produces. Once added, the walk runs through the whole
record with that q. The whitened
residuals stand in for the residuals afterwards ("explained down to the
noise": the innovations are white).
"""

from __future__ import annotations

import numpy as np


def kalman(e: np.ndarray, v: np.ndarray, t: np.ndarray, q: np.ndarray, reset=None):
    """Innovations of a random walk plus white noise, per channel.

    e: (M, n) residuals (data units); v: (M, n) white variances; t: (M,) s;
    q: (n,) density (unit/sqrt(s)); reset: (M,) bool, bins where the walk starts
    afresh (diffuse: each segment's level free). Returns (nu / sqrt(S), log S),
    both (M, n), 0 at the first bin and at every reset."""
    M, n = e.shape
    out = np.zeros((M, n))
    logs = np.zeros((M, n))
    x = e[0].copy()
    P = v[0].copy()
    q2 = np.asarray(q, float) ** 2
    dt = np.diff(t)
    for b in range(1, M):
        if reset is not None and reset[b]:
            x, P = e[b].copy(), v[b].copy()
            continue
        P = P + q2 * dt[b - 1]
        S = P + v[b]
        nu = e[b] - x
        out[b] = nu / np.sqrt(S)
        logs[b] = np.log(S)
        K = P / S
        x = x + K * nu
        P = (1 - K) * P
    return out, logs


class RandomWalkWhitener:
    """Whitens a sensor's (M, n) noise-unit residuals z under a random-walk bias."""

    def __init__(self, t, wh, q):
        self.t = np.asarray(t, float)
        self.wh = np.asarray(wh, float)
        self.q = np.asarray(q, float)
        self.logdet = kalman(np.zeros_like(self.wh), self.wh ** 2, self.t, self.q)[1]

    def whiten(self, z: np.ndarray) -> np.ndarray:
        return kalman(z * self.wh, self.wh ** 2, self.t, self.q)[0]

    def smoothed_bias(self, z: np.ndarray) -> np.ndarray:
        """The filtered bias wander (data units) implied by residuals z (noise units)."""
        e = z * self.wh
        nu = kalman(e, self.wh ** 2, self.t, self.q)[0]
        return e - nu * np.sqrt(np.exp(self.logdet))


def log_det_white(wh: np.ndarray) -> np.ndarray:
    """log v_b of the white model, first bin excluded (as in ``kalman``)."""
    out = np.log(wh ** 2)
    out[0] = 0.0
    return out


def within_segment_lr(t, z, wh, reset, n_grid: int = 28):
    """(q, LR per channel) of a random walk from the wander *within* segments only
    (the walk restarts at every segment): offsets between positions, which any
    position-dependent misfit also makes, are no evidence for it."""
    q = fit_q(t, z, wh, n_grid, reset)
    e, v = z * wh, wh ** 2
    keep = ~np.asarray(reset, bool)
    keep[0] = False
    nu0, logs0 = kalman(e, v, t, np.zeros_like(q), reset)  # white, each segment's level free
    ll0 = -0.5 * (nu0[keep] ** 2 + logs0[keep]).sum(axis=0)
    nu, logs = kalman(e, v, t, q, reset)
    ll = -0.5 * (nu[keep] ** 2 + logs[keep]).sum(axis=0)
    return q, np.where(q > 0, 2 * (ll - ll0), 0.0)


def fit_q(t, z, wh, n_grid: int = 28, reset=None) -> np.ndarray:
    """Per-channel maximum-likelihood q on a log grid (residuals z in noise units)."""
    t = np.asarray(t, float)
    span = max(t[-1] - t[0], 1e-9)
    # from a wander of 0.03 to 30 bin sigmas over the record
    base = np.median(wh, axis=0) / np.sqrt(span)
    grid = np.logspace(np.log10(0.03), np.log10(30.0), n_grid)
    e = z * wh
    v = wh ** 2
    best_ll = np.full(z.shape[1], -np.inf)
    best_q = np.zeros(z.shape[1])
    keep = np.ones(len(t), bool) if reset is None else ~np.asarray(reset, bool)
    keep[0] = False
    nu0, logs0 = kalman(e, v, t, np.zeros(z.shape[1]), reset)  # q = 0: the white model
    ll0 = -0.5 * (nu0[keep] ** 2 + logs0[keep]).sum(axis=0)
    for g in grid:
        q = g * base
        nu, logs = kalman(e, v, t, q, reset)
        ll = -0.5 * (nu[keep] ** 2 + logs[keep]).sum(axis=0)
        better = ll > best_ll
        best_ll = np.where(better, ll, best_ll)
        best_q = np.where(better, q, best_q)
    return np.where(best_ll > ll0, best_q, 0.0)
