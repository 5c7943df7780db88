"""Redundant-IMU (RIMU) calibration: per sensor b, ks, dEl, dAz (CONTRACT.md section 2).

Each single-axis sensor i follows the catalogue's ``Bias`` + ``Installation``:
m_i = b_i + (1 + ks_i) S_i . x. Over the positions of the experiment (static,
or turning at a known table rate about a fixed axis) every sensor is fitted on
its own by weighted nonlinear least squares (methods/lsq.py) through
``ImuModel.predict``.

Segment means are exact. The model is linear in the input x, so the mean of
the predicted output over a segment equals the prediction at the segment's
mean input. The mean input is built from the same kinematics as the simulator
(``table_kinematics``): the table rate along the table axis, the earth rate
(whose horizontal part turns in body axes during the segment) and gravity
(constant in body axes when the table axis is vertical). So the residuals are
the measured segment means minus ``predict`` at the mean kinematics.

The sensing direction is fitted as a small tilt (u1, u2) of the nominal axis
in its tangent plane, S = normalise(S0 + u1 e_El + u2 e_Az). That is regular
everywhere, including the poles El0 = +-90 deg, where (dEl, dAz) is singular.
The tilt is then converted to the contract's (dEl, dAz), with its covariance
through the conversion's Jacobian. At a pole that conversion is the tilt's
size (dEl, with |El| <= 90 deg) and direction (Az). The sigma of dAz
grows as 1/tilt there.

What the positions do not excite (a rank-deficient Jacobian) is reported as
unobservable (NaN sigma, stats.unobservable) and kept at its nominal value.
"""

from __future__ import annotations

import numpy as np

from calib_cli.data import CalibrationResult, Recording, Segment
from calib_cli.errors import EstimationError
from calib_cli.methods import lsq
from calib_cli.methods.noise import pooled_within
from calib_cli.model import kinematics as kn
from calib_cli.model.effects import Bias, Installation, Layout
from calib_cli.model.frames import attitude_to_rotation
from calib_cli.model.imu_model import ImuModel, base_model
from calib_cli.model.truth import describe_effect

SENSORS = ("accel", "gyro")
NAMES = ("bias", "scale_error", "dEl", "dAz")
UNITS = {"accel": ("m/s^2", "-", "rad", "rad"), "gyro": ("rad/s", "-", "rad", "rad")}
TYPICAL = {"accel": (0.05, 5e-3, 0.01, 0.01), "gyro": (5e-3, 5e-3, 0.01, 0.01)}


def _wrap(a):
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


# ---------------------------------------------------------------------------
# geometry: tangent-plane tilt <-> (dEl, dAz)


def tangent_basis(el0: float, az0: float):
    """Nominal axis S0 and unit tangents e_El (towards +El), e_Az (towards +Az)."""
    s0 = np.array([np.cos(el0) * np.cos(az0), np.cos(el0) * np.sin(az0), np.sin(el0)])
    e_el = np.array([-np.sin(el0) * np.cos(az0), -np.sin(el0) * np.sin(az0), np.cos(el0)])
    e_az = np.array([-np.sin(az0), np.cos(az0), 0.0])
    return s0, e_el, e_az


def direction(u, el0, az0) -> np.ndarray:
    s0, e1, e2 = tangent_basis(el0, az0)
    v = s0 + u[0] * e1 + u[1] * e2
    return v / np.linalg.norm(v)


def angles_of(S, el0: float, az0: float) -> tuple[float, float]:
    """(dEl, dAz) with S = axes(El0 + dEl, Az0 - dAz), on the branch next to El0.

    Where cos El0 >= 0 (including the poles El0 = +-90 deg) the branch is
    |El| <= 90 deg, so at El0 = +90 deg dEl <= 0 and Az is the tilt's direction.
    """
    s = -1.0 if np.cos(el0) < -1e-6 else 1.0
    # atan2, not asin: exact for tiny tilts next to a pole
    el = np.arctan2(S[2], s * np.hypot(S[0], S[1]))
    az = np.arctan2(s * S[1], s * S[0])
    return float(_wrap(el - el0)), float(_wrap(az0 - az))


