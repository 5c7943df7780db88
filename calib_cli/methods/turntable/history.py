"""The sigma history of the lever arms and proof-mass offsets: the filter's view of the
final linearisation, i.e. the parameters' covariance (and running estimate) given the
data up to each time, by forward elimination of the local states in time order, chunk by
chunk (``history_every`` seconds each). It shows when each entry became observable (the
rough-stand paper's fig. 4); no part of the estimate."""

from __future__ import annotations

import numpy as np

from calib_cli.methods.turntable.solve import whitened

HISTORY_POINTS = 100


def _labels(pb, theta) -> tuple[np.ndarray, np.ndarray, list]:
    """(T (k, p): each history entry as a row over theta, linearised there; its value at
    theta (k,); labels): each cycle's lever arm along its two basis vectors, the proof-mass
    offsets."""
    pm = pb.pm
    rows, vals, labels = [], [], []
    if pm.has("lever_arm"):
        for c, cy in enumerate(pm.rotating()):
            ds_du, ds_dG, gi = pm.lever_jacobian(theta, c)
            s = pm.lever(theta, c)
            for m in range(2):
                e = int(np.argmax(np.abs(cy.basis[:, m])))
                tag = "xyz"[e] if abs(abs(cy.basis[e, m]) - 1) < 1e-12 else f"b{m + 1}"
                labels.append(f"lever_arm[{c}].{tag}")
                row = np.zeros(pm.size)
                row[pm.idx["lever_arm"][c]] = cy.basis[:, m] @ ds_du
                row[gi] += cy.basis[:, m] @ ds_dG
                rows.append(row)
                vals.append(float(cy.basis[:, m] @ s))
    for q, (key, flat) in enumerate(pm.keys):
        if key == "proof_mass_offsets":
            i, j = divmod(flat, 3)
            labels.append(f"p_{'xyz'[i]}{'xyz'[j]}")
            row = np.zeros(pm.size)
            row[pm.idx["packing"][q]] = 1.0
            rows.append(row)
            vals.append(float(theta[pm.idx["packing"][q]]))
    return np.array(rows).reshape(-1, pm.size), np.array(vals), labels


def _chunk_system(cs, Al, Ag, rw, j0: int, j1: int, p: int):
    """The information (M, v) of chunk [j0, j1) of a cycle over (x_prev, x_j0 .. x_j1-1,
    theta): its blocks' rows, the propagation rows into each of its blocks (from x_prev
    into the first) and, at the cycle's start (j0 = 0), the start prior (x_prev then
    takes no part: it is left free of any row)."""
    nl = cs.nl
    k = j1 - j0
    nloc = (k + 1) * nl
    al, ag, r = Al[j0:j1], Ag[j0:j1], rw[j0:j1]
    blocks = np.zeros((k + 1, k + 1, nl, nl))
    ii = np.arange(1, k + 1)
    blocks[ii, ii] = np.einsum("bri,brj->bij", al, al)
    G = np.zeros((k + 1, nl, p))
    G[1:] = np.einsum("bri,brp->bip", al, ag)
    vl = np.zeros((k + 1, nl))
    vl[1:] = np.einsum("bri,br->bi", al, r)
    ag2 = ag.reshape(-1, p)
    Ltt = ag2.T @ ag2
    vt = ag2.T @ r.ravel()
    # propagation rows (-F x_i-1 + x_i - B dtheta_g = -e, weight wq) into each block i with
    # a predecessor: all but the cycle's first
    first = 1 if j0 > 0 else 2
    pos = np.arange(first, k + 1)  # chunk positions (1-based: 0 is x_prev)
    jj = j0 + pos - 1  # their block indices
    g = cs.gyro_idx
    Fm, B, e, Wq = cs.F[jj - 1], cs.B[jj - 1], cs.e[jj - 1], cs.Wq[jj - 1]
    FT = np.swapaxes(Fm, 1, 2)
    WF, WB, We = np.matmul(Wq, Fm), np.matmul(Wq, B), np.einsum("bij,bj->bi", Wq, e)
    blocks[pos - 1, pos - 1, :3, :3] += np.matmul(FT, WF)
    blocks[pos, pos, :3, :3] += Wq
    blocks[pos, pos - 1, :3, :3] -= WF
    blocks[pos - 1, pos, :3, :3] -= np.swapaxes(WF, 1, 2)
    G[np.ix_(pos - 1, np.arange(3), g)] += np.matmul(FT, WB)
    G[np.ix_(pos, np.arange(3), g)] -= WB
    Ltt[np.ix_(g, g)] += np.einsum("bip,biq->pq", B, WB)
    vl[pos - 1, :3] += np.einsum("bij,bj->bi", FT, We)
    vl[pos, :3] -= We
    vt[g] += np.einsum("bip,bi->p", B, We)
    if cs.anchor is not None:
        ii = np.arange(1, k + 1)
        blocks[ii, ii, :3, :3] += cs.anchor[j0:j1]
    if nl == 4:  # the rate channel's walk
        wr = 1.0 / cs.q_rho
        d = cs.rho[jj] - cs.rho[jj - 1]
        blocks[pos - 1, pos - 1, 3, 3] += wr
        blocks[pos, pos, 3, 3] += wr
        blocks[pos, pos - 1, 3, 3] -= wr
        blocks[pos - 1, pos, 3, 3] -= wr
        vl[pos - 1, 3] += wr * d
        vl[pos, 3] -= wr * d
    if j0 == 0:  # the cycle's start prior on its first block; x_prev held by a unit prior
        w0 = 1.0 / cs.sd0**2
        blocks[1, 1, :3, :3] += w0 * np.eye(3)
        vl[1, :3] += w0 * cs.r0
        if nl == 4:
            blocks[1, 1, 3, 3] += 1e12
            vl[1, 3] -= 1e12 * cs.rho[0]
        blocks[0, 0] += np.eye(nl)
    M = np.zeros((nloc + p, nloc + p))
    M[:nloc, :nloc] = blocks.transpose(0, 2, 1, 3).reshape(nloc, nloc)
    Gf = G.reshape(nloc, p)
    M[:nloc, nloc:] = Gf
    M[nloc:, :nloc] = Gf.T
    M[nloc:, nloc:] = Ltt
    return M, np.concatenate([vl.ravel(), vt]), nloc


