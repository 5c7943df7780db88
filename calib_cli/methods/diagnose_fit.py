"""The refit engine of ``calib diagnose``: fit an ``ImuModel`` (any list of
catalogue effects) to the bin means of a ``Problem`` through the catalogue's
own forward function.

The residual of a bin is (mean of the per-sample prediction - mean of the
data) / (sigma / sqrt(n)), so chi^2 is the log-likelihood of white noise and
two nested fits differ by a likelihood-ratio statistic. Gauss-Newton with a
finite-difference Jacobian (the models are nearly linear in their
parameters: one step from neutral values, a few chord steps after);
columns already known from the previous model are reused, so a candidate
costs only its own columns. Covariance and unobservable entries come from
``methods.lsq.covariance``.

Nuisance ``mount``: for methods that fix the instrument frame by the
accelerometers (lower-triangular K, the turntable method), the unit's small
mounting rotation on the fixture (3 angles) is fitted with the model: the
body inputs are R(mount)^T times the plan's.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from calib_cli.errors import EstimationError
from calib_cli.methods.diagnose_problem import Problem
from calib_cli.methods.lsq import RANK_TOL, covariance
from calib_cli.model.imu_model import ImuModel, Packing

MOUNT_KEY = "mount"
AXIAL_TOL = 1e-7  # m: weight of the lever arm's axial convention s . a = 0


@dataclass
class ModelSpec:
    model: ImuModel
    mount: bool = False
    stochastic: dict = field(default_factory=dict)  # sensor -> per-channel whitening (see stoch)


@dataclass
class Fit:
    spec: ModelSpec
    packing: Packing
    params: dict
    mount: np.ndarray | None
    theta: np.ndarray
    labels: list  # [(key, flat index)] of each column
    J: np.ndarray  # whitened Jacobian of the binned residuals
    r: np.ndarray  # whitened binned residuals (prediction - data)
    cov: np.ndarray
    unobs: np.ndarray
    sigma: dict  # key -> sigma array (NaN unobservable)
    nfev: int
    n_constraints: int = 0  # rows of J that are conventions, not data (lever-arm axial)

    @property
    def chi2(self) -> float:
        return float(self.r @ self.r)

    @property
    def n_free(self) -> int:
        """Parameters the data determine (conventions excluded)."""
        return int((~self.unobs).sum()) - self.n_constraints

    def residual_blocks(self, pb: Problem) -> dict:
        """sensor -> (M, n) whitened residual, data - model (the sign a user reads)."""
        out, i = {}, 0
        for s in pb.sensors:
            n = pb.y[s].shape[1]
            m = pb.n_bins * n
            out[s] = -self.r[i:i + m].reshape(pb.n_bins, n)
            i += m
        return out


def _rotate_kin(kin, mount):
    if mount is None or not np.any(mount):
        return kin
    R = Rotation.from_rotvec(mount).as_matrix()
    return kin.with_(f=kin.f @ R, w=kin.w @ R, dw=kin.dw @ R)


def predict_bins(pb: Problem, spec: ModelSpec, params: dict, mount=None) -> dict:
    """sensor -> (M, n) bin means of the model's prediction."""
    kin = _rotate_kin(pb.kin, mount)
    out = spec.model.predict(params, kin, sensors=pb.sensors)
    return {s: pb.bin_mean(out[s]) for s in pb.sensors}


def _residual(pb: Problem, spec: ModelSpec, params: dict, mount) -> np.ndarray:
    pred = predict_bins(pb, spec, params, mount)
    parts = []
    for s in pb.sensors:
        z = (pred[s] - pb.ymean[s]) / pb.whitener(s)
        if s in spec.stochastic:
            z = spec.stochastic[s].whiten(z)
        parts.append(z.ravel())
    return np.concatenate(parts)


def _steps(packing: Packing) -> np.ndarray:
    """Finite-difference steps: 1e-3 of each entry's typical size (the models are
    nearly linear in their parameters, so the step size hardly matters)."""
    typ = packing.scales()
    return np.where(typ > 0, typ, 1.0) * 1e-3


