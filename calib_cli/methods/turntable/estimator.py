"""The rotating-table estimator: Gauss-Newton on the whole record (every block's attitude
and the parameters), from a start grown window by window.

The likelihood is that of the error-state Kalman filter of the unit on the table (the
attitude propagated with the corrected gyros and walking with their noise, the
accelerometers' block means, the table axis, the table's channels), solved as a batch:
each pass linearises every row about the current trajectory and parameters and solves
for both (solve.py). For constant parameters its covariance is the filter's final one.

Start: the neutral unit with coarse lever arms from the holds, each cycle's attitude
from the plan's mounting turned to the first block's gravity; the first ``START_S``
seconds of every cycle are fitted first, then the windows double, the trajectory
propagated into each new part with the current estimate, until they span the cycles;
then the passes over the whole record until no parameter moves by more than
``converge_sigma`` of its sigma (exit 4 naming what still moves when ``passes`` do not
get there).

Noise: the accelerometers' and gyros' white noise from the data's third differences; the
table axis's per-block noise and the angle channel's reading noise from the rows'
residuals between passes (sum r^2 / (n - trace of the hat matrix): what the fit takes
out of them counted), from a loose start."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from calib_cli.methods.turntable import setup as su
from calib_cli.methods.turntable.blocks import accel_rows, gyro_part
from calib_cli.methods.turntable.rows import ACC, AXIS, ENC, RATE, cycle_system, propagate, table_angle
from calib_cli.methods.turntable.setup import RATE_ANGLE_FLOOR
from calib_cli.methods.turntable.solve import leverage, residuals_after, scale_weight, set_weight, solve
from calib_cli.model.strapdown import exp_matrix

START_S = 20.0  # s: the first window of every cycle
STAGE_PASSES = 3  # the most passes per start window
AXIS_START = 1e-3  # rad: the table axis's noise the start assumes (a rough stand's)
AXIS_CAP = 2e-2
AXIS_FLOOR = 1e-5
# the floor is at most this fraction of the attitude's random walk over one block: an axis
# noise assumed far above that walk while the true one is below it makes every sigma the
# axis carries too wide (issue 22)
AXIS_FLOOR_WALK = 0.5
NOISE_MOVE = np.log(1.2)  # a noise level that moves by less than 20 % is settled
# the most the axis noise's variance falls in one pass: a stiffer axis moves the solution
# along the directions it ties, which a step from far away does not bear (a vertical axis,
# where the axis and gravity tie the same two angles, crept at 2 sigma a pass after one
# jump from 1 mrad to 10 urad)
AXIS_STEP = 1e6
# the accelerometers' normalised residual RMS above which their noise is widened (the model
# does not explain the data: stats.accel_noise_inflation)
ACCEL_MISFIT = 1.3
SETTLED = 0.05  # a noise level that moves by less than this (in log) within a pass is settled
# the most a settling round extrapolates a level's move (SecantLevel): a rigid axis's noise
# falls to its floor sublinearly (each round 0.33, 0.61, 0.76, 0.83 of the last one's
# ratio), 8 rounds of re-solving at 1e-4 .. 1e-5 rad without it
EXTRAPOLATE_MAX = 5.0


@dataclass
class Problem:
    """Everything a pass needs: the recording, its cycles, the model and parameter map,
    the columns of each sensor, the channels and the noise."""

    rec: object
    cycles: list
    model: object
    pm: su.ParamMap
    opt: object
    block_n: int
    nb: list  # blocks per cycle
    gyro_cols: list
    gyro_idx: np.ndarray
    acc_cols: list
    acc_idx: np.ndarray
    sig_a: np.ndarray
    sig_g: np.ndarray
    lever: bool
    lever_known: np.ndarray | None
    enc: list | None = None
    sig_enc: float = 0.0
    rate: list | None = None
    sig_rate: float = 0.0
    notes: list = field(default_factory=list)
    free_heading: list = field(default_factory=list)  # per cycle: the heading not propagated
    sig_enc_floor: float = 0.0  # the angle channel's white noise (setup.angle_noise)
    sig_rate_row: float = AXIS_START  # the rate channel's rows' sigma (estimated, floored)
    fixed_levels: bool = False  # the noise levels are given (plan check: design.py)
    widen_accel: bool = True  # the accelerometer noise widened where the model misfits
    held: set = field(default_factory=set)  # the entries reported null (fit.hold_undetermined)
    # the rates' sensitivity carries the accelerometer columns' path through the gyros' D f
    # (blocks.rate_sensitivity; fit.hold_undetermined decides where)
    accel_path: bool = False
    follow_valley: bool = False  # the steps corrected along the mountings' valley
    pinned: np.ndarray = field(default_factory=lambda: np.zeros(0, int))  # theta not moved

    @property
    def g_n(self) -> np.ndarray:
        return self.rec.site.specific_force_enu


@dataclass
class State:
    """The linearisation point: theta, per cycle the block-start attitudes C (nb_c, 3,
    3) and the rate channel's walk rho (nb_c,), the attitudes the cycles started from."""

    theta: np.ndarray
    C: list
    rho: list
    C_start: list
    axis_var: float
    inflation: float = 1.0
    lever2: list | None = None  # |s|^2 per cycle in the accelerometer noise model
    # per cycle the table angle's reference (C_ref (3, 3), offset rad): the angle is offset +
    # its turn from C_ref; rebased onto the first block at every pass (angle_reference)
    angle_ref: list | None = None


