"""``calib fit turntable``: set up, start, iterate, check the table's channels, report."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from calib_cli.data import CalibrationResult, Recording
from calib_cli.errors import EstimationError, InputError
from calib_cli.methods.turntable import estimator as es
from calib_cli.methods.turntable import setup as su
from calib_cli.methods.turntable.options import TurntableOptions
from calib_cli.methods.turntable.result import build, held_scales, structural_unobservable, theta_labels
from calib_cli.methods.turntable.solve import damped, scaled
from calib_cli.model.correction import correct

# an angle channel whose residuals stand this far above its own white noise disagrees
# with the unit's motion in shape (a logged setpoint, a slipping coupling): not used
SHAPE_RATIO = 3.0
# a rate channel whose normalised residual RMS exceeds this is not used
RATE_MISFIT = 1.5
GAIN_TOL = 0.5  # chi^2: a full step that promises less is converged (see iterate)
HELD_BACK = 1.0  # sigma: a full step this large, damped to nothing, is not converged
# a step above the tolerance is taken as the last only where the passes shrink at this
# rate (_rate) or faster (a vertical axis without channels: 1.12 -> 0.27 sigma, its
# promise 2.8e4 -> 1.6e3 in chi^2, stopped 3.7 sigma from the truth; Gauss-Newton's pass
# 2 shrinks at 0.005-0.09)
EXTRAP_RATIO = 0.15
HOLD_FRACTION = 0.1  # a damped step promising less of the full one's chi^2: a line search
PROBE = 1.0 / 8.0  # the line search's first step, a fraction of the full one
ALPHA_MIN = PROBE  # shorter than its first step, the line search gives up
# with the table's channels the accelerometers' noise widened more than this: the fit is
# tried without them (solved)
CHANNEL_ACCEL_MISFIT = 2.0
START_MOUNT_SD = float(np.radians(0.3))  # rad: the mountings' prior during the start windows
# the noise levels are estimated once a pass moves less than this (sigma): a stiff axis row
# does not bear the linearisation of a large step
SETTLE_MOVE = 2.0
_DEBUG = bool(__import__("os").environ.get("CALIB_TT_DEBUG"))


def _check_options(opt: TurntableOptions) -> None:
    if opt.lever_arm not in ("off", "known", "estimate"):
        raise InputError(f"lever_arm must be off, known or estimate, got {opt.lever_arm!r}")
    if opt.proof_mass not in ("auto", "off", "estimate"):
        raise InputError(f"proof_mass must be auto, off or estimate, got {opt.proof_mass!r}")
    if opt.proof_mass == "estimate" and opt.lever_arm == "off":
        raise InputError("proof-mass offsets need the lever-arm terms (--lever-arm known|estimate)")
    if opt.axis_sigma is not None and not (np.isfinite(opt.axis_sigma) and opt.axis_sigma > 0):
        raise InputError(f"axis_sigma must be > 0 rad, got {opt.axis_sigma!r}")
    if not (np.isfinite(opt.runout_sigma) and opt.runout_sigma >= 0):
        raise InputError(f"runout_sigma must be >= 0 rad, got {opt.runout_sigma!r}")
    su.prior_widths(opt)


def problem(rec: Recording, opt: TurntableOptions) -> es.Problem:
    """The set-up of a fit (estimator.Problem): cycles, model, parameters, channels, noise."""
    _check_options(opt)
    cycles = su.select_cycles(rec, opt)
    rotating = [cy for cy in cycles if not cy.static]
    nc = len(rotating)
    est_p = opt.proof_mass == "estimate" or (opt.proof_mass == "auto" and opt.lever_arm != "off")
    model = su.turntable_model(nc, opt.lever_arm != "off", est_p, opt.tangential, opt.effects,
                               opt.g_sensitivity or any(n == "g_sensitivity"
                                                        for n, _ in opt.effects),
                               opt.base_structure)
    lever_known = None
    if opt.lever_arm == "known":
        missing = [cy.label for cy in rotating if cy.s_plan is None]
        if missing:
            raise InputError(f"--lever-arm known needs lever_arm_m in the plan for every rotating "
                             f"segment; missing: {', '.join(missing)}")
        lever_known = np.array([cy.s_plan for cy in rotating])
    fs = rec.sample_rate
    block_n = max(1, int(round(opt.block_s * fs)))
    # a static position too short for ten blocks is left out; a rotating segment is an error
    cycles = [cy for cy in cycles if not cy.static or (cy.sl.stop - cy.sl.start) >= 10 * block_n]
    nb = [(cy.sl.stop - cy.sl.start) // block_n for cy in cycles]
    for cy, n in zip(cycles, nb):
        if n < 10:
            raise EstimationError(f"rotating segment {cy.label!r} is too short "
                                  f"({cy.sl.stop - cy.sl.start} samples) for the turntable fit")
    enc, sig_enc, notes = su.angle_channels(rec, rotating, block_n, opt)
    rate, sig_rate, rnotes = su.rate_channels(rec, rotating, block_n, opt)
    n_static = len(cycles) - nc
    if enc is not None:
        enc = enc + [None] * n_static
    if rate is not None:
        rate = rate + [None] * n_static
    notes = notes + rnotes
    n_axes = 1 + max(cy.axis_group for cy in rotating)
    pm = su.param_map(model, cycles, opt, n_axes, enc is not None, rate is not None)
    on = np.concatenate([np.arange(cy.sl.start, cy.sl.stop) for cy in rotating])
    if opt.noise is not None:
        sig_a = np.asarray(opt.noise["accel"], float) * np.ones(3)
        sig_g = np.asarray(opt.noise["gyro"], float) * np.ones(3)
    else:
        sig_a = su.white_noise(rec.accel[on])
        sig_g = su.white_noise(rec.gyro[on])
    gyro_cols, gyro_idx = es.columns_of(model, pm, "gyro")
    acc_cols, acc_idx = es.columns_of(model, pm, "accel")
    pb = es.Problem(rec, cycles, model, pm, opt, block_n, nb, gyro_cols, gyro_idx, acc_cols,
                    acc_idx, sig_a, sig_g, pm.has("lever_arm"), lever_known, enc, sig_enc,
                    rate, sig_rate, notes)
    pb.sig_enc_floor = sig_enc
    # the channels start loose (as the axis: AXIS_START) and settle with the noise levels
    # (estimator.settle_noise): a rough start against a stiff channel does not linearise
    if enc is not None and not opt.encoder_sigma:
        pb.sig_enc = max(sig_enc, es.AXIS_START)
    pb.free_heading = [False for cy in cycles]  # (fit.hold_undetermined)
    return pb


def hold_undetermined(pb: es.Problem) -> None:
    """Without a gravity reference (result.structural_unobservable) a common tilt of the
    mountings, the accelerometers' K and biases, the lever arms and the gyros'
    misalignment turn together at nearly equal cost, and the entries only the mountings'
    prior decides are reported null and listed in stats.unobservable. The mountings keep
    their prior (held at the plan's, the accelerometers misfit by 20-26 % in RMS: the
    centripetal terms see each cycle's axis in body axes; with a table channel the gyro
    scale factors took the true mounting error times the misalignment, RMS z 2.5).
    With a table channel every step follows the valley the mountings form with the gyros'
    misalignment (estimator.follow_valley). Without one the heading about the vertical
    axis is measured by nothing but the earth rate's phase, and through it the gyro scale
    about the axis (sigma 2e-3: a heading of a radian by the cycle's end at one sigma,
    where that phase is far from linear; Gauss-Newton steps of 1.2 % in scale and 1.3 rad
    in heading were rejected, and the passes crept): the turn about the table axis is not
    propagated there (rows.cycle_system's free_heading), which leaves the up axis's gyro
    bias and scale to the other cycles and the centripetal terms. With a stated mounting
    but no angle channel and no static position, the gyro scale about a vertical axis is
    pinned at its prior mean (result.considered: its prior spread kept
    in the others' sigma)."""
    pb.held = structural_unobservable(pb)
    if su.gravity_reference(pb.cycles) or any(cy.static for cy in pb.cycles):
        # at most the gyro scale about a vertical axis held: pinned at its prior mean
        # (free, it crept with the heading and the earth rate's phase: 8 passes still
        # moving 6 sigma); its prior stays in the covariance (the biases' and
        # g-sensitivities' sigma keep its spread: fixed, they came out 3-4 sigma off)
        pb.pinned = held_scales(pb)
        return
    if pb.enc is not None or pb.rate is not None:
        pb.follow_valley = True
        pb.accel_path = True
    else:
        pb.free_heading = [not cy.static for cy in pb.cycles]


def start_state(pb: es.Problem) -> es.State:
    """Where the iterations start: the prior mean, coarse lever arms from the holds, each
    cycle's attitude from the plan's mounting turned to the gravity of its first block (a
    static position's: the plan's)."""
    theta = pb.pm.mean.copy()
    rec = pb.rec
    if pb.pm.has("lever_arm"):
        for cy in pb.cycles:
            s0 = None if cy.static else su.initial_lever_arm(rec, cy)
            if s0 is not None:
                theta[pb.pm.idx["lever_arm"][cy.model_index]] = cy.basis.T @ s0
    for c, cy in enumerate(pb.cycles):
        # on a vertical axis gravity does not modulate with the table angle: the mounting
        # starts where the gyros turn (started at the plan's 3 deg off, the passes ended in
        # a local optimum 30 mrad from the truth, gyro_K up to 14 sigma off)
        # (within the start windows' hold of the plan's, or where the plan states the
        # mounting, the plan's: the gyros' direction carries their misalignment, which the
        # windows then put into the mounting; with a stated one, 1 of 20 fits more ended
        # in exit 4)
        u0 = None if cy.static or cy.mount_stated or not su.vertical(cy) else \
            su.gyro_mounting(rec, cy)
        if u0 is not None and np.linalg.norm(u0) > 3.0 * START_MOUNT_SD:
            theta[pb.pm.idx["mount"][c]] = u0
    params = pb.pm.params(theta, pb.lever_known)
    C, rho, C0 = [], [], []
    g_n = pb.g_n
    for c, cy in enumerate(pb.cycles):
        if cy.static:
            R0 = cy.rot_nom.as_matrix()
        else:
            a = rec.accel[cy.sl][: pb.block_n]
            f0 = correct(pb.model, params, "accel", a).mean(axis=0)
            s = params.get("lever_arm")
            if s is not None:  # the rigid-body terms at the first block, from the raw rates
                w = rec.gyro[cy.sl][: pb.block_n].mean(axis=0)
                f0 = f0 - np.cross(w, np.cross(w, s[cy.model_index]))
            R0 = su.start_attitude(cy, f0, g_n, theta[pb.pm.idx["mount"][c]])
        C.append(R0[None].copy())
        C0.append(R0)
        rho.append(None if pb.rate is None or pb.rate[c] is None else np.zeros(1))
    axis_var = (pb.opt.axis_sigma if pb.opt.axis_sigma is not None else es.AXIS_START) ** 2
    return es.State(theta, C, rho, C0, axis_var)


def reported_columns(pb: es.Problem) -> np.ndarray:
    """The theta indices of the reported parameters that the record can determine
    (convergence is judged on them; pb.held, set by hold_undetermined: the others)."""
    held = pb.held
    idx = [int(pb.pm.idx["packing"][q]) for q, (key, flat) in enumerate(pb.pm.keys)
           if key not in held and (key, flat) not in held]
    if pb.pm.has("lever_arm") and "lever_arm" not in held:
        idx += list(pb.pm.idx["lever_arm"].ravel())
    if pb.pm.has("time_offset"):
        idx += list(pb.pm.idx["time_offset"])
    return np.array(idx, int)


class _TrustRegion:
    """Levenberg-Marquardt damping of the parameters' step between passes: a step whose
    cost at the next pass (the objective at the new point) rose is taken back and
    redone damped; damping shrinks again after steps that did what they predicted. A
    weakly determined, strongly curved direction (a vertical axis's gyro scale against
    the lever arms, seen only through omega^2 against d omega / dt) otherwise makes
    Gauss-Newton overshoot.
    Once the noise levels have settled, a damped step that promises less than
    HOLD_FRACTION of the full one's fall in chi^2 (or less than GAIN_TOL) is replaced by
    the full step shortened along its own direction, PROBE of it first (a line search:
    doubled where the step did what it promised, back to Gauss-Newton at the full length;
    the first rise of the cost shorter than twice PROBE ends it, and iterate then judges
    convergence): along a valley whose curvature is a tiny part of its parameters' own (a
    vertical axis's mountings against the gyros' misalignment: 1e-8 of diag(S)) the
    diagonal damping shrinks the step to nothing while it still promises chi^2, and the
    passes crept (5 of 20 vertical records with channels exit 4 after 8 passes)."""

    def __init__(self, pb):
        self.lam = 0.0
        self.alpha = None  # the line search's fraction of the full step; None: damped
        self.line_failed = False
        self.probe_failed = False  # the last check found the line search's step raised the cost
        self.prev = None  # (state before the step, its pass, the step taken)
        self.actual = np.inf  # the cost's fall over the last step kept
        self.axes = lambda st: es.table_axes(pb, st.theta)
        self.pb = pb

    def check(self, st, pr):
        """The state to linearise next and whether the pass ``pr`` at ``st`` is kept."""
        if self.prev is None:
            return st, True
        st0, pr0, step0 = self.prev
        self.probe_failed = False
        actual = pr0.step.cost - pr.step.cost
        predicted = pr0.step.cost - step0.predicted
        if actual < 0 and pr.step.cost > pr0.step.cost * (1 + 1e-9):  # rose: redo shorter
            if self.alpha is not None:
                self.alpha /= 4.0
                if self.alpha < ALPHA_MIN:  # the direction does not hold: damped again
                    self.alpha, self.line_failed, self.probe_failed = None, True, True
            else:
                self.lam = max(10.0 * self.lam, 1e-2)
            step = self._shortened(pr0)
            self.prev = (st0, pr0, step)
            return self._apply(st0, pr0, step), False
        self.actual = actual
        ratio = actual / predicted if predicted > 0 else 1.0
        if self.alpha is not None:
            if ratio > 0.75:
                self.alpha = min(1.0, 2.0 * self.alpha)
                if self.alpha == 1.0:  # Gauss-Newton again
                    self.alpha, self.lam = None, 0.0
            elif ratio < 0.25:
                self.alpha /= 2.0
                if self.alpha < ALPHA_MIN:
                    self.alpha, self.line_failed = None, True
        elif ratio > 0.75:
            self.lam = self.lam / 10.0 if self.lam > 1e-6 else 0.0
        elif ratio < 0.25:
            self.lam = max(4.0 * self.lam, 1e-3)
        return st, True

    def step(self, st, pr, settled: bool = False):
        # (not where the model does not explain the accelerometers, its noise widened:
        # its full step never comes to nothing, iterate reports it as it stands)
        if (settled and self.alpha is None and self.lam > 0 and not self.line_failed
                and st.inflation == 1.0):
            sd = np.sqrt(np.clip(np.diag(pr.step.cov), 1e-300, None))
            full = float(np.max(np.abs(pr.step.dtheta) / sd))
            gain = pr.step.cost - pr.step.predicted
            kept = pr.step.cost - damped(pr.step, self.lam, self.pb.pinned).predicted
            if full >= self.pb.opt.converge_sigma and kept < max(HOLD_FRACTION * gain,
                                                                 GAIN_TOL):
                self.alpha = PROBE
        step = self._shortened(pr)
        self.prev = (st, pr, step)
        return self._apply(st, pr, step)

    def _shortened(self, pr):
        if self.alpha is not None:
            return scaled(pr.step, self.alpha, self.pb.pinned)
        if self.lam == 0 and not len(self.pb.pinned):
            return pr.step
        return damped(pr.step, self.lam, self.pb.pinned)

    def _apply(self, st, pr, step):
        new = es.apply_step(st, pr, step=step, axes=self.axes(st))
        if self.pb.follow_valley:
            new.theta = es.follow_valley(self.pb, st.theta, new.theta)
        return new

    def reset(self):
        self.prev = None
        self.actual = np.inf


def iterate(pb: es.Problem, st: es.State, progress=None, windows: bool = True,
             strict: bool = True) -> tuple[es.State, es.PassResult, dict]:
    """The start windows, then the passes over the whole record to convergence. The
    noise levels (the table axis's, the angle channel's) are re-estimated from the first
    settled window on, at most AXIS_STEP in variance a pass: as the windows grow the
    estimate follows what the data determine at that stiffness. On a vertical axis a
    stiff axis makes the heading observable through the earth's rotation (the tilt it
    leaves where the heading is wrong), and with it the gyro scale about the axis; that
    is linear only while the heading is known to a few tenths of a radian, which the
    windows keep true and a jump to a stiff axis over the whole record does not.
    windows: False where the state is already a solution over the whole record (a refit
    with one more effect: methods/turntable/diagnose.py); strict: the pass limit reached
    is an error (else the last state, info["moving"] naming what still moves)."""
    T = pb.block_n / pb.rec.sample_rate
    rep = reported_columns(pb)
    info = {"start_windows": 0, "passes": 0, "last_move": None}
    longest = max(pb.nb) * T
    n_windows = max(0, int(np.ceil(np.log2(max(longest / es.START_S, 1.0)))))
    done = [0]

    def tick(final=False):
        """progress(done, total): the start windows, then about three passes."""
        if progress is None:
            return
        done[0] += 1
        left = 0 if final else max(n_windows - info["start_windows"], 0) + max(
            3 - info["passes"], 1)
        progress(done[0], done[0] + left)
    settled = False  # the noise levels are being estimated
    tr = _TrustRegion(pb)
    if windows:
        st = _start_windows(pb, st, tr, rep, info, tick)
    last, prev = np.inf, np.inf
    gain_prev = gain_last = np.inf  # what the last two kept passes' full steps promised
    tail = np.inf
    last_kept = (st, None)
    tr.reset()
    for k in range(max(1, pb.opt.passes)):
        pr = es.run_pass(pb, st, pb.nb)
        st, kept = tr.check(st, pr)
        info["passes"] = k + 1
        if not kept:
            if tr.probe_failed and last_kept[1] is not None and \
                    _damped_quiet(pb, tr, last_kept[1], rep):
                # the full step's direction raised the cost an eighth of the way along,
                # and the damped step promises nothing: what the full step still promises
                # is the linearisation's error (its sensitivities taken per group of
                # samples), the state a minimum of the cost itself
                info["moving"] = []
                tick(final=True)
                return last_kept[0], last_kept[1], info
            continue
        last_kept = (st, pr)
        mv = es.moved(pb, pr, rep)
        rms = es.residual_levels(pb, pr)[1] if not settled else None
        # (a model that does not explain the accelerometers settles at once: its noise is
        # widened before its steps are judged in sigma)
        if settled or float(np.max(mv)) < SETTLE_MOVE or (
                rms["accel"] > es.ACCEL_MISFIT and pb.widen_accel):
            # (the pass is re-solved at the settled levels: its cost and the next pass's
            # are of the same objective, so the trust region keeps judging the step)
            changed, rms = es.settle_noise(pb, st, pr)
            settled = True
            if changed:
                mv = es.moved(pb, pr, rep)
        else:
            changed = True
        st = tr.step(st, pr, settled)
        taken = es.moved_by(pb, pr, tr.prev[2], rep)  # the step taken (damped where damped)
        gain = pr.step.cost - pr.step.predicted  # what the full step promised
        prev, last = last, float(np.max(taken))
        gain_prev, gain_last = gain_last, gain
        if _DEBUG:
            print(f"pass {k + 1}: cost {pr.step.cost:.6g} gain {gain:.3g} actual "
                  f"{tr.actual:.3g} lam {tr.lam:.2g} alpha {tr.alpha} full "
                  f"{float(np.max(mv)):.3g} taken {last:.3g}"
                  f" settled {settled} levels {rms} axis {np.sqrt(st.axis_var):.3g}")
        tick()
        info["last_move"] = last
        info["residual_rms"] = rms
        # converged: this pass and all the passes after it together would move less than
        # the tolerance, at the rate the last two shrank (_rate: Gauss-Newton's 1.3 -> 0.1
        # -> 0.005 sigma; a creep of 0.2 -> 0.13 sigma is not converged); or
        # the full step promises, or the last one delivered, less than GAIN_TOL of chi^2
        # (the Jacobian's own error, the sensitivities taken per group of samples, leaves a
        # step of a few tenths of a sigma that improves nothing, more where the residuals
        # stand above the noise: the trust region then damps it away)
        # (a pass whose noise levels settled was re-solved at them: its step is the one
        # the new levels give, so it counts as any other)
        # (along a valley the steps do not shrink as Gauss-Newton's: not extrapolated there)
        # (a full step of HELD_BACK sigma or more that the damping holds back is stuck, not
        # converged, where the model explains the accelerometers: on a vertical axis 3 deg
        # off the plan, a full step of 7 sigma promising 58 in chi^2, damped to 0.1 sigma,
        # ended 11 sigma from the truth with exit 0; a model that does not, its noise
        # widened, never gets its full step to nothing and is reported as it stands; a
        # diagnosis's candidates, scored and never reported, stop as before)
        rate = _rate(last, prev, gain, gain_prev)
        tail = np.inf if rate >= 1.0 else last * rate / (1.0 - rate)
        plain = tr.lam == 0 and last < pb.opt.converge_sigma and tail < pb.opt.converge_sigma
        extrapolated = (tr.lam == 0 and not changed and np.isfinite(prev)
                        and not pb.follow_valley and rate <= EXTRAP_RATIO
                        and tail < pb.opt.converge_sigma)
        quiet = last < pb.opt.converge_sigma and (gain < GAIN_TOL or (
            tr.actual < GAIN_TOL and (float(np.max(mv)) < HELD_BACK or not strict
                                      or st.inflation != 1.0)))
        if plain or extrapolated or quiet:
            info["moving"] = []
            if _DEBUG:
                print(f"converged: pass {k + 1} plain {plain} extrapolated {extrapolated} "
                      f"quiet {quiet} taken {last:.3g} before {prev:.3g} gain {gain:.3g} "
                      f"before {gain_prev:.3g} actual {tr.actual:.3g}")
            tick(final=True)
            return st, pr, info
    names = _moving_names(pb, pr, rep, mv)
    if not strict:  # the last pass kept, at the point it linearised about
        info["moving"] = names
        return last_kept[0], last_kept[1], info
    big = float(np.max(mv))
    slow = "" if big >= pb.opt.converge_sigma else (
        f", shrinking so slowly that about {min(tail, 99.0):.2g} sigma would still follow")
    hint = "" if not any(pb.free_heading) else (
        " (a vertical table axis without the table's channels: the passes creep along the "
        "gyro biases and g-sensitivity; give the angle or rate channel, static positions or "
        "a tilted cycle: docs/turntable.md, \"Known limits on a vertical axis\")")
    raise EstimationError(f"the turntable fit did not converge in {pb.opt.passes} passes: "
                          f"{', '.join(names[:6])} still move by up to {big:.2g} sigma a "
                          f"pass{slow}{hint}")


def _start_windows(pb: es.Problem, st: es.State, tr: _TrustRegion, rep: np.ndarray,
                   info: dict, tick) -> es.State:
    """The start: windows doubling from START_S until they span every cycle. They hold
    each cycle's mounting closer than its prior (START_MOUNT_SD) about where the state
    starts (the plan's; setup.gyro_mounting's on a vertical axis): on a vertical axis a
    tilt of every mounting, the accelerometers' K and biases and the gyros' misalignment
    turn together along a valley of nearly equal cost, which short windows do not close;
    started along it, the passes ended in a local optimum 16 sigma from the truth and 11
    in chi^2 above the one near it."""
    T = pb.block_n / pb.rec.sample_rate
    L, first = es.START_S, True
    mi = pb.pm.idx["mount"]
    sd_mount, mean_mount = pb.pm.sd[mi].copy(), pb.pm.mean[mi].copy()
    pb.pm.sd[mi] = np.minimum(sd_mount, START_MOUNT_SD)
    pb.pm.mean[mi] = st.theta[mi]
    try:
        while True:
            nbs = [min(n, max(10, int(np.ceil(L / T)))) for n in pb.nb]
            if nbs == pb.nb:
                return st
            info["start_windows"] += 1
            # the first window from the coarse start until it settles; each later one a
            # pass (the next window's pass refines it again)
            tr.reset()
            for _ in range(es.STAGE_PASSES * 2 if first else 2):
                pr = es.run_pass(pb, st, nbs)
                st, kept = tr.check(st, pr)
                if not kept:
                    continue
                small = float(np.max(es.moved(pb, pr, rep))) < 1.0
                st = tr.step(st, pr)
                if not first or small:
                    break
            first = False
            L *= 2.0
            tick()
    finally:  # the priors as the plan gives them, whatever ends the windows
        pb.pm.sd[mi], pb.pm.mean[mi] = sd_mount, mean_mount


def _rate(last: float, prev: float, gain: float, gain_prev: float) -> float:
    """The rate the passes shrink at (0 where there is no earlier pass): the ratio of
    the last two steps (sigma), or the square root of the ratio of the chi^2 their full
    steps promised, whichever is slower. Gauss-Newton's steps and promises shrink
    together (1.3 -> 0.1 sigma, 1e7 -> 300 in chi^2); along a curved valley the steps
    shrink while the promise does not (a vertical axis without channels: 1.75 -> 0.12
    sigma promising 2430 -> 348, stopped there 6 sigma from the truth; 1.5 -> 0.2 -> 0.13
    sigma promising 1380 -> 240 -> 134, the passes after it delivering what they
    promised). The passes still to come move about last r / (1 - r) together."""
    if not (np.isfinite(prev) and np.isfinite(gain_prev)) or prev <= 0:
        return 0.0
    r_gain = float(np.sqrt(min(max(gain, 0.0) / gain_prev, 1.0))) if gain_prev > 0 else 0.0
    return max(min(last / prev, 1.0), r_gain)


def _damped_quiet(pb: es.Problem, tr: _TrustRegion, pr: es.PassResult, rep) -> bool:
    """Whether the damped step from the pass ``pr`` promises less than GAIN_TOL of chi^2
    and moves every reported entry less than the convergence tolerance."""
    d = damped(pr.step, max(tr.lam, 1e-6), pb.pinned)
    return (pr.step.cost - d.predicted < GAIN_TOL
            and float(np.max(es.moved_by(pb, pr, d, rep))) < pb.opt.converge_sigma)


def _moving_names(pb, pr, rep, mv) -> list:
    """The reported entries the last full step moves by the tolerance or more, largest
    first (the three largest where none does: the steps shrank below it too slowly)."""
    labels = theta_labels(pb)
    order = np.argsort(-mv)
    names = [f"{labels[rep[i]]} ({mv[i]:.2g})" for i in order]
    return names[:max(3, int(np.sum(mv >= pb.opt.converge_sigma)))]


def fit_turntable(rec: Recording, options: TurntableOptions = TurntableOptions(),
                  progress=None) -> CalibrationResult:
    """Fit the turntable model to a raw recording with rotating segments (module
    docstring of methods/turntable/estimator.py). progress: ``progress(done, total)``."""
    from calib_cli.methods.blas_threads import one_blas_thread

    with one_blas_thread():  # small dense systems: threads only contend
        return _fit(rec, options, progress)


def _fit(rec: Recording, opt: TurntableOptions, progress=None) -> CalibrationResult:
    return build(*solved(rec, opt, progress))


def prepared(rec: Recording, opt: TurntableOptions) -> tuple[es.Problem, es.State]:
    """The problem and the state the iterations start from (the undetermined held)."""
    pb = problem(rec, opt)
    st = start_state(pb)
    hold_undetermined(pb)
    return pb, st


def solved(rec: Recording, opt: TurntableOptions, progress=None, start=None) -> tuple:
    """(problem, state, last pass, iteration info) of the converged fit: iterated, the
    channels that disagree with the motion dropped, the accelerometer noise widened
    where the model does not explain it. start: (problem, state) from ``prepared``."""
    pb, st = start if start is not None else prepared(rec, opt)
    for _attempt in range(6):
        st, pr, info = iterate(pb, st, progress)
        rms = info["residual_rms"]
        # the table's channels against the model: an angle channel whose residuals stand far
        # above its white noise, or a rate channel whose residuals do not fit, disagree with
        # the motion in shape; the fit is then rerun without them
        if pb.enc is not None and pb.sig_enc > SHAPE_RATIO * pb.sig_enc_floor \
                and not opt.encoder_sigma:
            pb.notes.append(f"angle channel not used: its residuals ({pb.sig_enc * 1e3:.3g} mrad "
                            f"RMS) stand {pb.sig_enc / pb.sig_enc_floor:.0f}x above its white "
                            f"noise ({pb.sig_enc_floor * 1e3:.3g} mrad): it does not follow "
                            "the unit's motion")
            labels = theta_labels(pb)
            pb = _without(pb, "angle")
            st = _restart(pb, st, labels)
            continue
        if pb.rate is not None and rms.get("rate", 0.0) > RATE_MISFIT:
            pb.notes.append(f"rate channel not used: normalised residual RMS {rms['rate']:.3g}")
            labels = theta_labels(pb)
            pb = _without(pb, "rate")
            st = _restart(pb, st, labels)
            continue
        if opt.table_encoder == "auto" and (pb.enc is not None or pb.rate is not None) \
                and st.inflation > CHANNEL_ACCEL_MISFIT:
            # channels that scale the motion wrongly (a table logging its command, 0.2 %
            # off its true rate) agree in shape with the gyros, which take the error into
            # their scale (150 sigma), but not with the gravity the accelerometers see
            # turn: the fit is tried without them, and kept where that explains the data
            alt = _without_channels(pb, progress)
            if alt is not None:
                pb.notes.append(f"table channels not used: with them the accelerometers "
                                f"misfit (noise widened x{st.inflation:.3g}), without them "
                                f"x{alt[1].inflation:.3g}: they do not follow the unit's "
                                "motion (a table that logs its commanded profile?)")
                alt[0].notes = pb.notes
                pb, st, pr, info = alt
            else:
                pb.notes.append(f"table channels used although the accelerometers misfit "
                                f"with them (noise widened x{st.inflation:.3g}): the fit "
                                "without them did not explain the data better")
        break
    return pb, st, pr, info


def _without_channels(pb: es.Problem, progress=None) -> tuple | None:
    """The fit of pb's record without the table's channels, from a fresh start, where its
    accelerometers fit within CHANNEL_ACCEL_MISFIT (else None: the channels are not the
    cause)."""
    new = problem(pb.rec, replace(pb.opt, table_encoder="off"))
    st = start_state(new)
    hold_undetermined(new)
    try:
        st, pr, info = iterate(new, st, progress)
    except EstimationError:
        return None
    if st.inflation > CHANNEL_ACCEL_MISFIT:
        return None
    return new, st, pr, info


def _without(pb: es.Problem, channel: str) -> es.Problem:
    opt = pb.opt
    mode = {"angle": {"auto": "rate", "both": "rate", "angle": "off"},
            "rate": {"auto": "angle", "both": "angle", "rate": "off"}}[channel].get(
        opt.table_encoder, opt.table_encoder)
    if channel == "angle" and pb.rate is None:
        mode = "off"
    if channel == "rate" and pb.enc is None:
        mode = "off"
    new = problem(pb.rec, replace(opt, table_encoder=mode))
    new.notes = pb.notes
    hold_undetermined(new)
    return new


def _restart(pb: es.Problem, st: es.State, old_labels: list) -> es.State:
    """The state carried into a problem with other channels (the parameters' vector
    re-mapped by name; the trajectory kept)."""
    new = pb.pm.mean.copy()
    pos = {lab: i for i, lab in enumerate(old_labels)}
    for i, lab in enumerate(theta_labels(pb)):
        if lab in pos:
            new[i] = st.theta[pos[lab]]
    rho = [None if pb.rate is None or pb.rate[c] is None else
           (r if r is not None else np.zeros(len(C))) for c, (r, C) in enumerate(zip(st.rho, st.C))]
    return es.State(new, st.C, rho, st.C_start, st.axis_var, st.inflation,
                    angle_ref=st.angle_ref)