def _to_contract(theta, el0, az0) -> np.ndarray:
    """Fit vector (b, ks, u1, u2) -> contract vector (b, ks, dEl, dAz)."""
    d_el, d_az = angles_of(direction(theta[2:4], el0, az0), el0, az0)
    return np.array([theta[0], theta[1], d_el, d_az])


def _conversion_jacobian(theta, el0, az0) -> np.ndarray:
    J = np.eye(4)
    for k in (2, 3):
        h = 1e-7
        tp, tm = theta.copy(), theta.copy()
        tp[k] += h
        tm[k] -= h
        d = _to_contract(tp, el0, az0) - _to_contract(tm, el0, az0)
        d[2:] = _wrap(d[2:])
        J[:, k] = d / (2 * h)
        J[0:2, k] = 0.0
    return J


def sensor_model(sensor: str, el0: float, az0: float) -> ImuModel:
    """The catalogue's model of one single-axis sensor: Bias + Installation."""
    return ImuModel((Bias(sensor), Installation(sensor)),
                    Layout(1, np.array([el0]), np.array([az0])))


def sensor_params(sensor: str, contract_vec) -> dict:
    b, ks, d_el, d_az = contract_vec
    return {f"{sensor}_bias": np.array([b]), f"{sensor}_scale_error": np.array([ks]),
            f"{sensor}_dEl": np.array([d_el]), f"{sensor}_dAz": np.array([d_az])}


# ---------------------------------------------------------------------------
# positions: segment means and mean kinematics


def segment_kinematics(rec: Recording, seg: Segment) -> kn.Kinematics:
    """Per-sample true-input kinematics of a static or rotating segment with a
    known attitude (table angle from the recording where present, else the
    nominal table rate)."""
    t = rec.time[seg.slice]
    rot0 = attitude_to_rotation(seg.attitude)
    if seg.kind == "static":
        from scipy.spatial.transform import Rotation

        rot = Rotation.from_quat(np.tile(rot0.as_quat(), (len(t), 1)))
        return kn.from_attitude(t, rot, rec.site)
    angle = None if rec.table_angle is None else rec.table_angle[seg.slice]
    rate = None if rec.table_rate is None else rec.table_rate[seg.slice]
    if rate is None or not np.all(np.isfinite(rate)) or not np.any(rate):
        rate = np.full(len(t), seg.table_rate or 0.0)
    if angle is None or not np.all(np.isfinite(angle)):
        angle = np.concatenate([[0.0], np.cumsum(0.5 * (rate[1:] + rate[:-1]) * np.diff(t))])
    acc = np.gradient(rate, t) if len(t) > 2 else np.zeros(len(t))
    return kn.table_kinematics(t, seg.table_axis_enu, angle, rate, acc, rot0, rec.site)


def usable_segments(rec: Recording) -> tuple[list[Segment], list[str]]:
    """Static and rotating segments with a known attitude; the labels skipped."""
    use, skipped = [], []
    for s in rec.segments:
        ok = s.kind == "static" or (s.kind == "rotating" and s.table_axis_enu is not None)
        if ok and s.attitude is not None and s.n >= 2:
            use.append(s)
        else:
            skipped.append(s.label)
    return use, skipped