def angle_reference(pb: Problem, st: State) -> None:
    """Rebase each cycle's table angle onto its first block's attitude, the turn from the
    old reference moved into the offset: the angle's value stays, and its linearisation
    (d angle / d phi_0 = a^T C_0) is exact at the pass's point. Measured from a fixed
    reference (the cycle's start), the turn Log(C_0 C_ref^T) of a tilted and turned first
    block has J_l^-1 != I across the axis: on a vertical axis the channels' rows were 1 %
    off along the mountings' valley, a constant 2.5e-5 rad at the full step (the channels'
    sigma: 2-3e-5 rad), 4000 in chi^2 where the step promised a fall of 6."""
    if st.angle_ref is None:
        st.angle_ref = [(C0, 0.0) for C0 in st.C_start]
    out = []
    for cy, C, (ref, off) in zip(pb.cycles, st.C, st.angle_ref):
        out.append((C[0].copy(), off + float(table_angle(C[:1], cy.a_enu, ref)[0])))
    st.angle_ref = out


@dataclass
class PassResult:
    """A pass: its step (solve.Step), the cycles' rows and gyro parts, and the parameters
    it linearised about."""

    step: object
    systems: list
    gps: list
    theta_lin: np.ndarray


def axis_floor(sig_g: np.ndarray, block_n: int, fs: float) -> float:
    """The floor (rad per block) of the estimated axis noise."""
    walk = float(np.sqrt(block_n * np.mean(np.square(sig_g)))) / fs
    return min(AXIS_FLOOR, AXIS_FLOOR_WALK * walk) if walk > 0 else AXIS_FLOOR


def columns_of(model, pm: su.ParamMap, sensor: str) -> tuple[list, np.ndarray]:
    """The packing columns [(key, flat)] of one sensor's effects, and their indices in theta."""
    cols, idx = [], []
    for q, (key, flat) in enumerate(pm.keys):
        owner = next(e for e in model.effects if any(s.key == key for s in e.specs(model.layout)))
        if owner.sensor == sensor:
            cols.append((key, flat))
            idx.append(int(pm.idx["packing"][q]))
    return cols, np.array(idx, int)


