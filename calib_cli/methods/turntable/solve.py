"""One Gauss-Newton step of the rotating-table fit: the normal equations of every cycle's
rows (rows.py) and the prior, solved with the local states (each block's attitude error
and the rate channel's walk) eliminated cycle by cycle.

The local states of a cycle form a block-tridiagonal system (a block's rows touch its
own states, the propagation rows two neighbours), stored banded for LAPACK's banded
Cholesky; the parameters couple all blocks. Eliminating the local states leaves the
Schur complement S for the parameters: its inverse is their covariance (the Kalman
filter's, smoothed: for constant parameters the filter's final covariance), and the
smoothed local states follow by back-substitution. Cost per pass: linear in the blocks,
with p + 1 right-hand sides per cycle."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.linalg import cho_solve_banded, cholesky_banded

from calib_cli.methods.turntable.rows import CycleSystem


@dataclass
class Normal:
    """One cycle's normal equations: D (nb, nl, nl) diagonal blocks, O (nb - 1, nl, nl)
    the blocks (j + 1, j), G (nb, nl, p) local x parameter, bL (nb, nl), and the factor of
    the banded local part (``cho``)."""

    D: np.ndarray
    O: np.ndarray
    G: np.ndarray
    bL: np.ndarray
    cho: np.ndarray | None = None


def whitened(cs: CycleSystem):
    """(A_loc, A_glob, r) times the rows' weights (kept until the weights change)."""
    if cs.white is None:
        w = cs.weight
        cs.white = (cs.A_loc * w[..., None], cs.A_glob * w[..., None], cs.r * w)
    return cs.white


# the measurement rows' groups: a group's weights change together when its noise level is
# re-estimated (the normal equations are kept per group and rescaled, not rebuilt)
GROUPS = {"accel": slice(0, 3), "axis": slice(3, 5), "angle": slice(5, 6), "rate": slice(6, 7)}


def _group_parts(cs: CycleSystem, p: int) -> dict:
    """Each row group's contribution (D, G, bL, LGG, bG, cost) at the rows' weights."""
    Al, Ag, rw = whitened(cs)
    out = {}
    for name, sl in GROUPS.items():
        if not np.any(cs.weight[:, sl] > 0):
            continue
        al, ag, r = Al[:, sl], Ag[:, sl], rw[:, sl]
        ag2 = ag.reshape(-1, p)
        out[name] = (np.einsum("bri,brj->bij", al, al), np.einsum("bri,brp->bip", al, ag),
                     np.einsum("bri,br->bi", al, r), ag2.T @ ag2, ag2.T @ r.ravel(),
                     float(r.ravel() @ r.ravel()))
    return out


def normal_equations(cs: CycleSystem, p: int) -> tuple[Normal, np.ndarray, np.ndarray, float]:
    """(Normal, Lambda_GG (p, p), b_G (p,), cost) of one cycle's rows: the row groups'
    parts (cached on the system, scaled by ``cs.scales``), the propagation and the start."""
    nb, nl = cs.nb, cs.nl
    if cs.parts is None:
        cs.parts = _group_parts(cs, p)
    D = np.zeros((nb, nl, nl))
    G = np.zeros((nb, nl, p))
    bL = np.zeros((nb, nl))
    LGG = np.zeros((p, p))
    bG = np.zeros(p)
    cost = 0.0
    for name, (d, g_, b, L, bg, c) in cs.parts.items():
        k = cs.scales.get(name, 1.0)
        D += k * d
        G += k * g_
        bL += k * b
        LGG += k * L
        bG += k * bg
        cost += k * c
    O = np.zeros((max(nb - 1, 0), nl, nl))
    # propagation of phi: rows phi_j+1 - F_j phi_j - B_j dtheta_g + e_j with weight W_j (the
    # inverse of the attitude walk's covariance over the block, cs.Wq)
    Wq = cs.Wq
    g = cs.gyro_idx
    FT = np.swapaxes(cs.F, 1, 2)
    WF = np.matmul(Wq, cs.F)
    WB = np.matmul(Wq, cs.B)
    We = np.einsum("bij,bj->bi", Wq, cs.e)
    D[:-1, :3, :3] += np.matmul(FT, WF)
    D[1:, :3, :3] += Wq
    O[:, :3, :3] -= WF
    G[:-1, :3, g] += np.matmul(FT, WB)
    G[1:, :3, g] -= WB
    LGG[np.ix_(g, g)] += np.einsum("bip,biq->pq", cs.B, WB)
    bL[:-1, :3] += np.einsum("bij,bj->bi", FT, We)
    bL[1:, :3] -= We
    bG[g] += np.einsum("bip,bi->p", cs.B, We)
    cost += float(np.einsum("bi,bi->", cs.e, We))
    if cs.anchor is not None:  # weak priors on some directions of every block's phi
        D[:, :3, :3] += cs.anchor
    if nl == 4:  # the rate channel's integrated noise: (rho_j+1 - rho_j) / sqrt(q_rho)
        wr = 1.0 / cs.q_rho
        d = np.diff(cs.rho)
        D[:-1, 3, 3] += wr
        D[1:, 3, 3] += wr
        O[:, 3, 3] -= wr
        bL[:-1, 3] += wr * d
        bL[1:, 3] -= wr * d
        cost += wr * float(d @ d)
        # its start: the walk begins at the first reading (the zero is a parameter)
        w0 = 1e12
        D[0, 3, 3] += w0
        bL[0, 3] -= w0 * cs.rho[0]
        cost += w0 * cs.rho[0] ** 2
    # the start attitude's prior (around the coarse start: a weak one, for the directions
    # nothing else fixes, such as the heading on a vertical axis)
    w0 = 1.0 / cs.sd0**2
    D[0, :3, :3] += w0 * np.eye(3)
    bL[0, :3] += w0 * cs.r0
    cost += w0 * float(cs.r0 @ cs.r0)
    return Normal(D, O, G, bL), LGG, bG, cost