def position_means(rec: Recording, sensor: str, segs: list[Segment]):
    """Segment means (M, n), mean kinematics (M samples), counts (M,), and the
    pooled per-sample noise sigma (n,) of each channel: the scatter about the
    nominal model's time-varying prediction (the turning earth rate)."""
    data = rec.accel if sensor == "accel" else rec.gyro
    nominal = base_model(layout=rec.layout)
    means, f, w, resid = [], [], [], []
    for s in segs:
        kin = segment_kinematics(rec, s)
        y = data[s.slice]
        means.append(y.mean(axis=0))
        f.append(kin.f.mean(axis=0))
        w.append(kin.w.mean(axis=0))
        resid.append(y - nominal.predict({}, kin, sensors=(sensor,))[sensor])
    m = len(segs)
    kin = kn.Kinematics(np.zeros(m), np.array(f).reshape(m, 3), np.array(w).reshape(m, 3),
                        np.zeros((m, 3)))
    pooled = pooled_within(resid, data.shape[1])
    return np.array(means).reshape(m, -1), kin, pooled.counts, pooled.sigma


# ---------------------------------------------------------------------------
# one sensor


def fit_sensor(sensor: str, el0: float, az0: float, means, kin, sig_mean):
    """Fit (b, ks, dEl, dAz) of one sensor to its segment means.

    means, sig_mean: (M,) measured means and their 1-sigma; kin: mean
    kinematics (M samples). Returns (contract vector (4,), covariance (4, 4)
    with NaN for unobservable entries, unobservable mask (4,), residuals (M,),
    chi2, dof, inflation factor).
    """
    model = sensor_model(sensor, el0, az0)
    scales = np.array(TYPICAL[sensor])

    def predict(theta):
        p = sensor_params(sensor, _to_contract(theta, el0, az0))
        return model.predict(p, kin, sensors=(sensor,))[sensor][:, 0]

    # linear start: m = b + v . x, v = (1 + ks) S
    x = kin.f if sensor == "accel" else kin.w
    A = np.column_stack([np.ones(len(means)), x]) / sig_mean[:, None]
    coef, *_ = np.linalg.lstsq(A, means / sig_mean, rcond=None)
    theta0 = np.array([coef[0], 0.0, 0.0, 0.0])
    nv = np.linalg.norm(coef[1:])
    if len(means) >= 4 and np.linalg.matrix_rank(A) == 4 and nv > 0:
        s0, e1, e2 = tangent_basis(el0, az0)
        v = coef[1:] / nv
        if v @ s0 > 0.5:
            theta0 = np.array([coef[0], nv - 1.0, (v @ e1) / (v @ s0), (v @ e2) / (v @ s0)])

    def resid_full(theta):
        return (means - predict(theta)) / sig_mean

    # which parameters the positions determine: rank of the Jacobian at the start
    J0 = np.empty((len(means), 4))
    for k in range(4):
        h = 1e-6 * scales[k]
        tp, tm = theta0.copy(), theta0.copy()
        tp[k] += h
        tm[k] -= h
        J0[:, k] = (resid_full(tp) - resid_full(tm)) / (2 * h)
    # (zero rows keep J^T J and let the rank test see all 4 directions with < 4 positions)
    _, unobs = lsq.covariance(np.vstack([J0, np.zeros((4, 4))]), scales)
    free = ~unobs
    if not free.any():
        return (_to_contract(theta0, el0, az0), np.full((4, 4), np.nan), np.ones(4, bool),
                means - predict(theta0), 0.0, 0, 1.0)

    def resid(sub):
        th = theta0.copy()
        th[free] = sub
        return resid_full(th)

    fit = lsq.fit(resid, theta0[free], scales[free], what=f"{sensor} sensor fit")
    fit, inflation = fit.inflated()
    theta = theta0.copy()
    theta[free] = fit.theta
    cov_t = np.full((4, 4), np.nan)
    sub_unobs = fit.unobservable
    idx = np.flatnonzero(free)
    cov_t[np.ix_(idx, idx)] = fit.cov
    unobs_t = unobs.copy()
    unobs_t[idx[sub_unobs]] = True
    # to the contract's (b, ks, dEl, dAz)
    p = _to_contract(theta, el0, az0)
    Jc = _conversion_jacobian(theta, el0, az0)
    good = ~unobs_t
    cov = np.full((4, 4), np.nan)
    # an output entry is unobservable when it depends on an unobservable fit entry
    dep = np.abs(Jc[:, unobs_t]).sum(axis=1) > 1e-9 if unobs_t.any() else np.zeros(4, bool)
    out_ok = ~dep & np.all(np.isfinite(Jc), axis=1)
    if good.any():
        C = Jc[:, good] @ cov_t[np.ix_(good, good)] @ Jc[:, good].T
        cov[np.ix_(out_ok, out_ok)] = C[np.ix_(out_ok, out_ok)]
    r = means - predict(theta)
    return p, cov, ~out_ok, r, fit.chi2, fit.dof, inflation


