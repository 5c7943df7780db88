"""Strapdown integration of gyro rates: the rotation of the body between two
instants, relative to the local-level frame.

The inverse of ``kinematics.from_attitude``'s rate term: a gyro measures the
body rate against inertial space, w = w_rel + C(t)^T W_ie, where C(t) is the
body->ENU attitude; the local-level frame turns with the earth, so the
rotation of the unit on its bench is the integral of w_rel = w - C(t)^T W_ie.
At navigation grade the earth-rate term over a 10-20 s turn (~1e-3 rad) is far
larger than the errors sought, so it is removed here, sample by sample.

Convention: R_rel(t) maps body vectors at time t into body axes at the first
instant (C(t) = C0 R_rel(t)); R_rel(t + dt) = R_rel(t) Exp(w_rel dt) with the
trapezoid (mid-interval) rate over each sample interval.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from calib_cli.model.earth import Site
from calib_cli.model.frames import skew


@dataclass(frozen=True)
class RelativeRotation:
    """Result of ``integrate_relative``.

    dR: rotation body(end) -> body(start). duration: s.
    S_bias (3, 3): d psi / d(rate bias): psi = -S_bias d_eps for a change of
        the gyro bias d_eps (rad/s) subtracted from the rates.
    S_K (3, 9): d psi / d(vec dG) for a gyro transfer error G = I + dG
        (row-major vec), rates corrected by G^-1: psi = -S_K vec(dG).
    noise_cov (3, 3): covariance of psi from white rate noise of per-sample
        standard deviation ``sigma`` (rad/s) per axis.
    Here psi (rad, start-body axes) is the first-order change of the rotation:
    dR' = Exp(psi) dR. A change alpha (rad, ENU) of the start attitude,
    C0' = Exp(alpha) C0, changes the removed earth rate and gives
    psi = -duration C0^T [W_ie x] alpha (see ``earth_sensitivity``).
    """

    dR: Rotation
    duration: float
    S_bias: np.ndarray
    S_K: np.ndarray
    noise_cov: np.ndarray

    def earth_sensitivity(self, C0: Rotation, site: Site) -> np.ndarray:
        """d psi / d alpha (3, 3) for a change alpha (ENU) of the start attitude."""
        return -self.duration * C0.inv().as_matrix() @ skew(site.earth_rate_enu)


def integrate_relative(t: np.ndarray, w: np.ndarray, C0: Rotation, site: Site,
                       sigma=None) -> RelativeRotation:
    """Integrate body rates w (N, 3, rad/s, against inertial space, already
    corrected for bias and scale) at times t (N,) from the first sample to the
    last, removing the earth rate seen from the turning body, with C0 the
    body->ENU attitude at t[0]. sigma: per-sample white rate noise (3,) for
    ``noise_cov`` (None: zero)."""
    t = np.asarray(t, dtype=float)
    w = np.asarray(w, dtype=float)
    n = len(t)
    W_n = site.earth_rate_enu
    C0m = C0.as_matrix()
    R = np.empty((n, 3, 3))
    R[0] = np.eye(3)
    dts = np.diff(t)
    wmid = 0.5 * (w[1:] + w[:-1])
    for i in range(n - 1):
        Ri = R[i]
        # earth rate in body axes at mid-interval: a fixed vector seen from a body
        # turning at w moves by -w x e (second-order accurate step)
        e_body = (C0m @ Ri).T @ W_n
        e_body = e_body - 0.5 * np.cross(wmid[i] * dts[i], e_body)
        step = (wmid[i] - e_body) * dts[i]
        R[i + 1] = Ri @ exp_matrix(step)
    dt = np.concatenate([dts, [0.0]])
    # psi = sum_i R_{i+1/2} delta_w_i dt_i (left perturbation in start-body axes;
    # the mid-interval attitude carries a rate change within the step to second order)
    Rn = 0.5 * (R[1:] + R[:-1])
    S_bias = np.einsum("nij,n->ij", Rn, dts)
    S_K = np.einsum("nar,nc->arc", Rn, wmid * dts[:, None]).reshape(3, 9)
    if sigma is None:
        noise = np.zeros((3, 3))
    else:
        s2 = np.asarray(sigma, dtype=float) ** 2 * np.ones(3)
        noise = np.einsum("nij,j,nkj,n->ik", R, s2, R, dt**2)
    return RelativeRotation(Rotation.from_matrix(R[-1]), float(t[-1] - t[0]), S_bias, S_K, noise)


def exp_matrix(phi) -> np.ndarray:
    """Rotation matrix Exp([phi x]) (3, 3) of one rotation vector phi (3,), rad (Rodrigues;
    for one vector at a time, where SciPy's per-call overhead dominates a filter's time)."""
    phi = np.asarray(phi, dtype=float)
    a2 = float(phi @ phi)
    K = skew(phi)
    # [phi x]^2 = phi phi^T - |phi|^2 I
    if a2 < 1e-16:
        c0, c1, c2 = 1.0 - 0.5 * a2, 1.0, 0.5
    else:
        a = np.sqrt(a2)
        c0, c1, c2 = np.cos(a), np.sin(a) / a, (1.0 - np.cos(a)) / a2
    out = c1 * K + (c2 * phi)[:, None] * phi
    out[0, 0] += c0
    out[1, 1] += c0
    out[2, 2] += c0
    return out


def left_jacobian(phi: np.ndarray) -> np.ndarray:
    """SO(3)'s left Jacobian J_l(phi) (n, 3, 3) of rotation vectors phi (n, 3), rad:
    Exp(phi + d) = Exp(J_l(phi) d) Exp(phi) to first order in d, i.e. how a change of a
    step's rate moves the attitude at the step's end. J_l = I + a [phi x] + b [phi x]^2,
    a = (1 - cos t) / t^2, b = (t - sin t) / t^3, t = |phi| (series below 1e-3 rad)."""
    phi = np.asarray(phi, dtype=float)
    t2 = np.einsum("ni,ni->n", phi, phi)
    t = np.sqrt(t2)
    small = t < 1e-3
    ts = np.where(small, 1.0, t)
    a = np.where(small, 0.5 - t2 / 24.0, (1.0 - np.cos(ts)) / ts**2)
    b = np.where(small, 1.0 / 6.0 - t2 / 120.0, (ts - np.sin(ts)) / ts**3)
    # [phi x]^2 = phi phi^T - |phi|^2 I, without a batched matrix product
    J = b[:, None, None] * (phi[:, :, None] * phi[:, None, :]) + a[:, None, None] * skew(phi)
    J[:, (0, 1, 2), (0, 1, 2)] += (1.0 - b * t2)[:, None]
    return J


def log_matrix(M: np.ndarray) -> np.ndarray:
    """Rotation vector (3,) of one rotation matrix M (3, 3) of angle below 180 deg, rad
    (the inverse of ``exp_matrix``)."""
    v = 0.5 * np.array([M[2, 1] - M[1, 2], M[0, 2] - M[2, 0], M[1, 0] - M[0, 1]])
    sn = float(np.sqrt(v @ v))
    th = np.arctan2(sn, 0.5 * (M[0, 0] + M[1, 1] + M[2, 2] - 1.0))
    return v * (th / sn) if sn > 1e-12 else v


def step_rotvec(w: np.ndarray, dt: np.ndarray, sample_kind: str = "instant") -> np.ndarray:
    """Rotation vectors (N, 3) of the steps between samples, body axes, rad. w (N, 3)
    rad/s, dt (N,) s the step after each sample. ``instant`` samples (values at the
    stamps): the mid-interval rate (w_k + w_k+1)/2 over [t_k, t_k+1] (else the attitude
    lags half a sample); ``interval-mean`` samples (means over [t_k - dt, t_k]): sample
    k is the mean rate of its own period, so step k spans [t_k - dt, t_k] and is exact
    for a rotation about a fixed axis."""
    if sample_kind == "interval-mean":
        return w * dt[:, None]
    wmid = np.concatenate([0.5 * (w[1:] + w[:-1]), w[-1:]])
    return wmid * dt[:, None]


def mean_rotation(phi: np.ndarray) -> np.ndarray:
    """Mean over s in [0, 1] of Exp(s phi) (..., 3, 3), for rotation vectors phi (..., 3):
    I + (1 - cos a)/a [u x] + (1 - sin a / a) [u x]^2, a = |phi| (the mean attitude
    over a step of constant rate, for samples that are interval means)."""
    phi = np.asarray(phi, dtype=float)
    a = np.linalg.norm(phi, axis=-1)
    small = a < 1e-6
    a_safe = np.where(small, 1.0, a)
    c1 = np.where(small, 0.5, (1 - np.cos(a_safe)) / a_safe**2)  # (1 - cos a)/a / a
    c2 = np.where(small, 1.0 / 6.0, (1 - np.sin(a_safe) / a_safe) / a_safe**2)
    K = skew(phi)
    return np.eye(3) + c1[..., None, None] * K + c2[..., None, None] * (K @ K)


def rotation_increments(w: np.ndarray, t: np.ndarray, sample_kind: str = "instant",
                        s: np.ndarray | None = None):
    """Rotation vectors (N-1, 3) from stamp k to k+1 (instant samples) or over sample k+1's
    own period (interval means), body axes, rad, from rates w (N, 3) at times t (N,); with
    ``s`` (N, 3, P), d w / d theta, also their sensitivities (N-1, 3, P).

    Instant samples (the rate at the stamp): the integral of the cubic through the four
    nearest stamps, dt (-w_k-1 + 13 w_k + 13 w_k+1 - w_k+2) / 24, exact to the fourth order
    in dt (the mid-interval rate's error, dt^3 w'' / 12 a step, showed as a gyro scale
    error of 1.4e-5 on a sinusoidal profile at 100 Hz); the first and last intervals take
    the mid-interval rate. Plus the coning term (w_k x w_k+1) dt^2 / 12 of a rate vector
    that turns within the interval. Interval means (the mean rate over [t_k - dt, t_k]): the
    sample times its period, exact for a fixed axis, plus the coning term of two
    consecutive periods (phi_k-1 x phi_k) / 12."""
    w = np.asarray(w, dtype=float)
    dt = np.diff(np.asarray(t, dtype=float))
    if sample_kind == "interval-mean":
        phi = w[1:] * dt[:, None]
        coning = np.zeros_like(phi)
        coning[1:] = np.cross(phi[:-1], phi[1:]) / 12.0
        ds = None if s is None else s[1:] * dt[:, None, None]
        return (phi + coning, ds) if s is not None else phi + coning
    mean_w = _cubic_means(w)
    phi = mean_w * dt[:, None] + np.cross(w[:-1], w[1:]) * (dt[:, None] ** 2 / 12.0)
    if s is None:
        return phi
    return phi, _cubic_means(s) * dt.reshape((-1,) + (1,) * (s.ndim - 1))


def cumulative_integral(x: np.ndarray, t: np.ndarray) -> np.ndarray:
    """The integral (N,) of instant samples x (N,) at stamps t (N,) from t[0] to each stamp,
    by the cubic through four stamps (``_cubic_means``): a table's rate channel read as an
    angle. The trapezoid's error, dt^2 x'' / 12 a unit time, is a scale error of
    (w dt)^2 / 12 on an oscillation of w rad/s (7e-6 at 0.15 Hz and 100 Hz), which a cycle
    of another frequency does not share and the gyros' scale took."""
    x = np.asarray(x, dtype=float)
    steps = _cubic_means(x) * np.diff(np.asarray(t, dtype=float))
    return np.concatenate([[0.0], np.cumsum(steps)])


