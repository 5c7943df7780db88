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
body inputs are R(mount)^T times the plan's. For ``align`` the same 3 angles
are a rotation of the navigation frame (the alignment's tilt and heading
errors, common to all positions), which in each position's body axes is a
different rotation.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.spatial.transform import Rotation

from calib_cli.errors import EstimationError
from calib_cli.methods.diagnose_problem import Problem
from calib_cli.methods.lsq import RANK_TOL, mark_null_parameters
from calib_cli.model.imu_model import ImuModel, Packing

MOUNT_KEY = "mount"
MAX_REFRESH = 4  # Jacobian recomputations when the fixed-Jacobian steps do not converge
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
    def lever_constraints(self) -> int:
        """Axial conventions that pin an entry the data leave free: one per
        lever-arm row (cycle) with an observable entry. Not one per cycle: the
        rows the data do not reach have no observable entry to pin (an 18-cycle
        rimu plan gave 6 observable entries minus 18, issue 37)."""
        if not self.n_constraints:
            return 0
        rows = {int(i) // 3 for j, (k, i) in enumerate(self.labels)
                if k == "lever_arm" and not self.unobs[j]}
        return min(len(rows), self.n_constraints)

    @property
    def n_free(self) -> int:
        """Parameters the data determine (conventions excluded)."""
        return int((~self.unobs).sum()) - self.lever_constraints

    def residual_blocks(self, pb: Problem) -> dict:
        """sensor -> (M, n) whitened residual, data - model (the sign a user reads)."""
        out, i = {}, 0
        for s in pb.sensors:
            n = pb.y[s].shape[1]
            m = pb.n_bins * n
            out[s] = -self.r[i:i + m].reshape(pb.n_bins, n)
            i += m
        return out


def n_nuisance(pb: Problem, spec: ModelSpec) -> int:
    """Mount angles (3) and two tilt angles per position of unknown attitude."""
    return (3 if spec.mount else 0) + (2 * len(pb.tilt_basis) if pb.tilt_basis is not None
                                       else 0)


def _nuisance_kin(pb: Problem, spec: ModelSpec, nuis):
    """The problem's kinematics under the nuisance parameters: the unit's
    mount rotation, and the gravity direction of each position of unknown
    attitude (u_i + a e1_i + b e2_i, normalised, times g)."""
    kin = pb.kin
    if nuis is None or len(nuis) == 0:
        return kin
    i = 0
    if spec.mount and pb.seg_rot is not None:
        # align: the attitudes are off by one rotation Rn of the navigation frame (the
        # alignment's tilt and heading errors), the same for every position: in body
        # axes of position i that is R_i^T Rn^T R_i, different per position
        if np.any(nuis[:3]):
            Rn = Rotation.from_rotvec(nuis[:3]).as_matrix()
            f, w, dw = kin.f.copy(), kin.w.copy(), kin.dw.copy()
            for idx, Ri in pb.seg_rot.items():
                on = kin.segment == idx
                if on.any():
                    D = Ri.T @ Rn @ Ri  # rows: v_body' = v_body @ D
                    f[on], w[on], dw[on] = kin.f[on] @ D, kin.w[on] @ D, kin.dw[on] @ D
            kin = kin.with_(f=f, w=w, dw=dw)
        i = 3
    elif spec.mount:
        if np.any(nuis[:3]):
            R = Rotation.from_rotvec(nuis[:3]).as_matrix()
            kin = kin.with_(f=kin.f @ R, w=kin.w @ R, dw=kin.dw @ R)
        i = 3
    if pb.tilt_basis is not None:
        ab = np.asarray(nuis[i:], float).reshape(-1, 2)
        d = pb.tilt_u + ab[:, :1] * pb.tilt_basis[:, 0] + ab[:, 1:] * pb.tilt_basis[:, 1]
        fseg = pb.g * d / np.linalg.norm(d, axis=1)[:, None]
        on = pb.tilt_index >= 0
        f = kin.f.copy()
        f[on] = fseg[pb.tilt_index[on]]
        kin = kin.with_(f=f)
    return kin


def predict_bins(pb: Problem, spec: ModelSpec, params: dict, mount=None) -> dict:
    """sensor -> (M, n) bin means of the model's prediction (mount: the nuisance vector)."""
    kin = _nuisance_kin(pb, spec, mount)
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


