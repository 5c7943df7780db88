"""Exports for the tools robotics and drone engineers use next (docs/export.md):
Kalibr's ``imu.yaml``, PX4 and ArduPilot parameter files.

Everything is emitted through a serialiser (PyYAML for YAML, the ``csv``
module for the parameter files), never by formatting strings, so a value or
a name can never break the file's syntax.

Kalibr (``imu.yaml``, the IMU noise model of the Kalibr wiki): continuous-time
densities, one figure per sensor (Kalibr's model is isotropic: the largest of
the three axes is written):

- ``accelerometer_noise_density`` [m/s^2/sqrt(Hz)] = VRW N [m/s/sqrt(s)]
- ``gyroscope_noise_density`` [rad/s/sqrt(Hz)] = ARW N [rad/sqrt(s)]
- ``accelerometer_random_walk`` [m/s^3/sqrt(Hz)] = rate random walk K of the
  accelerometer [m/s^2/sqrt(s)]
- ``gyroscope_random_walk`` [rad/s^2/sqrt(Hz)] = rate random walk K [rad/s/sqrt(s)]

N is read off the Allan deviation at tau = 1 s on its -1/2 slope line
(sigma(tau) = N / sqrt(tau)), K at tau = 3 s on its +1/2 line
(sigma(tau) = K sqrt(tau / 3)); the units are the same numbers. From white
noise of per-sample standard deviation sigma at sample period dt (no Allan
file): N = sigma sqrt(dt).
"""

from __future__ import annotations

import csv
import io

import numpy as np

from calib_cli.data import CalibrationResult
from calib_cli.errors import InputError

AUTOPILOT_FORMATS = ("kalibr", "px4", "ardupilot")
KALIBR_KEYS = ("accelerometer_noise_density", "accelerometer_random_walk",
               "gyroscope_noise_density", "gyroscope_random_walk", "rostopic", "update_rate")


def _num(x):
    if x is None:
        return None
    x = float(x)
    return x if np.isfinite(x) else None


def _worst(values):
    v = np.asarray(values, dtype=float)
    v = v[np.isfinite(v)]
    return float(v.max()) if len(v) else None


def kalibr_from_allan(res, rostopic: str = "/imu0") -> dict:
    """Kalibr's imu.yaml from an AllanResult (methods.allan): N and K of the
    accelerometer and gyro channels, the largest axis of each."""
    ch = list(res.channels)
    rw = res.terms["random_walk"]["value"]
    rrw = res.terms["rate_random_walk"]["value"]

    def pick(arr, sensor):
        idx = [i for i, c in enumerate(ch) if c.startswith(sensor)]
        if any(res.units[i] == "count" for i in idx):
            raise InputError(f"the {sensor} channels are in counts: Kalibr needs SI units "
                             "(fit and apply a calibration first)", "<allan>")
        return _worst([arr[i] for i in idx])

    return kalibr_dict(pick(rw, "accel"), pick(rrw, "accel"), pick(rw, "gyro"), pick(rrw, "gyro"),
                       rostopic, 1.0 / res.tau0)


def kalibr_dict(acc_nd, acc_rw, gyr_nd, gyr_rw, rostopic, rate) -> dict:
    if rate is not None:  # 100 Hz, not the 100.00000000000213 of float time stamps
        rate = float(f"{float(rate):.10g}")
    vals = (acc_nd, acc_rw, gyr_nd, gyr_rw, str(rostopic), rate)
    return {k: (v if k == "rostopic" else _num(v)) for k, v in zip(KALIBR_KEYS, vals)}


def kalibr_yaml(d: dict) -> str:
    import yaml

    assert tuple(d) == KALIBR_KEYS
    return yaml.safe_dump(d, sort_keys=False, default_flow_style=False)


def kalibr_from_raw_noise(sigma_accel, sigma_gyro, dt) -> tuple:
    """White-noise densities from per-sample standard deviations: sigma sqrt(dt)."""
    return (_worst(np.asarray(sigma_accel) * np.sqrt(dt)),
            None if sigma_gyro is None else _worst(np.asarray(sigma_gyro) * np.sqrt(dt)))


