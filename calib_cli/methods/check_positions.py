"""Check positions (the rough-stand paper's verification, docs/turntable.md).

After a rotating-table calibration the paper puts the unit in static
positions with an instrument axis near the vertical and compares the
calibrated accelerometers with the local g. Here a check position is every
static segment of the record: the turntable fit uses only the rotating
segments, so these data are independent of the estimate. Per position, from
the calibration applied to the segment's mean (methods.apply, the one
correction):

- ``g_error``: |f| - g, f the corrected mean specific force (m/s^2). It does
  not depend on the attitude; with an axis near the vertical it is that
  accelerometer's own error (scale factor and bias) against g;
- ``earth_rate_up_error``: w . u - W sin(lat), u = f / |f| the vertical
  found by the accelerometers, w the corrected mean rate (rad/s): the
  gyros' error along the vertical against the earth rate's vertical
  component, independent of the heading;

each with its 1-sigma (the noise of the segment mean from the within-segment
scatter, plus the calibration's covariance propagated through the same
correction) and z = error / sigma. ``verdict`` is "pass" when every |z| is
below 3.3 (the 99.9 % two-sided bound of a normal), "fail" otherwise, "none"
without a static segment. Pure: arrays in, a dict out.
"""

from __future__ import annotations

import numpy as np

from calib_cli.data import CalibrationResult, Recording
from calib_cli.model.earth import EARTH_RATE

Z_LIMIT = 3.3
MIN_SAMPLES = 20
NEAR_VERTICAL_DEG = 10.0


def _quantities(cal: CalibrationResult, A: np.ndarray, W: np.ndarray, g: float, w_up: float):
    from calib_cli.methods.apply import apply_triad

    f, w = apply_triad(cal, A[None, :], W[None, :])
    f, w = f[0], w[0]
    u = f / np.linalg.norm(f)
    return np.array([np.linalg.norm(f) - g, w @ u - w_up]), f, w


def _calibration_jacobian(cal, A, W, g, w_up, q0) -> tuple[np.ndarray, np.ndarray]:
    """d(quantities)/d(the covariance's entries), central differences on the
    calibration's own correction; the covariance with undetermined entries at 0."""
    from dataclasses import replace

    order = list(cal.cov_order or [])
    cov = np.asarray(cal.covariance, float) if cal.covariance is not None else np.zeros((0, 0))
    if not order or cov.shape != (len(order), len(order)):
        return np.zeros((2, 0)), np.zeros((0, 0))
    J = np.zeros((2, len(order)))
    ok = np.isfinite(np.diag(cov)) & (np.diag(cov) > 0)
    for c, (key, flat) in enumerate(order):
        if not ok[c] or key not in cal.params:
            continue
        h = 1e-3 * float(np.sqrt(cov[c, c]))
        qs = []
        for sgn in (1.0, -1.0):
            v = np.array(cal.params[key], dtype=float, copy=True)
            v.reshape(-1)[int(flat)] += sgn * h
            qs.append(_quantities(replace(cal, params={**cal.params, key: v}), A, W, g, w_up)[0])
        J[:, c] = (qs[0] - qs[1]) / (2 * h)
    cov = np.where(np.outer(ok, ok), np.nan_to_num(cov), 0.0)
    return J, cov


def check_positions(rec: Recording, cal: CalibrationResult) -> dict:
    """The check of ``cal`` on the static segments of ``rec`` (module docstring)."""
    statics = [s for s in rec.segments if s.kind == "static" and s.stop - s.start >= MIN_SAMPLES]
    out = {"definition": "static segments (not used by the fit): |f| - g and w . f/|f| - "
                         "W sin(lat) of the calibrated means, with 1-sigma (noise of the mean "
                         "and the calibration's covariance); pass when every |z| < 3.3",
           "positions": [], "verdict": "none"}
    if not statics or rec.gyro is None:
        out["note"] = ("no static segment in the record: add static positions with an "
                       "instrument axis near the vertical (each axis up and down) to the plan")
        return out
    from calib_cli.methods.apply import apply_triad

    g = float(rec.site.gravity)
    w_up = float(np.asarray(rec.site.earth_rate_enu, float)[2])
    zs = []
    for seg in statics:
        A, W = rec.accel[seg.slice], rec.gyro[seg.slice]
        n = len(A)
        q, f, w = _quantities(cal, A.mean(axis=0), W.mean(axis=0), g, w_up)
        u = f / np.linalg.norm(f)
        fs, ws = apply_triad(cal, A, W)  # the corrected samples' scatter: noise of the mean
        var_f = fs.var(axis=0, ddof=1) / n
        var_w = ws.var(axis=0, ddof=1) / n
        var_noise = np.array([u**2 @ var_f, u**2 @ var_w])
        J, cov = _calibration_jacobian(cal, A.mean(axis=0), W.mean(axis=0), g, w_up, q)
        var_cal = np.einsum("ij,jk,ik->i", J, cov, J) if J.shape[1] else np.zeros(2)
        sig = np.sqrt(var_noise + np.clip(var_cal, 0, None))
        # a noise-free record with an exact calibration (experiment design): no z (a sigma
        # at the rounding level of the means, 1e-9 of g and of the earth rate, is none)
        has = sig > 1e-9 * np.array([g, EARTH_RATE])
        z = np.where(has, q / np.where(has, sig, 1.0), np.nan)
        k = int(np.argmax(np.abs(u)))
        tilt = float(np.degrees(np.arccos(min(abs(u[k]), 1.0))))
        zs.append(z)
        out["positions"].append({
            "label": seg.label, "duration_s": float(rec.time[seg.stop - 1] - rec.time[seg.start]),
            "vertical_axis": ("+" if u[k] > 0 else "-") + "xyz"[k],
            "axis_tilt_deg": tilt, "axis_near_vertical": tilt <= NEAR_VERTICAL_DEG,
            "g_error": float(q[0]), "g_error_sigma": float(sig[0]), "g_error_z": _opt(z[0]),
            "g_error_sigma_calibration": float(np.sqrt(max(var_cal[0], 0.0))),
            "earth_rate_up_error": float(q[1]), "earth_rate_up_error_sigma": float(sig[1]),
            "earth_rate_up_error_z": _opt(z[1]),
            "earth_rate_up_error_sigma_calibration": float(np.sqrt(max(var_cal[1], 0.0))),
        })
    Z = np.abs(np.array(zs))
    out["n"] = len(statics)
    if not np.all(np.isfinite(Z)):
        out.update({"verdict": "none", "note": "no noise and no calibration covariance: "
                                               "nothing to compare the errors with"})
        return out
    out.update({"g_error_z_rms": float(np.sqrt(np.mean(Z[:, 0] ** 2))),
                "earth_rate_up_error_z_rms": float(np.sqrt(np.mean(Z[:, 1] ** 2))),
                "max_abs_z": float(Z.max()),
                "verdict": "pass" if float(Z.max()) < Z_LIMIT else "fail"})
    return out


def _opt(x) -> float | None:
    return float(x) if np.isfinite(x) else None
