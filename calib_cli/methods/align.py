"""Two-position analytic alignment (docs/align.md).

At static position k the output means are f_k = C_k^T g_n + nabla and
w_k = C_k^T W_n + eps (C_k body->ENU). The positions are related by known
body-frame rotations C_{k+1} = C_k dR_k, from the gyros integrated through
the (continuously recorded) transition with the earth rate removed
(model/strapdown.py), or from the plan's turn segments.

1. Analytic solution from positions 1 and 2: f_2 - dR^T f_1 = (I - dR^T) nabla
   gives nabla across the turn axis a; |f_1 - nabla| = g the part along a
   (smaller root), or, when a is nearly horizontal, the angle condition
   (f_1 - nabla).(w_1 - eps) = g W sin(lat); likewise eps with |w_1 - eps| = W;
   then C_1 from the two vector pairs (gravity first).
2. Least squares over all positions (methods/lsq.py) of nabla, eps and a
   small rotation alpha (ENU) of C_1, with nuisance parameters that carry the
   errors of the integrated rotations into the covariance: the gyro transfer
   error dG (prior sigma_K per entry: scale factor and misalignment) and the
   rate noise integrated over each transition. Segment means are whitened by
   the noise of a mean (per-sample sigma / sqrt(N)).

Observability comes out of the Jacobian (lsq's rank test): a turn about a
horizontal East-West axis loses nabla and eps along the axis, the heading
and the tilt about North; any turn near 0 or 360 deg loses everything.

The grade check: the gyro equations need the earth rate well above the gyro
bias and the noise of a mean. When it is not (MEMS), the gyro means only
carry eps (with the earth rate as noise, W per axis), the heading is not
estimated, and the accelerometer results (nabla, roll, pitch) stand.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from calib_cli.data import CalibrationResult, Recording, Segment
from calib_cli.errors import EstimationError, InputError
from calib_cli.methods import lsq
from calib_cli.methods.noise import pooled_within
from calib_cli.model.earth import EARTH_RATE
from calib_cli.model.effects import Bias, Layout, ScaleMisalignment
from calib_cli.model.frames import attitude_to_rotation, rotation_to_attitude
from calib_cli.model.imu_model import ImuModel
from calib_cli.model.kinematics import from_attitude
from calib_cli.model.strapdown import integrate_relative

D2R = np.pi / 180.0
NAV_K_PRIOR = 30e-6  # default gyro scale/misalignment prior with a usable earth rate
MEMS_K_PRIOR = 3e-3  # default otherwise (the catalogue's typical MEMS size)
GRADE_NORM_TOL = 0.25  # |w_k| must lie within 25 % of W at every position ...
GRADE_NOISE_TOL = 0.02  # ... and the noise of a mean below 2 % of W
MIN_TURN = 5.0 * D2R  # turns nearer than this to 0 or 360 deg tell nothing
EW_TOL = 2.0  # deg: a turn axis this close to horizontal East-West counts as on it

MODEL = ImuModel((Bias("accel"), Bias("gyro"), ScaleMisalignment("gyro")), Layout())
KEYS = ("accel_bias", "gyro_bias", "attitude")
UNITS = {"accel_bias": "m/s^2", "gyro_bias": "rad/s", "attitude": "rad"}


@dataclass
class Gap:
    """The rotation between static positions k and k+1 (body k+1 -> body k)."""

    dR: Rotation
    source: str  # "gyro" or "plan"
    rel: object = None  # strapdown.RelativeRotation for "gyro"
    t: np.ndarray | None = None
    w: np.ndarray | None = None
    prior_cov: np.ndarray = field(default_factory=lambda: np.zeros((3, 3)))


@dataclass
class Inputs:
    segments: list
    f: np.ndarray  # (M, 3) accel means
    w: np.ndarray  # (M, 3) gyro means
    n: np.ndarray  # (M,) samples per mean
    sig_a: np.ndarray  # (3,) per-sample accel noise
    sig_w: np.ndarray  # (3,) per-sample gyro noise
    gaps: list


# ---------------------------------------------------------------------------
# inputs


def static_means(rec: Recording, segs) -> tuple:
    """Accel and gyro means (M, 3) of the static segments, their sample counts (M,)
    and the pooled per-sample noise sigma (3,) of each (methods/noise.py)."""
    acc = pooled_within((rec.accel[s.slice] for s in segs), 3)
    gyr = pooled_within((rec.gyro[s.slice] for s in segs), 3)
    if acc.dof <= 0:
        raise EstimationError("the static positions hold too few samples to estimate the noise")
    return acc.means, gyr.means, acc.counts, acc.sigma, gyr.sigma


def _plan_turn(rec: Recording, a: Segment, b: Segment) -> Rotation | None:
    turns = [s for s in rec.segments
             if s.kind == "turn" and a.stop <= s.start and s.stop <= b.start]
    if not turns:
        return None
    R = Rotation.identity()
    for s in turns:
        R = R * Rotation.from_rotvec(np.asarray(s.rotation_axis_body) * s.rotation_angle)
    return R


def _continuous(rec: Recording, i0: int, i1: int) -> bool:
    if rec.gyro is None or i1 <= i0:
        return False
    dt = np.diff(rec.time[i0:i1 + 1])
    med = 1.0 / rec.sample_rate if rec.sample_rate > 0 else 0.0
    return bool(len(dt)) and med > 0 and dt.max() < 1.5 * med and dt.min() > 0


def collect(rec: Recording, rotation: str = "auto", turn_sigma: float = 0.0) -> Inputs:
    """Segment means and the rotations between consecutive static positions.

    rotation: "gyro" (integrate the recorded transition), "plan" (the plan's
    turn segments), "auto" (gyro where the transition is recorded
    continuously, else plan). turn_sigma: 1-sigma error (rad, per axis) of a
    plan-stated turn."""
    if rec.layout.redundant:
        raise InputError("this is a redundant-unit recording: use `calib fit rimu`")
    if rec.gyro is None:
        raise EstimationError("the recording has no gyro data; alignment needs both sensors "
                              "(use `calib fit accel` for accelerometers alone)")
    if rec.in_counts("accel") or rec.in_counts("gyro"):
        raise EstimationError("alignment needs data in SI units (m/s^2, rad/s), not raw "
                              "counts: apply a scale calibration first")
    segs = rec.static_segments()
    if len(segs) < 2:
        raise EstimationError(f"alignment needs two static positions; the recording has "
                              f"{len(segs)}: add a second position after a turn of 60-180 deg")
    f, w, n, sa, sw = static_means(rec, segs)
    gaps = []
    for a, b in zip(segs[:-1], segs[1:], strict=True):
        i0, i1 = a.stop - 1, b.start
        plan_R = _plan_turn(rec, a, b)
        use_gyro = rotation == "gyro" or (rotation == "auto" and _continuous(rec, i0, i1))
        if use_gyro:
            if not _continuous(rec, i0, i1):
                raise EstimationError(
                    f"the transition {a.label!r} -> {b.label!r} is not recorded continuously: "
                    "record through the turn, or state the turn in the plan "
                    "(rotation_axis_body, rotation_angle_deg) and use --rotation plan")
            gaps.append(Gap(Rotation.identity(), "gyro", t=rec.time[i0:i1 + 1],
                            w=rec.gyro[i0:i1 + 1]))
        else:
            if plan_R is None:
                raise EstimationError(
                    f"no rotation known between {a.label!r} and {b.label!r}: record the "
                    "transition continuously (gyros integrated) or put a turn segment with "
                    "rotation_axis_body and rotation_angle_deg between them in the plan")
            gaps.append(Gap(plan_R, "plan", prior_cov=np.eye(3) * turn_sigma**2))
    return Inputs(segs, f, w, n, sa, sw, gaps)


def integrate_turns(inp: Inputs, C1: Rotation, eps, site, earth_noise: float = 0.0) -> None:
    """(Re)integrate the gyro gaps with bias eps removed and C1 the attitude
    of position 1; earth_noise (rad/s): earth rate unknown to this level."""
    C = C1
    for gap in inp.gaps:
        if gap.source == "gyro":
            rel = integrate_relative(gap.t, gap.w - eps, C, site, inp.sig_w)
            gap.rel, gap.dR = rel, rel.dR
            gap.prior_cov = rel.noise_cov + np.eye(3) * (earth_noise * rel.duration) ** 2
        C = C * gap.dR


# ---------------------------------------------------------------------------
# grade check and analytic solution


def earth_rate_usable(inp: Inputs) -> tuple[bool, str]:
    """Can the gyros see the earth rate? (norm of every mean near W, noise small)."""
    W = EARTH_RATE
    norms = np.linalg.norm(inp.w, axis=1)
    noise = float(np.max(inp.sig_w / np.sqrt(inp.n.min())))
    dev = float(np.max(np.abs(norms - W)))
    if dev > GRADE_NORM_TOL * W:
        return False, (f"the gyro means have |w| = {norms.min():.3g}..{norms.max():.3g} rad/s "
                       f"against an earth rate of {W:.3g} rad/s: the gyro bias is too large "
                       "to see the earth rate (MEMS grade)")
    if noise > GRADE_NOISE_TOL * W:
        return False, (f"the noise of a gyro mean ({noise:.2g} rad/s) is above "
                       f"{GRADE_NOISE_TOL:.0%} of the earth rate: record longer or use a "
                       "better gyro")
    return True, "the gyros resolve the earth rate"


def _root(v, a, r) -> float:
    """x with |v - x a| = r of smaller magnitude (a unit); the vertex when none."""
    b = float(a @ v)
    disc = b * b - (v @ v - r * r)
    if disc < 0:
        return b
    s = np.sqrt(disc)
    return b - s if abs(b - s) < abs(b + s) else b + s


def analytic(f1, f2, w1, w2, dR: Rotation, site, use_gyro: bool):
    """Closed-form nabla, eps, C_1 from two positions (see module docstring)."""
    g, W = site.gravity, EARTH_RATE
    A = np.eye(3) - dR.inv().as_matrix()
    a = dR.as_rotvec()
    ang = np.linalg.norm(a)
    a = a / ang if ang > 0 else np.array([0.0, 0.0, 1.0])
    Ap = np.linalg.pinv(A, rcond=1e-6)
    nab = Ap @ (f2 - dR.inv().apply(f1))
    eps = Ap @ (w2 - dR.inv().apply(w1)) if use_gyro else 0.5 * (w1 + w2)
    v = f1 - nab
    ug = v / np.linalg.norm(v)
    if use_gyro:
        o = w1 - eps
        x_w = _root(o, a, W)
        eps = eps + x_w * a
    if abs(a @ ug) >= 0.3 or not use_gyro:
        nab = nab + _root(v, a, g) * a
    else:
        # axis nearly horizontal: |f - nabla| = g is blind along a; use the angle
        # between gravity and earth rate, (f_1 - nabla).(w_1 - eps) = g W sin(lat)
        o = w1 - eps
        den = a @ o
        if abs(den) > 0.3 * W:
            nab = nab + (v @ o - g * W * np.sin(site.latitude)) / den * a
    if use_gyro:
        C1, _ = Rotation.align_vectors(
            [site.specific_force_enu / g, site.earth_rate_enu / W],
            [(f1 - nab) / np.linalg.norm(f1 - nab), (w1 - eps) / np.linalg.norm(w1 - eps)],
            weights=[1e6, 1.0])
    else:
        u = f1 - nab
        roll, pitch = np.arctan2(u[1], u[2]), np.arctan2(-u[0], np.hypot(u[1], u[2]))
        C1 = attitude_to_rotation([roll, pitch, 0.0])
    return nab, eps, C1


def tilt_only(f1, site) -> Rotation:
    u = f1
    return attitude_to_rotation([np.arctan2(u[1], u[2]), np.arctan2(-u[0], np.hypot(u[1], u[2])),
                                 0.0])


# ---------------------------------------------------------------------------
# least squares


class _Problem:
    """Parameter vector: nabla(3), eps(3), alpha(3), then z_G (9, dG = sK z_G)
    when a gap is gyro-integrated and sK > 0, then z_k (3) per gap with a prior
    (nu_k = L_k z_k). Every nuisance has a unit-normal prior residual."""

    def __init__(self, inp: Inputs, C1: Rotation, eps0, site, use_gyro: bool, sK: float):
        self.inp, self.C1, self.eps0, self.site = inp, C1, np.asarray(eps0, float), site
        self.use_gyro, self.sK = use_gyro, sK
        self.static_only = False
        self.M = len(inp.f)
        self.gyro_gaps = any(gp.source == "gyro" for gp in inp.gaps)
        self.nG = 9 if (self.gyro_gaps and sK > 0) else 0
        self.L, self.idx = [], []
        i = 9 + self.nG
        for gp in inp.gaps:
            if np.any(gp.prior_cov != 0):
                self.L.append(np.linalg.cholesky(gp.prior_cov + 1e-30 * np.eye(3)))
                self.idx.append(i)
                i += 3
            else:
                self.L.append(None)
                self.idx.append(None)
        self.p = i
        # nominal attitude of each position and the earth sensitivity at gap starts
        self.E = []
        C = C1
        for gp in inp.gaps:
            self.E.append(gp.rel.earth_sensitivity(C, site) if gp.source == "gyro" else None)
            C = C * gp.dR
        self.sa = inp.sig_a / np.sqrt(inp.n)[:, None]  # (M, 3)
        sw = inp.sig_w / np.sqrt(inp.n)[:, None]
        if not use_gyro:  # the earth rate is noise to a gyro that cannot resolve it
            sw = np.sqrt(sw**2 + EARTH_RATE**2)
        self.sw = sw

    def scales(self) -> np.ndarray:
        s = np.ones(self.p)
        s[0:3] = 1e-4
        s[3:6] = 1e-7 if self.use_gyro else 1e-5
        s[6:9] = 1e-4
        return s

    def attitudes(self, th) -> list[Rotation]:
        C = Rotation.from_rotvec(th[6:9]) * self.C1
        out = [C]
        dG = th[9:9 + self.nG] * self.sK if self.nG else np.zeros(9)
        for k, gp in enumerate(self.inp.gaps):
            psi = np.zeros(3)
            if gp.source == "gyro":
                psi = -gp.rel.S_K @ dG
                if not self.static_only:  # second-order channels (see fit_align)
                    psi = psi - gp.rel.S_bias @ (th[3:6] - self.eps0) + self.E[k] @ th[6:9]
            if self.idx[k] is not None:
                psi = psi + self.L[k] @ th[self.idx[k]:self.idx[k] + 3]
            C = C * (Rotation.from_rotvec(psi) * gp.dR)
            out.append(C)
        return out

    def params(self, th) -> dict:
        dG = (th[9:9 + self.nG] * self.sK).reshape(3, 3) if self.nG else np.zeros((3, 3))
        return {"accel_bias": th[0:3], "gyro_bias": th[3:6], "gyro_K": np.eye(3) + dG}

    def predict(self, th):
        rots = self.attitudes(th)
        C = Rotation.concatenate(rots)
        kin = from_attitude(np.zeros(self.M), C, self.site)
        return MODEL.predict(self.params(th), kin)

    def residual(self, th) -> np.ndarray:
        out = self.predict(th)
        ra = ((self.inp.f - out["accel"]) / self.sa).ravel()
        if self.use_gyro:
            rw = ((self.inp.w - out["gyro"]) / self.sw).ravel()
        else:
            rw = ((self.inp.w - th[3:6]) / self.sw).ravel()
        return np.concatenate([ra, rw, th[9:]])


def euler_cov(C1: Rotation, cov_alpha: np.ndarray, unobs_alpha: np.ndarray):
    """Roll, pitch, yaw of C1 and their covariance from alpha's; entries coupled
    to an unobservable alpha component are NaN."""
    e0 = rotation_to_attitude(C1)
    J = np.zeros((3, 3))
    h = 1e-7
    for j in range(3):
        d = np.zeros(3)
        d[j] = h
        de = rotation_to_attitude(Rotation.from_rotvec(d) * C1) - e0
        J[:, j] = (de + np.pi) % (2 * np.pi) - np.pi
    J /= h
    obs = ~unobs_alpha
    cov = np.full((3, 3), np.nan)
    Jo = J[:, obs]
    cov_e = Jo @ cov_alpha[np.ix_(obs, obs)] @ Jo.T
    bad = (np.abs(J[:, ~obs]) > 0.05).any(axis=1) if (~obs).any() else np.zeros(3, bool)
    good = ~bad
    cov[np.ix_(good, good)] = cov_e[np.ix_(good, good)]
    return e0, J, cov, bad


# ---------------------------------------------------------------------------
# the fit


def fit_align(rec: Recording, rotation: str = "auto", gyro: str = "auto",
              gyro_k_prior: float | None = None, turn_sigma: float = 0.0, *,
              noise: dict | None = None) -> CalibrationResult:
    """Accelerometer and gyro biases and the attitude of position 1 from >= 2
    static positions (docs/align.md).

    gyro: "auto" (grade check decides), "use" (exit 4 when the earth rate is
    not usable), "ignore" (accelerometer-only results: biases and tilt).
    gyro_k_prior: 1-sigma of each gyro transfer-error entry (scale factor,
    misalignment), dimensionless; None: 30 ppm when the earth rate is usable,
    3000 ppm otherwise. turn_sigma: rad, for plan-stated turns. noise: {"accel":
    sigma, "gyro": sigma} per sample to weight with instead of the measured noise
    (experiment design, design.py)."""
    site = rec.site
    inp = collect(rec, rotation, turn_sigma)
    if noise is not None:
        inp.sig_a = np.broadcast_to(np.asarray(noise["accel"], float), (3,)).copy()
        inp.sig_w = np.broadcast_to(np.asarray(noise["gyro"], float), (3,)).copy()
    usable, why = earth_rate_usable(inp)
    if gyro == "ignore":
        use_gyro, why = False, "earth rate not used (--gyro ignore)"
    elif gyro == "use" and not usable:
        raise EstimationError(f"{why}; the heading and gyro biases cannot be estimated: use a "
                              "navigation-grade unit, or --gyro ignore for the accelerometer "
                              "biases and tilt")
    else:
        use_gyro = usable
    sK = gyro_k_prior if gyro_k_prior is not None else (NAV_K_PRIOR if use_gyro else MEMS_K_PRIOR)
    earth_noise = 0.0 if use_gyro else EARTH_RATE

    # pass 1: rough attitude and bias, integrate, analytic solution; pass 2: again
    eps = np.zeros(3) if use_gyro else 0.5 * (inp.w[0] + inp.w[1])
    C1 = tilt_only(inp.f[0], site)
    if use_gyro:
        C1, _ = Rotation.align_vectors([site.specific_force_enu / site.gravity,
                                        site.earth_rate_enu / EARTH_RATE],
                                       [inp.f[0] / np.linalg.norm(inp.f[0]),
                                        inp.w[0] / np.linalg.norm(inp.w[0])], weights=[1e6, 1])
    for _ in range(2):
        integrate_turns(inp, C1, eps, site, earth_noise)
        ang = inp.gaps[0].dR.magnitude()
        if ang < MIN_TURN:
            raise EstimationError(
                f"the turn between {inp.segments[0].label!r} and {inp.segments[1].label!r} is "
                f"{np.degrees(ang):.1f} deg: nothing is observable from positions that "
                "close to each other (or a full turn apart); turn the unit 60-180 deg about "
                "an axis that is not horizontal East-West")
        nab, eps, C1 = analytic(inp.f[0], inp.f[1], inp.w[0], inp.w[1], inp.gaps[0].dR, site,
                                use_gyro)
    integrate_turns(inp, C1, eps, site, earth_noise)
    prob = _Problem(inp, C1, eps, site, use_gyro, sK)
    theta0 = np.zeros(prob.p)
    theta0[0:3], theta0[3:6] = nab, eps
    fixed = np.zeros(prob.p, bool)
    if not use_gyro:
        fixed[8] = True  # the heading (alpha up) is not seen by the accelerometers
    fit = lsq.fit(prob.residual, theta0, prob.scales(), what="alignment fit", fixed=fixed)
    # Observability is that of the static equations with the turn known (the
    # issue's twelve equations): the bias and attitude also bend the integrated
    # turn (eps T, W T alpha), which the fit uses, but that channel alone
    # cannot determine an entry to any useful accuracy (its sigma is swamped by
    # the gyro scale-factor prior), so such entries are reported unobservable.
    prob.static_only = True
    jac = _jacobian(prob.residual, fit.theta, prob.scales())
    prob.static_only = False
    _, unobs_static = lsq.covariance(jac, prob.scales(), fixed)
    unobs_static |= _east_west_loss(inp, prob, fit.theta, eps, site, use_gyro, sK, fixed)
    return _result(rec, inp, prob, fit, use_gyro, why, sK, fixed | unobs_static)


def _east_west_loss(inp, prob, theta, eps, site, use_gyro, sK, fixed) -> np.ndarray:
    """Entries lost to a turn about a horizontal East-West axis.

    Exactly there the twelve equations lose a 2-D subspace (nabla and eps
    along the axis, heading, tilt about North); the estimated attitude never
    puts the axis exactly East-West, so the rank test at the estimate sees
    only a weak direction. When every turn axis lies within EW_TOL of the
    East-West line, the data cannot tell the geometry from the degenerate one:
    the rank test is made there (the attitude turned by the small angle that
    makes the first axis exactly East-West)."""
    C = prob.attitudes(theta)
    east = np.array([1.0, 0.0, 0.0])
    axes = []
    for k in range(len(inp.gaps)):
        rv = (C[k].inv() * C[k + 1]).as_rotvec()
        axes.append(C[k].apply(rv / max(np.linalg.norm(rv), 1e-15)))
    off = [np.degrees(np.arccos(min(abs(a @ east), 1.0))) for a in axes]
    if max(off) > EW_TOL:
        return np.zeros(len(theta), bool)
    a = axes[0]
    tgt = np.sign(a @ east) * east
    cr = np.cross(a, tgt)
    snap = Rotation.from_rotvec(cr / max(np.linalg.norm(cr), 1e-15)
                                * np.arcsin(min(np.linalg.norm(cr), 1.0)))
    ps = _Problem(inp, snap * C[0], eps, site, use_gyro, sK)
    ps.static_only = True
    th = np.array(theta, float)
    th[6:9] = 0.0
    _, unobs = lsq.covariance(_jacobian(ps.residual, th, ps.scales()), ps.scales(), fixed)
    return unobs


def _jacobian(fn, th, scales) -> np.ndarray:
    r0 = fn(th)
    J = np.empty((len(r0), len(th)))
    for j in range(len(th)):
        h = 1e-3 * scales[j]
        d = np.zeros(len(th))
        d[j] = h
        J[:, j] = (fn(th + d) - fn(th - d)) / (2 * h)
    return J


def _result(rec, inp, prob, fit, use_gyro, why, sK, fixed) -> CalibrationResult:
    th = fit.theta
    site = rec.site
    unobs = fit.unobservable | fixed
    C_all = prob.attitudes(th)
    C1 = C_all[0]
    cov = fit.cov
    e, J, cov_e, bad_e = euler_cov(C1, np.nan_to_num(cov[6:9, 6:9]), unobs[6:9])
    # covariance over [nabla, eps, attitude] (9 x 9) with the cross terms through J
    T = np.zeros((9, prob.p))
    T[0:6, 0:6] = np.eye(6)
    T[6:9, 6:9] = J
    obs = ~unobs
    full = np.full((9, 9), np.nan)
    To = T[:, obs]
    full_o = To @ cov[np.ix_(obs, obs)] @ To.T
    main_unobs = np.concatenate([unobs[0:6], bad_e])
    if not use_gyro:
        main_unobs[3:6] = False  # eps is estimated, coarsely (to the earth rate)
    keep = ~main_unobs
    full[np.ix_(keep, keep)] = full_o[np.ix_(keep, keep)]
    sig = np.sqrt(np.abs(np.diag(full)))
    params = {"accel_bias": th[0:3].copy(), "gyro_bias": th[3:6].copy(),
              "attitude": np.array(e, float)}
    if not use_gyro:
        params["attitude"][2] = 0.0  # convention: heading not estimated
    sigma = {"accel_bias": sig[0:3], "gyro_bias": sig[3:6], "attitude": sig[6:9]}
    unobs_names = [f"{k}[{i}]" for j, (k, i) in enumerate(
        [(k, i) for k in KEYS for i in range(3)]) if main_unobs[j]]
    if unobs_names and len(unobs_names) == 9:
        raise EstimationError(
            "nothing is observable from these positions: turn the unit 60-180 deg about an "
            "axis that is not horizontal East-West (a turn about the vertical or a North axis "
            "is best)")
    out = prob.predict(th)
    ra = inp.f - out["accel"]
    rw = inp.w - out["gyro"] if use_gyro else inp.w - th[3:6]
    gaps = []
    for k, gp in enumerate(inp.gaps):
        dR = C_all[k].inv() * C_all[k + 1]
        rv = dR.as_rotvec()
        ang = float(np.linalg.norm(rv))
        gaps.append({"from": inp.segments[k].label, "to": inp.segments[k + 1].label,
                     "source": gp.source, "axis_body": (rv / ang if ang > 0 else rv).tolist(),
                     "angle": ang,
                     "duration": float(gp.rel.duration) if gp.rel is not None else None})
    stats = {
        "method": "two-position",
        "rotation_axis_body": gaps[0]["axis_body"], "rotation_angle": gaps[0]["angle"],
        "rotations": gaps,
        "n_positions": len(inp.f),
        "earth_rate_used": bool(use_gyro), "grade_check": why,
        "gyro_K_prior": sK,
        "accel_residual_rms": float(np.sqrt(np.mean(ra**2))),
        "gyro_residual_rms": float(np.sqrt(np.mean(rw**2))),
        "accel_noise_sigma": inp.sig_a.tolist(), "gyro_noise_sigma": inp.sig_w.tolist(),
        "chi2_dof": fit.chi2_dof,
        **g_error_stats(inp.f, th[0:3], site.gravity),
        "observability": observability_note(gaps[0]["axis_body"], gaps[0]["angle"], C1, site,
                                            main_unobs),
        "direct_readings": direct_readings(inp, C_all, site, use_gyro),
        "attitudes_all": [rotation_to_attitude(C).tolist() for C in C_all],
    }
    if not use_gyro:
        stats["unobservable_reason"] = ("heading: " + why + "; gyro_bias only to the size of "
                                        "the earth rate")
    stats["unobservable"] = unobs_names
    order = [(k, i) for k in KEYS for i in range(3)]
    return CalibrationResult(
        method="align", params=params, sigma=sigma, units=dict(UNITS),
        covariance=full, cov_order=order, stats=stats,
        residuals={"accel_segment": ra, "gyro_segment": rw},
        tables={"segment_labels": [s.label for s in inp.segments]},
        model=[{"name": "bias", "sensor": "accel"}, {"name": "bias", "sensor": "gyro"}],
        raw_units=dict(rec.units), layout=rec.layout, serial=rec.serial)


def g_error_stats(f: np.ndarray, nabla: np.ndarray, g: float) -> dict:
    """RMS over the positions of |mean f| - g, raw and bias-corrected (m/s^2),
    and the two figures of accel_lsq.g_figures."""
    from calib_cli.methods.accel_lsq import g_figures

    return {"g_reference": g, **g_figures(np.linalg.norm(f, axis=1),
                                          np.linalg.norm(f - nabla, axis=1), g),
            "g_error_rms_before": float(np.sqrt(np.mean((np.linalg.norm(f, axis=1) - g) ** 2))),
            "g_error_rms_after": float(np.sqrt(np.mean((np.linalg.norm(f - nabla, axis=1) - g)
                                                       ** 2)))}


def observability_note(axis_body, angle, C1: Rotation, site, unobs) -> str:
    """A sentence on what this turn lets the data see (CONTRACT stats)."""
    a_n = C1.apply(np.asarray(axis_body))
    elev = np.degrees(np.arcsin(np.clip(a_n[2], -1, 1)))
    az_from_north = np.degrees(np.arctan2(a_n[0], a_n[1]))
    s = (f"turn of {np.degrees(angle):.1f} deg about a body axis at elevation {elev:.1f} deg, "
         f"azimuth {az_from_north:.1f} deg from North")
    if abs(elev) < 20:
        c = abs(np.cos(np.radians(az_from_north)))
        s += (f"; nearly horizontal: nabla and eps along the axis, heading and tilt are held "
              f"only by the earth rate along it (W cos(lat) cos(beta), cos(beta) = {c:.2f})")
    if np.any(unobs):
        s += "; not observable: " + ", ".join(
            f"{k}[{i}]" for j, (k, i) in enumerate([(k, i) for k in KEYS for i in range(3)])
            if unobs[j])
    return s


def direct_readings(inp: Inputs, C_all, site, use_gyro, tol_deg: float = 2.0) -> list:
    """Special attitudes: an accelerometer axis within tol of the vertical reads
    its bias as f_i -+ g; a gyro axis within tol of the earth's axis reads its
    drift as w_i -+ W; the attitude error enters to second order only."""
    out = []
    up = np.array([0.0, 0.0, 1.0])
    polar = site.earth_rate_enu / EARTH_RATE
    c = np.cos(np.radians(tol_deg))
    for k, C in enumerate(C_all):
        M = C.as_matrix()  # columns: body axes in ENU
        for i in range(3):
            d = M[:, i] @ up
            if abs(d) >= c:
                out.append({"position": inp.segments[k].label, "sensor": "accel", "axis": i,
                            "bias": float(inp.f[k, i] - np.sign(d) * site.gravity),
                            "tilt_deg": float(np.degrees(np.arccos(min(abs(d), 1.0))))})
            p = M[:, i] @ polar
            if use_gyro and abs(p) >= c:
                out.append({"position": inp.segments[k].label, "sensor": "gyro", "axis": i,
                            "bias": float(inp.w[k, i] - np.sign(p) * EARTH_RATE),
                            "tilt_deg": float(np.degrees(np.arccos(min(abs(p), 1.0))))})
    return out