# ---------------------------------------------------------------------------
# the whole unit


def fit_rimu(rec: Recording, *, noise: dict | None = None,
             strict: bool = True) -> CalibrationResult:
    """The contract's ``fit rimu``: every sensor's b, ks, dEl, dAz with covariance.
    noise: {"accel": sigma (n,), "gyro": sigma (n,)} per sample to weight with
    instead of the measured noise; strict=False returns even when no parameter
    is determined (both for experiment design, design.py)."""
    layout = rec.layout
    if not layout.redundant:
        raise EstimationError("this is not a redundant-unit recording (plan kind \"rimu\" "
                              "with a [rimu] geometry): use `calib fit accel`/`fit gyro`")
    if any(rec.in_counts(s) for s in SENSORS):
        raise EstimationError("the RIMU fit needs data in SI units (m/s^2, rad/s)")
    segs, skipped = usable_segments(rec)
    if not segs:
        raise EstimationError("no usable positions: the RIMU fit needs static or rotating "
                              "segments with a known attitude_deg")
    n = layout.n
    lay = Layout(n, layout.el0, layout.az0)
    sensors = [s for s in SENSORS if (rec.accel if s == "accel" else rec.gyro) is not None]
    params, sigma, units, cov_blocks, order = {}, {}, {}, [], []
    stats = {"method": "rimu", "n_sensors": n, "n_positions": len(segs),
             "positions": [s.label for s in segs], "skipped_segments": skipped,
             "sample_rate_hz": rec.sample_rate}
    residuals, unobservable = {}, []
    any_estimated = False
    for sensor in sensors:
        means, kin, counts, sig = position_means(rec, sensor, segs)
        if noise is not None:
            sig = np.broadcast_to(np.asarray(noise[sensor], float), sig.shape).copy()
        if not np.all(np.isfinite(sig)) or np.any(sig <= 0):
            # too few samples for a noise estimate: fall back to the catalogue's noise floor
            sig = np.where(np.isfinite(sig) & (sig > 0), sig, TYPICAL[sensor][0] * 1e-3)
        vals = np.zeros((4, n))
        sigs = np.zeros((4, n))
        res = np.zeros((len(segs), n))
        chi2, dof, infl = [], [], []
        for i in range(n):
            p, C, un, r, c2, d, f = fit_sensor(sensor, float(layout.el0[i]),
                                               float(layout.az0[i]), means[:, i], kin,
                                               sig[i] / np.sqrt(counts))
            vals[:, i] = p
            sigs[:, i] = np.where(un, np.nan, np.sqrt(np.abs(np.diag(C))))
            C = C.copy()
            C[un, :] = np.nan
            C[:, un] = np.nan
            cov_blocks.append((sensor, i, C))
            res[:, i] = r
            chi2.append(c2)
            dof.append(d)
            infl.append(f)
            any_estimated |= bool((~un).any())
            unobservable += [f"{sensor}_{NAMES[k]}[{i}]" for k in range(4) if un[k]]
        for k, name in enumerate(NAMES):
            key = f"{sensor}_{name}"
            params[key] = vals[k]
            sigma[key] = sigs[k]
            units[key] = UNITS[sensor][k]
        residuals[f"{sensor}_segment"] = res
        stats[f"{sensor}_residual_rms"] = float(np.sqrt(np.mean(res**2)))
        stats[f"{sensor}_noise_sigma"] = sig.tolist()
        stats[f"{sensor}_noise_density"] = (sig / np.sqrt(rec.sample_rate)).tolist()
        stats[f"{sensor}_chi2"] = chi2
        stats[f"{sensor}_dof"] = dof
        stats[f"{sensor}_sigma_inflation"] = infl
        blocks = np.array([C for s_, i_, C in cov_blocks if s_ == sensor])
        mag = rec.site.gravity if sensor == "accel" else float(
            np.max(np.linalg.norm(kin.w, axis=1)))
        tmp = {f"{sensor}_{nm}": vals[k] for k, nm in enumerate(NAMES)}
        stats[f"{sensor}_body_error_input"] = mag
        stats[f"{sensor}_body_error_predicted"] = predicted_body_error(
            tmp, lay, sensor, blocks, mag).tolist()
    if not any_estimated and strict:
        raise EstimationError(
            f"the {len(segs)} positions determine none of the sensors' parameters: the inputs "
            "must point in at least two directions per sensor (e.g. the six-position test, "
            "each body axis up and down)")
    # covariance in contract order: key by key, sensor by sensor (block diagonal)
    keys = [f"{s}_{nm}" for s in sensors for nm in NAMES]
    order = [(k, i) for k in keys for i in range(n)]
    pos = {ki: j for j, ki in enumerate(order)}
    cov = np.zeros((len(order), len(order)))
    for sensor, i, C in cov_blocks:
        idx = [pos[(f"{sensor}_{nm}", i)] for nm in NAMES]
        cov[np.ix_(idx, idx)] = C
    stats["unobservable"] = unobservable
    stats["sigma_inflation"] = float(max(max(stats.get(f"{s}_sigma_inflation", [1.0]))
                                         for s in sensors))
    model = base_model(layout=lay, gyro="gyro" in sensors)
    return CalibrationResult(
        method="rimu", params=params, sigma=sigma, units=units, covariance=cov,
        cov_order=order, stats=stats, residuals=residuals,
        tables={"segment_labels": [s.label for s in segs]},
        model=[describe_effect(e) for e in model.effects], raw_units=dict(rec.units),
        layout=lay, serial=rec.serial)


