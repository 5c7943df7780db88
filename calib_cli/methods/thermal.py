"""Thermal calibration: bias and scale polynomial in T - T_ref on top of the
static model (docs/thermal.md).

Data: the static segments with known attitudes, at several temperatures
(soak steps) and/or while the temperature ramps. Each segment is cut into
blocks of ``BLOCK_S`` seconds; a block's mean output, mean temperature and
mean-noise (white sample noise / n) are what the fit sees, so a ramp
contributes a point every ``BLOCK_S`` seconds.

Model (the catalogue's, CONTRACT.md section 7):

    A_i = b_i + sum_k bT_ik dT^(k+1) + (1 + sum_k sT_ik dT^(k+1)) (K f)_i
    W_i = d_i + sum_k dT_ik dT^(k+1) + (G w)_i

G is the identity, or the base calibration's (``base``); static positions
do not determine it, nor the gyro scale drift (``gyro_temp_scale`` is null
and listed in stats.unobservable: it needs a rate table in the chamber).
With ``thermal_lag`` the sensing elements see the first-order lag of the
recorded temperature (``effects.lag_temperature``) and tau is estimated.

Warm-up rule: a static segment is a soak when its temperature over the last
quarter moves by less than SOAK_RATE degC/min, or by less than a fifth of
its fastest rate over any tenth of the segment (it is settling); its samples before the
temperature last leaves the band +-WARMUP_TOL degC about its final value
(median of the last 10 %) are the warm-up and are not used.

Order: N in 1..3 by the Bayesian information criterion unless given.

Hysteresis: blocks where the temperature rises faster than RAMP_RATE
degC/min (heating) or falls faster (cooling); over the temperature range
both branches cover, the mean residual of the heating blocks minus that of
the cooling blocks, per axis and sensor, with its sigma from the noise.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from calib_cli.data import CalibrationResult, Recording
from calib_cli.errors import EstimationError
from calib_cli.methods import lsq
from calib_cli.methods.noise import difference_sigma
from calib_cli.methods.result import build_result
from calib_cli.model.effects import (
    TEMP_REF_C,
    Bias,
    Layout,
    ScaleMisalignment,
    TemperatureDrift,
    ThermalLag,
    lag_temperature,
)
from calib_cli.model.frames import attitude_to_rotation
from calib_cli.model.imu_model import ImuModel, Packing
from calib_cli.model.kinematics import from_attitude

BLOCK_S = 10.0  # s, block length
SOAK_RATE = 0.1  # degC/min: a segment whose last quarter moves less is a soak
WARMUP_TOL = 0.2  # degC: warm-up ends when the temperature stays within this of its final value
RAMP_RATE = 0.1  # degC/min: heating / cooling blocks for the hysteresis
MIN_BLOCK = 10  # samples
ORDERS = (1, 2, 3)
TAU0 = 120.0  # s, start of the lag estimate


@dataclass(frozen=True)
class Blocks:
    """Block means of the usable samples."""

    start: np.ndarray  # (M,) first sample index
    stop: np.ndarray  # (M,) one past the last
    t: np.ndarray  # (M,) mean time
    temp: np.ndarray  # (M,) mean recorded temperature
    rate: np.ndarray  # (M,) temperature rate, degC/s (smoothed)
    accel: np.ndarray  # (M, 3)
    gyro: np.ndarray | None  # (M, 3)
    counts: np.ndarray  # (M,)
    rots: object  # Rotation, one per block
    seg: np.ndarray  # (M,) segment index
    warmup_s: float  # excluded warm-up, s in total


def make_blocks(rec: Recording, block_s: float = BLOCK_S) -> Blocks:
    if rec.temp is None:
        raise EstimationError("the recording has no temperature column: a thermal fit needs "
                              "the unit's temperature (`temp`)")
    segs = [s for s in rec.static_segments() if s.n >= MIN_BLOCK]
    missing = [s.label for s in segs if s.attitude is None]
    if missing:
        raise EstimationError("the thermal fit needs known attitudes; static segments without "
                              f"attitude_deg: {', '.join(missing[:5])}")
    if not segs:
        raise EstimationError("the recording has no static segments to fit")
    fs = rec.sample_rate
    nb = max(int(round(block_s * fs)), MIN_BLOCK)
    T = np.asarray(rec.temp, float)
    t = np.asarray(rec.time, float)
    starts, stops, seg_idx, warm = [], [], [], 0.0
    for k, s in enumerate(segs):
        a, b = s.start, s.stop
        q = a + 3 * (b - a) // 4
        tq = t[q:b]
        if len(tq) > 2 and tq[-1] > tq[0]:
            slope = np.polyfit(tq - tq[0], T[q:b], 1)[0] * 60.0
            edges = np.linspace(a, b - 1, 11).astype(int)
            tenths = np.abs(np.diff(T[edges]) / np.maximum(np.diff(t[edges]), 1e-9)) * 60.0
            if abs(slope) < SOAK_RATE or abs(slope) < tenths.max() / 5:  # a soak: drop its warm-up
                tail = T[b - max((b - a) // 10, 1):b]
                out = np.flatnonzero(np.abs(T[a:b] - np.median(tail)) > WARMUP_TOL)
                if len(out):
                    a2 = min(a + int(out[-1]) + 1, b)
                    warm += t[a2 - 1] - t[a] if a2 > a else 0.0
                    a = a2
        for c in range(a, b - nb + 1, nb):
            starts.append(c)
            stops.append(c + nb)
            seg_idx.append(k)
        if (b - a) % nb >= MIN_BLOCK and (b - a) >= nb:  # the tail joins the last block
            stops[-1] = b
        elif b - a < nb and b - a >= MIN_BLOCK:
            starts.append(a)
            stops.append(b)
            seg_idx.append(k)
    if not starts:
        raise EstimationError("no static data left after the warm-up of each soak")
    starts, stops = np.array(starts), np.array(stops)
    counts = (stops - starts).astype(float)

    def bmean(x):
        cs = np.concatenate([np.zeros((1,) + x.shape[1:]), np.cumsum(x, axis=0)])
        return (cs[stops] - cs[starts]) / (counts if x.ndim == 1 else counts[:, None])

    # temperature rate: slope of a 60 s (or block) window about each block
    half = max(int(30 * fs), nb // 2)
    lo = np.clip((starts + stops) // 2 - half, 0, len(t) - 1)
    hi = np.clip((starts + stops) // 2 + half, 0, len(t) - 1)
    rate = (T[hi] - T[lo]) / np.maximum(t[hi] - t[lo], 1e-9)
    seg_idx = np.array(seg_idx)
    att = np.array([segs[k].attitude for k in seg_idx])
    return Blocks(starts, stops, bmean(t), bmean(T), rate, bmean(rec.accel),
                  None if rec.gyro is None else bmean(rec.gyro), counts,
                  attitude_to_rotation(att), seg_idx, float(warm))


@dataclass(frozen=True)
class _Problem:
    model: ImuModel  # without the lag (applied to the sample series here)
    full: ImuModel  # what the result records
    packing: Packing
    base: dict
    sensors: tuple


def _problem(order, temp_ref, sensors, lag, base_params) -> _Problem:
    eff = []
    if "accel" in sensors:
        eff += [Bias("accel"), ScaleMisalignment("accel", "full"),
                TemperatureDrift("accel", order=order, temp_ref=temp_ref)]
    if "gyro" in sensors:
        eff += [Bias("gyro")]
        if base_params and "gyro_K" in base_params:
            eff += [ScaleMisalignment("gyro", "full")]
        eff += [TemperatureDrift("gyro", order=order, temp_ref=temp_ref)]
    model = ImuModel(tuple(eff), Layout())
    full = model.with_effect(ThermalLag()) if lag else model
    fixed = ["gyro_temp_scale", "gyro_K"]
    if base_params and "accel_K" in base_params and "accel" in sensors:
        fixed.append("accel_K")
    packing = Packing.for_model(full, fixed_keys=fixed)
    base = full.neutral_params()
    if lag:
        base["thermal_lag_tau"] = np.array(TAU0)
    for k in ("accel_K", "gyro_K"):
        if base_params and k in base_params:
            base[k] = np.asarray(base_params[k], float)
    return _Problem(model, full, packing, base, tuple(sensors))


def _fit_one(rec, bl: Blocks, prob: _Problem, sig: dict, start: dict | None):
    kin0 = from_attitude(bl.t, bl.rots, rec.site)
    cs_counts = bl.counts
    ys = {s: getattr(bl, s) for s in prob.sensors}
    lag = prob.full.has("thermal_lag")
    t_all, T_all = np.asarray(rec.time, float), np.asarray(rec.temp, float)

    def block_temp(tau):
        if not lag:
            return bl.temp
        Tm = lag_temperature(t_all, T_all, tau)
        cs = np.concatenate([[0.0], np.cumsum(Tm)])
        return (cs[bl.stop] - cs[bl.start]) / cs_counts

    def predict(p):
        kin = kin0.with_(temp=block_temp(float(p["thermal_lag_tau"])) if lag else bl.temp)
        return prob.model.predict(p, kin, sensors=prob.sensors)

    w = {s: np.sqrt(cs_counts)[:, None] / sig[s][None, :] for s in prob.sensors}

    def resid(theta):
        p = prob.packing.unpack(theta, prob.base)
        out = predict(p)
        return np.concatenate([((ys[s] - out[s]) * w[s]).ravel() for s in prob.sensors])

    p0 = dict(prob.base)
    if start:
        for k, v in start.items():
            if k in p0:
                v = np.asarray(v, float)
                if v.shape == p0[k].shape:
                    p0[k] = v
                elif v.ndim >= 1 and p0[k].ndim == 2:  # a lower order start: pad
                    v2 = np.zeros(p0[k].shape)
                    vv = v if v.ndim == 2 else v[:, None]
                    m = min(vv.shape[1], v2.shape[1])
                    v2[:, :m] = vv[:, :m]
                    p0[k] = v2
    else:  # ordinary least squares on [1, f] per axis (temperature terms 0)
        if "accel" in prob.sensors:
            H = np.column_stack([np.ones(len(bl.t)), kin0.f])
            coef = np.linalg.lstsq(H, bl.accel, rcond=None)[0]
            p0["accel_bias"] = coef[0]
            if "accel_K" in [s.key for s in prob.packing.specs]:
                p0["accel_K"] = coef[1:].T
        if "gyro" in prob.sensors:
            p0["gyro_bias"] = bl.gyro.mean(0) - (kin0.w @ np.asarray(p0.get(
                "gyro_K", np.eye(3))).T).mean(0)
    theta0 = prob.packing.pack(p0)
    scales = prob.packing.scales()
    fit = lsq.fit(resid, theta0, scales, what="thermal fit")
    p = prob.packing.unpack(fit.theta, prob.base)
    out = predict(p)
    res = {s: ys[s] - out[s] for s in prob.sensors}
    return fit, p, res, block_temp(float(p["thermal_lag_tau"])) if lag else bl.temp


def hysteresis(bl: Blocks, res: np.ndarray, sig_block: np.ndarray, temp: np.ndarray):
    """Mean residual heating minus cooling over the common temperature range
    (per axis) and its sigma; (None, None) without both branches."""
    rate = bl.rate * 60.0
    h, c = rate > RAMP_RATE, rate < -RAMP_RATE
    if h.sum() < 2 or c.sum() < 2:
        return None, None, None
    lo = max(temp[h].min(), temp[c].min())
    hi = min(temp[h].max(), temp[c].max())
    if not hi > lo:
        return None, None, None
    h &= (temp >= lo) & (temp <= hi)
    c &= (temp >= lo) & (temp <= hi)
    if h.sum() < 2 or c.sum() < 2:
        return None, None, None
    d = res[h].mean(0) - res[c].mean(0)
    var = (sig_block[h] ** 2).sum(0) / h.sum() ** 2 + (sig_block[c] ** 2).sum(0) / c.sum() ** 2
    return d, np.sqrt(var), [float(lo), float(hi)]


def fit_thermal(rec: Recording, order: int | None = None, temp_ref: float = TEMP_REF_C,
                sensors=("accel", "gyro"), base: CalibrationResult | None = None,
                lag: bool = False, noise: dict | None = None) -> CalibrationResult:
    """``calib fit thermal`` (pure): see the module docstring. ``noise``: the
    per-sample white noise per sensor ({"accel": (3,), "gyro": (3,)}) instead of
    the estimate from the data (``plan check`` predicts on noise-free data)."""
    if rec.layout.redundant:
        raise EstimationError("thermal fit: triads only (a redundant unit is not supported yet)")
    if any(rec.in_counts(s) for s in sensors):
        raise EstimationError("thermal fit: the recording is in raw counts; import it in SI units")
    sensors = tuple(s for s in sensors if s == "accel" or rec.gyro is not None)
    if not sensors:
        raise EstimationError("thermal fit: no sensor to fit")
    bl = make_blocks(rec)
    span = float(bl.temp.max() - bl.temp.min())
    if span < 5.0:
        raise EstimationError(f"the usable data spans only {span:.1f} degC of temperature; a "
                              "thermal fit needs several temperatures (soak steps or a ramp)")
    parts = [(int(a), int(b)) for a, b in zip(bl.start, bl.stop)]
    # first differences: white noise on the slow temperature trend (methods/noise.py)
    sig = {s: (np.broadcast_to(np.asarray(noise[s], float), (3,)).copy() if noise is not None
               else difference_sigma(getattr(rec, s), 1, parts, robust="std")) for s in sensors}
    base_params = None if base is None else {k: np.asarray(v, float)
                                             for k, v in base.params.items()}
    if base_params is not None and "accel_bias" in base_params and "accel" in sensors:
        start0 = {k: v for k, v in base_params.items() if k in ("accel_bias", "gyro_bias")}
    else:
        start0 = None
    n_res = len(bl.t) * 3 * len(sensors)
    tried, best = {}, None
    for N in ([order] if order else ORDERS):
        prob = _problem(N, temp_ref, sensors, lag, base_params)
        fit, p, res, Tm = _fit_one(rec, bl, prob, sig, best[2] if best else start0)
        k = int((~fit.unobservable).sum())
        bic = fit.chi2 + k * np.log(n_res)
        tried[N] = {"chi2": fit.chi2, "n_params": k, "bic": float(bic)}
        if best is None or bic < best[4]:
            best = (N, prob, p, (fit, res, Tm), bic)
        elif order is None:
            break  # BIC rose: higher orders are not tried
    N, prob, p, (fit, res, Tm), _ = best
    fit, inflation = fit.inflated()
    stats = {
        "method": "thermal", "temp_order": int(N), "temp_order_bic": {str(k): v for k, v in
                                                                      tried.items()},
        "temp_ref_degC": float(temp_ref),
        "temp_range_degC": [float(bl.temp.min()), float(bl.temp.max())],
        "warmup_excluded_s": bl.warmup_s, "n_blocks": int(len(bl.t)),
        "block_s": BLOCK_S, "chi2_dof": fit.chi2_dof, "sigma_inflation": inflation,
        "thermal_lag": bool(lag),
    }
    hyst, hsig, rng = {}, {}, None
    for s in sensors:
        stats[f"{s}_residual_rms"] = float(np.sqrt(np.mean(res[s] ** 2)))
        stats[f"{s}_noise_sigma"] = sig[s].tolist()
        sb = sig[s][None, :] / np.sqrt(bl.counts)[:, None]
        d, ds, r = hysteresis(bl, res[s], sb, bl.temp)
        hyst[s] = None if d is None else d.tolist()
        hsig[s] = None if ds is None else ds.tolist()
        rng = r or rng
    stats["temp_hysteresis"] = hyst
    stats["temp_hysteresis_sigma"] = hsig
    stats["temp_hysteresis_range_degC"] = rng
    if "accel" in sensors:
        from calib_cli.model.correction import correct

        f = correct(prob.model, p, "accel", bl.accel, temp=Tm)
        g = rec.site.gravity
        before = np.linalg.norm(bl.accel, axis=1) - g
        after = np.linalg.norm(f, axis=1) - g
        stats["g_reference"] = g
        stats["g_error_rms_before"] = float(np.sqrt(np.mean(before ** 2)))
        stats["g_error_rms_after"] = float(np.sqrt(np.mean(after ** 2)))
    extra_unobs = []
    if "gyro" in sensors:
        extra_unobs = [f"gyro_temp_scale[{i}]" for i in range(3)] if N == 1 else \
            [f"gyro_temp_scale[{i},{k}]" for i in range(3) for k in range(N)]
    tables = {"block_temp": bl.temp, "block_t": bl.t, "block_rate": bl.rate,
              "block_segment": bl.seg.astype(float)}
    for s in sensors:
        tables[f"block_{s}"] = getattr(bl, s)
        tables[f"block_{s}_resid"] = res[s]
    result = build_result("thermal", prob.full, prob.packing, fit, prob.base,
                          rec.units, stats, serial=rec.serial,
                          residuals={s: res[s] for s in sensors}, tables=tables,
                          extra_unobservable=extra_unobs)
    if "gyro" in sensors:
        shape = result.params["gyro_temp_bias"].shape
        result.params["gyro_temp_scale"] = np.zeros(shape)
        result.sigma["gyro_temp_scale"] = np.full(shape, np.nan)
        result.units["gyro_temp_scale"] = "1/degC^k"
    for k in ("accel_K", "gyro_K"):
        if base is not None and k in prob.base and k in base.params and k not in result.params \
                and prob.full.has("scale_misalignment", k.split("_")[0]):
            result.params[k] = np.asarray(base.params[k], float)
            result.sigma[k] = np.asarray(base.sigma.get(k, np.full((3, 3), np.nan)), float)
            result.units[k] = base.units.get(k, "-")
    return result
