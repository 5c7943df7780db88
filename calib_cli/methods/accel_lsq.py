"""Static multi-position accelerometer calibration.

vector: known attitudes (>= 4 positions), A_k = b + K f_k over the segment
    means, generalised least squares with each mean's covariance (white
    sample noise / N_k, plus the fixture's attitude error where the plan gives
    attitude_sigma_deg). Linear, so one step; done through the generic
    least-squares engine for its covariance and observability checks.
scalar: unknown attitudes (>= 9 positions), |K^-1 (A_k - b)| = g with K lower
    triangular (the instrument frame fixed by the accelerometers), started
    from an algebraic ellipsoid fit so it converges on SI or raw-count data.

Both inflate the covariance by chi2/dof only when the residual scatter is
significantly (p < 0.001) larger than the noise explains, and say so in
stats.sigma_inflation.
"""

from __future__ import annotations

import numpy as np

from calib_cli.data import CalibrationResult, Recording
from calib_cli.errors import EstimationError, InputError
from calib_cli.methods import lsq
from calib_cli.methods.result import build_result
from calib_cli.methods.segstats import StaticStats, static_stats
from calib_cli.methods.static_detect import too_few_hint
from calib_cli.model.correction import correct
from calib_cli.model.effects import Bias, Layout, ScaleMisalignment
from calib_cli.model.frames import attitude_to_rotation, skew
from calib_cli.model.imu_model import ImuModel, Packing
from calib_cli.model.kinematics import from_attitude

MIN_VECTOR = 4
MIN_SCALAR = 9


def accel_model(structure: str) -> ImuModel:
    return ImuModel((Bias("accel"), ScaleMisalignment("accel", structure)), Layout())


def _unit_scale(st: StaticStats, g: float) -> float:
    """Size of one m/s^2 in the data's units (1 for SI, ~400 for raw counts)."""
    spread = np.ptp(st.means, axis=0).max() / 2.0
    return max(spread / g, 1e-12) if spread > 0 else 1.0


def _scales(packing: Packing, unit: float) -> np.ndarray:
    out = []
    for spec, m in zip(packing.specs, packing.masks):
        out.append(np.full(int(m.sum()), spec.typical * unit))
    return np.concatenate(out)


def g_figures(before, after, g: float) -> dict:
    """Avrutov et al.'s two figures of merit of an accelerometer triad, from
    |f| per static position (m/s^2) raw (``before``, None for counts) and
    corrected (``after``): the standard deviation of |f| over the positions
    (``g_norm_std_*``, population std, ddof 0) and the offset of its mean
    from the reference g (``g_mean_error_*`` = |mean |f| - g|). They split
    the RMS: g_error_rms^2 = g_norm_std^2 + g_mean_error^2."""
    out = {}
    for tag, v in (("before", before), ("after", after)):
        if v is None:
            out[f"g_norm_std_{tag}"] = out[f"g_mean_error_{tag}"] = None
        else:
            v = np.asarray(v, float)
            out[f"g_norm_std_{tag}"] = float(np.std(v))
            out[f"g_mean_error_{tag}"] = float(abs(np.mean(v) - g))
    return out


def _g_stats(model, params, st: StaticStats, g: float, counts: bool):
    """|g| per position before/after correction, and the noise floor of the
    corrected |g| (what the sample noise and averaging time allow)."""
    f = correct(model, params, "accel", st.means)
    after = np.linalg.norm(f, axis=1)
    before = None if counts else np.linalg.norm(st.means, axis=1)
    Kinv = np.linalg.inv(params["accel_K"])
    u = f / after[:, None]
    cov = st.mean_cov()
    var = np.einsum("ki,ij,kjl,ml,km->k", u, Kinv, cov, Kinv, u)
    stats = {
        "g_reference": g,
        "g_error_rms_before": None if before is None else float(np.sqrt(np.mean((before - g) ** 2))),
        "g_error_rms_after": float(np.sqrt(np.mean((after - g) ** 2))),
        **g_figures(before, after, g),
        "g_error_floor": float(np.sqrt(np.mean(var))),
        "n_positions": int(len(st.means)),
    }
    table = np.column_stack([st.counts, np.full(len(after), np.nan) if before is None else before,
                             after, after - g, np.sqrt(var)])
    return stats, table


