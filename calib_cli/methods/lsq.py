"""Weighted nonlinear least squares with an honest covariance, shared by
every estimator.

The residual function returns *whitened* residuals (residual / its 1-sigma),
so J^T J is the Fisher information. Parameters that the data cannot
determine (directions of the scaled Jacobian with no singular value to speak
of) are reported as unobservable: NaN variance, excluded from the covariance
of the rest, never a made-up number.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import optimize, stats

from calib_cli.errors import EstimationError

RANK_TOL = 1e-7  # singular values below RANK_TOL * largest (scaled problem) count as zero


@dataclass(frozen=True)
class LsqFit:
    theta: np.ndarray
    cov: np.ndarray  # (p, p); NaN rows/cols for unobservable entries
    unobservable: np.ndarray  # bool (p,)
    residuals: np.ndarray  # whitened, at the solution
    chi2: float
    dof: int
    nfev: int

    @property
    def chi2_dof(self) -> float:
        return self.chi2 / self.dof if self.dof > 0 else float("nan")

    def inflated(self, p_threshold: float = 1e-3) -> tuple["LsqFit", float]:
        """Scale the covariance by chi2/dof when the residual scatter is
        significantly larger than the stated noise (p < p_threshold), so the
        reported sigma stays honest under unmodelled errors. Returns the fit
        and the factor applied to the variances (1.0 when none)."""
        if self.dof <= 0 or stats.chi2.sf(self.chi2, self.dof) >= p_threshold:
            return self, 1.0
        f = self.chi2_dof
        return LsqFit(self.theta, self.cov * f, self.unobservable, self.residuals, self.chi2,
                      self.dof, self.nfev), f


def covariance(jac: np.ndarray, scales: np.ndarray, fixed=None) -> tuple[np.ndarray, np.ndarray]:
    """Covariance (J^T J)^-1 over the observable parameters, and the mask of
    unobservable ones. ``fixed``: parameters to treat as known (mask)."""
    p = jac.shape[1]
    scales = np.where(scales > 0, scales, 1.0)
    unobs = np.zeros(p, bool) if fixed is None else np.asarray(fixed, bool).copy()
    for _ in range(p):
        keep = ~unobs
        Js = jac[:, keep] * scales[keep]
        if Js.shape[1] == 0:
            break
        # full V when there are fewer equations than unknowns: the reduced SVD
        # would hide the null directions beyond the number of rows
        _, s, vt = np.linalg.svd(Js, full_matrices=Js.shape[0] < Js.shape[1])
        s = np.concatenate([s, np.zeros(vt.shape[0] - len(s))])
        null = s < RANK_TOL * (s[0] if len(s) and s[0] > 0 else 1.0)
        if not null.any():
            break
        mark_null_parameters(unobs, keep, vt[null].T)
    cov = np.full((p, p), np.nan)
    keep = ~unobs
    if keep.any():
        Js = jac[:, keep] * scales[keep]
        inv = np.linalg.pinv(Js.T @ Js)
        cov[np.ix_(keep, keep)] = inv * np.outer(scales[keep], scales[keep])
    if fixed is not None:
        unobs &= ~np.asarray(fixed, bool)
    return cov, unobs


def mark_null_parameters(unobs: np.ndarray, keep: np.ndarray, null_vectors: np.ndarray) -> None:
    """Set ``unobs`` (in place) for the kept parameters that take part in the null
    directions (columns of ``null_vectors``, one row per kept parameter): they
    cannot be told apart. Weight > 0.05, or else the largest one."""
    weight = np.sqrt((null_vectors ** 2).sum(axis=1))
    idx = np.flatnonzero(keep)
    worst = weight > 0.05
    if not worst.any():
        worst = weight == weight.max()
    unobs[idx[worst]] = True


def fit(residual_fn, theta0, scales, *, max_nfev: int = 200, what: str = "fit",
        fixed=None) -> LsqFit:
    """Minimise the sum of squares of ``residual_fn(theta)`` (whitened).

    scales: typical size of each parameter (optimiser scaling, rank test).
    Raises EstimationError when the optimiser fails or returns non-finite values.
    """
    theta0 = np.asarray(theta0, dtype=float)
    scales = np.asarray(scales, dtype=float)
    r0 = residual_fn(theta0)
    if not np.all(np.isfinite(r0)):
        raise EstimationError(f"{what}: the starting point gives non-finite residuals")
    if len(r0) < len(theta0):
        raise EstimationError(f"{what}: {len(r0)} equations for {len(theta0)} unknowns")
    try:
        sol = optimize.least_squares(residual_fn, theta0, x_scale=np.where(scales > 0, scales, 1.0),
                                     method="lm" if len(r0) >= len(theta0) else "trf",
                                     max_nfev=max_nfev * (len(theta0) + 1))
    except (ValueError, np.linalg.LinAlgError) as exc:
        raise EstimationError(f"{what}: the optimiser failed ({exc})") from None
    if not np.all(np.isfinite(sol.x)) or not np.all(np.isfinite(sol.fun)):
        raise EstimationError(f"{what}: the optimiser diverged (non-finite result)")
    if sol.status <= 0:
        raise EstimationError(f"{what}: did not converge ({sol.message})")
    cov, unobs = covariance(sol.jac, scales, fixed)
    n_obs_params = int((~unobs).sum())
    chi2 = float(sol.fun @ sol.fun)
    return LsqFit(sol.x, cov, unobs, sol.fun, chi2, len(sol.fun) - n_obs_params, sol.nfev)
