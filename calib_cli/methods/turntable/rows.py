"""A cycle's whitened rows at a linearisation point, over its local states (per block:
the attitude error phi_j, and where the rate channel is used its integrated noise rho_j)
and the parameter vector theta (setup.ParamMap):

- the accelerometers' block means (blocks.accel_rows);
- the table axis: the attitude at each block's start maps the axis in body axes (the
  plan's, turned by the cycle's mounting error) onto the table's axis in ENU (the plan's,
  tilted), up to the bearing's runout (the second harmonic of the table angle) and a
  white noise per block (estimated);
- the table's angle channel: the attitude's angle about the axis since the cycle start,
  plus the channel's zero, its once-per-revolution error and scale (and the time offset
  between the IMU and the table, where the model has it);
- the rate channel integrated to an angle: the same angle with the channel's scale error,
  offset (times the time), zero and its integrated reading noise rho;
- the propagation: phi_j+1 = r_end^T (phi_j + q_end dtheta_gyro) + the gyro noise over the
  block (the attitude's random walk), against the trajectory's own mismatch at the
  linearisation point.

The attitude errors are in body axes, C = C_j Exp(phi_j): the propagation then does not
depend on the attitude's heading, which on a vertical table axis nothing but the weak
start prior fixes (in ENU axes a step's heading change of a few tenths of a radian turned
the gyro parameters' propagation with it, a second-order error of 40 times the data's
cost).

Each row is A_loc dx_loc + A_glob dtheta = r (the data minus the prediction) with weight
1 / sigma; solve.py forms and solves the normal equations."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from calib_cli.methods.turntable.blocks import AccelRows, GyroPart
from calib_cli.methods.turntable.setup import RATE_ANGLE_FLOOR, axis_in_body, perp_basis
from calib_cli.model.frames import skew

# row slots of a block: accelerometers 0-2, table axis 3-4, angle channel 5, rate channel 6
ACC, AXIS, ENC, RATE = slice(0, 3), slice(3, 5), 5, 6
N_ROWS = 7
RUNOUT_HARMONIC = 2.0  # an oval bearing race rocks the axis twice per revolution
HEADING_SD = 1.0  # rad: the per-block prior of a turn about the axis that does not propagate


@dataclass
class CycleSystem:
    """The rows of one cycle (nb blocks, nl local states per block): measurement rows
    A_loc (nb, 7, nl), A_glob (nb, 7, p), r (nb, 7), weight (nb, 7) (0: no row);
    propagation rows between blocks j and j+1, phi_j+1 - F_j phi_j - B_j dtheta_g = -e_j:
    F (nb - 1, 3, 3) the blocks' relative turn (its attitude errors are in body axes), B
    (nb - 1, 3, P_g) on the rates' columns ``gyro_idx`` (the gyros', and where the rates'
    sensitivity carries them the accelerometers': estimator.run_pass), e (nb - 1, 3) the
    trajectory's mismatch,
    q_phi the attitude walk's variance per block; the rate channel's walk q_rho (variance per block) and its
    current values rho (nb,); the start prior on phi_0 (r0 (3,), sd0)."""

    nb: int
    nl: int
    A_loc: np.ndarray
    A_glob: np.ndarray
    r: np.ndarray
    weight: np.ndarray
    F: np.ndarray
    B: np.ndarray
    gyro_idx: np.ndarray
    e: np.ndarray
    q_phi: float
    Wq: np.ndarray  # (nb - 1, 3, 3) the propagation rows' weight (inverse covariance)
    anchor: np.ndarray | None  # (nb, 3, 3) weak priors on each block's phi, or None
    q_rho: float
    rho: np.ndarray | None
    r0: np.ndarray
    sd0: float
    psi: np.ndarray  # (nb,) the trajectory's angle about the table axis since the start
    accel: AccelRows
    axis_var: float
    parts: dict | None = None  # the row groups' normal equations (solve.py)
    scales: dict = field(default_factory=dict)  # their weights' changes since
    white: tuple | None = None  # the whitened rows (solve.whitened)


def table_angle(C: np.ndarray, a_enu: np.ndarray, C_ref: np.ndarray | None = None
                ) -> np.ndarray:
    """The trajectory's angle (nb,) about the table axis, unwrapped (rad): the sum of the
    block-to-block rotations' components along the axis, from the fixed reference attitude
    C_ref (the cycle's start: then each block's angle depends on its own attitude alone, as
    its rows' linearisation says; measured from the first block instead, a turn of the
    whole trajectory about a vertical axis, which nothing else fixes, moved the rows'
    prediction in the linearisation and not in the next pass) or from the first block."""
    rel = np.einsum("bij,bkj->bik", C[1:], C[:-1])  # C_j+1 C_j^T
    steps = Rotation.from_matrix(rel).as_rotvec() @ a_enu
    first = 0.0 if C_ref is None else float(
        Rotation.from_matrix(C[0] @ C_ref.T).as_rotvec() @ a_enu)
    return first + np.concatenate([[0.0], np.cumsum(steps)])


def propagate(C0: np.ndarray, r_end: np.ndarray, E: np.ndarray) -> np.ndarray:
    """Block-start attitudes (nb, 3, 3) from the first, C_j+1 = E C_j r_end_j."""
    out = np.empty((len(r_end), 3, 3))
    out[0] = C0
    for j in range(len(r_end) - 1):
        out[j + 1] = E @ out[j] @ r_end[j]
    return out


def cycle_system(c: int, cy, gp: GyroPart, acc: AccelRows, C: np.ndarray, rho, theta: np.ndarray,
                 pm, gyro_idx: np.ndarray, acc_idx: np.ndarray, E: np.ndarray,
                 sig_g: np.ndarray, axis_var: float, enc=None, sig_enc: float = 0.0,
                 rate=None, sig_rate: float = 0.0, C_start: np.ndarray | None = None,
                 sd0: float = float(np.radians(5.0)), free_heading: bool = False,
                 rate_row_sd: float = RATE_ANGLE_FLOOR, angle_ref=None) -> CycleSystem:
    """The rows of cycle c at (theta, trajectory C (nb, 3, 3), rate walk rho); the table
    angle from angle_ref = (C_ref, offset) (estimator.angle_reference), else from C_start."""
    nb = gp.nb
    use_rate = rate is not None
    # the integrated channel's own noise over the whole cycle: below the rows' floor it is
    # absorbed in their white noise and needs no state (a quiet channel: most logs)
    walk = sig_rate * gp.T / np.sqrt(gp.m) * np.sqrt(gp.m * nb) if use_rate else 0.0
    rate_walk = use_rate and walk > RATE_ANGLE_FLOOR
    nl = 4 if rate_walk else 3
    p = pm.size
    A_loc = np.zeros((nb, N_ROWS, nl))
    A_glob = np.zeros((nb, N_ROWS, p))
    r = np.zeros((nb, N_ROWS))
    wt = np.zeros((nb, N_ROWS))
    # accelerometers
    A_loc[:, ACC, :3] = acc.H_phi
    A_glob[:, ACC][:, :, acc_idx] = acc.H_acc
    A_glob[:, ACC][:, :, gyro_idx] += acc.H_gyr
    if acc.H_lever is not None:  # the lever arm as u = s / gamma^2 (setup.ParamMap)
        ds_du, ds_dG, gi = pm.lever_jacobian(theta, cy.model_index)
        A_glob[:, ACC][:, :, pm.idx["lever_arm"][cy.model_index]] = acc.H_lever @ ds_du
        A_glob[:, ACC][:, :, gi] += acc.H_lever @ ds_dG
    r[:, ACC] = acc.z - acc.h
    wt[:, ACC] = 1.0 / np.sqrt(acc.var)
    if gp.skip is not None:
        wt[gp.skip, ACC] = 0.0
    # the table axis: N (C_j r_mean a_b) = tilt - runout, N the ENU directions across it
    a_b, da = axis_in_body(cy, theta[pm.idx["mount"][c]])
    # at each block's start (its mean attitude would carry the gyro noise integrated within
    # the block, 2e-5 rad at MEMS noise, correlated with the propagation's walk)
    ra = C @ a_b  # (nb, 3)
    N = perp_basis(cy.a_enu).T  # (2, 3)
    # d/d phi (body axes): C Exp(phi) a_b = ra - C [a_b x] phi
    Nra = -np.einsum("ai,bij,jk->bak", N, C, skew(a_b))
    A_loc[:, AXIS, :3] = Nra
    A_glob[:, AXIS][:, :, pm.idx["mount"][c]] = np.einsum("ai,bij,jk->bak", N, C, da)
    if cy.static:  # a static position: no table axis
        A_loc[:, AXIS] = 0.0
        A_glob[:, AXIS] = 0.0
        h_ax = np.zeros((nb, 2))
    else:
        ti = pm.idx["tilt"][cy.axis_group]
        A_glob[:, AXIS][:, :, ti] = -np.eye(2)
        h_ax = ra @ N.T - theta[ti]
    ref, offset = (C_start, 0.0) if angle_ref is None else angle_ref
    psi = offset + table_angle(C, cy.a_enu, ref)
    if pm.has("runout") and not cy.static:
        ir = pm.idx["runout"][c]
        hp = RUNOUT_HARMONIC * psi
        cs, sn = np.cos(hp), np.sin(hp)
        A_glob[:, 3, ir[0]], A_glob[:, 3, ir[1]] = -cs, -sn
        A_glob[:, 4, ir[2]], A_glob[:, 4, ir[3]] = -cs, -sn
        h_ax[:, 0] -= cs * theta[ir[0]] + sn * theta[ir[1]]
        h_ax[:, 1] -= cs * theta[ir[2]] + sn * theta[ir[3]]
    r[:, AXIS] = -h_ax
    wt[:, AXIS] = 0.0 if cy.static else 1.0 / np.sqrt(axis_var)
    omega = np.einsum("bi,i->b", gp.w[::gp.m], cy.a_nom)  # the rate at each block start
    # the angle channel
    if enc is not None:
        k = min(nb, len(enc.z))
        ok = np.zeros(nb, bool)
        ok[:k] = enc.ok[:k]
        ok[0] = False  # the first reading defines the channel's zero
        iz, io, isc = pm.idx["enc_zero"][c], pm.idx["enc_opr"], pm.idx["enc_scale"][0]
        th = np.zeros(nb)
        th[:k] = enc.theta[:k]
        zz = np.zeros(nb)
        zz[:k] = enc.z[:k]
        h = psi * (1.0 + theta[isc]) + theta[iz] + theta[io[0]] * np.cos(th) + \
            theta[io[1]] * np.sin(th)
        A_loc[:, ENC, :3] = np.einsum("bji,j->bi", C, cy.a_enu)  # C^T a: body axes
        A_glob[:, ENC, iz] = 1.0
        A_glob[:, ENC, io[0]], A_glob[:, ENC, io[1]] = np.cos(th), np.sin(th)
        A_glob[:, ENC, isc] = psi
        if pm.has("time_offset"):
            it = pm.idx["time_offset"][0]
            A_glob[:, ENC, it] = omega
            h = h + omega * theta[it]
        r[:, ENC] = np.where(ok, zz - h, 0.0)
        wt[:, ENC] = np.where(ok, 1.0 / sig_enc, 0.0)
    if use_rate:
        k = min(nb, len(rate.z))
        ok = np.zeros(nb, bool)
        ok[:k] = rate.ok[:k]
        ok[0] = False
        zz, tt = np.zeros(nb), np.zeros(nb)
        zz[:k], tt[:k] = rate.z[:k], rate.t[:k]
        ik, ib, iz = pm.idx["rate_scale"][0], pm.idx["rate_bias"][0], pm.idx["rate_zero"][c]
        h = psi * (1.0 + theta[ik]) + theta[ib] * tt + theta[iz] + (rho if rate_walk else 0.0)
        A_loc[:, RATE, :3] = np.einsum("bji,j->bi", C, cy.a_enu)
        if rate_walk:
            A_loc[:, RATE, 3] = 1.0
        A_glob[:, RATE, ik] = psi
        A_glob[:, RATE, ib] = tt
        A_glob[:, RATE, iz] = 1.0
        if pm.has("time_offset"):
            it = pm.idx["time_offset"][0]
            A_glob[:, RATE, it] = omega
            h = h + omega * theta[it]
        r[:, RATE] = np.where(ok, zz - h, 0.0)
        wt[:, RATE] = np.where(ok, 1.0 / (rate_row_sd if rate_walk else
                                          np.hypot(rate_row_sd, walk)), 0.0)
    # the propagation: the mismatch e_j = Log((E C_j r_end_j)^T C_j+1) (body axes)
    # exactly to first order: Log(Exp(-r_end^T (phi_j + q_end dtheta)) Exp(e_j) Exp(phi_j+1))
    # is e_j + J_r(e_j)^-1 (phi_j+1 - Exp(-e_j) r_end^T (phi_j + q_end dtheta)), and the rows
    # are that times J_r(e_j) (~ I): F = Exp(-e_j) r_end^T, the blocks' actual relative
    # turn C_j+1^T E C_j. (With r_end^T alone, a step that re-propagates a trajectory,
    # phi_j+1 ~ F phi_j, as a vertical axis's heading with the gyros' bias and scale,
    # carried an error e_j x phi_j of the size of its small net change: the passes
    # undershot by 1.7x and crept, 14 of 20 records not converged in 8 passes)
    pred = np.einsum("ij,bjk,bkl->bil", E, C[:-1], gp.r_end[:-1])
    rel = np.einsum("bji,bjk->bik", pred, C[1:])  # Exp(e_j)
    e = Rotation.from_matrix(rel).as_rotvec()
    F = np.swapaxes(np.einsum("bij,bjk->bik", gp.r_end[:-1], rel), 1, 2)
    B = np.einsum("bij,bjp->bip", F, gp.q_end[:-1])
    q_phi = gp.m * float(np.mean(sig_g**2)) * (gp.T / gp.m) ** 2
    Wq = np.tile(np.eye(3) / q_phi, (nb - 1, 1, 1))
    anchor = None
    if free_heading:  # the turn about the table axis does not propagate (fit.hold_undetermined)
        ah = np.einsum("bji,j->bi", C, cy.a_enu)  # the table axis in each block's body axes
        P = np.einsum("bi,bj->bij", ah[1:], ah[1:])
        Wq = Wq - P / q_phi
        anchor = np.einsum("bi,bj->bij", ah, ah) / HEADING_SD**2
    # the integrated channel's walk per block (a noise-free channel: a tenth of the reading
    # floor, so the system stays well conditioned)
    q_rho = max(sig_rate**2 * gp.m * (gp.T / gp.m) ** 2, (0.1 * RATE_ANGLE_FLOOR) ** 2) \
        if rate_walk else 0.0
    r0 = np.zeros(3) if C_start is None else \
        Rotation.from_matrix(C[0].T @ C_start).as_rotvec()
    return CycleSystem(nb, nl, A_loc, A_glob, r, wt, F, B, gyro_idx, e, q_phi, Wq, anchor, q_rho,
                       None if not rate_walk else np.asarray(rho, float), r0,
                       cy.mount_sigma if cy.static else sd0, psi, acc,
                       axis_var)
