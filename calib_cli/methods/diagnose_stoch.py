"""Wandering biases as ``diagnose`` candidates: ``bias_random_walk`` and
``bias_instability``.

The bin residuals of a channel are e_b = B(t_b) + w_b with w the white noise
of the bin mean (variance v_b) and B a bias process: a level that walks with
density q (the catalogue's ``bias_random_walk``; rate random walk for gyros),
plus, for ``bias_instability``, the catalogue's sum of first-order
Gauss-Markov components (time constants ``FLICKER_TAUS``, each of standard
deviation FLICKER_SCALE * B, the mapping to the Allan bias-instability
figure B documented in model/effects.py). One Kalman filter over the bins in
time order, with the level diffuse at the start (the deterministic bias is
fitted beside it), gives the innovations nu_b with variance S_b, so

    log L = -1/2 sum_b (log S_b + nu_b^2 / S_b)       (first bin: diffuse start)

and nu_b / sqrt(S_b) are the whitened residuals a generalised least-squares
refit minimises. The two processes differ in their spectra (1/f^2 against
1/f), so on the same record the larger likelihood tells them apart.

The evidence for a wander must show *within* segments: the score is also
computed with the level restarting (diffuse) at every segment, because
offsets between positions visited one after the other are what any
position-dependent misfit (attitude errors, an effect in a form the
catalogue lacks) also produces. Once added, the process runs through the
whole record. The whitened residuals stand in for the residuals afterwards
("explained down to the noise": the innovations are white).
"""

from __future__ import annotations

import numpy as np

from calib_cli.model.effects import FLICKER_SCALE, FLICKER_TAUS


def _bin_variance_factor(tau: np.ndarray, T: float) -> np.ndarray:
    """Variance of the mean over T seconds of a unit Gauss-Markov process of time
    constant tau (the bins are means, not samples)."""
    x = T / np.asarray(tau, float)
    return 2.0 / x ** 2 * (x - 1.0 + np.exp(-x))


def kalman(e: np.ndarray, v: np.ndarray, t: np.ndarray, q: np.ndarray, gm=None,
           reset=None, bin_s: float = 0.5, gains: list | None = None):
    """Innovations of (level random walk + Gauss-Markov sum) plus white noise.

    e: (M, n, C) or (M, n) residuals (data units); v: (M, n) white variances;
    t: (M,) s; q: (..., n) level density (unit/sqrt(s)); gm: None or
    (taus (k,) s, sig (..., n, k) each component's standard deviation);
    reset: (M,) bool, bins where the level starts afresh (diffuse; bin 0 always).
    The leading batch shape (...) of q/sig evaluates many parameter sets at once.
    gains: a list that receives each bin's (F, K, sqrt S) (None at diffuse bins), which
    do not depend on the data (``whiten_with``).
    Returns (nu / sqrt(S), log S) of shapes (M, ..., n[, C]) and (M, ..., n), 0 at
    the diffuse bins."""
    e = np.asarray(e, float)
    cols = e.ndim == 3
    if not cols:
        e = e[..., None]
    M, n, C = e.shape
    q2 = np.asarray(q, float) ** 2
    if gm is None:
        taus = np.zeros(0)
        s2 = np.zeros(q2.shape + (0,))
    else:
        taus = np.asarray(gm[0], float)
        s2 = np.asarray(gm[1], float) ** 2 * _bin_variance_factor(taus, bin_s)
    batch = np.broadcast_shapes(q2.shape, s2.shape[:-1])
    q2 = np.broadcast_to(q2, batch)
    s2 = np.broadcast_to(s2, batch + (len(taus),))
    d = 1 + len(taus)
    x = np.zeros(batch + (d, C))
    P = np.zeros(batch + (d, d))
    gi = np.arange(1, d)
    P[..., gi, gi] = s2  # Gauss-Markov components start stationary
    out = np.zeros((M,) + batch + (C,))
    logs = np.zeros((M,) + batch)
    reset = np.zeros(M, bool) if reset is None else np.asarray(reset, bool)
    for b in range(M):
        F = None
        if b > 0:
            dt = t[b] - t[b - 1]
            phi = np.exp(-dt / taus)
            F = np.concatenate([[1.0], phi])
            P = P * np.outer(F, F)
            P[..., 0, 0] += q2 * dt
            P[..., gi, gi] += s2 * (1 - phi ** 2)
            x = x * F[:, None]
        eb = e[b]  # (n, C)
        if b == 0 or reset[b]:
            # diffuse level: it absorbs this bin whole; the components keep their
            # distribution and the level is correlated with them
            Pg = P[..., 1:, 1:]
            x[..., 0, :] = eb - x[..., 1:, :].sum(axis=-2)
            P[..., 0, 1:] = -Pg.sum(axis=-2)
            P[..., 1:, 0] = -Pg.sum(axis=-1)
            P[..., 0, 0] = Pg.sum(axis=(-1, -2)) + v[b]
            if gains is not None:
                gains.append((F if b > 0 else None, None, None))
            continue
        PH = P.sum(axis=-1)
        S = PH.sum(axis=-1) + v[b]
        nu = eb - x.sum(axis=-2)
        out[b] = nu / np.sqrt(S)[..., None]
        logs[b] = np.log(S)
        K = PH / S[..., None]
        if gains is not None:
            gains.append((F, K, np.sqrt(S)))
        x = x + K[..., :, None] * nu[..., None, :]
        P = P - K[..., :, None] * PH[..., None, :]
    if not cols:
        out = out[..., 0]
    return out, logs


