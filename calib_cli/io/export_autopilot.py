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
