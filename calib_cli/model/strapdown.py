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
        R[i + 1] = Ri @ exp_matrix(step)
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
    return RelativeRotation(Rotation.from_matrix(R[-1]), float(t[-1] - t[0]), S_bias, S_K, noise)


def exp_matrix(phi) -> np.ndarray:
    """Rotation matrix Exp([phi x]) (3, 3) of one rotation vector phi (3,), rad (Rodrigues;
    for one vector at a time, where SciPy's per-call overhead dominates a filter's time)."""
    phi = np.asarray(phi, dtype=float)
    a2 = float(phi @ phi)
    K = skew(phi)
    # [phi x]^2 = phi phi^T - |phi|^2 I
    if a2 < 1e-16:
        c0, c1, c2 = 1.0 - 0.5 * a2, 1.0, 0.5
    else:
        a = np.sqrt(a2)
        c0, c1, c2 = np.cos(a), np.sin(a) / a, (1.0 - np.cos(a)) / a2
    out = c1 * K + (c2 * phi)[:, None] * phi
    out[0, 0] += c0
    out[1, 1] += c0
    out[2, 2] += c0
    return out


def left_jacobian(phi: np.ndarray) -> np.ndarray:
    """SO(3)'s left Jacobian J_l(phi) (n, 3, 3) of rotation vectors phi (n, 3), rad:
    Exp(phi + d) = Exp(J_l(phi) d) Exp(phi) to first order in d, i.e. how a change of a
    step's rate moves the attitude at the step's end. J_l = I + a [phi x] + b [phi x]^2,
    a = (1 - cos t) / t^2, b = (t - sin t) / t^3, t = |phi| (series below 1e-3 rad)."""
    phi = np.asarray(phi, dtype=float)
    t2 = np.einsum("ni,ni->n", phi, phi)
    t = np.sqrt(t2)
    small = t < 1e-3
    ts = np.where(small, 1.0, t)
    a = np.where(small, 0.5 - t2 / 24.0, (1.0 - np.cos(ts)) / ts**2)
    b = np.where(small, 1.0 / 6.0 - t2 / 120.0, (ts - np.sin(ts)) / ts**3)
    # [phi x]^2 = phi phi^T - |phi|^2 I, without a batched matrix product
    J = b[:, None, None] * (phi[:, :, None] * phi[:, None, :]) + a[:, None, None] * skew(phi)
    J[:, (0, 1, 2), (0, 1, 2)] += (1.0 - b * t2)[:, None]
    return J


def log_matrix(M: np.ndarray) -> np.ndarray:
    """Rotation vector (3,) of one rotation matrix M (3, 3) of angle below 180 deg, rad
    (the inverse of ``exp_matrix``)."""
    v = 0.5 * np.array([M[2, 1] - M[1, 2], M[0, 2] - M[2, 0], M[1, 0] - M[0, 1]])
    sn = float(np.sqrt(v @ v))
    th = np.arctan2(sn, 0.5 * (M[0, 0] + M[1, 1] + M[2, 2] - 1.0))
    return v * (th / sn) if sn > 1e-12 else v


def step_rotvec(w: np.ndarray, dt: np.ndarray, sample_kind: str = "instant") -> np.ndarray:
    """Rotation vectors (N, 3) of the steps between samples, body axes, rad. w (N, 3)
    rad/s, dt (N,) s the step after each sample. ``instant`` samples (values at the
    stamps): the mid-interval rate (w_k + w_k+1)/2 over [t_k, t_k+1] (else the attitude
    lags half a sample); ``interval-mean`` samples (means over [t_k - dt, t_k]): sample
    k is the mean rate of its own period, so step k spans [t_k - dt, t_k] and is exact
    for a rotation about a fixed axis."""
    if sample_kind == "interval-mean":
        return w * dt[:, None]
    wmid = np.concatenate([0.5 * (w[1:] + w[:-1]), w[-1:]])
    return wmid * dt[:, None]


def mean_rotation(phi: np.ndarray) -> np.ndarray:
    """Mean over s in [0, 1] of Exp(s phi) (..., 3, 3), for rotation vectors phi (..., 3):
    I + (1 - cos a)/a [u x] + (1 - sin a / a) [u x]^2, a = |phi| (the mean attitude
    over a step of constant rate, for samples that are interval means)."""
    phi = np.asarray(phi, dtype=float)
    a = np.linalg.norm(phi, axis=-1)
    small = a < 1e-6
    a_safe = np.where(small, 1.0, a)
    c1 = np.where(small, 0.5, (1 - np.cos(a_safe)) / a_safe**2)  # (1 - cos a)/a / a
    c2 = np.where(small, 1.0 / 6.0, (1 - np.sin(a_safe) / a_safe) / a_safe**2)
    K = skew(phi)
    return np.eye(3) + c1[..., None, None] * K + c2[..., None, None] * (K @ K)