def _cubic_means(x: np.ndarray) -> np.ndarray:
    """The mean over each interval k..k+1 (N-1, ...) of the cubic through the samples
    k-1..k+2 of x (N, ...): (-x_k-1 + 13 x_k + 13 x_k+1 - x_k+2) / 24; the first and
    last intervals (and records of fewer than four samples) the mid-interval value."""
    out = 0.5 * (x[:-1] + x[1:])
    if len(x) >= 4:
        out[1:-1] += (-(x[:-3] + x[3:]) + (x[1:-2] + x[2:-1])) / 24.0
    return out


@dataclass(frozen=True)
class BlockIntegration:
    """The attitude within blocks of m samples, relative to each block's start, from the
    corrected rates (``block_integration``). dR (nb, m, 3, 3): each sample's attitude
    (instant: at its stamp; interval means: the mean over its period), body(sample) ->
    body(block start); r_mean (nb, 3, 3) their mean; r_end (nb, 3, 3) the next block's
    start. The sensitivity to the parameters theta (P of them) as the left perturbation in
    block-start axes, dR' = Exp(q dtheta) dR: q_end (nb, 3, P) at the block's end, qbar
    (nb, 3, P) the samples' mean, wg (3, nb, 3, P) the mean of dR^T [e_c x] q (how the
    samples' gravity moves: sum_c gamma_c wg[c] for gravity gamma in block-start axes)."""

    dR: np.ndarray
    r_mean: np.ndarray
    r_end: np.ndarray
    q_end: np.ndarray
    qbar: np.ndarray
    wg: np.ndarray