def run_pass(pb: Problem, st: State, nbs: list) -> PassResult:
    """The rows of every cycle at the state (over the first nbs[c] blocks) and their step."""
    params = pb.pm.params(st.theta, pb.lever_known)
    angle_reference(pb, st)
    fs = pb.rec.sample_rate
    T = pb.block_n / fs
    E = exp_matrix(-pb.rec.site.earth_rate_enu * T)
    systems, gps = [], []
    rate_idx = np.concatenate([pb.gyro_idx, pb.acc_idx]) if pb.accel_path else pb.gyro_idx
    for c, cy in enumerate(pb.cycles):
        gp = gyro_part(pb.rec, cy.sl, pb.model, params, pb.block_n, nbs[c], pb.gyro_cols,
                       pb.opt.tangential, pb.sig_g, pb.opt.accel_skip,
                       pb.acc_cols if pb.accel_path else ())
        if len(st.C[c]) < nbs[c]:  # a new window: the trajectory propagated into it
            ext = propagate(st.C[c][-1], gp.r_end[len(st.C[c]) - 1:], E)
            st.C[c] = np.concatenate([st.C[c], ext[1:nbs[c] - len(st.C[c]) + 1]])
            if st.rho[c] is not None:
                st.rho[c] = np.concatenate([st.rho[c], np.full(nbs[c] - len(st.rho[c]),
                                                                st.rho[c][-1])])
        C = st.C[c][:nbs[c]]
        if st.lever2 is None:  # the noise model's lever arms: fixed at the start's
            s0 = params.get("lever_arm")
            st.lever2 = [0.0 if s0 is None else float(np.sum(s0[k] ** 2))
                         for k in range(len(pb.pm.rotating()))]
        acc = accel_rows(pb.rec, cy.sl, gp, C, pb.model, params, cy.model_index, pb.acc_cols,
                         pb.lever and not cy.static, pb.g_n, pb.sig_a, pb.sig_g,
                         0.0 if cy.static else st.lever2[cy.model_index])
        if pb.rate is not None and pb.rate[c] is not None and st.rho[c] is None:
            st.rho[c] = np.zeros(nbs[c])
        cs = cycle_system(c, cy, gp, acc, C, None if st.rho[c] is None else st.rho[c][:nbs[c]],
                          st.theta, pb.pm, rate_idx, pb.acc_idx, E, pb.sig_g, st.axis_var,
                          None if pb.enc is None else pb.enc[c], pb.sig_enc,
                          None if pb.rate is None else pb.rate[c], pb.sig_rate,
                          st.C_start[c], free_heading=pb.free_heading[c],
                          rate_row_sd=pb.sig_rate_row, angle_ref=st.angle_ref[c])
        if st.inflation != 1.0:  # the accelerometer rows' sigma widened (settle_noise)
            cs.weight[:, ACC] /= st.inflation
        systems.append(cs)
        gps.append(gp)
    step = solve(systems, pb.pm.size, pb.pm.mean, pb.pm.sd, st.theta)
    return PassResult(step, systems, gps, st.theta.copy())


def apply_step(st: State, pr: PassResult, alpha: float = 1.0, step=None,
               axes: list | None = None) -> State:
    """The state moved by alpha times the pass's step (or ``step``). Each block's attitude
    error phi (body axes) is applied as Exp(psi a) C Exp(phi - psi a_b), a the cycle's
    table axis in ENU (``axes``), a_b = C^T a, psi = phi . a_b: to first order C Exp(phi),
    and a turn about the table axis in ENU (which the earth's rotation, the propagation's
    only ENU term, nearly commutes with) leaves the propagation's cost as it was. On a
    vertical axis that turn is the heading, which nothing measures: a step moves it by a
    tenth of a radian with the gyros' weak bias about the axis, and composed as one
    rotation its second-order term (phi_j+1 x F phi_j / 2) cost 40 times the step's gain."""
    step = pr.step if step is None else step
    C, rho = [], []
    for c, (cs, dl) in enumerate(zip(pr.systems, step.dlocal)):
        phi = alpha * dl[:, :3]
        Cc = st.C[c][:cs.nb]
        if axes is not None:
            a = axes[c]
            a_b = np.einsum("bji,j->bi", Cc, a)
            psi = np.einsum("bi,bi->b", phi, a_b)
            turn = Rotation.from_rotvec(np.outer(psi, a)).as_matrix()
            rest = Rotation.from_rotvec(phi - psi[:, None] * a_b).as_matrix()
            new = np.einsum("bij,bjk,bkl->bil", turn, Cc, rest)
        else:
            new = np.einsum("bij,bjk->bik", Cc, Rotation.from_rotvec(phi).as_matrix())
        C.append(np.concatenate([new, st.C[c][cs.nb:]]))
        rho.append(None if st.rho[c] is None or cs.nl < 4 else
                   np.concatenate([st.rho[c][:cs.nb] + alpha * dl[:, 3], st.rho[c][cs.nb:]]))
    return State(st.theta + alpha * step.dtheta, C, rho, st.C_start, st.axis_var,
                 st.inflation, st.lever2, st.angle_ref)