def sigma_history(pb, pr) -> dict:
    """{"sigma_history_time" (H,), "sigma_history" (H, k), "estimate_history" (H, k),
    "sigma_history_labels" [k]}; empty without lever arms or proof masses."""
    Tm, vals, labels = _labels(pb, pr.theta_lin)
    if not labels:
        return {}
    pm = pb.pm
    p = pm.size
    w = 1.0 / pm.sd**2
    lin = pr.theta_lin  # the history is of the last pass's step about its point
    Lam = np.diag(w)
    eta = w * (pm.mean - lin)
    T = pb.block_n / pb.rec.sample_rate
    # history_every seconds, at most about HISTORY_POINTS per cycle (a plot's resolution)
    longest = max(cs.nb for cs in pr.systems)
    K = max(1, int(round(pb.opt.history_every / T)), int(np.ceil(longest / HISTORY_POINTS)))
    times, sig, est = [], [], []
    for cs, gp in zip(pr.systems, pr.gps):
        Al, Ag, rw = whitened(cs)
        nl = cs.nl
        carried = None  # information over (x_prev, theta)
        for j0 in range(0, cs.nb, K):
            j1 = min(cs.nb, j0 + K)
            M, v, nloc = _chunk_system(cs, Al, Ag, rw, j0, j1, p)
            if carried is None:
                M[nloc:, nloc:] += Lam
                v[nloc:] += eta
            else:
                Mc, vc = carried
                M[:nl, :nl] += Mc[:nl, :nl]
                M[:nl, nloc:] += Mc[:nl, nl:]
                M[nloc:, :nl] += Mc[nl:, :nl]
                M[nloc:, nloc:] += Mc[nl:, nl:]
                v[:nl] += vc[:nl]
                v[nloc:] += vc[nl:]
            # eliminate every local state but the chunk's last
            keep = np.r_[nloc - nl:nloc, nloc:nloc + p]
            carried = _schur(M, v, keep, np.arange(nloc - nl))
            Mt, vt = _schur(carried[0], carried[1], np.arange(nl, nl + p), np.arange(nl))
            cov = np.linalg.inv(0.5 * (Mt + Mt.T))
            times.append(float(gp.t0[j1 - 1]))
            sig.append(np.sqrt(np.clip(np.einsum("ip,pq,iq->i", Tm, cov, Tm), 0, None)))
            est.append(vals + Tm @ (cov @ vt))
        # the cycle's end: its last local state leaves
        Lam, eta = _schur(carried[0], carried[1], np.arange(nl, nl + p), np.arange(nl))
    return {"sigma_history_time": np.array(times), "sigma_history": np.array(sig),
            "estimate_history": np.array(est), "sigma_history_labels": labels}


def _schur(M, v, keep, drop):
    if len(drop) == 0:
        return M[np.ix_(keep, keep)], v[keep]
    A = M[np.ix_(drop, drop)]
    B = M[np.ix_(drop, keep)]
    X = np.linalg.solve(A, np.column_stack([B, v[drop]]))
    return (M[np.ix_(keep, keep)] - B.T @ X[:, :-1], v[keep] - B.T @ X[:, -1])
