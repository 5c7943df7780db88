"""Static-only two-position analytic alignment (Tan et al.; docs/align.md,
`calib fit align RAW --out CAL --method static`).

No turn recorded or stated: at each static position k the output means are
f_k = C_k^T g_n + nabla and w_k = C_k^T W_n + eps with C_k (body->ENU)
unknown. Two positions give twelve equations for twelve unknowns (nabla,
eps, C_1, C_2); more positions add six equations and three unknowns each.

Per position the six equations determine the attitude (3) and leave three
conditions on the biases: |f_k - nabla| = g, |w_k - eps| = W and
(f_k - nabla).(w_k - eps) = g W sin(lat). Two positions: six conditions for
the six biases. Linearised, the norm conditions hold nabla in the plane of
the two gravity directions (body axes) and eps in the plane of the two
earth-rate directions; the components along g_1 x g_2 and W_1 x W_2 are
held only by the two angle conditions, which mix nabla with eps in the
ratio W : g. That is why the method is weak at navigation grade: the
accelerometer bias along g_1 x g_2 inherits the gyro-mean noise times g/W.

Degenerate relative attitudes: a turn about the vertical (g_1 = g_2: the
norm conditions coincide), about the earth's axis (W_1 = W_2), or by a small
angle. The conditioning is measured by the condition number of the
Jacobian of the twelve equations in normalised units (accelerometer
equations / g, gyro equations / W; nabla / g, eps / W, angles in rad), which
does not depend on the noise; above COND_MAX the weak directions are
reported unobservable (sigma null, stats.unobservable), exit 4 when nothing
is left.

Solution: TRIAD attitudes from the raw means (biases zero), then Gauss-Newton
on the twelve equations (methods/lsq.py), predicted means from the one
forward model (kinematics.from_attitude, effect catalogue biases). With no
redundancy the residuals vanish and the covariance J^-1 Sigma J^-T comes from
the noise of the segment means (within-position noise / sqrt(N)).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from calib_cli.data import CalibrationResult, Recording
from calib_cli.errors import EstimationError, InputError
from calib_cli.methods import lsq
from calib_cli.methods.align import KEYS, UNITS, earth_rate_usable, euler_cov, g_error_stats, static_means
from calib_cli.model.earth import EARTH_RATE
from calib_cli.model.effects import Bias, Layout
from calib_cli.model.imu_model import ImuModel
from calib_cli.model.kinematics import from_attitude

COND_MAX = 1.0e3  # normalised condition number above which weak directions are unobservable
MODEL = ImuModel((Bias("accel"), Bias("gyro")), Layout())


class _Inputs:
    def __init__(self, segs, f, w, n, sa, sw):
        self.segments, self.f, self.w, self.n, self.sig_a, self.sig_w = segs, f, w, n, sa, sw


def _triad(f, w, site) -> Rotation:
    C, _ = Rotation.align_vectors([site.specific_force_enu / site.gravity,
                                   site.earth_rate_enu / EARTH_RATE],
                                  [f / np.linalg.norm(f), w / np.linalg.norm(w)],
                                  weights=[1e6, 1.0])
    return C


class _Problem:
    """theta = [nabla (3), eps (3), alpha_1 (3), ..., alpha_M (3)], C_k = Exp(alpha_k) C_k0."""

    def __init__(self, inp: _Inputs, C0: list, site):
        self.inp, self.C0, self.site = inp, C0, site
        self.M = len(C0)
        self.p = 6 + 3 * self.M
        self.sa = inp.sig_a / np.sqrt(inp.n)[:, None]
        self.sw = inp.sig_w / np.sqrt(inp.n)[:, None]

    def scales(self) -> np.ndarray:
        s = np.full(self.p, 1e-4)
        s[3:6] = 1e-7
        return s

    def attitudes(self, th) -> list:
        return [Rotation.from_rotvec(th[6 + 3 * k:9 + 3 * k]) * C for k, C in enumerate(self.C0)]

    def predict(self, th) -> dict:
        kin = from_attitude(np.zeros(self.M), Rotation.concatenate(self.attitudes(th)), self.site)
        return MODEL.predict({"accel_bias": th[0:3], "gyro_bias": th[3:6]}, kin)

    def residual(self, th) -> np.ndarray:
        out = self.predict(th)
        return np.concatenate([((self.inp.f - out["accel"]) / self.sa).ravel(),
                               ((self.inp.w - out["gyro"]) / self.sw).ravel()])

    def pscale(self) -> np.ndarray:
        """Normalising units of the parameters: g for nabla, W for eps, rad."""
        return np.concatenate([[self.site.gravity] * 3, [EARTH_RATE] * 3, [1.0] * (3 * self.M)])

    def normalised_jacobian(self, th) -> np.ndarray:
        """d(equations)/d(parameters) in units of g and W (noise-free conditioning)."""
        g = self.site.gravity
        pscale = self.pscale()

        def eqs(x):
            out = self.predict(x * pscale)
            return np.concatenate([(out["accel"] / g).ravel(), (out["gyro"] / EARTH_RATE).ravel()])

        x0 = th / pscale
        J = np.empty((6 * self.M, self.p))
        for j in range(self.p):
            d = np.zeros(self.p)
            d[j] = 1e-6
            J[:, j] = (eqs(x0 + d) - eqs(x0 - d)) / 2e-6
        return J


def condition(J: np.ndarray) -> tuple[float, np.ndarray]:
    """Condition number of J and the right singular vectors of its weak directions
    (singular value below largest / COND_MAX), one per column."""
    _, s, vt = np.linalg.svd(J, full_matrices=True)
    s = np.concatenate([s, np.zeros(vt.shape[0] - len(s))])
    cond = float(s[0] / s[-1]) if s[-1] > 0 else float("inf")
    return cond, vt[s < s[0] / COND_MAX].T


def fit_align_static(rec: Recording) -> CalibrationResult:
    """nabla, eps and the attitudes of every static position from the static
    means alone (no turn needed; docs/align.md, "Static-only alignment")."""
    site = rec.site
    if rec.layout.redundant:
        raise InputError("this is a redundant-unit recording: use `calib fit rimu`")
    if rec.gyro is None:
        raise EstimationError("the recording has no gyro data; static alignment needs both "
                              "sensors")
    if rec.in_counts("accel") or rec.in_counts("gyro"):
        raise EstimationError("alignment needs data in SI units (m/s^2, rad/s), not raw "
                              "counts: apply a scale calibration first")
    segs = rec.static_segments()
    if len(segs) < 2:
        raise EstimationError(f"static alignment needs two static positions; the recording "
                              f"has {len(segs)}")
    inp = _Inputs(segs, *static_means(rec, segs))
    usable, why = earth_rate_usable(inp)
    if not usable:
        raise EstimationError(f"{why}; the static-only alignment needs the earth rate at both "
                              "positions (a navigation-grade unit)")
    C0 = [_triad(inp.f[k], inp.w[k], site) for k in range(len(segs))]
    prob = _Problem(inp, C0, site)
    th = np.zeros(prob.p)
    for _ in range(2):
        # weak directions at the current point are held where they are (the
        # fit runs in the well-conditioned complement), so a degenerate
        # geometry cannot send the solver wandering along its null space
        cond, weak = condition(prob.normalised_jacobian(th))
        th, cov, unobs, fit = _fit_complement(prob, th, weak)
        cond_after, weak_after = condition(prob.normalised_jacobian(th))
        if weak_after.shape[1] <= weak.shape[1]:
            break
    cond = max(cond, cond_after)
    C_all = prob.attitudes(th)
    att, sig_att, bad_att = [], [], []
    for k, C in enumerate(C_all):
        sl = slice(6 + 3 * k, 9 + 3 * k)
        e, _, cov_e, bad = euler_cov(C, np.nan_to_num(cov[sl, sl]), unobs[sl])
        att.append(e)
        sig_att.append(np.sqrt(np.abs(np.diag(cov_e))))
        bad_att.append(bad)
    # covariance over [nabla, eps, attitude_1] (9 x 9), through the Euler Jacobian
    _, J1, _, _ = euler_cov(C_all[0], np.zeros((3, 3)), np.zeros(3, bool))
    T = np.zeros((9, prob.p))
    T[0:6, 0:6] = np.eye(6)
    T[6:9, 6:9] = J1
    main_unobs = np.concatenate([unobs[0:6], bad_att[0]])
    obs = ~unobs
    full = np.full((9, 9), np.nan)
    fo = T[:, obs] @ cov[np.ix_(obs, obs)] @ T[:, obs].T
    keep = ~main_unobs
    full[np.ix_(keep, keep)] = fo[np.ix_(keep, keep)]
    sig = np.where(main_unobs, np.nan, np.sqrt(np.abs(np.diag(full))))
    order = [(k, i) for k in KEYS for i in range(3)]
    names = [f"{k}[{i}]" for (k, i), u in zip(order, main_unobs, strict=True) if u]
    if len(names) == 9:
        raise EstimationError(
            f"nothing is observable from these two static positions (condition number "
            f"{cond:.3g} above {COND_MAX:.0e}): {degeneracy(C_all, site)}")
    att2_unobs = [f"attitude_2[{i}]" for i in range(3) if bad_att[1][i]]
    out = prob.predict(th)
    ra, rw = inp.f - out["accel"], inp.w - out["gyro"]
    rel = (C_all[0].inv() * C_all[1]).as_rotvec()
    ang = float(np.linalg.norm(rel))
    stats = {
        "method": "static",
        "condition_number": cond, "condition_max": COND_MAX,
        "degeneracy": degeneracy(C_all, site) if cond > COND_MAX else None,
        "rotation_axis_body": (rel / ang if ang > 0 else rel).tolist(), "rotation_angle": ang,
        "attitude_2": att[1].tolist(),
        "attitude_2_sigma": [None if b else float(s) for s, b in zip(sig_att[1], bad_att[1],
                                                                      strict=True)],
        "attitudes_all": [a.tolist() for a in att],
        "attitudes_all_sigma": [[None if b else float(s) for s, b in zip(sa, ba, strict=True)]
                                for sa, ba in zip(sig_att, bad_att, strict=True)],
        "n_positions": len(inp.f), "earth_rate_used": True, "grade_check": why,
        "accel_residual_rms": float(np.sqrt(np.mean(ra**2))),
        "gyro_residual_rms": float(np.sqrt(np.mean(rw**2))),
        "accel_noise_sigma": inp.sig_a.tolist(), "gyro_noise_sigma": inp.sig_w.tolist(),
        "chi2_dof": fit.chi2_dof if fit.dof > 0 else None,
        **g_error_stats(inp.f, th[0:3], site.gravity),
        "unobservable": names + att2_unobs,
    }
    return CalibrationResult(
        method="align", params={"accel_bias": th[0:3].copy(), "gyro_bias": th[3:6].copy(),
                                "attitude": np.array(att[0], float)},
        sigma={"accel_bias": sig[0:3], "gyro_bias": sig[3:6], "attitude": sig[6:9]},
        units=dict(UNITS), covariance=full, cov_order=order, stats=stats,
        residuals={"accel_segment": ra, "gyro_segment": rw},
        tables={"segment_labels": [s.label for s in inp.segments]},
        model=[{"name": "bias", "sensor": "accel"}, {"name": "bias", "sensor": "gyro"}],
        raw_units=dict(rec.units), layout=rec.layout, serial=rec.serial)


WEAK_WEIGHT = 1e-3  # a parameter taking part in a weak direction by more than this is unobservable


def _fit_complement(prob: _Problem, th0, weak):
    """Gauss-Newton on the twelve (6M) equations with the parameters moving
    only across the weak directions (columns of weak, normalised units).
    Returns theta, its covariance (NaN for unobservable entries), the
    unobservable mask and the lsq fit."""
    pscale = prob.pscale()
    nw = weak.shape[1]
    if nw:
        q, _ = np.linalg.qr(np.hstack([weak, np.eye(prob.p)]))
        Q = q[:, nw:prob.p]
    else:
        Q = np.eye(prob.p)
    P = pscale[:, None] * Q  # theta = th0 + P y

    def res(y):
        return prob.residual(th0 + P @ y)

    fit = lsq.fit(res, np.zeros(Q.shape[1]), np.full(Q.shape[1], 1e-4),
                  what="static alignment fit")
    th = th0 + P @ fit.theta
    cov = P @ np.nan_to_num(fit.cov) @ P.T
    unobs = np.zeros(prob.p, bool)
    if nw:
        unobs |= np.sqrt((weak**2).sum(axis=1)) > WEAK_WEIGHT
    if fit.unobservable.any():
        unobs |= np.abs(P[:, fit.unobservable] / pscale[:, None]).max(axis=1) > WEAK_WEIGHT
    cov[unobs, :] = np.nan
    cov[:, unobs] = np.nan
    return th, cov, unobs, fit


def degeneracy(C_all, site, tol_deg: float = 5.0) -> str:
    """A sentence naming what makes the first two positions degenerate."""
    rv = (C_all[0].inv() * C_all[1]).as_rotvec()
    ang = float(np.linalg.norm(rv))
    if np.degrees(ang) < tol_deg:
        return (f"the positions are only {np.degrees(ang):.1f} deg apart: turn the unit "
                "60-180 deg")
    a_n = C_all[0].apply(rv / ang)
    up = np.degrees(np.arccos(min(abs(a_n[2]), 1.0)))
    polar = site.earth_rate_enu / EARTH_RATE
    pol = np.degrees(np.arccos(min(abs(a_n @ polar), 1.0)))
    if up < tol_deg:
        return (f"the turn axis is {up:.1f} deg from the vertical: gravity is the same in both "
                "positions, so the norm conditions coincide; tilt the turn axis, or record "
                "the turn (--method two-position)")
    if pol < tol_deg:
        return (f"the turn axis is {pol:.1f} deg from the earth's axis: the earth rate is the "
                "same in both positions; turn about another axis")
    return "the two gravity or earth-rate directions are nearly the same in body axes"