def set_weight(cs: CycleSystem, group: str, w: float) -> None:
    """Give a row group (with uniform weights) the weight w: its rows' weights and the
    scale of its cached normal-equation part."""
    sl = GROUPS[group]
    used = cs.weight[:, sl] > 0
    if not used.any():
        return
    old = float(cs.weight[:, sl][used][0])
    cs.weight[:, sl] = np.where(used, w, 0.0)
    cs.scales[group] = cs.scales.get(group, 1.0) * (w / old) ** 2
    cs.white = None


def scale_weight(cs: CycleSystem, group: str, factor: float) -> None:
    """Multiply a row group's weights by ``factor`` (and its cached part's scale)."""
    sl = GROUPS[group]
    cs.weight[:, sl] *= factor
    cs.scales[group] = cs.scales.get(group, 1.0) * factor ** 2
    cs.white = None


def banded(nm: Normal) -> np.ndarray:
    """LAPACK lower banded storage of the block-tridiagonal local matrix."""
    nb, nl = nm.D.shape[:2]
    n = nb * nl
    kd = 2 * nl - 1
    ab = np.zeros((kd + 1, n))
    for a in range(nl):
        for d in range(kd + 1):
            if a + d < nl:  # within the diagonal block
                ab[d, a::nl] = nm.D[:, a + d, a]
            elif a + d - nl < nl and nb > 1:  # the block below
                ab[d, a:n - nl:nl] = nm.O[:, a + d - nl, a]
    return ab


def factor(nm: Normal) -> None:
    nm.cho = cholesky_banded(banded(nm), lower=True)


def local_solve(nm: Normal, rhs: np.ndarray) -> np.ndarray:
    """Lambda_LL^-1 rhs, rhs (nb * nl, k)."""
    return cho_solve_banded((nm.cho, True), rhs)


@dataclass
class Step:
    """A solved step: dtheta (p,), the local steps per cycle (nb, nl), the parameters'
    covariance S^-1 (p, p), the cost at the linearisation point and its predicted value
    after the step, the Schur complement S and right-hand side s, the normal equations
    (for further right-hand sides: ``solve_more``) and the locals' solutions X_G, X_b
    (the locals' step is X_b - X_G dtheta for any parameter step)."""

    dtheta: np.ndarray
    dlocal: list
    cov: np.ndarray
    cost: float
    predicted: float
    S: np.ndarray
    normals: list
    XG: list
    s: np.ndarray = None
    Xb: list = None
    base: float = 0.0  # the cost with the locals at their best and dtheta = 0


def solve(systems: list, p: int, prior_mean: np.ndarray, prior_sd: np.ndarray,
          theta: np.ndarray) -> Step:
    """One Gauss-Newton step over all cycles' rows and the parameters' prior."""
    prior_w = 1.0 / prior_sd**2
    S = np.diag(prior_w)
    s = prior_w * (prior_mean - theta)
    cost = float(np.sum(prior_w * (prior_mean - theta) ** 2))
    normals, XG, Xb = [], [], []
    base = 0.0
    for cs in systems:
        nm, LGG, bG, c = normal_equations(cs, p)
        factor(nm)
        Gf = nm.G.reshape(-1, p)
        # only the parameters the cycle's rows touch (not the other cycles' lever arms,
        # mountings, runout, channel zeros) take part in its elimination
        cols = np.flatnonzero(np.any(Gf != 0.0, axis=0))
        Gc = Gf[:, cols]
        X = local_solve(nm, np.column_stack([Gc, nm.bL.ravel()]))
        S[np.ix_(cols, cols)] += -Gc.T @ X[:, :-1]
        S += LGG
        s += bG
        s[cols] -= Gc.T @ X[:, -1]
        cost += c
        normals.append(nm)
        xg = np.zeros((Gf.shape[0], p))
        xg[:, cols] = X[:, :-1]
        XG.append(xg)
        Xb.append(X[:, -1])
        base += float(nm.bL.ravel() @ X[:, -1])
    S = 0.5 * (S + S.T)
    L = np.linalg.cholesky(S)
    dtheta = np.linalg.solve(L.T, np.linalg.solve(L, s))
    Li = np.linalg.solve(L, np.eye(p))
    cov = Li.T @ Li
    dlocal = [(xb - xg @ dtheta).reshape(nm.D.shape[0], nm.D.shape[1])
              for nm, xg, xb in zip(normals, XG, Xb)]
    pred = cost - base - float(dtheta @ s)
    return Step(dtheta, dlocal, cov, cost, pred, S, normals, XG, s, Xb, base)