# ---------------------------------------------------------------------------
# applying a calibration


def measurement_matrix(cal_params: dict, layout: Layout, sensor: str) -> np.ndarray:
    """Calibrated sensing directions H (n, 3) from dEl, dAz."""
    return layout.axes(np.asarray(cal_params[f"{sensor}_dEl"], float),
                       np.asarray(cal_params[f"{sensor}_dAz"], float))


def corrected_outputs(cal_params: dict, sensor: str, m: np.ndarray) -> np.ndarray:
    """Single-axis inputs S_i . x = (m_i - b_i) / (1 + ks_i), (N, n)."""
    b = np.asarray(cal_params[f"{sensor}_bias"], float)
    ks = np.asarray(cal_params[f"{sensor}_scale_error"], float)
    return (np.asarray(m, float) - b) / (1.0 + ks)


def body_estimate(H: np.ndarray, c: np.ndarray, use=None) -> np.ndarray:
    """Least-squares body vector x = (H^T H)^-1 H^T c (N, 3), optionally over
    the sensors in the boolean mask ``use``."""
    if use is not None:
        H, c = H[use], c[:, use]
    return np.linalg.lstsq(H, np.asarray(c, float).T, rcond=None)[0].T


def apply_rimu(cal: CalibrationResult, accel: np.ndarray, gyro: np.ndarray | None):
    """Corrected single-axis outputs and body-frame estimates of a chunk:
    {"accel": (N, n), "accel_body": (N, 3), "gyro": ..., "gyro_body": ...}.
    Channels the calibration does not cover pass through (no body estimate)."""
    out = {"accel": accel, "gyro": gyro}
    for sensor, m in (("accel", accel), ("gyro", gyro)):
        if m is None or f"{sensor}_bias" not in cal.params:
            continue
        c = corrected_outputs(cal.params, sensor, m)
        out[sensor] = c
        out[f"{sensor}_body"] = body_estimate(measurement_matrix(cal.params, cal.layout, sensor), c)
    return out