def _finish(method, model, packing, fit, base, rec, st, resid, extra_stats) -> CalibrationResult:
    fit, inflation = fit.inflated()
    params = packing.unpack(fit.theta, base)
    counts = rec.in_counts("accel")
    gst, table = _g_stats(model, params, st, rec.site.gravity, counts)
    stats = {"method": method, **gst, **extra_stats,
             "accel_residual_rms": float(np.sqrt(np.mean(resid**2))),
             "accel_noise_sigma": st.sigma.tolist(),
             "chi2_dof": fit.chi2_dof, "sigma_inflation": inflation}
    return build_result(
        method, model, packing, fit, base, rec.units, stats, serial=rec.serial,
        residuals={"accel_segment": resid},
        tables={"g_table": table, "g_table_columns": ["samples", "g_before", "g_after",
                                                      "g_error_after", "g_sigma_after"],
                "segment_labels": st.labels})


# ---------------------------------------------------------------------------
# vector method


def _with_noise(st: StaticStats, noise) -> StaticStats:
    """The segment statistics with a stated per-sample noise (experiment design,
    design.py) instead of the one measured in the recording."""
    if noise is None:
        return st
    from dataclasses import replace

    return replace(st, sigma=np.broadcast_to(np.asarray(noise, float), st.sigma.shape).copy())


def fit_vector(rec: Recording, segments=None, screen: bool = True, *, noise=None,
               strict: bool = True) -> CalibrationResult:
    """noise: per-sample accel sigma to weight with instead of the measured one;
    strict=False reports unobservable entries instead of failing (plan check).
    ``segments``: a subset of the static segments (the gross-error screen's
    leave-one-out refits); ``screen``: run that screen (methods/gross.py)."""
    st = _with_noise(static_stats(rec, "accel", segments), noise)
    m = len(st.segments)
    missing = [s.label for s in st.segments if s.attitude is None]
    if missing:
        raise EstimationError(f"the vector method needs known attitudes; segments without "
                              f"attitude_deg: {', '.join(missing[:5])}"
                              f"{' ...' if len(missing) > 5 else ''} (use --method scalar)")
    if m < MIN_VECTOR:
        raise EstimationError(f"the vector method needs >= {MIN_VECTOR} static positions; "
                              f"the recording has {m}{too_few_hint(rec, MIN_VECTOR)}")
    g = rec.site.gravity
    rots = attitude_to_rotation(np.array([s.attitude for s in st.segments]))
    kin = from_attitude(np.zeros(m), rots, rec.site)
    model = accel_model("full")
    packing = Packing.for_model(model)
    base = model.neutral_params()
    unit = _unit_scale(st, g)

    # start: ordinary least squares per axis, H = [1, f]
    H = np.column_stack([np.ones(m), kin.f])
    coef = np.linalg.lstsq(H, st.means, rcond=None)[0]
    start = dict(base, accel_bias=coef[0], accel_K=coef[1:].T)
    theta0 = packing.pack(start)

    sig_att = np.array([s.attitude_sigma or 0.0 for s in st.segments])

    def whiteners(K):
        cov = st.mean_cov().copy()
        for k in range(m):
            if sig_att[k] > 0:
                # a small attitude error dtheta (ENU) moves f_k by R^T [g x] dtheta
                J = K @ rots[k].inv().as_matrix() @ skew([0, 0, g])
                cov[k] += sig_att[k] ** 2 * J @ J.T
        return np.linalg.inv(np.linalg.cholesky(cov))

    def residual_fn(W):
        def fn(theta):
            p = packing.unpack(theta, base)
            r = st.means - model.predict(p, kin, sensors=("accel",))["accel"]
            return np.einsum("kij,kj->ki", W, r).ravel()
        return fn

    W = whiteners(start["accel_K"])
    fit = lsq.fit(residual_fn(W), theta0, _scales(packing, unit), what="vector fit")
    if sig_att.any():  # the attitude term depends on K: refit once with the estimate
        W = whiteners(packing.unpack(fit.theta, base)["accel_K"])
        fit = lsq.fit(residual_fn(W), fit.theta, _scales(packing, unit), what="vector fit")
    if fit.unobservable.any() and strict:
        raise EstimationError(
            f"the {m} positions do not determine bias and K: the gravity directions must "
            f"span 3-D (at least 4 positions, e.g. +x, +y, +z up and one more, not all in "
            f"one plane)")
    p = packing.unpack(fit.theta, base)
    resid = st.means - model.predict(p, kin, sensors=("accel",))["accel"]
    if screen and strict:
        _screen_vector(rec, st, kin, np.linalg.norm(np.einsum("kij,kj->ki", W, resid), axis=1),
                       np.linalg.norm(resid, axis=1))
    return _finish("vector", model, packing, fit, base, rec, st, resid,
                   {"attitude_sigma_used": bool(sig_att.any())})