def damped(step: Step, lam: float, pinned: np.ndarray | None = None) -> Step:
    """The step with the parameters' part damped (Levenberg-Marquardt: S + lam diag(S)),
    the locals at their best for it; its predicted cost on the same linearisation.
    pinned: parameter indices that do not move (the others at their best given that;
    the covariance stays the full one, so their sigma keeps the pinned ones' spread)."""
    Sd = step.S + lam * np.diag(np.diag(step.S))
    if pinned is None or len(pinned) == 0:
        d = np.linalg.solve(Sd, step.s)
    else:
        free = np.setdiff1d(np.arange(len(step.s)), pinned)
        d = np.zeros_like(step.s)
        d[free] = np.linalg.solve(Sd[np.ix_(free, free)], step.s[free])
    return _moved_by(step, d)


def scaled(step: Step, alpha: float, pinned: np.ndarray | None = None) -> Step:
    """The Gauss-Newton step (pinned: as in ``damped``) shortened to alpha of itself along
    its own direction, the locals at their best for it; its predicted cost."""
    return _moved_by(step, alpha * damped(step, 0.0, pinned).dtheta)


def _moved_by(step: Step, d: np.ndarray) -> Step:
    """The step whose parameters' part is d, the locals at their best given d."""
    dlocal = [(xb - xg @ d).reshape(dl.shape) for xb, xg, dl in zip(step.Xb, step.XG,
                                                                     step.dlocal)]
    pred = step.cost - step.base - 2.0 * float(d @ step.s) + float(d @ step.S @ d)
    return Step(d, dlocal, step.cov, step.cost, pred, step.S, step.normals, step.XG, step.s,
                step.Xb, step.base)


def solve_more(step: Step, yL: list, yG: np.ndarray) -> tuple[list, np.ndarray]:
    """The full system's solution for further right-hand sides: yL per cycle (nb * nl, k),
    yG (p, k). Returns (x_L per cycle, x_G)."""
    rhs = yG.copy()
    Z = []
    for nm, y in zip(step.normals, yL):
        z = local_solve(nm, y)
        Z.append(z)
        rhs -= nm.G.reshape(-1, yG.shape[0]).T @ z
    xG = np.linalg.solve(step.S, rhs)
    xL = [z - xg @ xG for z, xg in zip(Z, step.XG)]
    return xL, xG


def residuals_after(cs: CycleSystem, dl: np.ndarray, dtheta: np.ndarray) -> np.ndarray:
    """The measurement rows' residuals (nb, 7) after the step, in the data's units."""
    return cs.r - np.einsum("bri,bi->br", cs.A_loc, dl) - cs.A_glob @ dtheta


def leverage(step: Step, systems: list, groups: dict, probes: int = 4,
             seed: int = 0) -> dict:
    """Per row group {name: row slot or slice}: the trace of the hat matrix over its used
    rows (Hutchinson's estimator with ``probes`` Rademacher vectors per group, fixed seed,
    all groups in one solve): what the fit takes out of the rows' noise, for the noise
    levels' estimates sum r^2 / (n - trace)."""
    rng = np.random.default_rng(seed)
    p = step.S.shape[0]
    names = list(groups)
    k = probes * len(names)
    V, yL, W = [], [], []
    yG = np.zeros((p, k))
    for cs in systems:
        Al, Ag, _ = whitened(cs)
        nb, R = cs.weight.shape
        v = np.zeros((nb, R, k))
        for g, name in enumerate(names):
            slot = groups[name]
            mask = np.zeros(cs.weight.shape, bool)
            mask[:, slot] = cs.weight[:, slot] > 0
            v[:, :, g * probes:(g + 1) * probes] = rng.choice(
                [-1.0, 1.0], size=(nb, R, probes)) * mask[:, :, None]
        V.append(v)
        W.append((Al, Ag))
        yL.append(np.matmul(np.swapaxes(Al, 1, 2), v).reshape(-1, k))  # (nb nl, k)
        yG += Ag.reshape(-1, p).T @ v.reshape(-1, k)
    xL, xG = solve_more(step, yL, yG)
    tot = np.zeros(k)
    for cs, v, xl, (Al, Ag) in zip(systems, V, xL, W):
        Ax = np.matmul(Al, xl.reshape(cs.nb, cs.nl, k)) + (Ag.reshape(-1, p) @ xG).reshape(
            cs.nb, -1, k)
        tot += np.einsum("brk,brk->k", v, Ax)
    return {name: float(tot[g * probes:(g + 1) * probes].mean()) for g, name in enumerate(names)}
