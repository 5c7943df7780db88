"""One cycle's measurement rows at a linearisation point: the block means of the
accelerometers against the model's prediction, the table axis, the table's channels,
and the attitude's propagation from block to block, each with its derivatives by the
attitude error of the block and by the parameter vector.

The attitude of the unit is held at the block starts, C_j (body -> ENU), with a
small error phi_j (ENU): C = Exp(phi_j) C_j. Within a block it follows the corrected
gyros (model/strapdown.py: the integrator, both sample kinds), so every sample's
specific force is known from C_j and the parameters: gravity dR_i^T C_j^T g plus the
rigid-body terms, which the catalogue's lever-arm and proof-mass effects add. The
prediction and its derivatives come from ``ImuModel.jacobian`` (model/jacobian.py) on
the blocks' mean kinematics (the mean attitude, rates, angular acceleration and the mean
centripetal operator: exact for every effect linear in them), or on the samples for
effects that are not (u^2, |u|). The gyro parameters act through the corrected rates:
d w / d theta = -(d W / d w)^-1 d W / d theta from the gyro model's own Jacobian, carried
through the integration (the attitude within the block and at its end) and the
rigid-body terms.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calib_cli.data import Recording
from calib_cli.model.correction import correct
from calib_cli.model.frames import skew
from calib_cli.model.kinematics import Kinematics, rigid_accel
from calib_cli.model.strapdown import block_integration, edge_rates, edge_stencil, group_means


@dataclass
class GyroPart:
    """A cycle's gyro-driven quantities at the linearisation point (nb blocks of m
    samples). P_g: the number of gyro columns. w, dwdth: per-sample corrected rates (n, 3)
    and their sensitivity (n, 3, P_g). The integration (model/strapdown.block_integration):
    r_mean (nb, 3, 3) mean attitude of the samples relative to the block start, r_end
    (nb, 3, 3) the next block's start, q_end (nb, 3, P_g) its sensitivity, qbar (nb, 3,
    P_g) the mean sensitivity, wg (3, nb, 3, P_g) mean dR^T [e_c x] q. The blocks' mean
    kinematics: wbar (nb, 3), dwbar (nb, 3) the mean angular acceleration (edge rates),
    cen (nb, 3, 3) mean [w x]^2, and their sensitivities dcen (nb, 3, 3, P_g), ddw (nb,
    3, P_g); dw_var (nb,) the variance of the tangential term's timing at corners
    ((rad/s^2)^2), wabs (nb,) mean |w|; skip (nb,) the blocks left out of the accelerometer
    rows (the tangential term off: those in which the table accelerates), or None."""

    nb: int
    m: int
    t0: np.ndarray
    w: np.ndarray
    f_ref: np.ndarray
    dwdth: np.ndarray
    dR: np.ndarray
    r_mean: np.ndarray
    r_end: np.ndarray
    q_end: np.ndarray
    qbar: np.ndarray
    wg: np.ndarray
    wbar: np.ndarray
    dwbar: np.ndarray
    cen: np.ndarray
    dcen: np.ndarray
    ddw: np.ndarray
    dw_var: np.ndarray
    wabs: np.ndarray
    temp: np.ndarray | None
    T: float = 0.0  # block length (s)
    skip: np.ndarray | None = None


def gyro_part(rec: Recording, sl: slice, model, params: dict, block_n: int, nb: int,
              gyro_cols: list, tangential: bool, sig_g: np.ndarray,
              accel_skip: float = 0.02, acc_cols: list = ()) -> GyroPart:
    """The gyro-driven quantities of the first ``nb`` blocks of a cycle (GyroPart), from
    its samples (and two after the last block, where the segment has them, for the
    integration's and the edge rates' stencils). The rates' sensitivity to the parameters
    is taken per group of samples (``sensitivity_group``): the Jacobian of effects linear
    in the kinematics at a group's mean kinematics is its mean over the group. Without the
    tangential term the blocks whose mean angular acceleration exceeds ``accel_skip``
    (rad/s^2) are marked to be left out of the accelerometer rows. acc_cols: accelerometer
    columns appended to the gyro columns of the sensitivity (``rate_sensitivity``)."""
    n = nb * block_n
    n_ext = min(n + 2, sl.stop - sl.start)
    t = rec.time[sl][:n_ext]
    W = rec.gyro[sl][:n_ext]
    temp = None if rec.temp is None else np.asarray(rec.temp[sl][:n_ext], float)
    # the specific force the gyros' D sees: the corrected accelerometers at the reference
    # point (each axis's proof-mass term removed), then the rates
    f = correct(model, params, "accel", rec.accel[sl][:n_ext], temp=temp)
    w = correct(model, params, "gyro", W, other=f, temp=temp)
    P = params.get("proof_mass_offsets")
    if P is not None and np.any(P):
        # the proof-mass terms from the corrected rates (from the raw ones, a 3x wide unit's
        # scale errors left 1e-3 m/s^2 in f, 1e-6 rad/s through D: 9 sigma of the gyro
        # biases at 1 % of MEMS noise), then the rates again from that f
        kin0 = Kinematics(t, f, w, np.gradient(w, t, axis=0))
        f = f - np.stack([rigid_accel(kin0, P[i])[:, i] for i in range(3)], axis=1)
        w = correct(model, params, "gyro", W, other=f, temp=temp)
    # d w / d theta = -(d W / d w)^-1 d W / d theta (the implicit inverse of the gyro
    # model), per group of samples
    grp = sensitivity_group(block_n)
    # (the angular acceleration only where the accelerometer model's inverse needs it)
    dwdt = np.gradient(w, t, axis=0) if acc_cols and len(t) > 1 else np.zeros_like(w)
    kin_g = Kinematics(group_means(t[:n], grp), group_means(f[:n], grp),
                       group_means(w[:n], grp), group_means(dwdt[:n], grp),
                       temp=None if temp is None else group_means(temp[:n], grp))
    sg = rate_sensitivity(model, params, kin_g, gyro_cols, acc_cols)
    kind = rec.sample_kind
    integ = block_integration(w, sg, t, block_n, nb, kind, grp)
    # the blocks' mean kinematics: rates, the centripetal operator and its sensitivity
    # (s constant over each group), the mean angular acceleration from the edge rates
    wb = w[:n].reshape(nb, block_n, 3)
    ww = np.einsum("bmi,bmj->bij", wb, wb) / block_n
    cen = ww - np.trace(ww, axis1=1, axis2=2)[:, None, None] * np.eye(3)
    G = block_n // grp
    wgm = kin_g.w.reshape(nb, G, 3)
    sgb = sg.reshape(nb, G, 3, -1)
    ws = np.einsum("bgi,bgjp->bijp", wgm, sgb) / G  # mean w_a dw_b
    dcen = ws + np.swapaxes(ws, 1, 2)
    tr = np.einsum("biip->bp", ws)
    dcen = dcen - 2.0 * tr[:, None, None, :] * np.eye(3)[None, :, :, None]
    dt = float(np.median(np.diff(t))) if len(t) > 1 else 1.0
    T = block_n * dt
    e_w = edge_rates(w, block_n, nb, kind)
    dwbar = (e_w[1:] - e_w[:-1]) / T
    # the edges' sensitivity: the same stencil on the samples' sensitivity, evaluated at
    # the stencil's samples alone
    idx, cw = edge_stencil(len(w), block_n, nb, kind)
    ue = np.unique(idx)
    kin_e = Kinematics(t[ue], f[ue], w[ue], dwdt[ue],
                       temp=None if temp is None else temp[ue])
    se = rate_sensitivity(model, params, kin_e, gyro_cols, acc_cols)
    s_edge = np.einsum("kj,kjap->kap", cw, se[np.searchsorted(ue, idx)])
    ddw = (s_edge[1:] - s_edge[:-1]) / T
    dw_var = _corner_variance(w[:n], sig_g, block_n, nb, dt)
    skip = None
    if not tangential:
        skip = np.linalg.norm(dwbar, axis=1) > accel_skip
        dwbar = np.zeros_like(dwbar)
        ddw = np.zeros_like(ddw)
        dw_var = np.zeros_like(dw_var)
    return GyroPart(nb, block_n, t[:n:block_n], w[:n], f[:n], sg, integ.dR,
                    integ.r_mean, integ.r_end, integ.q_end, integ.qbar, integ.wg,
                    wb.mean(axis=1), dwbar, cen, dcen, ddw, dw_var,
                    np.linalg.norm(wb, axis=2).mean(axis=1),
                    None if temp is None else temp[:n].reshape(nb, block_n).mean(axis=1), T,
                    skip)


def rate_sensitivity(model, params: dict, kin: Kinematics, gyro_cols: list,
                     acc_cols: list = ()) -> np.ndarray:
    """d w / d theta (n, 3, P_g + P_a) of the corrected rates at the kinematics ``kin``:
    by the gyro columns, -(d W / d w)^-1 d W / d theta of the gyro model; by the
    accelerometer columns ``acc_cols``, their path through the specific force the gyros'
    g-sensitivity sees, -(d W / d w)^-1 (d W / d f) (d f / d theta_a), d f / d theta_a =
    -(d A / d f)^-1 d A / d theta_a of the accelerometer model's inverse. That path is
    left out where the accelerometers are determined (a few 1e-3 m/s^2 through a D of
    1e-3: 1e-2 of the gyro biases' sigma, for 60 % more time a pass); without a gravity
    reference their biases and K move freely along the mountings' valley and the gyros'
    D f with them (0.1 m/s^2: 5 sigma of the gyro biases), and the fixed point of the
    passes without it lay 5-15 sigma from the truth in the gyro biases and D."""
    lin = model.jacobian(params, kin, "gyro", gyro_cols, ("w", "f") if acc_cols else ("w",))
    inv = inverse3(lin.d_inputs["w"])
    sg = -np.einsum("nij,njp->nip", inv, lin.d_params)
    if not acc_cols:
        return sg
    la = model.jacobian(params, kin, "accel", acc_cols, ("f",))
    dfa = -np.einsum("nij,njp->nip", inverse3(la.d_inputs["f"]), la.d_params)
    sa = -np.einsum("nij,njk,nkp->nip", inv, lin.d_inputs["f"], dfa)
    return np.concatenate([sg, sa], axis=2)


def sensitivity_group(block_n: int) -> int:
    """Samples per group of the rates' sensitivity: five groups a block (one sample each
    in blocks of up to five), a divisor of the block."""
    g = max(1, block_n // 5)
    while block_n % g:
        g -= 1
    return g


def inverse3(A: np.ndarray) -> np.ndarray:
    """Inverses (N, 3, 3) of 3 x 3 matrices by their adjugates (LAPACK's per-matrix
    overhead dominates at this size)."""
    a, b, c = A[:, 0, 0], A[:, 0, 1], A[:, 0, 2]
    d, e, f = A[:, 1, 0], A[:, 1, 1], A[:, 1, 2]
    g, h, i = A[:, 2, 0], A[:, 2, 1], A[:, 2, 2]
    adj = np.empty_like(A)
    adj[:, 0, 0], adj[:, 0, 1], adj[:, 0, 2] = e * i - f * h, c * h - b * i, b * f - c * e
    adj[:, 1, 0], adj[:, 1, 1], adj[:, 1, 2] = f * g - d * i, a * i - c * g, c * d - a * f
    adj[:, 2, 0], adj[:, 2, 1], adj[:, 2, 2] = d * h - e * g, b * g - a * h, a * e - b * d
    det = a * adj[:, 0, 0] + b * adj[:, 1, 0] + c * adj[:, 2, 0]
    return adj / det[:, None, None]


def _corner_variance(w, sig_g: np.ndarray, block_n: int, nb: int, dt: float) -> np.ndarray:
    """Where the angular acceleration jumps (a ramp's corners) the accelerometers see its
    value at each stamp on one side of the corner and the edge rates the mean of both: the
    block mean's tangential term is off by jump (u - 1/2) / m per corner, u the corner's
    phase between stamps (uniform): variance jump^2 / 12 / m^2. The jump from the second
    differences, E sum (d2 / dt^2)^2 / 8 = jump^2 / 12, counted where it stands 4 sigma
    above the gyro noise ``sig_g`` ((rad/s^2)^2 per block)."""
    d2 = np.zeros(len(w))
    d2[1:-1] = np.sum((w[2:] - 2 * w[1:-1] + w[:-2]) ** 2, axis=1)
    noise2 = 6.0 * float(np.sum(np.square(sig_g)))
    jump2 = np.where(d2 > 16.0 * noise2, (d2 - noise2) / dt**4, 0.0)
    return jump2[: nb * block_n].reshape(nb, block_n).sum(axis=1) / 8.0 / block_n**2


@dataclass
class AccelRows:
    """A cycle's accelerometer block rows at the linearisation point: z (nb, 3) the block
    means, h (nb, 3) the prediction, H_phi (nb, 3, 3), H_acc (nb, 3, k_a) by the accel
    columns, H_gyr (nb, 3, P_g) by the gyro columns, H_lever (nb, 3, 3) by the cycle's
    lever arm in body axes, var (nb, 3) the noise variance per block."""

    z: np.ndarray
    h: np.ndarray
    H_phi: np.ndarray
    H_acc: np.ndarray
    H_gyr: np.ndarray
    H_lever: np.ndarray | None
    var: np.ndarray


def accel_rows(rec: Recording, sl: slice, gp: GyroPart, C: np.ndarray, model, params: dict,
               cycle: int, acc_cols: list, lever: bool, g_n: np.ndarray, sig_a: np.ndarray,
               sig_g: np.ndarray, lever_norm2: float | None = None) -> AccelRows:
    """The accelerometer rows of a cycle's blocks at the block-start attitudes C (nb, 3, 3).
    acc_cols: the accelerometer model's columns [(key, flat)]; lever: the cycle's lever
    arm is estimated (its three body-axis derivatives in H_lever)."""
    nb, m = gp.nb, gp.m
    z = rec.accel[sl][: nb * m].reshape(nb, m, 3).mean(axis=1)
    gam = np.einsum("bji,j->bi", C, g_n)  # gravity in block-start body axes, C^T g
    fbar = np.einsum("bji,bj->bi", gp.r_mean, gam)  # its mean over the block, r_mean^T gam
    cols = list(acc_cols) + ([("lever_arm", 3 * cycle + k) for k in range(3)] if lever else [])
    kin = Kinematics(gp.t0, fbar, gp.wbar, gp.dwbar, temp=gp.temp, cycle=np.full(nb, cycle),
                     cen=gp.cen)
    lin = model.jacobian(params, kin, "accel", cols, ("f", "cen", "dw"))
    dyf = lin.d_inputs["f"]  # (nb, 3, 3) at the block's mean kinematics
    if any(not e.linear_in_kinematics for e in model.effects if e.sensor == "accel"):
        # terms such as u^2: the blocks' means of the samples' prediction
        h, dparams, M = _sample_means(rec, sl, gp, gam, model, params, cycle, cols)
    else:
        h, dparams = lin.y, lin.d_params
        M = np.einsum("bia,bca->bic", dyf, gp.r_mean)  # mean (d y / d f) dR^T
    # the attitude error phi_j (body axes): gamma = Exp(-phi) C^T g = gamma + [gamma x] phi
    H_phi = np.einsum("bic,bce->bie", M, skew(gam))
    # the gyro parameters: through the attitude within the block (mean dR^T [gam x] q), the
    # centripetal operator and the angular acceleration
    Wg = np.einsum("bc,cbap->bap", gam, gp.wg)
    H_gyr = np.einsum("bia,bap->bip", dyf, Wg)
    H_gyr += np.einsum("nicd,ncdp->nip", lin.d_inputs["cen"], gp.dcen)
    H_gyr += np.einsum("nia,nap->nip", lin.d_inputs["dw"], gp.ddw)
    k_a = len(acc_cols)
    # noise: the accelerometers' own over the block, plus the gyro noise in the rigid-body
    # terms the model computes from the corrected gyros (centripetal: 2 |w| |r| per unit of
    # rate noise; tangential: the edge rates' noise over the block, and the corners)
    # (at a fixed lever arm, ``lever_norm2``: weights that moved with the estimate would make
    # the fit's objective move too, and without their log-determinant pull the lever arms
    # towards larger noise at the corners)
    if lever_norm2 is None:
        s = params.get("lever_arm")
        lever_norm2 = float(np.sum(s[cycle] ** 2)) if s is not None and 0 <= cycle < len(s) \
            else 0.0
    r2 = lever_norm2
    sg2 = float(np.mean(sig_g**2))
    extra = 4.0 * gp.wabs**2 * r2 * sg2 / m + (1.3 * sg2 / gp.T**2 + gp.dw_var) * r2
    var = sig_a[None, :] ** 2 / m + extra[:, None]
    return AccelRows(z, h, H_phi, dparams[:, :, :k_a], H_gyr,
                     dparams[:, :, k_a:] if lever else None, var)


def _sample_means(rec, sl, gp: GyroPart, gam, model, params, cycle, cols):
    """Block means of the prediction, its parameter derivatives and the mean of
    (d y / d f) dR^T, from the samples (for effects not linear in the kinematics)."""
    nb, m = gp.nb, gp.m
    n = nb * m
    t = rec.time[sl][:n]
    f = np.einsum("bmji,bj->bmi", gp.dR, gam).reshape(n, 3)
    dw = np.gradient(gp.w, t, axis=0)
    temp = None if rec.temp is None else np.asarray(rec.temp[sl][:n], float)
    kin = Kinematics(t, f, gp.w, dw, temp=temp, cycle=np.full(n, cycle))
    lin = model.jacobian(params, kin, "accel", cols, ("f",))
    h = lin.y.reshape(nb, m, 3).mean(axis=1)
    dp = lin.d_params.reshape(nb, m, 3, -1).mean(axis=1)
    dyf = np.einsum("bmia,bmca->bic", lin.d_inputs["f"].reshape(nb, m, 3, 3), gp.dR) / m
    return h, dp, dyf