def follow_valley(pb: Problem, th0: np.ndarray, th1: np.ndarray) -> np.ndarray:
    """th1, a step from th0, with each rotating cycle's gyro response about its table axis
    (K a_b, the rate the gyros see per unit of table rate) put where the step's
    linearisation takes it, by the least change of K that does it for every cycle (least
    squares where the cycles outnumber the axes): the scale factors take the step's
    second-order part. On a vertical axis the mountings and the gyros' misalignment trade
    along a valley whose second-order terms (|du|^2 / 2 in the axis's component along
    itself, dK du) the table's channels see at 2e-5 rad: measured there, a Gauss-Newton
    step promising a fall of 6 in chi^2 raised it by 5000 (1200 per unit step squared),
    and the passes crept (8 and more, one record 5 sigma off where it stopped); with the
    correction 3-8 passes, to a lower cost (fit.hold_undetermined decides where)."""
    pm = pb.pm
    if "gyro_K" not in pm.model.neutral_params():
        return th1
    K0 = np.asarray(pm.params(th0)["gyro_K"], float)
    K1 = np.asarray(pm.params(th1)["gyro_K"], float).copy()
    dK = K1 - K0
    A, R = [], []
    for c, cy in enumerate(pb.cycles):
        if cy.static:
            continue
        u0, u1 = th0[pm.idx["mount"][c]], th1[pm.idx["mount"][c]]
        a0, J0 = su.axis_in_body(cy, u0)
        a1, _ = su.axis_in_body(cy, u1)
        A.append(a1)
        R.append(K0 @ a0 + dK @ a0 + K0 @ (J0 @ (u1 - u0)) - K1 @ a1)
    if not A:
        return th1
    # the least change dK with dK a_c = r_c for every cycle (least squares where more
    # cycles than axes ask for it)
    K1 = K1 + np.linalg.lstsq(np.array(A), np.array(R), rcond=None)[0].T
    out = th1.copy()
    pm.set_params(out, {"gyro_K": K1})
    return out


def table_axes(pb: Problem, theta: np.ndarray | None = None) -> list:
    """Each cycle's table axis in ENU (the plan's)."""
    return [cy.a_enu for cy in pb.cycles]


def moved(pb: Problem, pr: PassResult, reported: np.ndarray) -> np.ndarray:
    """Each reported parameter's (undamped) step in its sigma."""
    sd = np.sqrt(np.clip(np.diag(pr.step.cov), 1e-300, None))
    return np.abs(pr.step.dtheta[reported]) / sd[reported]


def moved_by(pb: Problem, pr: PassResult, step, reported: np.ndarray) -> np.ndarray:
    """Each reported parameter's move by ``step`` in its sigma."""
    sd = np.sqrt(np.clip(np.diag(pr.step.cov), 1e-300, None))
    return np.abs(step.dtheta[reported]) / sd[reported]


def reweight(pb: Problem, pr: PassResult, axis_var: float, accel_factor: float = 1.0) -> None:
    """Set the axis and channel rows' weights to the current noise levels (the
    accelerometers' scaled by ``accel_factor``) and re-solve the pass (the rows do not
    depend on them: the same linearisation)."""
    for cs in pr.systems:
        if accel_factor != 1.0:
            scale_weight(cs, "accel", accel_factor)
        set_weight(cs, "axis", 1.0 / np.sqrt(axis_var))
        cs.axis_var = axis_var
        if pb.enc is not None:
            set_weight(cs, "angle", 1.0 / pb.sig_enc)
        if pb.rate is not None:
            set_weight(cs, "rate", 1.0 / pb.sig_rate_row)
    pr.step = solve(pr.systems, pb.pm.size, pb.pm.mean, pb.pm.sd, pr.theta_lin)


def row_groups(pb: Problem) -> dict:
    groups = {"accel": ACC, "axis": AXIS}
    if pb.enc is not None:
        groups["angle"] = ENC
    if pb.rate is not None:
        groups["rate"] = RATE
    return groups


def residual_levels(pb: Problem, pr: PassResult, tr: dict | None = None) -> tuple[dict, dict]:
    """Per row group: (the mean squared residual after the step in the data's units, and
    the RMS normalised by the rows' sigma), both over n - trace of the hat matrix (``tr``,
    else computed: solve.leverage): what the fit takes out counted."""
    groups = row_groups(pb)
    if tr is None:
        tr = leverage(pr.step, pr.systems, groups)
    raw, norm = {}, {}
    after = [residuals_after(cs, dl, pr.step.dtheta) for cs, dl in zip(pr.systems,
                                                                        pr.step.dlocal)]
    for name, slot in groups.items():
        ss, ssw, n = 0.0, 0.0, 0
        for cs, r_all in zip(pr.systems, after):
            r = r_all[:, slot]
            w = cs.weight[:, slot]
            used = w > 0
            ss += float(np.sum(r[used] ** 2))
            ssw += float(np.sum((r * w)[used] ** 2))
            n += int(used.sum())
        dof = max(n - tr[name], 1.0)
        raw[name] = ss / dof
        norm[name] = float(np.sqrt(ssw / dof))
    return raw, norm