def fit_model(pb: Problem, spec: ModelSpec, start: dict | None = None,
              start_mount=None, known_cols: dict | None = None, refresh: bool = False,
              max_chord: int = 8) -> Fit:
    """Fit every free parameter of ``spec`` to the problem's bins.

    start: parameter values to start from (missing keys neutral).
    known_cols: {(key, idx): column} Jacobian columns to reuse.
    refresh: recompute the whole Jacobian at the solution (for final covariances).
    """
    model = spec.model
    packing = Packing.for_model(model)
    base = model.neutral_params()
    if start:
        base.update({k: np.asarray(v, float) for k, v in start.items() if k in base})
    labels = packing.labels() + ([(MOUNT_KEY, i) for i in range(3)] if spec.mount else [])
    nm = packing.size
    theta = packing.pack(base)
    if spec.mount:
        theta = np.concatenate([theta, np.zeros(3) if start_mount is None else start_mount])
    typ = np.concatenate([packing.scales(), np.full(3 if spec.mount else 0, 1e-3)])
    typ = np.where(typ > 0, typ, 1.0)
    steps = np.concatenate([_steps(packing), np.full(3 if spec.mount else 0, 1e-5)])
    nfev = 0

    lever = model.has("lever_arm") and pb.cycle_axes is not None and len(pb.cycle_axes)

    def fun(th):
        nonlocal nfev
        nfev += 1
        p = packing.unpack(th[:nm], base)
        r = _residual(pb, spec, p, th[nm:] if spec.mount else None)
        if lever:  # the lever arm's axial component is unobservable: s . a = 0
            r = np.concatenate([r, (p["lever_arm"] * pb.cycle_axes).sum(axis=1) / AXIAL_TOL])
        return r

    def jac(th, r0, reuse):
        J = np.empty((len(r0), len(th)))
        for j, lab in enumerate(labels):
            if reuse and lab in reuse:
                col = reuse[lab][:len(r0)]
                J[:len(col), j] = col
                J[len(col):, j] = 0.0
                continue
            t2 = th.copy()
            t2[j] += steps[j]
            J[:, j] = (fun(t2) - r0) / steps[j]
        return J

    r = fun(theta)
    J = jac(theta, r, known_cols)

    def scales_at(th):
        # typical sizes, or the value itself where it is larger (K of a fit in counts)
        return np.maximum(typ, np.abs(th))

    def chord(theta, r, J, n_iter):
        sc = scales_at(theta)
        for _ in range(n_iter):
            dx = np.linalg.lstsq(J * sc, -r, rcond=RANK_TOL)[0] * sc
            t2 = theta + dx
            r2 = fun(t2)
            c0, c1 = r @ r, r2 @ r2
            if not np.isfinite(c1) or c1 > c0:
                break
            theta, r = t2, r2
            if c0 - c1 < 1e-8 * c0 + 1e-6:
                break
        return theta, r

    theta, r = chord(theta, r, J, max_chord)
    if refresh:
        J = jac(theta, r, None)
        theta, r = chord(theta, r, J, 3)
    if not np.all(np.isfinite(r)):
        raise EstimationError("diagnose: the fit diverged (non-finite residuals)")
    cov, unobs = covariance(J, scales_at(theta))
    params = packing.unpack(theta[:nm], base)
    sig = packing.sigma_arrays(np.diag(cov)[:nm])
    n_con = len(pb.cycle_axes) if lever else 0
    if lever:  # entries pinned by the axial convention: sigma 0
        sig["lever_arm"] = np.where(sig["lever_arm"] < 2 * AXIAL_TOL, 0.0, sig["lever_arm"])
    r = r[:len(r) - n_con]
    mount = theta[nm:] if spec.mount else None
    if spec.mount:
        sig[MOUNT_KEY] = np.sqrt(np.abs(np.diag(cov)[nm:]))
    return Fit(spec, packing, params, mount, theta, labels, J, r, cov, unobs, sig, nfev, n_con)


def columns(fit: Fit) -> dict:
    """{label: Jacobian column} of a fit, to reuse in a nested fit."""
    return {lab: fit.J[:, j] for j, lab in enumerate(fit.labels)}