def gram_covariance(jac: np.ndarray, scales: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``methods.lsq.covariance`` through the normal matrix J^T J (p x p) instead of an
    SVD of the tall J: the same rank test (singular values = sqrt of the eigenvalues),
    and orders of magnitude faster where the BLAS threads are contended."""
    p = jac.shape[1]
    Js = jac * scales
    G = Js.T @ Js
    unobs = np.zeros(p, bool)
    for _ in range(p):
        keep = ~unobs
        if not keep.any():
            break
        lam, V = np.linalg.eigh(G[np.ix_(keep, keep)])
        sv = np.sqrt(np.clip(lam, 0, None))
        null = sv < RANK_TOL * max(sv[-1], 1e-300)
        if not null.any():
            break
        mark_null_parameters(unobs, keep, V[:, null])
    cov = np.full((p, p), np.nan)
    keep = ~unobs
    if keep.any():
        inv = np.linalg.pinv(G[np.ix_(keep, keep)], hermitian=True)
        cov[np.ix_(keep, keep)] = inv * np.outer(scales[keep], scales[keep])
    return cov, unobs


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
    nn = n_nuisance(pb, spec)
    labels = packing.labels() + [(MOUNT_KEY, i) for i in range(nn)]
    nm = packing.size
    theta = packing.pack(base)
    theta = np.concatenate([theta, np.zeros(nn) if start_mount is None else start_mount])
    unit = np.concatenate([np.full(int(m.sum()), pb.scale_of(sp.key))
                           for sp, m in zip(packing.specs, packing.masks)] or [np.zeros(0)])
    typ = np.concatenate([packing.scales() * unit, np.full(nn, 1e-3)])
    typ = np.where(typ > 0, typ, 1.0)
    steps = np.concatenate([typ[:nm] * 1e-3, np.full(nn, 1e-6)])
    nfev = 0

    lever = model.has("lever_arm") and pb.cycle_axes is not None and len(pb.cycle_axes)

    def fun(th):
        nonlocal nfev
        nfev += 1
        p = packing.unpack(th[:nm], base)
        r = _residual(pb, spec, p, th[nm:])
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
        """Gauss-Newton steps on a fixed Jacobian: (theta, r, converged)."""
        sc = scales_at(theta)
        Js = J * sc
        G = Js.T @ Js
        lam, V = np.linalg.eigh(G)
        inv = np.where(lam > RANK_TOL ** 2 * max(lam[-1], 1e-300), 1.0 / np.where(lam > 0, lam, 1),
                       0.0)
        for _ in range(n_iter):
            dx = (V @ (inv * (V.T @ (Js.T @ -r)))) * sc
            c0 = r @ r
            for _half in range(6):  # step halving where the model is not linear enough
                t2 = theta + dx
                r2 = fun(t2)
                c1 = r2 @ r2
                if np.isfinite(c1) and c1 <= c0:
                    break
                dx = dx / 2
            if not np.isfinite(c1) or c1 > c0:
                return theta, r, False
            theta, r = t2, r2
            if c0 - c1 < 1e-8 * c0 + 1e-6:
                return theta, r, True
        return theta, r, False

    theta, r, done = chord(theta, r, J, max_chord)
    # bilinear couplings (a scale drift times a rotated input, the attitude nuisance)
    # defeat a fixed Jacobian: recompute it until the steps converge
    for _ in range(MAX_REFRESH):
        if done and not refresh:
            break
        J = jac(theta, r, None)
        theta, r, done = chord(theta, r, J, max_chord if not done else 3)
        if done:
            break
    if not np.all(np.isfinite(r)):
        raise EstimationError("diagnose: the fit diverged (non-finite residuals)")
    cov, unobs = gram_covariance(J, scales_at(theta))
    params = packing.unpack(theta[:nm], base)
    sig = packing.sigma_arrays(np.diag(cov)[:nm])
    n_con = len(pb.cycle_axes) if lever else 0
    if lever:  # entries pinned by the axial convention: sigma 0
        sig["lever_arm"] = np.where(sig["lever_arm"] < 2 * AXIAL_TOL, 0.0, sig["lever_arm"])
    r = r[:len(r) - n_con]
    mount = theta[nm:]
    if nn:
        sig[MOUNT_KEY] = np.sqrt(np.abs(np.diag(cov)[nm:]))
    return Fit(spec, packing, params, mount, theta, labels, J, r, cov, unobs, sig, nfev, n_con)


def columns(fit: Fit) -> dict:
    """{label: Jacobian column} of a fit, to reuse in a nested fit."""
    return {lab: fit.J[:, j] for j, lab in enumerate(fit.labels)}


def settle_noise(pb: Problem, fit: Fit, initial: Fit | None = None):
    """(problem, fit, initial) with each channel's white sigma settled for the final model.

    With ``--noise-floor auto`` the working sigma of a channel is raised to the bins'
    scatter within the positions where that is significantly above the
    high-frequency estimate (``diagnose_problem.apply_noise``). The scatter is
    measured on the data, before any model: a drift the final model explains (a
    temperature drift inside long positions) raises it as much as coloured noise
    does, and the raised sigma then stays in the final fit's covariance (sigma
    conservative: the alignment's thermal drift gave RMS z 0.77). Here each raised
    channel's level is re-estimated from the final model's residuals, at its most
    likely value between the high-frequency estimate and the raised one (the rule of
    ``diagnose.neg2ll``), and the model is refitted under it. Channels under a
    wandering-bias whitening keep theirs. ``initial``'s residual is rescaled to the
    settled units. Nothing changes where no channel was raised."""
    from dataclasses import replace

    if not pb.raised:
        return pb, fit, initial
    blocks = fit.residual_blocks(pb)
    sigma, scale, changed = dict(pb.sigma), [], False
    for s in pb.sensors:
        n = pb.y[s].shape[1]
        f = np.ones(n)
        if s not in fit.spec.stochastic and s in (pb.sigma_hf or {}):
            z = blocks[s]
            lo = (np.asarray(pb.sigma_hf[s], float) / np.asarray(pb.sigma[s], float)) ** 2
            a = np.clip((z ** 2).mean(axis=0), np.minimum(lo, 1.0), 1.0)
            f = np.sqrt(a)
            changed = changed or bool(np.any(f < 1.0))
            sigma[s] = np.asarray(pb.sigma[s], float) * f
        scale.append(np.tile(1.0 / f, pb.n_bins))
    if not changed:
        return pb, fit, initial
    pb2 = replace(pb, sigma=sigma)
    fit2 = fit_model(pb2, fit.spec, start=fit.params, start_mount=fit.mount, refresh=True)
    if initial is not None:
        k = np.concatenate(scale)
        r = np.asarray(initial.r, float).copy()
        r[:len(k)] *= k
        initial = replace(initial, r=r)
    return pb2, fit2, initial