class SecantLevel:
    """The fixed point x = g(x) of one noise level's re-estimate (x its log), reached by
    secant steps on g(x) - x: where the last two rounds show g contracting (0 < g' < 1)
    the move g(x) - x is extrapolated by 1 / (1 - g'), at most EXTRAPOLATE_MAX times;
    else the plain re-estimate. The fixed point (and the settled test on the plain move)
    are those of the plain iteration; only fewer rounds get there."""

    def __init__(self):
        self.prev = None  # (x, g(x) - x) of the last round

    def next(self, x: float, gx: float) -> float:
        f = gx - x
        out = gx
        if self.prev is not None:
            x0, f0 = self.prev
            if x != x0 and f * f0 > 0:
                slope = (f - f0) / (x - x0)  # g' - 1
                if -1.0 < slope < 0.0:
                    out = x + min(-1.0 / slope, EXTRAPOLATE_MAX) * f
        self.prev = (x, f)
        return out


def settle_noise(pb: Problem, st: State, pr: PassResult, rounds: int = 8) -> tuple[bool, dict]:
    """The table axis's and the angle channel's noise re-estimated from the pass's
    residuals and the pass re-solved at them, until they settle (within 5 %): the rows
    stay, only their weights change. Returns whether a level moved by more than 20 % from
    where the pass started, and each row group's normalised residual RMS."""
    if pb.fixed_levels:
        return False, residual_levels(pb, pr)[1]
    axis0, enc0, rate0, infl0 = st.axis_var, pb.sig_enc, pb.sig_rate_row, st.inflation
    floor = axis_floor(pb.sig_g, pb.block_n, pb.rec.sample_rate)
    norm = {}
    tr, at = None, None  # the hat matrix's traces, and the levels they were taken at
    sec_axis, sec_enc, sec_rate = SecantLevel(), SecantLevel(), SecantLevel()
    for _ in range(rounds):
        levels = np.log([st.axis_var, max(pb.sig_enc, 1e-300), pb.sig_rate_row, st.inflation])
        # (the traces move slowly with the weights: taken again after a move of 20 %)
        if tr is None or np.abs(levels - at).max() > NOISE_MOVE:
            tr, at = leverage(pr.step, pr.systems, row_groups(pb)), levels
        raw, norm = residual_levels(pb, pr, tr)
        moved_any = False
        if pb.opt.axis_sigma is None:
            lo, hi = max(floor**2, axis0 / AXIS_STEP), AXIS_CAP**2
            new = float(np.clip(raw["axis"], lo, hi))
            moved_any |= abs(0.5 * np.log(new / st.axis_var)) > SETTLED
            st.axis_var = float(np.clip(np.exp(sec_axis.next(np.log(st.axis_var),
                                                              np.log(new))), lo, hi))
        if pb.enc is not None and not pb.opt.encoder_sigma:
            lo = max(pb.sig_enc_floor, enc0 / np.sqrt(AXIS_STEP))
            new = max(float(np.sqrt(raw["angle"])), lo)
            moved_any |= abs(np.log(new / pb.sig_enc)) > SETTLED
            pb.sig_enc = max(float(np.exp(sec_enc.next(np.log(pb.sig_enc), np.log(new)))), lo)
        if pb.rate is not None:
            new = max(float(np.sqrt(raw["rate"])), RATE_ANGLE_FLOOR)
            moved_any |= abs(np.log(new / pb.sig_rate_row)) > SETTLED
            pb.sig_rate_row = max(float(np.exp(sec_rate.next(np.log(pb.sig_rate_row),
                                                             np.log(new)))), RATE_ANGLE_FLOOR)
        # the accelerometers' noise widened where the model does not explain them (never
        # below their white noise)
        cand = st.inflation * norm["accel"]
        new = cand if cand > ACCEL_MISFIT and pb.widen_accel else 1.0
        factor = st.inflation / new
        moved_any |= abs(np.log(factor)) > SETTLED
        st.inflation = new
        if not moved_any:
            break
        reweight(pb, pr, st.axis_var, factor)
    changed = abs(0.5 * np.log(st.axis_var / axis0)) > NOISE_MOVE or \
        abs(np.log(st.inflation / infl0)) > NOISE_MOVE or \
        (enc0 > 0 and abs(np.log(pb.sig_enc / enc0)) > NOISE_MOVE) or \
        abs(np.log(pb.sig_rate_row / rate0)) > NOISE_MOVE
    return changed, norm
