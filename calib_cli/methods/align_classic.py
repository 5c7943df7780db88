"""Classic multi-position alignment: the baseline of docs/align.md.

The unit turns about its own z axis, held near the vertical by a servo
table, by known steps (180 deg: two positions; 90 deg: four). With
C_k = C_1 Rz(psi_k), the horizontal readings are
f_k,xy = R2(psi_k)^T v_xy + b_xy and w_k,xy = R2(psi_k)^T u_xy + eps_xy
(v = C_1^T g_n, u = C_1^T W_n in body axes of position 1): linear least
squares gives the horizontal biases (for 180 deg simply the average of the two
readings). The z axis stays (near) vertical, so its readings do not change:
b_z = mean f_z - sqrt(g^2 - |v_xy|^2) (|f| = g) and
eps_z = mean w_z - u_z with u_z from the angle between gravity and earth
rate, u . v = g W sin(lat). C_1 then follows from v and u (TRIAD).
Sigma: the noise of the segment means propagated through these formulas.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from calib_cli.data import CalibrationResult, Recording
from calib_cli.errors import EstimationError
from calib_cli.methods.align import KEYS, UNITS, collect, g_error_stats, integrate_turns, tilt_only
from calib_cli.model.earth import EARTH_RATE
from calib_cli.model.frames import rotation_to_attitude

AXIS_TOL = 3.0  # deg: the turns must be about body z to this


def _r2(psi: float) -> np.ndarray:
    c, s = np.cos(psi), np.sin(psi)
    return np.array([[c, -s], [s, c]])


def classic_solve(f: np.ndarray, w: np.ndarray, psi: np.ndarray, site) -> np.ndarray:
    """[b (3), eps (3), roll, pitch, yaw] from the means f, w (M, 3) at yaw steps psi (M,)."""
    g, W, lat = site.gravity, EARTH_RATE, site.latitude
    H = np.vstack([np.hstack([_r2(p).T, np.eye(2)]) for p in psi])
    sol_f = np.linalg.lstsq(H, f[:, :2].ravel(), rcond=None)[0]
    sol_w = np.linalg.lstsq(H, w[:, :2].ravel(), rcond=None)[0]
    v_xy, b_xy = sol_f[:2], sol_f[2:]
    u_xy, e_xy = sol_w[:2], sol_w[2:]
    sgn = np.sign(np.mean(f[:, 2])) or 1.0
    v_z = sgn * np.sqrt(max(g * g - v_xy @ v_xy, 0.0))
    b_z = np.mean(f[:, 2]) - v_z
    u_z = (g * W * np.sin(lat) - u_xy @ v_xy) / v_z
    e_z = np.mean(w[:, 2]) - u_z
    v = np.array([*v_xy, v_z])
    u = np.array([*u_xy, u_z])
    C1, _ = Rotation.align_vectors([site.specific_force_enu / g, site.earth_rate_enu / W],
                                   [v / np.linalg.norm(v), u / np.linalg.norm(u)],
                                   weights=[1e6, 1.0])
    return np.concatenate([b_xy, [b_z], e_xy, [e_z], rotation_to_attitude(C1)])


def fit_classic(rec: Recording, rotation: str = "auto") -> CalibrationResult:
    """The classic 2-position (180 deg) or 4-position (90 deg) alignment: turns
    about body z (near vertical) by known angles; any number >= 2 of positions."""
    rot = "plan" if rotation == "auto" and any(s.kind == "turn" for s in rec.segments) else rotation
    inp = collect(rec, rot)
    site = rec.site
    integrate_turns(inp, tilt_only(inp.f[0], site), 0.5 * (inp.w[0] + inp.w[1]), site)
    psi = [0.0]
    for gp in inp.gaps:
        rv = gp.dR.as_rotvec()
        ang = np.linalg.norm(rv)
        if ang < 1e-9 or np.degrees(np.arccos(min(abs(rv[2]) / ang, 1.0))) > AXIS_TOL:
            raise EstimationError(
                "the classic method needs turns about the body z axis (held vertical by a "
                "table); this recording turns about "
                f"{np.round(rv / max(ang, 1e-12), 3).tolist()}: use --method two-position")
        psi.append(psi[-1] + np.sign(rv[2]) * ang)
    psi = np.array(psi)
    if np.ptp(np.cos(psi)) < 0.5 and np.ptp(np.sin(psi)) < 0.5:
        raise EstimationError("the classic method needs yaw steps that separate the bias from "
                              "the earth's vectors: 180 deg (two positions) or 90 deg steps")
    if abs(np.mean(inp.f[:, 2])) < 0.9 * site.gravity:
        raise EstimationError("the classic method needs body z near the vertical "
                              f"(mean f_z = {np.mean(inp.f[:, 2]):.3f} m/s^2)")
    x = classic_solve(inp.f, inp.w, psi, site)
    # covariance: the noise of the means propagated through the formulas
    M = len(inp.f)
    var_in = np.concatenate([np.tile(inp.sig_a**2, (M, 1)) / inp.n[:, None],
                             np.tile(inp.sig_w**2, (M, 1)) / inp.n[:, None]], axis=1)
    J = np.zeros((9, M * 6))
    for k in range(M):
        for j in range(6):
            h = np.sqrt(var_in[k, j]) * 1e-2 or 1e-12
            f2, w2 = inp.f.copy(), inp.w.copy()
            if j < 3:
                f2[k, j] += h
            else:
                w2[k, j - 3] += h
            d = classic_solve(f2, w2, psi, site) - x
            d[6:] = (d[6:] + np.pi) % (2 * np.pi) - np.pi
            J[:, k * 6 + j] = d / h
    cov = J @ np.diag(var_in.ravel()) @ J.T
    sig = np.sqrt(np.diag(cov))
    steps = np.degrees(np.diff(psi))
    stats = {"method": f"classic-{M}", "yaw_steps_deg": steps.tolist(), "n_positions": M,
             "rotation_axis_body": [0.0, 0.0, 1.0], "rotation_angle": float(psi[1]),
             "earth_rate_used": True, "unobservable": [],
             "accel_noise_sigma": inp.sig_a.tolist(), "gyro_noise_sigma": inp.sig_w.tolist(),
             "accel_residual_rms": None, "gyro_residual_rms": None,
             **g_error_stats(inp.f, x[0:3], site.gravity)}
    return CalibrationResult(
        method="align-classic", params={"accel_bias": x[0:3], "gyro_bias": x[3:6],
                                        "attitude": x[6:9]},
        sigma={"accel_bias": sig[0:3], "gyro_bias": sig[3:6], "attitude": sig[6:9]},
        units=dict(UNITS), covariance=cov, cov_order=[(k, i) for k in KEYS for i in range(3)],
        stats=stats, tables={"segment_labels": [s.label for s in inp.segments]},
        model=[{"name": "bias", "sensor": "accel"}, {"name": "bias", "sensor": "gyro"}],
        raw_units=dict(rec.units), layout=rec.layout, serial=rec.serial)
