"""Gyro calibration from the rotations between static positions.

Model (CONTRACT.md section 2): W = d + G w + D f + noise, through the effect
catalogue (Bias, ScaleMisalignment "full", GSensitivity) and corrected with
``model.correction.correct``; the frame is the one the accelerometer
calibration fixes (the gravity directions come from it).

Three kinds of equations, each whitened by its own noise:

- static positions: the mean gyro output equals d + G w_e + D f, with w_e
  the earth rate in body axes (exact where the plan gives the attitude; only
  its vertical part otherwise, the unknown horizontal part added to the
  variance).
- transitions between consecutive static positions that are recorded without
  a gap: the corrected gyro output, integrated as a rotation from the last
  sample of one position to the first of the next, must carry the gravity
  direction measured (by the calibrated accelerometer) at the first onto the
  one measured at the second. Two residuals per transition (the tangent
  plane of the measured direction).
- turns of known angle (plan segments with rotation_axis_body and
  rotation_angle_deg, e.g. 360 deg by hand): the integral of the corrected
  rate over the segment equals axis * angle (plus the earth rate).

Integration: per sample interval the rotation vector
phi = (w_n + w_n+1) dt / 2 + (w_n x w_n+1) dt^2 / 12 (exact to third order
for a rate that varies linearly over the interval, the coning correction),
rotations (SciPy's ``Rotation``) composed in body order by a pairwise (tree) product.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from calib_cli.data import CalibrationResult, Recording
from calib_cli.errors import EstimationError, InputError
from calib_cli.methods import lsq
from calib_cli.methods.noise import pooled_within
from calib_cli.methods.result import build_result
from calib_cli.methods.static_detect import too_few_hint
from calib_cli.model.correction import correct
from calib_cli.model.earth import EARTH_RATE
from calib_cli.model.effects import Bias, GSensitivity, Layout, ScaleMisalignment
from calib_cli.model.frames import attitude_to_rotation, axis_angle
from calib_cli.model.imu_model import ImuModel, Packing
from calib_cli.model.kinematics import Kinematics
from calib_cli.model.strapdown import exp_matrix
from calib_cli.model.truth import effect_from_description

GAP_FACTOR = 1.5  # a sample interval > 1.5 x the median is a gap: no integration across it


def gyro_model(g_sensitivity: bool, extra=(), structure: str = "full") -> ImuModel:
    """bias + G (+ D) and any further catalogue effects (``fit gyro --with``)."""
    eff = (Bias("gyro"), ScaleMisalignment("gyro", structure))
    return ImuModel(eff + ((GSensitivity(),) if g_sensitivity else ()) + tuple(extra), Layout())


def increments(w, dt):
    """Rotation vectors (n-1, 3) of the sample intervals from rates w (n, 3), rad/s."""
    w0, w1 = w[:-1], w[1:]
    return 0.5 * (w0 + w1) * dt[:, None] + np.cross(w0, w1) * (dt[:, None] ** 2 / 12.0)


def integrate(phi_list) -> np.ndarray:
    """Total rotation (as matrices (m, 3, 3), body start -> body end: v_start = C v_end)
    of each list of increments, by a pairwise product that keeps the order."""
    m = len(phi_list)
    L = max(1, max(len(p) for p in phi_list))
    L2 = 1 << int(np.ceil(np.log2(L)))
    phi = np.zeros((m, L2, 3))  # padded with identities
    for i, p in enumerate(phi_list):
        phi[i, :len(p)] = p
    r = Rotation.from_rotvec(phi.reshape(-1, 3))
    while len(r) > m:  # neighbours pair up within each row (L2 is a power of two)
        r = r[0::2] * r[1::2]
    return r.as_matrix().reshape(m, 3, 3)


# ---------------------------------------------------------------------------
# the experiment, reduced to what the fit needs


def _accel_model(acc: CalibrationResult) -> ImuModel:
    effects = tuple(effect_from_description(d) for d in acc.model if d.get("sensor") == "accel")
    return ImuModel(effects, Layout())


class GyroProblem:
    """Static means, transitions and turns of a recording, with their noise."""

    def __init__(self, rec: Recording, acc: CalibrationResult):
        self.rec = rec
        t = rec.time
        self.dt_med = float(np.median(np.diff(t)))
        site = rec.site
        self.g = site.gravity
        w_enu = site.earth_rate_enu
        self.w_h = EARTH_RATE * np.cos(site.latitude)  # horizontal earth rate, rad/s
        amodel = _accel_model(acc)
        self.f_all = correct(amodel, acc.params, "accel", rec.accel)  # m/s^2, every sample
        statics = sorted(rec.static_segments(), key=lambda s: s.start)
        self.statics = statics
        if not statics:
            self.f_static = np.zeros((0, 3))
        # static means (gyro in the data's units, accel corrected, SI)
        gyr = pooled_within((rec.gyro[s.slice] for s in statics), 3)
        acc = pooled_within((self.f_all[s.slice] for s in statics), 3)
        self.W_static = gyr.means
        self.n_static = np.array([s.n for s in statics], dtype=float)
        self.f_static = acc.means
        self.sig_gyro = np.nan_to_num(gyr.sigma)  # per sample, data units
        self.sig_f = float(np.sqrt(np.mean(np.nan_to_num(acc.sigma) ** 2)))  # per sample, m/s^2
        self.u = self.f_static / np.linalg.norm(self.f_static, axis=1)[:, None]
        # earth rate in body axes at each static position
        self.we_static = np.zeros((len(statics), 3))
        self.known_att = np.array([s.attitude is not None for s in statics], bool)
        for k, s in enumerate(statics):
            if s.attitude is not None:
                self.we_static[k] = attitude_to_rotation(s.attitude).inv().apply(w_enu)
            else:
                self.we_static[k] = EARTH_RATE * np.sin(site.latitude) * self.u[k]
        # transitions between consecutive static positions
        self.transitions, self.skipped = [], []
        for k in range(len(statics) - 1):
            a, b = statics[k].stop - 1, statics[k + 1].start
            if b - a < 2:
                self.skipped.append((statics[k].label, statics[k + 1].label, "no samples between"))
                continue
            inside = [s.label for s in rec.segments if s.kind != "static"
                      and s.start < b and s.stop > a + 1]
            if inside:
                # integrating through it would trust that nothing was cut out around it
                self.skipped.append((statics[k].label, statics[k + 1].label,
                                     f"segment {inside[0]!r} lies between"))
                continue
            dts = np.diff(t[a:b + 1])
            if np.any(dts > GAP_FACTOR * self.dt_med):
                self.skipped.append((statics[k].label, statics[k + 1].label, "time gap"))
                continue
            self.transitions.append((k, a, b))
        self.tr_dt = [np.diff(t[a:b + 1]) for _, a, b in self.transitions]
        self.tr_T = np.array([t[b] - t[a] for _, a, b in self.transitions])
        # earth-rate rotation of the level frame over each transition, in body axes at a
        self.tr_earth = []
        for k, a, b in self.transitions:
            T = t[b] - t[a]
            if self.known_att[k]:
                self.tr_earth.append(exp_matrix(self.we_static[k] * T))
            else:
                self.tr_earth.append(np.eye(3))
        self.tr_earth = np.array(self.tr_earth).reshape(-1, 3, 3)
        # tangent bases of the destination directions
        self.tr_basis = []
        for k, _, _ in self.transitions:
            u = self.u[k + 1]
            e1 = np.cross(u, [1.0, 0, 0] if abs(u[0]) < 0.9 else [0, 1.0, 0])
            e1 /= np.linalg.norm(e1)
            self.tr_basis.append(np.stack([e1, np.cross(u, e1)]))
        self.tr_basis = np.array(self.tr_basis).reshape(-1, 2, 3)
        # turns of known angle
        self.turns = [s for s in rec.segments if s.kind == "turn"]
        for s in self.turns:
            if s.n < 3:
                raise EstimationError(f"turn segment {s.label!r} has {s.n} samples: too short "
                                      "to integrate")
            if np.any(np.diff(t[s.slice]) > GAP_FACTOR * self.dt_med):
                raise InputError(f"turn segment {s.label!r} has a time gap: it cannot be "
                                 "integrated", None)
        self.turn_dt = [np.diff(t[s.slice]) for s in self.turns]
        self.turn_we = [None if s.attitude is None else
                        attitude_to_rotation(s.attitude).inv().apply(w_enu) for s in self.turns]
        self.turn_T = np.array([t[s.stop - 1] - t[s.start] for s in self.turns])
        # samples to correct in each evaluation
        idx = [np.arange(a, b + 1) for _, a, b in self.transitions] + \
              [np.arange(s.start, s.stop) for s in self.turns]
        self.idx = np.concatenate(idx) if idx else np.zeros(0, int)
        self.bounds = np.cumsum([0] + [len(i) for i in idx])
        # temperature (for a model with temperature_drift): per corrected sample, and the
        # mean of each static position
        self.temp_idx = self.temp_static = None
        if rec.temp is not None and np.all(np.isfinite(rec.temp)):
            self.temp_idx = np.asarray(rec.temp, float)[self.idx]
            self.temp_static = np.array([np.mean(rec.temp[s.slice]) for s in statics])

    def _temp(self, model, which):
        if not model.has("temperature_drift"):
            return None
        return self.temp_idx if which == "idx" else self.temp_static

    def static_kin(self, model) -> Kinematics:
        n = len(self.statics)
        return Kinematics(np.zeros(n), self.f_static, self.we_static, np.zeros((n, 3)),
                          temp=self._temp(model, "static"))

    @property
    def n_rot(self) -> int:
        return len(self.transitions) + len(self.turns)

    # -- predictions ------------------------------------------------------
    def rates(self, model, p):
        """Corrected rates (rad/s) over the transition and turn samples, per piece."""
        if not len(self.idx):
            return []
        w = correct(model, p, "gyro", self.rec.gyro[self.idx], other=self.f_all[self.idx],
                    temp=self._temp(model, "idx"))
        return [w[self.bounds[i]:self.bounds[i + 1]] for i in range(len(self.bounds) - 1)]

    def transition_pred(self, pieces):
        """Predicted destination gravity directions (m, 3)."""
        if not self.transitions:
            return np.zeros((0, 3))
        phis = [increments(w, dt) for w, dt in zip(pieces, self.tr_dt, strict=False)]
        C = integrate(phis)
        src = np.array([self.u[k] for k, _, _ in self.transitions])
        src = np.einsum("mij,mj->mi", self.tr_earth, src)
        return np.einsum("mji,mj->mi", C, src)  # C^T u_k

    def turn_integrals(self, pieces):
        """Integral of the corrected rate over each turn, minus the earth rate (m, 3), rad."""
        out = []
        for s, w, dt, we in zip(self.turns, pieces, self.turn_dt, self.turn_we, strict=False):
            total = (0.5 * (w[:-1] + w[1:]) * dt[:, None]).sum(axis=0)
            if we is not None:
                a = s.rotation_axis_body
                theta = np.concatenate([[0.0], np.cumsum(0.5 * (w[:-1] + w[1:]) @ a * dt)])
                e = axis_angle(a, -theta).apply(we)
                total = total - (0.5 * (e[:-1] + e[1:]) * dt[:, None]).sum(axis=0)
            out.append(total)
        return np.array(out).reshape(-1, 3)

    def sigmas(self, model, p):
        """1-sigma of the static, transition (per tangent component) and turn
        (per axis) equations at the parameters p."""
        G = p["gyro_K"]
        Ginv = np.linalg.inv(G)
        sig_w = float(np.sqrt(np.mean(np.diag(Ginv @ np.diag(self.sig_gyro**2) @ Ginv.T))))
        # static means: white noise plus the unknown horizontal earth rate
        var_e = np.where(self.known_att, 0.0, self.w_h**2 / 2.0)
        g_row2 = (G**2).sum(axis=1)  # per output axis, for an isotropic rate error
        var_s = (self.sig_gyro[None, :] ** 2 / self.n_static[:, None]
                 + var_e[:, None] * g_row2[None, :] / 3.0)
        # transitions: both directions' noise, integrated gyro noise, unknown earth rate
        var_tr = []
        for (k, _a, _b), dt, T in zip(self.transitions, self.tr_dt, self.tr_T, strict=False):
            v = (self.sig_f / self.g) ** 2 * (1 / self.n_static[k] + 1 / self.n_static[k + 1])
            v += sig_w**2 * float(np.sum(dt**2))
            if not self.known_att[k]:
                v += (self.w_h * T) ** 2 / 2.0
            var_tr.append(v)
        var_turn = []
        for _s, dt, we, T in zip(self.turns, self.turn_dt, self.turn_we, self.turn_T, strict=False):
            v = sig_w**2 * float(np.sum(dt**2))
            if we is None:
                v += (EARTH_RATE * T) ** 2 / 3.0
            var_turn.append(v)
        return np.sqrt(var_s), np.sqrt(np.array(var_tr)), np.sqrt(np.array(var_turn))

    def residuals(self, model, p, sig):
        """Whitened residuals [static (3 each), transitions (2 each), turns (3 each)]."""
        sig_s, sig_tr, sig_turn = sig
        kin = self.static_kin(model)
        r_s = (self.W_static - model.predict(p, kin, sensors=("gyro",))["gyro"]) / sig_s
        pieces = self.rates(model, p)
        ntr = len(self.transitions)
        pred = self.transition_pred(pieces[:ntr])
        r_tr = -np.einsum("mkj,mj->mk", self.tr_basis, pred) / sig_tr[:, None]
        ints = self.turn_integrals(pieces[ntr:])
        want = np.array([s.rotation_axis_body * s.rotation_angle
                         for s in self.turns]).reshape(-1, 3)
        r_turn = (ints - want) / sig_turn[:, None] if len(self.turns) else np.zeros((0, 3))
        return np.concatenate([r_s.ravel(), r_tr.ravel(), r_turn.ravel()])


# ---------------------------------------------------------------------------
# the fit


def _start(prob: GyroProblem, model: ImuModel, base: dict, counts: bool) -> dict:
    """Bias from the static means; G = s I with s from the turns or a search."""
    W = prob.rec.gyro
    d0 = np.median(prob.W_static, axis=0) if len(prob.statics) else np.zeros(3)
    start = dict(base, gyro_bias=d0)
    if prob.turns:
        ratios = []
        for s, dt in zip(prob.turns, prob.turn_dt, strict=False):
            x = W[s.slice] - d0
            tot = (0.5 * (x[:-1] + x[1:]) * dt[:, None]).sum(axis=0)
            ratios.append(tot @ s.rotation_axis_body / s.rotation_angle)
        s0 = float(np.median(ratios))
        if s0 == 0:
            s0 = 1.0
        return dict(start, gyro_K=np.eye(3) * s0)
    if not counts:
        return dict(start, gyro_K=np.eye(3))
    # counts and transitions only: 1-D search of the scale. The path length of
    # the raw rate bounds it from above (gravity turns by no more than the body).
    ang = np.arccos(np.clip(np.einsum("ij,ij->i", prob.u[[k for k, _, _ in prob.transitions]],
                                      prob.u[[k + 1 for k, _, _ in prob.transitions]]), -1, 1))
    path = np.array([np.sum(np.linalg.norm(W[a:b] - d0, axis=1) * np.diff(prob.rec.time[a:b + 1]))
                     for _, a, b in prob.transitions])
    ok = ang > 0.2
    s_hi = float(np.min(path[ok] / ang[ok])) if ok.any() else float(np.max(path) / 0.2 + 1e-9)
    ntr = len(prob.transitions)

    def cost(s):
        pred = prob.transition_pred(prob.rates(model, dict(start, gyro_K=np.eye(3) * s))[:ntr])
        return float(np.sum(np.einsum("mkj,mj->mk", prob.tr_basis, pred) ** 2))

    # coarse grid (4 % steps), then a fine one (0.5 %) around its best
    grid = s_hi * np.exp(np.arange(np.log(0.1), np.log(1.05), 0.04))
    best = grid[int(np.argmin([cost(s) for s in grid]))]
    fine = best * np.exp(np.arange(-0.04, 0.0401, 0.005))
    best = fine[int(np.argmin([cost(s) for s in fine]))]
    return dict(start, gyro_K=np.eye(3) * best)


def _observable_D(prob: GyroProblem) -> bool:
    """g-sensitivity is observable from the static positions when their specific
    forces span 3-D (with the bias: rank 4 of [1, f])."""
    if len(prob.statics) < 4:
        return False
    H = np.column_stack([np.ones(len(prob.f_static)), prob.f_static / prob.g])
    s = np.linalg.svd(H, compute_uv=False)
    return bool(s[-1] > 0.05 * s[0])


def excitation(rec: Recording, accel: CalibrationResult, base: str = "full"):
    """What this record excites for the gyro method's optional effects
    (``Effect.not_excited``): turns both ways, temperature, gravity in 3-D."""
    from calib_cli.model.effects import Excitation

    prob = GyroProblem(rec, accel)
    both = False
    if len(prob.idx):
        d0 = np.median(prob.W_static, axis=0) if len(prob.statics) else 0.0
        model = gyro_model(False)
        unit = abs(float(np.mean(np.diag(_start(prob, model, model.neutral_params(),
                                                  rec.in_counts("gyro"))["gyro_K"]))))
        w = (rec.gyro[prob.idx] - d0) / max(unit, 1e-300)
        both = bool(np.any((w > 0.05).any(axis=0) & (w < -0.05).any(axis=0)))
    span = None
    if rec.temp is not None and np.all(np.isfinite(rec.temp)):
        span = float(np.ptp(rec.temp))
    # 0.5 s bins over the record, as the wandering biases' rule reads them
    n_bins = int((rec.time[-1] - rec.time[0]) / 0.5) if len(rec.time) > 1 else 0
    return Excitation("gyro", ("gyro",), base, 0, both, span, n_bins, False, False,
                      _observable_D(prob))


def fit_gyro(rec: Recording, accel: CalibrationResult | None = None,
             g_sensitivity: str = "auto", accel_independent: bool = False, *,
             noise: dict | None = None, strict: bool = True, extra=(),
             structure: str = "full") -> CalibrationResult:
    """The contract's ``fit gyro``. accel: the accelerometer calibration (fitted
    here from the same recording when None). g_sensitivity: auto (fit gyro_D
    when the static positions make it observable), on, off. accel_independent:
    the calibration was fitted on other data, so its errors are independent of
    this recording's noise and are propagated (``_independent_accel``).
    noise: {"accel": sigma, "gyro": sigma} per sample, to weight with instead of
    the measured noise; strict=False reports unobservable entries instead of
    failing (both for experiment design, design.py). extra: further
    catalogue effects (``fit gyro --with``: gyro scale asymmetry, temperature drift,
    misalignment from a diagonal base, ``structure="diagonal"``)."""
    extra = tuple(extra)
    if any(e.name == "g_sensitivity" for e in extra):
        extra = tuple(e for e in extra if e.name != "g_sensitivity")
        g_sensitivity = "on"
    if rec.gyro is None:
        raise EstimationError("the recording has no gyro data")
    if rec.layout.redundant:
        raise InputError("this is a redundant-unit recording: use `calib fit rimu`")
    accel_independent = accel_independent and accel is not None  # fitted here: same data
    if accel is None:
        from calib_cli.methods.accel_lsq import fit_accel

        accel = fit_accel(rec, noise=None if noise is None else noise["accel"], strict=strict)
    if accel.raw_units.get("accel") != rec.units.get("accel"):
        raise EstimationError(f"the accelerometer calibration was fitted on data in "
                              f"{accel.raw_units.get('accel')}, this recording is in "
                              f"{rec.units.get('accel')}")
    if len(rec.static_segments()) < 2:
        raise EstimationError(f"the gyro fit needs static positions (bias, noise, gravity "
                              f"directions); the recording has {len(rec.static_segments())}"
                              f"{too_few_hint(rec, 2)}")
    prob = GyroProblem(rec, accel)
    if noise is not None:
        prob.sig_gyro = np.broadcast_to(np.asarray(noise["gyro"], float), (3,)).copy()
        prob.sig_f = float(np.sqrt(np.mean(np.asarray(noise["accel"], float) ** 2)))
    if prob.n_rot == 0:
        why = "; ".join(f"{a} -> {b}: {r}" for a, b, r in prob.skipped[:3])
        raise EstimationError(
            "no rotations to integrate: the gyro fit needs static positions recorded "
            "continuously with the motions between them, or turn segments of known angle "
            f"(rotation_angle_deg){' (skipped: ' + why + ')' if why else ''}")
    counts = rec.in_counts("gyro")
    use_D = {"on": True, "off": False}.get(g_sensitivity, None)
    if use_D is None:
        use_D = _observable_D(prob)
    model = gyro_model(use_D, extra, structure)
    packing = Packing.for_model(model)
    base = model.neutral_params()
    p0 = _start(prob, model, base, counts)
    unit = abs(float(np.mean(np.diag(p0["gyro_K"]))))
    g_unit = unit  # data units per rad/s
    scales = np.concatenate([np.full(int(m.sum()), spec.typical * g_unit)
                             for spec, m in zip(packing.specs, packing.masks, strict=False)])
    n_eq = 3 * len(prob.statics) + 2 * len(prob.transitions) + 3 * len(prob.turns)
    if n_eq < packing.size:
        raise EstimationError(f"{n_eq} equations for {packing.size} unknowns: the gyro fit needs "
                              "more static positions and rotations between them")
    theta = packing.pack(p0)
    fit = None
    for _ in range(2):  # weights from the start, then from the estimate
        p = packing.unpack(theta, base)
        sig = prob.sigmas(model, p)
        fit = lsq.fit(lambda th, sig=sig: prob.residuals(model, packing.unpack(th, base), sig),
                      theta, scales, what="gyro fit")
        theta = fit.theta
    unobs_G = [lab for lab, u in zip(packing.labels(), fit.unobservable, strict=False)
               if u and lab[0] in ("gyro_bias", "gyro_K")]
    if unobs_G and strict:
        raise EstimationError(
            f"the rotations do not determine {', '.join(f'{k}[{i}]' for k, i in unobs_G[:4])}: "
            f"the experiment needs rotations about all three axes ({len(prob.transitions)} "
            f"transitions, {len(prob.turns)} turns used)")
    if use_D and g_sensitivity == "auto" and fit.unobservable.any():
        return fit_gyro(rec, accel, "off", accel_independent, noise=noise, strict=strict,
                        extra=extra, structure=structure)
    cross = None
    if accel_independent:
        fit, cross = _independent_accel(prob, model, packing, fit, base, sig, scales, accel)
    # (an inflation scales the gyro noise part only: Cov(theta, a) = -A J_a C_a keeps)
    fit, inflation = fit.inflated()
    p = packing.unpack(fit.theta, base)
    return _finish(prob, model, packing, fit, base, p, sig, inflation, accel, use_D, cross)


def _independent_accel(prob, model, packing, fit, base, sig, scales, accel):
    """Refit with an accelerometer calibration from other data as an uncertain
    input. The gravity directions and the specific force come from it, so its
    error da (covariance C_a) moves the whitened residuals by J_a da: generalised
    least squares with the residual covariance I + J_a C_a J_a^T (da
    marginalised) gives the gyro parameters, their covariance including the
    calibration's uncertainty, and Cov(theta, a) = -Cov(theta) Jw^T W J_a C_a
    (Jw, W: Jacobian and whitening of the generalised problem). Fitted on the
    same recording instead, the calibration's errors come from the same position
    means whose noise the weights already carry (docs/gyro.md).
    Returns (fit, cross block (n_gyro, n_accel) in accel.cov_order's accel_ entries)."""
    from dataclasses import replace

    from scipy.linalg import solve_triangular

    aidx = [j for j, (k, _) in enumerate(accel.cov_order) if k.startswith("accel_")]
    C_a = np.asarray(accel.covariance, float)[np.ix_(aidx, aidx)]
    ok = np.isfinite(np.diag(C_a)) & (np.diag(C_a) > 0)
    C_a = np.where(ok[:, None] & ok[None, :], C_a, 0.0)
    p = packing.unpack(fit.theta, base)
    r0 = prob.residuals(model, p, sig)
    J_a = np.zeros((len(r0), len(aidx)))
    for m, j in enumerate(aidx):
        if not ok[m]:
            continue
        key, flat = accel.cov_order[j]
        h = 0.1 * float(np.sqrt(C_a[m, m]))
        params = {k: np.array(v, float, copy=True) for k, v in accel.params.items()}
        params[key].reshape(-1)[flat] += h
        J_a[:, m] = (GyroProblem(prob.rec, replace(accel, params=params)).residuals(model, p, sig)
                     - r0) / h
    L = np.linalg.cholesky(np.eye(len(r0)) + J_a @ C_a @ J_a.T)

    def white(th):
        return solve_triangular(L, prob.residuals(model, packing.unpack(th, base), sig),
                                lower=True)

    gls = lsq.fit(white, fit.theta, scales, what="gyro fit")
    rw = white(gls.theta)
    Jw = np.empty((len(rw), packing.size))
    for j in range(packing.size):
        th = gls.theta.copy()
        h = 1e-4 * scales[j]
        th[j] += h
        Jw[:, j] = (white(th) - rw) / h
    obs = ~gls.unobservable
    cross = np.full((packing.size, len(aidx)), np.nan)
    WJa = solve_triangular(L, J_a, lower=True)
    cov = gls.cov[np.ix_(obs, obs)]
    cross[obs] = -cov @ Jw[:, obs].T @ WJa @ C_a
    return gls, cross


def _finish(prob, model, packing, fit, base, p, sig, inflation, accel, use_D, cross=None):
    rec = prob.rec
    pieces = prob.rates(model, p)
    ntr = len(prob.transitions)
    pred = prob.transition_pred(pieces[:ntr])
    tr_err = np.array([np.arccos(np.clip(x @ prob.u[k + 1] / np.linalg.norm(x), -1, 1))
                       for x, (k, _, _) in zip(pred, prob.transitions, strict=False)])
    ints = prob.turn_integrals(pieces[ntr:])
    want = np.array([s.rotation_axis_body * s.rotation_angle for s in prob.turns]).reshape(-1, 3)
    turn_err = np.linalg.norm(ints - want, axis=1) if len(prob.turns) else np.zeros(0)
    # angle the calibrated gyro integrates about each turn's axis
    turn_angles = [float(a @ s.rotation_axis_body) * 180 / np.pi
                   for a, s in zip(ints, prob.turns, strict=True)]
    n = len(prob.statics)
    kin = prob.static_kin(model)
    r_static = prob.W_static - model.predict(p, kin, sensors=("gyro",))["gyro"]
    allr = np.concatenate([tr_err, turn_err])
    stats = {
        "method": "gyro",
        "gyro_residual_rms": float(np.sqrt(np.mean(allr**2))) if len(allr) else None,
        "transition_residual_rms_rad": float(np.sqrt(np.mean(tr_err**2))) if ntr else None,
        "turn_residual_rms_rad": float(np.sqrt(np.mean(turn_err**2))) if len(turn_err) else None,
        "static_residual_rms": float(np.sqrt(np.mean(r_static**2))) if n else None,
        "n_positions": n, "n_transitions": ntr, "n_turns": len(prob.turns),
        "transitions_skipped": [f"{a} -> {b}: {r}" for a, b, r in prob.skipped],
        # names of the entries of residuals transition_angle (the report's figure)
        "transitions_used": [f"{prob.statics[k].label} -> {prob.statics[k + 1].label}"
                             for k, _, _ in prob.transitions],
        "turn_angles_deg": {s.label: ang for s, ang in zip(prob.turns, turn_angles, strict=False)},
        "gyro_noise_sigma": prob.sig_gyro.tolist(),
        "g_sensitivity": bool(use_D),
        "accel_method": accel.method,
        "accel_uncertainty": "propagated (independent calibration)" if cross is not None
        else "not added (the position noise is in the weights)",
        "chi2_dof": fit.chi2_dof, "sigma_inflation": inflation,
        "chi2": fit.chi2, "dof": fit.dof, "n_equations": int(len(fit.residuals)),
        "warnings": _warnings(p, prob),
    }
    res = build_result("gyro", model, packing, fit, base, rec.units, stats, serial=rec.serial,
                       residuals={"transition_angle": tr_err, "turn_angle": turn_err,
                                  "static_gyro": r_static})
    return with_accel(res, accel, cross)


def _warnings(p: dict, prob: GyroProblem) -> list[str]:
    out = []
    if np.any(np.diag(p["gyro_K"]) < 0):
        out.append("gyro_K has a negative scale factor: the sign of a turn's rotation_angle_deg "
                   "(right-hand rule about rotation_axis_body) may be wrong, or an axis is "
                   "wired reversed")
    if prob.skipped and not prob.transitions:
        out.append("no transition between static positions could be integrated (spliced or "
                   "gapped recording): G rests on the turns alone")
    return out


def with_accel(res: CalibrationResult, accel: CalibrationResult,
               cross: np.ndarray | None = None) -> CalibrationResult:
    """The gyro result with the accelerometer calibration it used, so the file
    corrects both sensors (the gyro's D needs the corrected specific force).
    cross: Cov(gyro parameters, accelerometer parameters) of an independent
    calibration (``_independent_accel``); None: block-diagonal."""
    from dataclasses import replace

    from scipy.linalg import block_diag

    akeys = [k for k in accel.params if k.startswith("accel_")]
    params = {**{k: accel.params[k] for k in akeys}, **res.params}
    sigma = {**{k: accel.sigma[k] for k in akeys}, **res.sigma}
    units = {**{k: accel.units[k] for k in akeys}, **res.units}
    aorder = [(k, i) for k, i in accel.cov_order if k.startswith("accel_")]
    aidx = [j for j, (k, _) in enumerate(accel.cov_order) if k.startswith("accel_")]
    acov = np.asarray(accel.covariance)[np.ix_(aidx, aidx)]
    stats = dict(res.stats)
    for k in ("g_reference", "g_error_rms_before", "g_error_rms_after", "accel_residual_rms"):
        if k in accel.stats:
            stats[k] = accel.stats[k]
    stats["unobservable"] = [u for u in accel.stats.get("unobservable", [])
                             if u.startswith("accel_")] + list(res.stats["unobservable"])
    cov = block_diag(acov, res.covariance)
    if cross is not None:
        na = len(aidx)
        cov[na:, :na] = cross
        cov[:na, na:] = cross.T
    return replace(res, params=params, sigma=sigma, units=units,
                   covariance=cov, cov_order=aorder + res.cov_order,
                   stats=stats, model=[d for d in accel.model if d.get("sensor") == "accel"]
                   + res.model, raw_units=dict(res.raw_units), tables={**accel.tables,
                                                                         **res.tables})
