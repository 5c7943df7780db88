"""Frames and attitudes (CONTRACT.md section 1).

Navigation frame ENU; attitude [roll, pitch, yaw] is R = Rz(yaw) Ry(pitch) Rx(roll),
mapping body vectors into ENU (v_enu = R v_body).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation


def attitude_to_rotation(rpy_rad) -> Rotation:
    """[roll, pitch, yaw] (rad) -> Rotation body->ENU. Accepts (3,) or (N, 3)."""
    rpy = np.asarray(rpy_rad, dtype=float)
    return Rotation.from_euler("ZYX", rpy[..., ::-1])


def rotation_to_attitude(rot: Rotation) -> np.ndarray:
    """Rotation body->ENU -> [roll, pitch, yaw] (rad). At pitch +-90 deg roll
    and yaw are not separable: yaw is set to 0 and roll takes their combination."""
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", UserWarning)  # gimbal lock: handled as documented
        return rot.as_euler("ZYX")[..., ::-1]


def axis_angle(axis, angle_rad) -> Rotation:
    """Right-hand rotation by angle (rad) about a unit axis; angle may be an array."""
    a = np.asarray(axis, dtype=float)
    a = a / np.linalg.norm(a)
    ang = np.asarray(angle_rad, dtype=float)
    return Rotation.from_rotvec(np.multiply.outer(ang, a))


def rotation_from_wxyz(q) -> Rotation:
    """Rotations of quaternions (..., 4) stored scalar first (w, x, y, z: PX4's and
    ArduPilot's logs, Hamilton convention); SciPy's ``Rotation`` takes them scalar last.
    The package's one conversion between the two orders (``rotation_to_wxyz`` back)."""
    return Rotation.from_quat(np.roll(np.asarray(q, dtype=float), -1, axis=-1))


def rotation_to_wxyz(rot: Rotation) -> np.ndarray:
    """Quaternions (..., 4), scalar first, of rotations (the inverse of
    ``rotation_from_wxyz``)."""
    return np.roll(rot.as_quat(), 1, axis=-1)


def skew(v) -> np.ndarray:
    """Cross-product matrices [v x] (..., 3, 3) of 3-vectors v (..., 3)."""
    v = np.asarray(v, dtype=float)
    if v.ndim == 1:  # one vector: a filter's per-step call, where the general path's overhead shows
        x, y, z = v
        return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])
    S = np.zeros(v.shape[:-1] + (3, 3))
    S[..., 0, 1], S[..., 0, 2], S[..., 1, 2] = -v[..., 2], v[..., 1], -v[..., 0]
    S[..., 1, 0], S[..., 2, 0], S[..., 2, 1] = v[..., 2], -v[..., 1], v[..., 0]
    return S


def attitude_from_static(f_mean, w_mean=None, earth_rate: float | None = None,
                         latitude: float | None = None) -> np.ndarray:
    """[roll, pitch, yaw] (rad) of a unit at rest from its mean specific force f_mean
    (3,) in body axes (it points up) and, where the gyros resolve the earth rate
    (``w_mean`` (3,) rad/s of a magnitude within 10 % of ``earth_rate``, its horizontal
    part at least half the earth rate's at ``latitude``), the heading from the horizontal
    part of the rate, which points north; else yaw 0."""
    u = np.asarray(f_mean, float) / np.linalg.norm(f_mean)
    n = None
    if w_mean is not None and earth_rate and latitude is not None:
        w = np.asarray(w_mean, float)
        wh = w - (w @ u) * u
        if (abs(np.linalg.norm(w) - earth_rate) < 0.1 * earth_rate
                and np.linalg.norm(wh) > 0.5 * earth_rate * abs(np.cos(latitude))):
            n = wh / np.linalg.norm(wh)
    if n is None:
        roll = np.arctan2(u[1], u[2])
        pitch = np.arctan2(-u[0], np.hypot(u[1], u[2]))
        return np.array([roll, pitch, 0.0])
    # the rows: the ENU axes in body axes (east = north x up), i.e. the body -> ENU matrix
    return rotation_to_attitude(Rotation.from_matrix(np.array([np.cross(n, u), n, u])))
