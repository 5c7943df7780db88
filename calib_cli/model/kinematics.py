"""What the sensors are exposed to: specific force and angular rate in body axes.

A ``Kinematics`` holds the true inputs, per sample, at the point of the unit
about which lever arms are measured (a point on the table axis on a rotating
table, the unit's reference point otherwise). The effect catalogue turns it
into sensor outputs; the simulator and every estimator build one the same way.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import numpy as np

from calib_cli.model.earth import Site

if TYPE_CHECKING:  # imported where used: SciPy's spatial module costs ~0.5 s of start-up
    from scipy.spatial.transform import Rotation


@dataclass(frozen=True)
class Kinematics:
    """True inputs per sample (samples along axis 0, SI units).

    t: (N,) s. f: (N, 3) specific force, m/s^2, body axes. w: (N, 3) body rate
    against inertial space, rad/s. dw: (N, 3) angular acceleration, rad/s^2.
    temp: (N,) degC or None. cycle: (N,) int, row of ``lever_arm`` in force
    for the sample (-1: none). segment: (N,) int, raw segment index (-1:
    between segments). cen: (N, 3, 3) the centripetal operator, for rows that
    are means over an interval (a filter's measurement blocks: the mean of
    [w x]^2 is not [mean(w) x]^2, the rows' w and dw being the means); None:
    [w x]^2 of each row's w.
    """

    t: np.ndarray
    f: np.ndarray
    w: np.ndarray
    dw: np.ndarray
    temp: np.ndarray | None = None
    cycle: np.ndarray | None = None
    segment: np.ndarray | None = None
    cen: np.ndarray | None = None

    def __len__(self) -> int:
        return len(self.t)

    def take(self, index) -> "Kinematics":
        """A subset of samples (boolean mask or integer index)."""
        opt = {k: (None if getattr(self, k) is None else getattr(self, k)[index])
               for k in ("temp", "cycle", "segment", "cen")}
        return Kinematics(self.t[index], self.f[index], self.w[index], self.dw[index], **opt)

    def with_(self, **changes) -> "Kinematics":
        return replace(self, **changes)

    @staticmethod
    def concatenate(parts: list["Kinematics"]) -> "Kinematics":
        def cat(name):
            vals = [getattr(p, name) for p in parts]
            if any(v is None for v in vals):
                return None
            return np.concatenate(vals)
        return Kinematics(*(np.concatenate([getattr(p, k) for p in parts])
                            for k in ("t", "f", "w", "dw")),
                          temp=cat("temp"), cycle=cat("cycle"), segment=cat("segment"),
                          cen=cat("cen"))


def from_attitude(t, rot: Rotation, site: Site, w_rel=None, dw_rel=None) -> Kinematics:
    """Kinematics of a unit at attitudes ``rot`` (body->ENU, one per sample).

    w_rel, dw_rel: body rate and angular acceleration relative to the
    local-level frame (N, 3), zero for a static unit. The earth rate is added
    here, so the gyros see rotation against inertial space.
    """
    t = np.asarray(t, dtype=float)
    n = len(t)
    inv = rot.inv()
    f = inv.apply(np.tile(site.specific_force_enu, (n, 1)))
    w_earth = inv.apply(np.tile(site.earth_rate_enu, (n, 1)))
    w_rel = np.zeros((n, 3)) if w_rel is None else np.asarray(w_rel, dtype=float)
    dw_rel = np.zeros((n, 3)) if dw_rel is None else np.asarray(dw_rel, dtype=float)
    # d/dt(R^T W_ie) = -w_rel x (R^T W_ie): the earth rate seen from a turning body
    dw = dw_rel - np.cross(w_rel, w_earth)
    return Kinematics(t, f, w_earth + w_rel, dw)


def table_attitude(axis_enu, theta, rot0: Rotation) -> Rotation:
    """R(t) = Rot(axis, theta(t) - theta(t0)) R0 (CONTRACT.md section 1)."""
    theta = np.asarray(theta, dtype=float)
    a = np.asarray(axis_enu, dtype=float)
    a = a / np.linalg.norm(a)
    from scipy.spatial.transform import Rotation

    return Rotation.from_rotvec(np.outer(theta - theta[0], a)) * rot0


def table_kinematics(t, axis_enu, theta, rate, accel, rot0: Rotation, site: Site,
                     axis_wobble: tuple[float, float] | None = None) -> Kinematics:
    """Kinematics on a single-axis table turning about ``axis_enu``.

    theta (rad), rate (rad/s), accel (rad/s^2): table angle and its
    derivatives, (N,). rot0: attitude at the first sample. axis_wobble:
    (amplitude rad, phase rad) of a bearing's runout: the turning part rocks by
    eps(theta) = amp (cos(theta + phase) e1 + sin(2 theta + phase) e2), e1, e2
    perpendicular to the axis (a tilt that turns with the table would be a
    constant mounting error, not a wobble).
    """
    a = np.asarray(axis_enu, dtype=float)
    a = a / np.linalg.norm(a)
    if axis_wobble is not None and axis_wobble[0] != 0.0:
        return _wobbling_table(t, a, theta, rate, accel, rot0, site, *axis_wobble)
    rot = table_attitude(a, theta, rot0)
    inv = rot.inv()
    a_body = inv.apply(np.tile(a, (len(theta), 1)))
    # the table axis is fixed in ENU, so d/dt(R^T a theta') = R^T a theta''
    w_rel = a_body * np.asarray(rate, dtype=float)[:, None]
    dw_rel = a_body * np.asarray(accel, dtype=float)[:, None]
    return from_attitude(t, rot, site, w_rel, dw_rel)


def _wobbling_table(t, a, theta, rate, accel, rot0, site, amp, phase) -> Kinematics:
    """table_kinematics with the axis rocking (runout): R = W(theta) A W(theta_0)^T
    R0, W = exp([eps x]). The rate is exact (the left Jacobian of SO(3)); the angular
    acceleration is first order in eps (its error ~ amp^2 rate^2, far below any sensor's)."""
    from scipy.spatial.transform import Rotation

    theta = np.asarray(theta, dtype=float)
    rate = np.asarray(rate, dtype=float)
    accel = np.asarray(accel, dtype=float)
    e1 = np.cross(a, [1.0, 0.0, 0.0] if abs(a[0]) < 0.9 else [0.0, 1.0, 0.0])
    e1 /= np.linalg.norm(e1)
    e2 = np.cross(a, e1)
    u, v = theta + phase, 2 * theta + phase
    eps = amp * (np.outer(np.cos(u), e1) + np.outer(np.sin(v), e2))
    deps = amp * (np.outer(-np.sin(u), e1) + np.outer(2 * np.cos(v), e2))  # d eps / d theta
    d2eps = amp * (np.outer(-np.cos(u), e1) + np.outer(-4 * np.sin(v), e2))
    W = Rotation.from_rotvec(eps)
    rot = W * Rotation.from_rotvec(np.outer(theta - theta[0], a)) * W[0].inv() * rot0
    # the left Jacobian of exp at eps: the spatial rate of W is J_l(eps) d(eps)/dt
    n = np.linalg.norm(eps, axis=1)[:, None]
    epsd = deps * rate[:, None]
    ex_d = np.cross(eps, epsd)
    Om_w = (epsd + (1 - np.cos(n)) / n**2 * ex_d
            + (n - np.sin(n)) / n**3 * np.cross(eps, ex_d))
    Wa = W.apply(np.tile(a, (len(theta), 1)))
    Om = Om_w + Wa * rate[:, None]
    dOm = (d2eps * rate[:, None] ** 2 + deps * accel[:, None] + np.cross(epsd, Wa * rate[:, None])
           + Wa * accel[:, None])
    inv = rot.inv()
    return from_attitude(t, rot, site, inv.apply(Om), inv.apply(dOm))


def slew_kinematics(t, rot_a: Rotation, rot_b: Rotation, site: Site, phi=None) -> Kinematics:
    """A smooth turn from rot_a to rot_b about a body-fixed axis over the times t.

    phi: the body-frame rotation vector of the turn (rad); by default the
    shortest one from rot_a to rot_b (give it for turns of 180 deg or more).
    The fraction turned follows a minimum-jerk profile s(u) = 10u^3 - 15u^4 + 6u^5,
    so rate and angular acceleration start and end at zero.
    """
    t = np.asarray(t, dtype=float)
    T = t[-1] - t[0]
    u = (t - t[0]) / T if T > 0 else np.zeros_like(t)
    s = 10 * u**3 - 15 * u**4 + 6 * u**5
    ds = (30 * u**2 - 60 * u**3 + 30 * u**4) / T
    dds = (60 * u - 180 * u**2 + 120 * u**3) / T**2
    if phi is None:
        phi = (rot_a.inv() * rot_b).as_rotvec()  # body-frame rotation vector
    phi = np.asarray(phi, dtype=float)
    from scipy.spatial.transform import Rotation

    rot = rot_a * Rotation.from_rotvec(np.outer(s, phi))
    # the rotation axis is fixed in the body, so w_rel = s' phi and dw_rel = s'' phi
    return from_attitude(t, rot, site, np.outer(ds, phi), np.outer(dds, phi))


def cross3(a, b) -> np.ndarray:
    """a x b over the last axis (..., 3): np.cross without its general-axis set-up, which
    costs ~100 us per call (a filter's per-block prediction)."""
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return np.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=-1)


def rigid_body_accel(w, dw, r) -> np.ndarray:
    """Centripetal plus tangential acceleration w x (w x r) + dw x r (N, 3) of a point at
    body offset r ((3,) or (N, 3), m), body rate w (N, 3, rad/s), angular acceleration dw."""
    w = np.asarray(w, dtype=float)
    r = np.broadcast_to(np.asarray(r, dtype=float), w.shape)
    return cross3(w, cross3(w, r)) + cross3(dw, r)


def rigid_accel(kin: Kinematics, r, tangential: bool = True) -> np.ndarray:
    """Acceleration (N, 3) of the point at body offset r ((3,) or (N, 3), m) relative to
    the kinematics point: w x (w x r) + dw x r, with the rows' centripetal operator
    ``kin.cen`` where given (interval means); tangential=False drops dw x r."""
    if kin.cen is None:
        return rigid_body_accel(kin.w, kin.dw if tangential else np.zeros_like(kin.dw), r)
    r = np.broadcast_to(np.asarray(r, dtype=float), kin.f.shape)
    out = np.einsum("nij,nj->ni", kin.cen, r)
    return out + cross3(kin.dw, r) if tangential else out


def force_at(kin: Kinematics, r, tangential: bool = True) -> np.ndarray:
    """Specific force (N, 3) at body offset r ((3,) or (N, 3), m) from the kinematics point:
    f + w x (w x r) + dw x r (centripetal and tangential terms)."""
    return kin.f + rigid_accel(kin, r, tangential)