def _screen_vector(rec, st, kin, z, rnorm) -> None:
    """Gross-error screen of the vector fit (methods/gross.py): leave-one-out
    refits where at least one residual degree of freedom remains (12
    unknowns, 3 equations per position: >= 5 positions after leaving one out)."""
    from calib_cli.methods import gross

    segs = list(st.segments)
    unit = _unit_scale(st, rec.site.gravity)  # 1 for SI data, counts per m/s^2 otherwise
    big_thr = gross.BIG_G * rec.site.gravity * unit

    def without(k):
        rest = segs[:k] + segs[k + 1:]
        if 3 * len(rest) <= 12:
            return None
        st2 = static_stats(rec, "accel", rest)
        rots = attitude_to_rotation(np.array([s.attitude for s in rest]))
        kin2 = from_attitude(np.zeros(len(rest)), rots, rec.site)
        try:
            r2 = fit_vector(rec, rest, screen=False)
        except EstimationError:
            return None
        model = accel_model("full")
        resid = st2.means - model.predict(r2.params, kin2, sensors=("accel",))["accel"]
        L = np.linalg.cholesky(st2.mean_cov())
        zr = np.linalg.norm(np.linalg.solve(L, resid[..., None])[..., 0], axis=1)
        return zr, np.linalg.norm(resid, axis=1) > big_thr

    def describe(k):
        a, f = st.means[k], kin.f[k]
        c = float(np.dot(a, f) / (np.linalg.norm(a) * np.linalg.norm(f) or 1.0))
        return (f"the gravity direction it measured is {np.degrees(np.arccos(np.clip(c, -1, 1))):.0f}"
                " deg from the one its attitude_deg states")

    gross.screen(z, rnorm > big_thr, st.labels, without, "position", describe)


# ---------------------------------------------------------------------------
# scalar method


def ellipsoid_start(means: np.ndarray, g: float) -> tuple[np.ndarray, np.ndarray]:
    """Bias and lower-triangular K from an algebraic fit of the quadric that
    the static means lie on: (A - b)^T (K K^T)^-1 (A - b) = g^2.

    Works in centred, scaled coordinates (raw counts as well as SI). Falls
    back to an axis-aligned ellipsoid, then a sphere, when the general fit
    is not an ellipsoid (too few or badly spread positions).
    """
    mu = means.mean(axis=0)
    s = np.abs(means - mu).max() or 1.0
    X = (means - mu) / s
    x, y, z = X.T
    one = np.ones(len(X))
    designs = [
        ("full", np.column_stack([x * x, y * y, z * z, 2 * x * y, 2 * x * z, 2 * y * z, x, y, z, one])),
        ("axis", np.column_stack([x * x, y * y, z * z, x, y, z, one])),
        ("sphere", np.column_stack([x * x + y * y + z * z, x, y, z, one])),
    ]
    for kind, D in designs:
        if len(X) < D.shape[1] - 1:
            continue
        v = np.linalg.svd(D, full_matrices=False)[2][-1]
        if kind == "full":
            Q = np.array([[v[0], v[3], v[4]], [v[3], v[1], v[5]], [v[4], v[5], v[2]]])
            lin, c = v[6:9], v[9]
        elif kind == "axis":
            Q, lin, c = np.diag(v[:3]), v[3:6], v[6]
        else:
            Q, lin, c = np.eye(3) * v[0], v[1:4], v[4]
        if np.linalg.det(Q) == 0:
            continue
        if np.trace(Q) < 0:
            Q, lin, c = -Q, -lin, -c
        center = -0.5 * np.linalg.solve(Q, lin)
        rhs = center @ Q @ center - c
        if rhs <= 0:
            continue
        M = Q / rhs  # (X - center)^T M (X - center) = 1
        if np.any(np.linalg.eigvalsh(M) <= 0):
            continue
        S = np.linalg.inv(M) * (s / g) ** 2  # K K^T in data units per (m/s^2)
        return mu + s * center, np.linalg.cholesky(S)
    # last resort: centroid and mean radius
    r = np.linalg.norm(means - mu, axis=1).mean() or 1.0
    return mu, np.eye(3) * r / g