def calibration_variance(params: dict, layout: Layout, sensor: str, x: np.ndarray,
                         cov: np.ndarray) -> np.ndarray:
    """(K, n) variance of each corrected output's calibration error at body
    inputs x (K, 3): J_i C_i J_i^T with J_i = d(b + (1+ks) S.x)/d(b, ks, dEl, dAz)."""
    d_el = np.asarray(params[f"{sensor}_dEl"], float)
    d_az = np.asarray(params[f"{sensor}_dAz"], float)
    ks = np.asarray(params[f"{sensor}_scale_error"], float)
    el = layout.el0 + d_el
    az = layout.az0 - d_az
    S = layout.axes(d_el, d_az)
    dS_el = np.stack([-np.sin(el) * np.cos(az), -np.sin(el) * np.sin(az), np.cos(el)], axis=1)
    dS_daz = np.stack([np.cos(el) * np.sin(az), -np.cos(el) * np.cos(az), np.zeros_like(el)],
                      axis=1)
    J = np.stack([np.ones((len(x), layout.n)), x @ S.T, (1 + ks) * (x @ dS_el.T),
                  (1 + ks) * (x @ dS_daz.T)], axis=2)  # (K, n, 4)
    return np.einsum("kia,iab,kib->ki", J, cov, J) / (1 + ks) ** 2


def predicted_body_error(params: dict, layout: Layout, sensor: str, cov: np.ndarray,
                         magnitude: float, k: int = 500) -> np.ndarray:
    """Expected RMS per body axis (3,) of the body-frame error that the
    calibration's uncertainty (cov: (n, 4, 4) per sensor) leaves, for inputs of
    the given magnitude over the sphere of directions (the covariance's
    prediction of ``body_error_rms``)."""
    d = fibonacci_sphere(k) * magnitude
    var = calibration_variance(params, layout, sensor, d, np.nan_to_num(cov))  # (k, n)
    Hp = np.linalg.pinv(measurement_matrix(params, layout, sensor))  # (3, n)
    return np.sqrt(np.mean(var @ (Hp.T ** 2), axis=0))


def fibonacci_sphere(k: int = 2000) -> np.ndarray:
    """k nearly uniform unit vectors (k, 3)."""
    i = np.arange(k) + 0.5
    z = 1 - 2 * i / k
    r = np.sqrt(1 - z**2)
    phi = np.pi * (1 + 5**0.5) * i
    return np.column_stack([r * np.cos(phi), r * np.sin(phi), z])


def body_error_rms(cal_params: dict, true_params: dict, layout: Layout, sensor: str,
                   magnitude: float, k: int = 2000) -> np.ndarray:
    """RMS per body axis (3,) of the error the calibration leaves in the
    body-frame estimate: noise-free outputs of the true model (catalogue
    ``predict``) for inputs of the given magnitude over the sphere of
    directions, corrected with the calibration, against the true input."""
    d = fibonacci_sphere(k) * magnitude
    model = ImuModel((Bias(sensor), Installation(sensor)), Layout(layout.n, layout.el0,
                                                                  layout.az0))
    zeros = np.zeros_like(d)
    kin = kn.Kinematics(np.zeros(len(d)), d if sensor == "accel" else zeros,
                        d if sensor == "gyro" else zeros, zeros)
    tp = {k_: v for k_, v in true_params.items() if k_.startswith(sensor)}
    m = model.predict(tp, kin, sensors=(sensor,))[sensor]
    c = corrected_outputs(cal_params, sensor, m)
    x = body_estimate(measurement_matrix(cal_params, layout, sensor), c)
    return np.sqrt(np.mean((x - d) ** 2, axis=0))