def whiten_with(gains: list, e: np.ndarray) -> np.ndarray:
    """The innovations nu / sqrt(S) of data e (M, n) through a stored gain
    sequence (``kalman(..., gains=[])`` of the same t, v and process)."""
    M, n = e.shape
    d = len(gains[0][0]) if gains[0][0] is not None else len(gains[1][0])
    x = np.zeros((n, d))
    out = np.zeros((M, n))
    for b, (F, K, sS) in enumerate(gains):
        if F is not None:
            x = x * F
        if K is None:  # diffuse level
            x[:, 0] = e[b] - x[:, 1:].sum(axis=1)
            continue
        nu = e[b] - x.sum(axis=1)
        out[b] = nu / sS
        x = x + K * nu[:, None]
    return out


def loglik(e, v, t, q, gm=None, reset=None, bin_s=0.5):
    """Log-likelihood per channel (..., n), the diffuse bins left out."""
    nu, logs = kalman(e, v, t, q, gm, reset, bin_s)
    return -0.5 * (nu ** 2 + logs).sum(axis=0)


class ProcessWhitener:
    """Whitens a sensor's (M, n) noise-unit residuals z (units of wh, the bin
    sigma of the white model) under a wandering bias: a random walk of density q
    (n,), plus the flicker components of figure B (n,) when given, over white
    noise of bin sigma ``white`` (default wh)."""

    def __init__(self, t, wh, q, B=None, bin_s: float = 0.5, white=None):
        self.t = np.asarray(t, float)
        self.wh = np.asarray(wh, float)
        self.v = (self.wh if white is None else np.asarray(white, float)) ** 2
        self.q = np.asarray(q, float)
        self.gm = None if B is None else flicker(B)
        self.gains: list = []
        self.logdet = kalman(np.zeros_like(self.wh), self.v, self.t, self.q, self.gm,
                             bin_s=bin_s, gains=self.gains)[1]

    def whiten(self, z: np.ndarray) -> np.ndarray:
        return whiten_with(self.gains, z * self.wh)


def flicker(B):
    """(taus, sig) of the catalogue's flicker model for Allan bias-instability B (..., n)."""
    B = np.asarray(B, float)
    return FLICKER_TAUS, np.repeat(FLICKER_SCALE * B[..., None], len(FLICKER_TAUS), axis=-1)


def log_det_white(wh: np.ndarray) -> np.ndarray:
    """log v_b of the white model, first bin excluded (as in ``kalman``)."""
    out = np.log(wh ** 2)
    out[0] = 0.0
    return out


def _grid(t, wh, kind: str, n_grid: int) -> np.ndarray:
    """(G, n) trial values: a random walk (q) or a flicker figure (B) from 0.03 to
    30 bin sigmas of wander over the record."""
    span = max(t[-1] - t[0], 1e-9)
    sig = np.median(wh, axis=0)
    g = np.logspace(np.log10(0.03), np.log10(30.0), n_grid)[:, None]
    return g * (sig / np.sqrt(span) if kind == "random_walk" else sig)


def _args(kind, vals):
    """(q, gm) of the filter for trial values of one kind."""
    if kind == "random_walk":
        return vals, None
    return np.zeros(vals.shape), flicker(vals)


def fit_process(t, z, wh, kind: str, reset=None, n_grid: int = 24, bin_s=0.5, white=None):
    """Per-channel maximum-likelihood value (q or B) on a log grid, its rough sigma
    from the curvature of log L in log value, and the likelihood ratio against the
    white model (level free at every reset). z: (M, n) residuals in units of wh, the
    white model's bin sigma; white: the bin sigma of the white noise under the
    process (default wh; the high-frequency estimate where the white model's sigma
    was raised to the bins' scatter, which a wander makes)."""
    e = z * wh
    v = (wh if white is None else np.asarray(white, float)) ** 2
    vals = _grid(t, wh, kind, n_grid)
    q, gm = _args(kind, vals)
    ll = loglik(e, v, t, q, gm, reset, bin_s)  # (G, n)
    ll0 = loglik(e, wh ** 2, t, np.zeros(z.shape[1]), None, reset, bin_s)
    i = np.argmax(ll, axis=0)
    ch = np.arange(z.shape[1])
    best = vals[i, ch]
    lr = 2 * (ll[i, ch] - ll0)
    # curvature from the neighbouring grid points (log spacing h)
    h = np.log(vals[1, 0] / vals[0, 0])
    lo, hi = np.clip(i - 1, 0, n_grid - 1), np.clip(i + 1, 0, n_grid - 1)
    c = (ll[lo, ch] - 2 * ll[i, ch] + ll[hi, ch]) / h ** 2
    inner = (i > 0) & (i < n_grid - 1) & (c < 0)
    sig = np.where(inner, best / np.sqrt(np.where(c < 0, -c, 1.0)), np.nan)
    found = lr > 0
    return np.where(found, best, 0.0), np.where(found, sig, np.nan), np.where(found, lr, 0.0)