def block_integration(w: np.ndarray, s: np.ndarray, t: np.ndarray, block_n: int, nb: int,
                      sample_kind: str = "instant", group: int = 1) -> BlockIntegration:
    """Integrate corrected rates w (N, 3) over nb blocks of block_n samples (N >= nb
    block_n; a sample after the last block is used where there is one), with the rates'
    sensitivity s = d w / d theta given per group of ``group`` consecutive samples (its
    mean over the group: (nb block_n / group, 3, P)). Instant samples: block j starts at
    the stamp of its first sample; interval means: at the start of its first sample's
    period. The attitude is integrated sample by sample, the sensitivity (the sum of
    R J_l(step) dt times the step's rate sensitivity) sample by sample with s constant
    over each group: exact for a sensitivity constant over the group (a bias), else an
    error of the Jacobian (of the order of the group's length squared), not of the
    prediction."""
    w = np.asarray(w, dtype=float)
    P = s.shape[-1]
    n = nb * block_n
    G = block_n // group
    interval = sample_kind == "interval-mean"
    if interval:  # increment k: sample k's own period; prepend the first period
        t_ext = np.concatenate([[t[0] - (t[1] - t[0])], t[:n]])
        phi = rotation_increments(np.concatenate([w[:1], w[:n]]), t_ext, sample_kind)
        dts = np.diff(t_ext)
    else:
        m_end = min(len(w), n + 2)
        tt = np.asarray(t[:m_end], float)
        ww = w[:m_end]
        if m_end == n:  # no stamp after the last block: the last interval repeated
            tt = np.append(tt, 2 * tt[-1] - tt[-2])
            ww = np.concatenate([ww, ww[-1:]])
        phi = rotation_increments(ww, tt, sample_kind)[:n]
        dts = np.diff(tt)[:n]
    rots = Rotation.from_rotvec(phi).as_matrix().reshape(nb, block_n, 3, 3)
    # each step's weight of the rate's sensitivity: R_i J_l(step_i) dt_i (the attitude's
    # left perturbation at the step's end per unit of rate change over the step)
    Jl = (left_jacobian(phi) * dts[:, None, None]).reshape(nb, block_n, 3, 3)
    R = np.tile(np.eye(3), (nb, 1, 1))
    dR = np.empty((nb, block_n, 3, 3))
    RJ = np.empty((nb, block_n, 3, 3))
    for i in range(block_n):
        RJ[:, i] = R @ Jl[:, i]
        dR[:, i] = R @ mean_rotation(phi.reshape(nb, block_n, 3)[:, i]) if interval else R
        R = R @ rots[:, i]
    # the sensitivity: sample i's rate sensitivity s_g + (i - mid) ds_g within group g (its
    # mean and slope), so the sums of R J dt s over a group take the first and second
    # moments of R J dt: q_k+1 = q_k + M0 s_g + M1 ds_g
    # X (nb, G, 9, P): each group's [qb; s; ds], the sensitivity at the group's start, the
    # rates' sensitivity and its slope, in one buffer (no concatenation of the largest
    # arrays of a pass)
    X = np.empty((nb, G, 9, P))
    X[:, :, 3:6] = s.reshape(nb, G, 3, P)
    flat = s.reshape(nb * G, 3, P)
    slope = np.zeros_like(flat)  # per sample, from the neighbouring groups' means
    if len(flat) > 2:
        slope[1:-1] = (flat[2:] - flat[:-2]) / (2.0 * group)
    if len(flat) > 1:
        slope[0] = (flat[1] - flat[0]) / group
        slope[-1] = (flat[-1] - flat[-2]) / group
    X[:, :, 6:9] = slope.reshape(nb, G, 3, P)
    RJg = RJ.reshape(nb, G, group, 3, 3)
    # each step's offset from the group's middle: instant samples' step k -> k+1 takes the
    # sensitivity half-way between the stamps (at stamp k, the step lagged by half a
    # sample: 1e-3 of every gyro column on ramps, a gradient 6x off along a vertical
    # axis's valley); an interval mean's step is its own sample's
    off = np.arange(group) - 0.5 * (group - 1) + (0.0 if interval else 0.5)
    RJ1 = RJg * off[None, None, :, None, None]
    dq = np.matmul(RJg.sum(axis=2), X[:, :, 3:6]) + np.matmul(RJ1.sum(axis=2), X[:, :, 6:9])
    X[:, 0, :3] = 0.0
    if G > 1:
        np.cumsum(dq[:, :-1], axis=1, out=X[:, 1:, :3])
    q_end = X[:, -1, :3] + dq[:, -1]
    # within a group, sample i's sensitivity is qb + P0_i s + P1_i ds, the partial sums of
    # R J dt (times the offset) up to it (instant samples: the steps before its stamp;
    # interval means: to the middle of its own period)
    half = 0.5 if interval else 1.0
    P0 = np.cumsum(RJg, axis=2) - half * RJg
    P1 = np.cumsum(RJ1, axis=2) - half * RJ1
    # wg[c] = mean dR^T [e_c x] q over the block's samples, q_i = qb_g + P0_i s_g + P1_i
    # ds_g: (dR^T [e_c x] Y)_an = sum_km eps_kcm dR_ka Y_mn, so each group's mean of the
    # per-sample products dR_ka Y_mn (one 9 x 9 product over the group's samples) and then
    # the Levi-Civita contraction; rows (nb, 12, G, 9): per group [mean N, mean N P0, mean
    # N P1] (N = dR^T [e_c x], the three c stacked: 9 x 3) over [I, mean P0, mean P1],
    # times X in one product over the groups
    dRf = np.swapaxes(dR.reshape(nb, G, group, 9), 2, 3)  # (nb, G, 9 [k a], group)
    rows = np.empty((nb, 12, G, 9))
    top = rows[:, :9].reshape(nb, 3, 3, G, 9)  # [c, a, g, j]
    top[..., :3] = np.einsum("kcm,bgka->bcagm", _LEVI_CIVITA,
                             dR.reshape(nb, G, group, 3, 3).mean(axis=2), optimize=True)
    for j, Y in ((3, P0), (6, P1)):
        S = np.matmul(dRf, Y.reshape(nb, G, group, 9)).reshape(nb, G, 3, 3, 3, 3) / group
        top[..., j:j + 3] = np.einsum("kcm,bgkamn->bcagn", _LEVI_CIVITA, S, optimize=True)
    rows[:, :9] = top.reshape(nb, 9, G, 9)
    rows[:, 9:, :, :3] = np.eye(3)[None, :, None, :]
    rows[:, 9:, :, 3:6] = np.swapaxes(P0.mean(axis=2), 1, 2)
    rows[:, 9:, :, 6:9] = np.swapaxes(P1.mean(axis=2), 1, 2)
    out = np.matmul(rows.reshape(nb, 12, G * 9), X.reshape(nb, G * 9, P)) / G  # (nb, 12, P)
    wg = np.moveaxis(out[:, :9].reshape(nb, 3, 3, P), 1, 0)
    q_mean = out[:, 9:]
    return BlockIntegration(dR, dR.mean(axis=1), R, q_end, q_mean, wg)