# ---------------------------------------------------------------------------
# ArduPilot's temperature calibration (INS_TCALn_*), docs/export.md
#
# From ArduPilot's libraries/AP_InertialSensor/AP_InertialSensor_tempcal.cpp:
# per IMU, INS_TCALn_ENABLE, _TMIN, _TMAX and vectors ACC1..ACC3, GYR1..GYR3,
# the coefficients of a polynomial without constant term in T - 35 degC
# (TEMP_REFERENCE), stored times 1e6 (SCALE_FACTOR):
#     P(T) = (c1 + (c2 + c3 d) d) d * 1e-6,  d = T - 35,
# applied in the sensor frame before the offsets and scales
# (AP_InertialSensor_Backend::_rotate_and_correct_accel/gyro):
#     v -= P(clamp(T)) ; v += P(clamp(CALTEMP)),  clamp to [TMIN, TMAX],
# CALTEMP being INS_ACCn_CALTEMP / INS_GYRn_CALTEMP, the temperature the
# offsets hold at. Units: m/s^2 and rad/s, as the offsets.

AP_TEMP_REFERENCE = 35.0  # degC, TEMP_REFERENCE
AP_SCALE_FACTOR = 1.0e6  # SCALE_FACTOR
AP_TCAL_ORDER = 3


def reexpand(coef, t_ref: float, t0: float = AP_TEMP_REFERENCE) -> np.ndarray:
    """B(T) = sum_k coef[:, k] (T - t_ref)^(k+1) as sum_j c[:, j] (T - t0)^j,
    j = 0..N (column 0 the constant B(t0)). coef: (3,) or (3, N)."""
    from math import comb

    b = np.asarray(coef, dtype=float).reshape(3, -1)
    n = b.shape[1]
    delta = t0 - t_ref
    c = np.zeros((3, n + 1))
    for k in range(1, n + 1):  # (v + delta)^k = sum_j C(k, j) v^j delta^(k - j)
        for j in range(k + 1):
            c[:, j] += b[:, k - 1] * comb(k, j) * delta ** (k - j)
    return c


def ap_poly(params_c: np.ndarray, temp, tmin: float, tmax: float) -> np.ndarray:
    """ArduPilot's polynomial_eval at clamp(temp): params_c (3, 3) as stored (x 1e6)."""
    d = np.clip(np.asarray(temp, float), tmin, tmax) - AP_TEMP_REFERENCE
    c = np.asarray(params_c, float) / AP_SCALE_FACTOR
    return ((c[:, 0][:, None] + (c[:, 1][:, None] + c[:, 2][:, None] * d) * d) * d).T


def ardupilot_tcal(cal: CalibrationResult, instance: int, path: str):
    """({sensor: (3, 3) stored coefficients}, tmin, tmax, caltemp, {sensor: bias at
    caltemp}) of a thermal calibration, or None without bias drift terms."""
    p, st = cal.params, cal.stats
    sensors = [s for s in ("accel", "gyro")
               if np.any(np.nan_to_num(np.asarray(p.get(f"{s}_temp_bias", 0.0), float)))]
    if not sensors:
        return None
    if not 0 <= instance <= 2:
        raise InputError("ArduPilot holds temperature calibrations for IMUs 1-3 "
                         "(INS_TCAL1..3): use --instance 0, 1 or 2", path)
    coef = {s: np.asarray(p[f"{s}_temp_bias"], float).reshape(3, -1) for s in sensors}
    if max(c.shape[1] for c in coef.values()) > AP_TCAL_ORDER:
        raise InputError("ArduPilot's temperature polynomials are third order at most", path)
    t_ref = float(st.get("temp_ref_degC", 25.0))
    rng = st.get("temp_range_degC") or [t_ref, t_ref]
    tmin, tmax = float(rng[0]), float(rng[1])
    # the offsets hold at CALTEMP; ArduPilot clamps it to [TMIN, TMAX] too
    caltemp = float(np.clip(t_ref, tmin, tmax))
    stored, bias_at = {}, {}
    for s, c in coef.items():
        e = reexpand(c, t_ref)  # the constant e[:, 0] cancels between T and CALTEMP
        full = np.zeros((3, AP_TCAL_ORDER))
        full[:, :e.shape[1] - 1] = e[:, 1:]
        stored[s] = full * AP_SCALE_FACTOR
        from calib_cli.model.effects import temp_poly

        bias_at[s] = np.asarray(p[f"{s}_bias"], float) + temp_poly(c, np.array([caltemp - t_ref]))[0]
    return stored, tmin, tmax, caltemp, bias_at


# ---------------------------------------------------------------------------
# PX4 / ArduPilot: per-axis offsets and scales


