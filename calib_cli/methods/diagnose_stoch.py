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


def reml_basis(cols: np.ndarray, tol: float = 1e-8) -> np.ndarray:
    """(M, n, r) per channel an orthonormal basis of the deterministic model's columns
    cols (M, n, p) with the constant taken out (the filter's diffuse level holds it);
    zero-padded where a channel's rank is below r."""
    M, n, _ = cols.shape
    bases = []
    for k in range(n):
        X = cols[:, k, :] - cols[:, k, :].mean(axis=0)
        U, sv, _ = np.linalg.svd(X, full_matrices=False)
        r = int((sv > tol * max(sv[0], 1e-300)).sum()) if len(sv) else 0
        bases.append(U[:, :r])
    r = max([b.shape[1] for b in bases] + [0])
    out = np.zeros((M, n, r))
    for k, b in enumerate(bases):
        out[:, k, :b.shape[1]] = b
    return out


def loglik_reml(e, basis, v, t, q, gm=None, bin_s=0.5):
    """Restricted log-likelihood per channel (..., n) of residuals e (M, n) whose model's
    columns (``reml_basis``, (M, n, r)) were fitted: the filter whitens the data and the
    columns together, the columns are projected out of the innovations (generalised least
    squares) and log det of their whitened Gram matrix is added, so the wander the fit
    absorbed is not read as missing (REML; issue 18, benchmarks/allan18_crb.py)."""
    E = np.concatenate([np.asarray(e, float)[..., None], basis], axis=-1)  # (M, n, 1 + r)
    nu, logs = kalman(E, v, t, q, gm, None, bin_s)  # (M, ..., n, 1 + r)
    u, X = nu[..., 0], nu[..., 1:]
    r = basis.shape[-1]
    live = np.abs(basis).sum(axis=0) > 0  # (n, r) padded columns are not live
    G = np.einsum("m...i,m...j->...ij", X, X)
    G = G + np.where(live, 0.0, 1.0)[..., :, None] * np.eye(r)
    b = np.einsum("m...i,m...->...i", X, u)
    L = np.linalg.cholesky(G)
    w = np.linalg.solve(L, b[..., None])[..., 0]
    rss = (u ** 2).sum(axis=0) - (w ** 2).sum(axis=-1)
    logdet = 2 * np.log(np.diagonal(L, axis1=-2, axis2=-1)).sum(axis=-1)
    return -0.5 * (rss + logs.sum(axis=0) + logdet)


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


def fit_process(t, z, wh, kind: str, reset=None, n_grid: int = 24, bin_s=0.5, white=None,
                n_fine: int = 17, cols=None):
    """Per-channel maximum-likelihood value (q or B), its rough sigma from the curvature
    of log L in log value, and the likelihood ratio against the white model (level free
    at every reset). z: (M, n) residuals in units of wh, the white model's bin sigma;
    white: the bin sigma of the white noise under the process (default wh; the
    high-frequency estimate where the white model's sigma was raised to the bins'
    scatter, which a wander makes). The maximum is found on a coarse log grid (n_grid
    points over a factor 1000: steps of 35 %), then on ``n_fine`` points between the
    coarse maximum's neighbours, then at the vertex of the parabola through the finest
    three (the coarse grid alone quantised the figure by +-15 %, a scatter of 9 % on
    top of the likelihood's own; issue 18, benchmarks/allan18_crb.py). cols: (M, n, p)
    the columns (data units) of the deterministic model the residuals were fitted with;
    given (and no reset), the likelihood of the value is the restricted one
    (``loglik_reml``)."""
    e = z * wh
    v = (wh if white is None else np.asarray(white, float)) ** 2
    vals = _grid(t, wh, kind, n_grid)
    basis = None if (cols is None or reset is not None) else reml_basis(np.asarray(cols, float))

    def ll_of(q, gm):
        if basis is None:
            return loglik(e, v, t, q, gm, reset, bin_s)
        return loglik_reml(e, basis, v, t, q, gm, bin_s)

    q, gm = _args(kind, vals)
    ll = ll_of(q, gm)  # (G, n)
    ll0 = (loglik(e, wh ** 2, t, np.zeros(z.shape[1]), None, reset, bin_s) if basis is None
           else loglik_reml(e, basis, wh ** 2, t, np.zeros(z.shape[1]), None, bin_s))
    ch = np.arange(z.shape[1])
    h = np.log(vals[1, 0] / vals[0, 0])
    i = np.argmax(ll, axis=0)
    inner = (i > 0) & (i < n_grid - 1)
    if n_fine > 2 and np.any(inner):
        # a fine grid over [i - 1, i + 1] of the coarse one, the same for every channel
        # in units of the coarse step (channels at the grid's ends keep the coarse value)
        u = np.linspace(-1.0, 1.0, n_fine)
        fine = vals[i, ch][None, :] * np.exp(h * u)[:, None]  # (F, n)
        qf, gmf = _args(kind, fine)
        llf = ll_of(qf, gmf)
        j = np.clip(np.argmax(llf, axis=0), 1, n_fine - 2)
        hf = h * (u[1] - u[0])
        a, b, c = llf[j - 1, ch], llf[j, ch], llf[j + 1, ch]
        curv = (a - 2 * b + c) / hf ** 2
        shift = np.where(curv < 0, -(c - a) / (2 * hf * np.where(curv < 0, curv, -1.0)),
                         0.0)
        shift = np.clip(shift, -hf, hf)
        ref = fine[j, ch] * np.exp(shift)
        llr = b - 0.5 * curv * shift ** 2  # log L at the vertex
        llr = np.maximum(np.maximum(llr, b), ll[i, ch])
        best = np.where(inner, ref, vals[i, ch])
        llb = np.where(inner, llr, ll[i, ch])
        c2 = np.where(inner, curv, 0.0)
    else:
        best, llb, c2 = vals[i, ch], ll[i, ch], np.zeros(z.shape[1])
    lr = 2 * (llb - ll0)
    sig = np.where(inner & (c2 < 0), best / np.sqrt(np.where(c2 < 0, -c2, 1.0)), np.nan)
    found = lr > 0
    return np.where(found, best, 0.0), np.where(found, sig, np.nan), np.where(found, lr, 0.0)
