"""Fault detection and isolation (FDI) of a redundant unit in parity space.

With the calibrated measurement matrix H (n, 3) and corrected single-axis
outputs c = H x + e, the parity vector p = V c (V: (n-3, n), orthonormal rows
spanning the left null space of H, V H = 0) does not depend on the motion x:
it holds only noise and faults.

Detection: the outputs are averaged over non-overlapping windows of w samples
(``window_s``). Without a fault the window's parity p ~ N(0, P), P = V Sigma V^T
with Sigma = diag(sigma_i^2) / w (white noise, per-sample sigma_i from the
calibration's noise density at the data's sample rate), so

    T = p^T P^-1 p ~ chi-square with n - 3 degrees of freedom.

A window alarms when T > chi2.isf(alpha, n - 3), alpha = rate * window_s / 3600
for a stated false-alarm rate per hour (default 0.1/h: one per 10 hours).

The calibration is not exact: its error in output i at input x is
d(b + (1+ks) S.x) with the fitted covariance, which grows with the rate or
force. Where the calibration's covariance is given it is added to Sigma per
window (at the window's body estimate x), so fast motion does not raise
false alarms; at rest it is a few per cent of the noise variance.

Isolation: for a fault f on sensor i, p = f v_i (v_i = V e_i). The generalised
likelihood ratio picks the sensor with the largest normalised parity residual
z_i = v_i^T P^-1 p / sqrt(v_i^T P^-1 v_i). The body estimate is then made
again from the other n - 1 sensors, and the parity test is repeated on them
(n - 4 degrees of freedom) to say whether the rest is consistent.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy import stats

from calib_cli.errors import EstimationError
from calib_cli.methods.rimu import (
    body_estimate,
    calibration_variance,
    corrected_outputs,
    measurement_matrix,
)
from calib_cli.model.effects import Layout

DEFAULT_WINDOW_S = 0.5
DEFAULT_RATE_PER_HOUR = 0.1  # one false alarm per 10 hours of fault-free data
ISOLATION_COS = 0.999  # parity directions closer than this cannot be told apart


def parity_matrix(H: np.ndarray) -> np.ndarray:
    """V (n-3, n): orthonormal basis of the left null space of H (V H = 0)."""
    U, s, _ = np.linalg.svd(H, full_matrices=True)
    if s[-1] < 1e-6 * s[0]:
        raise EstimationError("the sensing directions do not span 3-D: no parity test possible")
    return U[:, 3:].T


@dataclass(frozen=True)
class FdiReport:
    """Per-window parity test of one sensor kind.

    t: (K,) window start times, s. stat: (K,) chi-square statistic. z: (K, n)
    normalised parity residuals. alarm: (K,) bool. isolated: (K,) sensor
    index (-1 no alarm). x_all, x_excl: (K, 3) body estimates with all sensors
    and without the isolated one (same as x_all where no alarm). stat_rest:
    (K,) statistic of the remaining sensors (NaN where not tested).
    """

    sensor: str
    n: int
    dof: int
    window_s: float
    samples_per_window: int
    rate_per_hour: float
    alpha: float
    threshold: float
    t: np.ndarray
    stat: np.ndarray
    z: np.ndarray
    alarm: np.ndarray
    isolated: np.ndarray
    isolable: np.ndarray
    x_all: np.ndarray
    x_excl: np.ndarray
    stat_rest: np.ndarray
    threshold_rest: float
    sigma: np.ndarray = field(default_factory=lambda: np.zeros(0))

    @property
    def fault(self) -> bool:
        return bool(self.alarm.any())

    @property
    def first_alarm(self) -> float | None:
        return float(self.t[np.argmax(self.alarm)]) if self.fault else None

    @property
    def faulty_sensor(self) -> int | None:
        """The sensor isolated most often over the alarmed windows."""
        if not self.fault:
            return None
        return int(np.bincount(self.isolated[self.alarm], minlength=self.n).argmax())

    def summary(self) -> dict:
        k = self.faulty_sensor
        sel = self.alarm & (self.isolated == k) if k is not None else self.alarm
        return {
            "sensor": self.sensor, "n_sensors": self.n, "dof": self.dof,
            "window_s": self.window_s, "windows": int(len(self.t)),
            "false_alarm_rate_per_hour": self.rate_per_hour, "alpha_per_window": self.alpha,
            "threshold": self.threshold, "alarms": int(self.alarm.sum()),
            "fault": self.fault, "first_alarm_time": self.first_alarm,
            "faulty_sensor": k,
            "isolable": None if k is None else bool(self.isolable[sel].all()),
            "stat_max": float(np.max(self.stat)) if len(self.stat) else None,
            "stat_mean": float(np.mean(self.stat)) if len(self.stat) else None,
            "rest_consistent": None if k is None else bool(
                np.all(~(self.stat_rest[sel] > self.threshold_rest))),
            "x_all_mean": None if k is None else self.x_all[sel].mean(axis=0),
            "x_excluded_mean": None if k is None else self.x_excl[sel].mean(axis=0),
        }


def noise_sigma(cal_stats: dict, sensor: str, sample_rate: float, n: int) -> np.ndarray:
    """Per-sample noise sigma (n,) at ``sample_rate`` from the calibration's
    white-noise density (stats <sensor>_noise_density, unit/sqrt(Hz))."""
    dens = cal_stats.get(f"{sensor}_noise_density")
    if dens is None or len(dens) != n:
        raise EstimationError(f"the calibration holds no {sensor} noise density for the "
                              "parity test (fit it with `calib fit rimu`)")
    return np.asarray(dens, float) * np.sqrt(sample_rate)


def sensor_cov_blocks(cal, sensor: str) -> np.ndarray | None:
    """(n, 4, 4) covariance of each sensor's (b, ks, dEl, dAz) from a RIMU
    calibration (NaN, i.e. unobservable, entries as 0); None when absent."""
    n = cal.layout.n
    pos = {(k, int(i)): j for j, (k, i) in enumerate(cal.cov_order)}
    names = ("bias", "scale_error", "dEl", "dAz")
    out = np.zeros((n, 4, 4))
    for i in range(n):
        idx = [pos.get((f"{sensor}_{nm}", i)) for nm in names]
        if any(j is None for j in idx):
            return None
        out[i] = np.nan_to_num(np.asarray(cal.covariance)[np.ix_(idx, idx)])
    return out


def parity_check(params: dict, layout: Layout, sensor: str, time: np.ndarray, m: np.ndarray,
                 sigma: np.ndarray, window_s: float = DEFAULT_WINDOW_S,
                 rate_per_hour: float = DEFAULT_RATE_PER_HOUR,
                 cal_cov: np.ndarray | None = None) -> FdiReport:
    """Window-by-window parity test of raw outputs m (N, n) with the calibration
    ``params``. sigma: per-sample noise (n,) in the sensor's unit. cal_cov:
    (n, 4, 4) covariance of the calibration (sensor_cov_blocks); when given,
    the calibration's own uncertainty at each window's motion is added to the
    noise covariance, so large rates or forces do not raise false alarms."""
    n = layout.n
    if n < 4:
        raise EstimationError(f"parity-space FDI needs >= 4 sensors; the unit has {n}")
    H = measurement_matrix(params, layout, sensor)
    V = parity_matrix(H)
    dof = n - 3
    fs = 1.0 / float(np.median(np.diff(time))) if len(time) > 1 else 1.0
    w = max(int(round(window_s * fs)), 1)
    K = len(time) // w
    if K < 1:
        raise EstimationError(f"the recording is shorter than one test window ({window_s} s)")
    c = corrected_outputs(params, sensor, m)[: K * w].reshape(K, w, n).mean(axis=1)
    t = time[: K * w: w]
    x_all = body_estimate(H, c)
    var = np.tile(np.asarray(sigma, float) ** 2 / w, (K, 1))  # (K, n)
    if cal_cov is not None:
        var = var + calibration_variance(params, layout, sensor, x_all, cal_cov)
    P = np.einsum("ai,ki,bi->kab", V, var, V)  # (K, dof, dof)
    Pinv = np.linalg.inv(P)
    p = c @ V.T  # (K, dof)
    stat = np.einsum("ki,kij,kj->k", p, Pinv, p)
    window = float(f"{w / fs:.10g}")  # 0.5 s, not 0.49999999999998934 (float time stamps)
    alpha = rate_per_hour * window / 3600.0
    thr = float(stats.chi2.isf(alpha, dof))
    alarm = stat > thr
    # isolation: normalised parity residual of each sensor
    G = np.einsum("ai,kab->kib", V, Pinv)  # (K, n, dof): v_i^T P^-1
    M = np.einsum("kib,bj->kij", G, V)  # (K, n, n): v_i^T P^-1 v_j
    norm = np.sqrt(np.einsum("kii->ki", M))
    z = np.einsum("kib,kb->ki", G, p) / norm
    best = np.argmax(np.abs(z), axis=1)
    isolated = np.where(alarm, best, -1)
    # can the best sensor be told apart from the runner-up?
    second = np.argsort(np.abs(z), axis=1)[:, -2]
    kk = np.arange(K)
    cos = M[kk, best, second] / (norm[kk, best] * norm[kk, second])
    isolable = np.abs(cos) < ISOLATION_COS
    x_excl = x_all.copy()
    stat_rest = np.full(K, np.nan)
    thr_rest = float(stats.chi2.isf(alpha, dof - 1)) if dof > 1 else float("nan")
    for i in np.unique(isolated[alarm]):
        sel = isolated == i
        use = np.arange(n) != i
        x_excl[sel] = body_estimate(H, c[sel], use)
        if dof > 1:
            Vr = parity_matrix(H[use])
            Pr = np.einsum("ai,ki,bi->kab", Vr, var[sel][:, use], Vr)
            pr = c[sel][:, use] @ Vr.T
            stat_rest[sel] = np.einsum("ki,kij,kj->k", pr, np.linalg.inv(Pr), pr)
    return FdiReport(sensor, n, dof, window, w, rate_per_hour, alpha, thr, t, stat, z, alarm,
                     isolated, isolable, x_all, x_excl, stat_rest, thr_rest,
                     np.asarray(sigma, float))