def _diag_model(cal: CalibrationResult, sensor: str, path: str):
    """(offset, scale, dropped) with f = (raw - offset) * scale per axis, the
    autopilots' model; ``dropped``: what the model cannot hold."""
    p = cal.params
    if cal.raw_units.get(sensor, "m/s^2" if sensor == "accel" else "rad/s") == "count":
        raise InputError(f"the {sensor} calibration is in counts; the autopilot's parameters "
                         "are in SI units", path)
    dropped = {}
    bias = p.get(f"{sensor}_bias")
    K = p.get(f"{sensor}_K")
    if bias is None:
        return None, None, dropped
    bias = np.asarray(bias, dtype=float).reshape(3)
    for k in (f"{sensor}_temp_bias", f"{sensor}_temp_scale"):  # docs/thermal.md
        v = np.nan_to_num(np.asarray(p.get(k, 0.0), dtype=float))
        if np.any(v != 0):
            if k.endswith("temp_scale"):
                rng = cal.stats.get("temp_range_degC") or [0.0, 0.0]
                t_ref = float(cal.stats.get("temp_ref_degC", 25.0))
                from calib_cli.model.effects import temp_poly

                dts = np.linspace(float(rng[0]), float(rng[1]), 51) - t_ref
                size = float(np.abs(temp_poly(v.reshape(3, -1), dts)).max())
                dropped[f"{k}: scale-factor change with temperature (not held by the "
                        "autopilot; largest relative change over the calibrated range)"] = size
            else:
                dropped[f"{k}: temperature terms (the values at T_ref are written; largest "
                        "coefficient)"] = float(np.abs(v).max())
    if K is None:
        return bias, np.ones(3), dropped
    K = np.asarray(K, dtype=float).reshape(3, 3)
    Kinv = np.linalg.inv(K)
    off = Kinv - np.diag(np.diag(Kinv))
    if np.any(off != 0):
        dropped[f"{sensor} cross-axis/misalignment (largest off-diagonal of K^-1)"] = \
            float(np.abs(off).max())
    if sensor == "gyro" and "gyro_D" in p and np.any(np.asarray(p["gyro_D"]) != 0):
        dropped["gyro g-sensitivity D (largest entry, (rad/s)/(m/s^2))"] = \
            float(np.abs(np.asarray(p["gyro_D"])).max())
    return bias, np.diag(Kinv).copy(), dropped


def autopilot_params(cal: CalibrationResult, target: str, instance: int = 0,
                     path: str = "<calibration>") -> tuple[list[tuple[str, float]], list[str]]:
    """(parameters [(name, value)], notes) for ``target`` px4 or ardupilot."""
    a_off, a_scale, dropped = _diag_model(cal, "accel", path)
    g_off, g_scale, g_dropped = _diag_model(cal, "gyro", path)
    dropped.update(g_dropped)
    if a_off is None and g_off is None:
        raise InputError("no accel_bias or gyro_bias in the calibration", path)
    params: list[tuple[str, float]] = []
    notes: list[str] = []
    axes = "XYZ"
    if target == "px4":
        for i in range(3):
            if a_off is not None:
                params.append((f"CAL_ACC{instance}_{axes[i]}OFF", float(a_off[i])))
        for i in range(3):
            if a_scale is not None:
                params.append((f"CAL_ACC{instance}_{axes[i]}SCALE", float(a_scale[i])))
        for i in range(3):
            if g_off is not None:
                params.append((f"CAL_GYRO{instance}_{axes[i]}OFF", float(g_off[i])))
        notes.append(f"set CAL_ACC{instance}_ID and CAL_GYRO{instance}_ID to the sensors' "
                     "device ids (sensor_accel/sensor_gyro device_id in a ULog)")
    elif target == "ardupilot":
        n = "" if instance == 0 else str(instance + 1)
        tcal = ardupilot_tcal(cal, instance, path)
        if tcal is not None:  # the bias drift goes to INS_TCALn_*, offsets at CALTEMP
            stored, tmin, tmax, caltemp, bias_at = tcal
            for s in stored:
                dropped = {k: v for k, v in dropped.items() if not k.startswith(f"{s}_temp_bias")}
            a_off = bias_at.get("accel", a_off)
            g_off = bias_at.get("gyro", g_off)
        for i in range(3):
            if a_off is not None:
                params.append((f"INS_ACC{n}OFFS_{axes[i]}", float(a_off[i])))
        for i in range(3):
            if a_scale is not None:
                params.append((f"INS_ACC{n}SCAL_{axes[i]}", float(a_scale[i])))
        for i in range(3):
            if g_off is not None:
                params.append((f"INS_GYR{n}OFFS_{axes[i]}", float(g_off[i])))
        notes.append("ArduPilot re-learns the gyro offsets at every boot unless INS_GYR_CAL = 0")
        if tcal is not None:
            m = instance + 1
            params.append((f"INS_TCAL{m}_ENABLE", 1.0))
            params.append((f"INS_TCAL{m}_TMIN", tmin))
            params.append((f"INS_TCAL{m}_TMAX", tmax))
            for s, short in (("accel", "ACC"), ("gyro", "GYR")):
                c = stored.get(s, np.zeros((3, 3)))
                for k in range(AP_TCAL_ORDER):
                    for i in range(3):
                        params.append((f"INS_TCAL{m}_{short}{k + 1}_{axes[i]}", float(c[i, k])))
            for s, short in (("accel", "ACC"), ("gyro", "GYR")):
                if s in stored:
                    params.append((f"INS_{short}{m}_CALTEMP", caltemp))
            notes.append(
                f"INS_TCAL{m}_*: the bias-drift polynomials re-expanded about ArduPilot's "
                f"fixed 35 degC reference (AP_InertialSensor_tempcal.cpp: third order, no "
                f"constant term, times 1e6), valid over TMIN..TMAX = {tmin:g}..{tmax:g} degC; "
                f"the offsets hold at INS_*_CALTEMP = {caltemp:g} degC; scale terms are not "
                "held (see below)")
            if "gyro" in stored:
                notes.append("with INS_GYR_CAL = 1 ArduPilot re-learns the gyro offsets at "
                             "boot and sets INS_GYRn_CALTEMP to that temperature itself")
    else:
        raise InputError(f"unknown autopilot {target!r}", path)
    if g_scale is not None and np.any(np.abs(g_scale - 1) > 0):
        dropped["gyro scale factors (largest |1/G_ii - 1|)"] = float(np.abs(g_scale - 1).max())
    for what, size in dropped.items():
        notes.append(f"not representable, dropped: {what} = {size:.3g}")
    return params, notes


