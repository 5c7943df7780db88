"""Strapdown integration of gyro rates: the rotation of the body between two
instants, relative to the local-level frame.

The inverse of ``kinematics.from_attitude``'s rate term: a gyro measures the
body rate against inertial space, w = w_rel + C(t)^T W_ie, where C(t) is the
body->ENU attitude; the local-level frame turns with the earth, so the
rotation of the unit on its bench is the integral of w_rel = w - C(t)^T W_ie.
At navigation grade the earth-rate term over a 10-20 s turn (~1e-3 rad) is far
larger than the errors sought, so it is removed here, sample by sample.

Convention: R_rel(t) maps body vectors at time t into body axes at the first
instant (C(t) = C0 R_rel(t)); R_rel(t + dt) = R_rel(t) Exp(w_rel dt) with the
trapezoid (mid-interval) rate over each sample interval.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial.transform import Rotation

from calib_cli.model.earth import Site
from calib_cli.model.frames import skew


def _qmul(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """Hamilton product of scalar-last quaternions (x, y, z, w)."""
    ax, ay, az, aw = a
    bx, by, bz, bw = b
    return np.array([aw * bx + ax * bw + ay * bz - az * by,
                     aw * by - ax * bz + ay * bw + az * bx,
                     aw * bz + ax * by - ay * bx + az * bw,
                     aw * bw - ax * bx - ay * by - az * bz])


def _qexp(v: np.ndarray) -> np.ndarray:
    """Quaternion of the rotation vector v (rad)."""
    a = float(np.sqrt(v @ v))
    if a < 1e-12:
        return np.array([0.5 * v[0], 0.5 * v[1], 0.5 * v[2], 1.0])
    s = np.sin(0.5 * a) / a
    return np.array([s * v[0], s * v[1], s * v[2], np.cos(0.5 * a)])


def _qmat(q: np.ndarray) -> np.ndarray:
    """Rotation matrix of a unit scalar-last quaternion."""
    x, y, z, w = q / np.sqrt(q @ q)
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


@dataclass(frozen=True)
class RelativeRotation:
    """Result of ``integrate_relative``.

    dR: rotation body(end) -> body(start). duration: s.
    S_bias (3, 3): d psi / d(rate bias): psi = -S_bias d_eps for a change of
        the gyro bias d_eps (rad/s) subtracted from the rates.
    S_K (3, 9): d psi / d(vec dG) for a gyro transfer error G = I + dG
        (row-major vec), rates corrected by G^-1: psi = -S_K vec(dG).
    noise_cov (3, 3): covariance of psi from white rate noise of per-sample
        standard deviation ``sigma`` (rad/s) per axis.
    Here psi (rad, start-body axes) is the first-order change of the rotation:
    dR' = Exp(psi) dR. A change alpha (rad, ENU) of the start attitude,
    C0' = Exp(alpha) C0, changes the removed earth rate and gives
    psi = -duration C0^T [W_ie x] alpha (see ``earth_sensitivity``).
    """

    dR: Rotation
    duration: float
    S_bias: np.ndarray
    S_K: np.ndarray
    noise_cov: np.ndarray

    def earth_sensitivity(self, C0: Rotation, site: Site) -> np.ndarray:
        """d psi / d alpha (3, 3) for a change alpha (ENU) of the start attitude."""
        return -self.duration * C0.inv().as_matrix() @ skew(site.earth_rate_enu)


def integrate_relative(t: np.ndarray, w: np.ndarray, C0: Rotation, site: Site,
                       sigma=None) -> RelativeRotation:
    """Integrate body rates w (N, 3, rad/s, against inertial space, already
    corrected for bias and scale) at times t (N,) from the first sample to the
    last, removing the earth rate seen from the turning body, with C0 the
    body->ENU attitude at t[0]. sigma: per-sample white rate noise (3,) for
    ``noise_cov`` (None: zero)."""
    t = np.asarray(t, dtype=float)
    w = np.asarray(w, dtype=float)
    n = len(t)
    W_n = site.earth_rate_enu
    C0m = C0.as_matrix()
    q = np.array([0.0, 0.0, 0.0, 1.0])
    R = np.empty((n, 3, 3))
    R[0] = np.eye(3)
    dts = np.diff(t)
    wmid = 0.5 * (w[1:] + w[:-1])
    for i in range(n - 1):
        Ri = R[i]
        # earth rate in body axes at mid-interval: a fixed vector seen from a body
        # turning at w moves by -w x e (second-order accurate step)
        e_body = (C0m @ Ri).T @ W_n
        e_body = e_body - 0.5 * np.cross(wmid[i] * dts[i], e_body)
        step = (wmid[i] - e_body) * dts[i]
        q = _qmul(q, _qexp(step))
        R[i + 1] = _qmat(q)
    dt = np.concatenate([dts, [0.0]])
    # psi = sum_i R_{i+1/2} delta_w_i dt_i (left perturbation in start-body axes;
    # the mid-interval attitude carries a rate change within the step to second order)
    Rn = 0.5 * (R[1:] + R[:-1])
    S_bias = np.einsum("nij,n->ij", Rn, dts)
    S_K = np.einsum("nar,nc->arc", Rn, wmid * dts[:, None]).reshape(3, 9)
    if sigma is None:
        noise = np.zeros((3, 3))
    else:
        s2 = np.asarray(sigma, dtype=float) ** 2 * np.ones(3)
        noise = np.einsum("nij,j,nkj,n->ik", R, s2, R, dt**2)
    return RelativeRotation(Rotation.from_quat(q), float(t[-1] - t[0]), S_bias, S_K, noise)