def cross_columns(r: np.ndarray, Y: np.ndarray) -> np.ndarray:
    """r x (each column of Y): r (..., 3), Y (..., 3, k)."""
    r0, r1, r2 = r[..., 0, None], r[..., 1, None], r[..., 2, None]
    y0, y1, y2 = Y[..., 0, :], Y[..., 1, :], Y[..., 2, :]
    return np.stack([r1 * y2 - r2 * y1, r2 * y0 - r0 * y2, r0 * y1 - r1 * y0], axis=-2)


def cross_e(c: int, X: np.ndarray) -> np.ndarray:
    """[e_c x] X for X (..., 3, k): a signed swap of its rows."""
    out = np.zeros_like(X)
    a, b = (c + 1) % 3, (c + 2) % 3
    out[..., a, :] = -X[..., b, :]
    out[..., b, :] = X[..., a, :]
    return out


# eps[k, c, m] = ([e_c x])_km, so (M [e_c x])_am = sum_k M_ak eps[k, c, m]
_LEVI_CIVITA = np.stack([cross_e(c, np.eye(3)) for c in range(3)], axis=1)


def group_means(x: np.ndarray, group: int) -> np.ndarray:
    """Means over consecutive groups of ``group`` rows (len(x) a multiple of it)."""
    if group == 1:
        return x
    return x.reshape((len(x) // group, group) + x.shape[1:]).mean(axis=1)


def edge_stencil(N: int, block_n: int, nb: int, sample_kind: str = "instant"):
    """(idx (nb + 1, 4), weights (nb + 1, 4)) of ``edge_rates``: the samples and weights
    of the rate at each block edge, from a record of N samples."""
    k = np.arange(nb + 1) * block_n  # the interface between samples k-1 and k
    wt = np.array([-1.0, 9.0, 9.0, -1.0]) / 16.0 if sample_kind != "interval-mean" else \
        np.array([-1.0, 7.0, 7.0, -1.0]) / 12.0
    idx = k[:, None] + np.arange(-2, 2)[None, :]
    ok = (idx[:, 0] >= 0) & (idx[:, 3] <= N - 1)
    c = np.tile(wt, (nb + 1, 1))
    c[~ok] = 0.0
    first, last = k == 0, k >= N
    mid2 = ~ok & ~first & ~last
    c[mid2, 1] = c[mid2, 2] = 0.5
    idx = np.clip(idx, 0, N - 1)
    if np.any(first):
        idx[first] = [0, 0, 0, 1]
        c[first] = [0.0, 0.0, 1.5, -0.5]
    if np.any(last):
        idx[last] = [N - 2, N - 2, N - 1, N - 1]
        c[last] = [0.0, -0.5, 1.5, 0.0]
    return idx, c


def edge_rates(w: np.ndarray, block_n: int, nb: int, sample_kind: str = "instant"
               ) -> np.ndarray:
    """The rate (nb + 1, ...) (w (N, ...): rates, or any quantity linear in them) at the
    edges of nb blocks: the bounds of the interval whose mean the block's samples are
    (instant samples: half a sample before the first stamp and after the last; interval
    means: the start of the first period and the last stamp), by the cubic through the
    four nearest samples (instant: (-1, 9, 9, -1) / 16 of the values; interval means:
    (-1, 7, 7, -1) / 12 of the period means), linear at the ends of the record. The
    block's mean angular acceleration is the difference of its edges over its length,
    exact to the second order (the mean of central differences, which this replaces,
    lags a curved rate)."""
    w = np.asarray(w, dtype=float)
    idx, c = edge_stencil(len(w), block_n, nb, sample_kind)
    return np.einsum("kj,kj...->k...", c, w[idx])