def params_file(params, notes, target: str, source: str) -> str:
    """A QGroundControl parameter file (px4: vehicle, component, name, value,
    type, tab separated) or a Mission Planner .parm file (ardupilot: NAME,VALUE),
    with the notes as comment lines."""
    buf = io.StringIO()
    w = csv.writer(buf, delimiter="\t" if target == "px4" else ",", lineterminator="\n")
    for line in [f"calib export from {source}"] + notes:
        buf.write("# " + line.replace("\n", " ").replace("\r", " ") + "\n")
    for name, value in params:
        if target == "px4":
            w.writerow([1, 1, name, repr(float(value)), 9])  # 9: MAV_PARAM_TYPE_REAL32
        else:
            w.writerow([name, repr(float(value))])
    return buf.getvalue()


def export_for_tool(cal: CalibrationResult, fmt: str, source: str, path: str,
                    allan=None, raw=None, rostopic: str = "/imu0", instance: int = 0,
                    rate: float | None = None) -> tuple[str, list[str]]:
    """(text, warnings) of ``fmt`` in AUTOPILOT_FORMATS. kalibr: noise
    densities and random walks from ``allan`` (an AllanResult); without it,
    densities from ``raw`` (a Recording: pooled within-position noise) and
    random walks null."""
    warnings: list[str] = []
    if fmt == "kalibr":
        if allan is not None:
            d = kalibr_from_allan(allan, rostopic)
        else:
            acc_nd = gyr_nd = None
            if raw is not None and raw.static_segments():
                from calib_cli.methods.segstats import static_stats

                dt = 1.0 / raw.sample_rate
                sa = static_stats(raw, "accel").sigma
                sg = static_stats(raw, "gyro").sigma if raw.gyro is not None else None
                acc_nd, gyr_nd = kalibr_from_raw_noise(sa, sg, dt)
                rate = raw.sample_rate
            else:
                warnings.append("no noise figures: give --allan ALLAN.h5 (or --raw RAW.h5 for "
                                "the noise densities)")
            warnings.append("random walks null: they need an Allan analysis (--allan ALLAN.h5)")
            d = kalibr_dict(acc_nd, None, gyr_nd, None, rostopic, rate)
        return kalibr_yaml(d), warnings
    params, notes = autopilot_params(cal, fmt, instance, path)
    return params_file(params, notes, fmt, source), warnings