def fit_scalar(rec: Recording, start: str = "ellipsoid", *, noise=None,
               strict: bool = True) -> CalibrationResult:
    """start: "ellipsoid" (robust, default) or "identity" (b = 0, K = I).
    noise, strict: as for fit_vector."""
    st = _with_noise(static_stats(rec, "accel"), noise)
    m = len(st.segments)
    if m < MIN_SCALAR:
        raise EstimationError(f"the scalar method needs >= {MIN_SCALAR} static positions "
                              f"(9 unknowns); the recording has {m}"
                              f"{too_few_hint(rec, MIN_SCALAR)}")
    g = rec.site.gravity
    model = accel_model("lower")
    packing = Packing.for_model(model)
    base = model.neutral_params()
    if start == "identity":
        b0, K0 = np.zeros(3), np.eye(3)
    else:
        b0, K0 = ellipsoid_start(st.means, g)
    theta0 = packing.pack(dict(base, accel_bias=b0, accel_K=K0))
    unit = _unit_scale(st, g)
    cov = st.mean_cov()

    def sigmas(p):
        f = correct(model, p, "accel", st.means)
        u = f / np.linalg.norm(f, axis=1)[:, None]
        Kinv = np.linalg.inv(p["accel_K"])
        return np.sqrt(np.einsum("ki,ij,kjl,ml,km->k", u, Kinv, cov, Kinv, u))

    def residual_fn(sig):
        def fn(theta):
            p = packing.unpack(theta, base)
            f = correct(model, p, "accel", st.means)
            return (np.linalg.norm(f, axis=1) - g) / sig
        return fn

    scales = _scales(packing, unit)
    fit = None
    for _ in range(2):  # weights from the current estimate, then once more
        p = packing.unpack(theta0 if fit is None else fit.theta, base)
        if np.linalg.cond(p["accel_K"]) > 1e8:
            break
        fit = lsq.fit(residual_fn(sigmas(p)), theta0 if fit is None else fit.theta, scales,
                      what="scalar fit")
    if fit is None:
        raise EstimationError("scalar fit: the start is singular; check that the data holds "
                              "static positions in many orientations")
    p = packing.unpack(fit.theta, base)
    if np.any(np.diag(p["accel_K"]) <= 0):
        # |K^-1 (A - b)| cannot see the sign of a column of K: take the positive one
        D = np.diag(np.sign(np.diag(p["accel_K"])))
        theta = packing.pack(dict(p, accel_K=p["accel_K"] @ D))
        fit = lsq.fit(residual_fn(sigmas(packing.unpack(theta, base))), theta, scales,
                      what="scalar fit")
        p = packing.unpack(fit.theta, base)
    if fit.unobservable.any() and strict:
        raise EstimationError(
            f"the {m} positions do not determine bias and K by the scalar method: "
            "the unit must be placed in many orientations spread over the sphere "
            "(>= 9, with each axis pointing up and down)")
    f = correct(model, p, "accel", st.means)
    resid = np.linalg.norm(f, axis=1) - g
    return _finish("scalar", model, packing, fit, base, rec, st, resid, {"start": start})


def fit_accel(rec: Recording, method: str = "auto", *, noise=None,
              strict: bool = True) -> CalibrationResult:
    """The contract's ``fit accel``: auto = vector when every static segment
    has an attitude, else scalar."""
    if rec.layout.redundant:
        raise InputError("this is a redundant-unit recording: use `calib fit rimu`")
    statics = rec.static_segments()
    if not statics:
        raise EstimationError("the recording has no static segments to fit")
    if method == "auto":
        method = "vector" if all(s.attitude is not None for s in statics) else "scalar"
    if method == "vector":
        return fit_vector(rec, noise=noise, strict=strict)
    if method == "scalar":
        return fit_scalar(rec, noise=noise, strict=strict)
    raise ValueError(f"unknown method {method!r}")
