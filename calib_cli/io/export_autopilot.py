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
from calib_cli.errors import CalibError, InputError
from calib_cli.io import fc_params

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
# PX4 / ArduPilot parameters (docs/export.md)
#
# Both firmwares correct each sensor in its own frame, then rotate
# (io/fc_params.py writes their equations out):  y = R S (x - o - thermal(T)).
# A fit on logged data y gives  y = b + B(T) + K f  (contract section 2, bias
# drift B with B(T_ref) = 0), so  f = K^-1 (y - b - B(T))
#   = K^-1 R S (x - o - thermal(T) - S^-1 R^T (b + B(T))).
# The firmware can hold  f = R S' (x - o' - thermal'(T))  with
#   S' = diag(R^T K^-1 R S)     (the off-diagonal of R^T K^-1 R S is dropped)
#   o' + thermal'(T) = o + thermal(T) + S^-1 R^T (b + B(T))      (exact)
# which is PX4's own update (Accelerometer.hpp BiasCorrectedSensorOffset:
# "existing offset + bias rotated to sensor frame and unscaled"). For raw data
# (o, thermal) = 0 and S = R = I: the absolute calibration.

AP_TEMP_REFERENCE = fc_params.AP_TEMP_REFERENCE
AP_SCALE_FACTOR = fc_params.AP_SCALE_FACTOR
AP_TCAL_ORDER = fc_params.TCAL_ORDER


class UsageProblem(CalibError):
    """An option the firmware has no parameters for (exit 2)."""

    exit_code = 2


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


def _drift(p: dict, sensor: str):
    """The bias drift coefficients (3, N) of a thermal fit, or None."""
    v = p.get(f"{sensor}_temp_bias")
    if v is None:
        return None
    v = np.nan_to_num(np.asarray(v, dtype=float)).reshape(3, -1)
    return v if np.any(v != 0) else None


def _scale_drift_note(cal: CalibrationResult, sensor: str, dropped: dict) -> None:
    v = np.nan_to_num(np.asarray(cal.params.get(f"{sensor}_temp_scale", 0.0), dtype=float))
    if np.any(v != 0):
        from calib_cli.model.effects import temp_poly

        rng = cal.stats.get("temp_range_degC") or [0.0, 0.0]
        t_ref = float(cal.stats.get("temp_ref_degC", 25.0))
        dts = np.linspace(float(rng[0]), float(rng[1]), 51) - t_ref
        size = float(np.abs(temp_poly(v.reshape(3, -1), dts)).max())
        dropped[f"{sensor}_temp_scale: scale-factor change with temperature (not held by the "
                "autopilot; largest relative change over the calibrated range)"] = size


def _check_triad(cal: CalibrationResult, path: str) -> None:
    for sensor in ("accel", "gyro"):
        b = cal.params.get(f"{sensor}_bias")
        if b is not None and np.asarray(b).size != 3 or cal.method == "rimu":
            n = np.asarray(b).size if b is not None else "n"
            raise InputError(f"a redundant-unit (RIMU) calibration of {n} single-axis sensors "
                             "has no per-axis triad offsets and scales for an autopilot: export "
                             "it as json, yaml, csv or c-header", path)
        if cal.raw_units.get(sensor, "m/s^2" if sensor == "accel" else "rad/s") == "count" \
                and b is not None:
            raise InputError(f"the {sensor} calibration is in counts; the autopilot's parameters "
                             "are in SI units", path)


def compose(old: fc_params.SensorCal, firmware: str, sensor: str, cal: CalibrationResult,
            path: str, shared_range=None) -> tuple[fc_params.SensorCal, dict]:
    """The firmware parameters that apply ``cal`` on top of ``old`` (the
    calibration in force when the data was logged; identity for raw data), and
    {what is dropped: its size}. Module comment above for the algebra."""
    p, st = cal.params, cal.stats
    R, S, o = old.R, old.scale, old.offset
    dropped: dict = {}
    bias = np.asarray(p[f"{sensor}_bias"], dtype=float).reshape(3)
    K = p.get(f"{sensor}_K")
    Kinv = np.eye(3) if K is None else np.linalg.inv(np.asarray(K, dtype=float).reshape(3, 3))
    # the whole correction in the sensor frame: R^T K^-1 R S; the firmware holds its diagonal
    A = (R.T @ Kinv @ R) * S[None, :]
    off = A - np.diag(np.diag(A))
    inv = "K^-1" if sensor == "accel" else "G^-1"
    if np.any(off != 0):
        where = "" if fc_params.is_axis_permutation(R) and np.allclose(R, np.eye(3)) else \
            " in the sensor frame"
        dropped[f"{sensor} cross-axis/misalignment (largest off-diagonal of {inv}{where})"] = \
            float(np.abs(off).max())
    if sensor == "accel":
        scale = np.diag(A).copy()
    else:
        scale = np.ones(3)
        g = np.diag(A)
        if np.any(np.abs(g - 1) > 0):
            dropped["gyro scale factors (largest |(G^-1)_ii - 1|: neither autopilot has a gyro "
                    "scale parameter)"] = float(np.abs(g - 1).max())
        D = p.get("gyro_D")
        if D is not None and np.any(np.asarray(D) != 0):
            dropped["gyro g-sensitivity D (largest entry, (rad/s)/(m/s^2))"] = \
                float(np.abs(np.asarray(D)).max())
    _scale_drift_note(cal, sensor, dropped)
    to_sensor = R.T / S[:, None]  # logged-frame offsets -> sensor-frame offsets: S^-1 R^T
    offset = o + to_sensor @ bias
    B = _drift(p, sensor)
    thermal = old.thermal
    if B is not None:
        t_ref = float(st.get("temp_ref_degC", 25.0))
        rng = st.get("temp_range_degC") or [t_ref, t_ref]
        lo, hi = float(rng[0]), float(rng[1])
        Bs = to_sensor @ B  # the drift's coefficient vectors in the sensor frame
        thermal, offset = _thermal(old.thermal, firmware, sensor, Bs, t_ref, lo, hi, offset,
                                   path, shared_range, old.slot)
    new = fc_params.SensorCal(offset, scale, np.eye(3), thermal, old.device_id, old.slot)
    return new, dropped


def _thermal(old, firmware, sensor, Bs, t_ref, lo, hi, offset, path, shared_range, slot):
    """(new Thermal, new offset) holding old thermal(T) + Bs(T) (Bs: (3, N) in T - t_ref,
    zero at t_ref) over the fitted range [lo, hi]."""
    from calib_cli.model.effects import temp_poly

    order = Bs.shape[1]
    if old is not None and (lo < old.tmin - 1e-9 or hi > old.tmax + 1e-9):
        raise fc_params.CompositionError(
            f"the {sensor} temperature calibration in force holds over {old.tmin:g}..{old.tmax:g} "
            f"degC, the fit over {lo:g}..{hi:g} degC: the firmware clamps each polynomial to "
            "its range, so their sum is not one polynomial")
    if firmware == "px4":
        if old is None:
            if order > fc_params.TCAL_ORDER:
                raise InputError("PX4's temperature polynomials (TC_*_X0..X3) are third order "
                                 "at most", path)
            coef = np.zeros((3, fc_params.TCAL_ORDER + 1))
            coef[:, 1:order + 1] = Bs
            return fc_params.Thermal("px4", coef, lo, hi, t_ref, slot), offset
        e = reexpand(Bs, t_ref, old.tref)  # about the TREF in force: X0 + X1 d + ...
        if e.shape[1] - 1 > fc_params.TCAL_ORDER:
            raise InputError("PX4's temperature polynomials are third order at most", path)
        coef = np.array(old.coef, dtype=float)
        coef[:, 1:e.shape[1]] += e[:, 1:]
        return fc_params.Thermal("px4", coef, old.tmin, old.tmax, old.tref, old.slot), \
            offset + e[:, 0]
    # ArduPilot: P(T) - P(CALTEMP), P without constant term in T - 35, times 1e6
    if order > fc_params.TCAL_ORDER:
        raise InputError("ArduPilot's temperature polynomials are third order at most", path)
    e = reexpand(Bs, t_ref)
    stored = np.zeros((3, fc_params.TCAL_ORDER))
    stored[:, :order] = e[:, 1:] * AP_SCALE_FACTOR
    if old is None:
        tmin, tmax = shared_range or (lo, hi)
        caltemp = float(np.clip(t_ref, tmin, tmax))  # ArduPilot clamps CALTEMP too
        return (fc_params.Thermal("ardupilot", stored, tmin, tmax, caltemp, slot),
                offset + temp_poly(Bs, np.array([caltemp - t_ref]))[0])
    caltemp = float(np.clip(old.tref, old.tmin, old.tmax))
    return (fc_params.Thermal("ardupilot", np.asarray(old.coef, float) + stored, old.tmin,
                              old.tmax, old.tref, old.slot),
            offset + temp_poly(Bs, np.array([caltemp - t_ref]))[0])


def _mode(source: dict, target: str, residual: bool, in_force: dict | None) -> str:
    """absolute | composed | residual | unknown (no origin recorded)."""
    if residual:
        return "residual"
    if in_force is not None:
        return "composed"
    samples = source.get("samples")
    if samples == "corrected":
        return "composed"
    if samples == "raw":
        return "absolute"
    return "unknown"


def autopilot_export(cal: CalibrationResult, target: str, instance: int | None = None,
                     path: str = "<calibration>", source: dict | None = None,
                     residual: bool = False, in_force: dict | None = None) -> tuple:
    """(parameters [(name, value)], notes, meta) for ``target`` px4 or ardupilot.

    ``source``: the calibration's /source (io/h5.read_source); a fit on data the
    firmware had already corrected is composed with the parameters in force
    (``in_force`` overrides the log's) unless ``residual``. ``meta``: what the
    --json object reports (mode, instance, parameters in force, dropped terms)."""
    if target not in fc_params.FIRMWARES:
        raise InputError(f"unknown autopilot {target!r}", path)
    _check_triad(cal, path)
    source = dict(source or {})
    sensors = [s for s in ("accel", "gyro") if cal.params.get(f"{s}_bias") is not None]
    if not sensors:
        raise InputError("no accel_bias or gyro_bias in the calibration", path)
    mode = _mode(source, target, residual, in_force)
    log_fw = source.get("firmware")
    if instance is not None:
        try:
            fc_params.check_instance(target, instance)
        except ValueError as exc:
            raise UsageProblem(str(exc)) from None
    notes: list[str] = []
    params_in_force = in_force if in_force is not None else (source.get("parameters") or {})
    if mode == "composed":
        if in_force is None and log_fw and log_fw != target:
            raise fc_params.CompositionError(
                f"the data was corrected by {log_fw} parameters; a {target} export of this fit "
                f"would mix two firmwares: use --format {log_fw}, or --residual")
        changed = source.get("parameters_changed") or []
        if changed and in_force is None:
            raise fc_params.CompositionError(
                "calibration parameters changed during the log (" + ", ".join(changed[:5])
                + "), so no one set of parameters was in force: import a log recorded with "
                "fixed parameters, or give them with --in-force FILE")
    ids = source.get("device_ids") or {}
    log_inst = source.get("instance")
    olds: dict = {}
    for s in sensors:
        dev = ids.get(s)
        if mode == "composed":
            if target == "px4" and dev is None and in_force is None:
                raise fc_params.CompositionError(
                    f"the log does not say which {s} sensor_combined comes from (no "
                    "sensor_selection, several sensor_* instances), so its CAL_* slot is not "
                    "known: import --source sensor, or give --in-force FILE with --instance")
            inst = instance if target == "ardupilot" and instance is not None and \
                log_inst is None else (log_inst if target == "ardupilot" else instance)
            olds[s] = fc_params.in_force(target, params_in_force, s,
                                         instance=inst if inst is not None else 0,
                                         device_id=dev if target == "px4" else None)
        else:
            olds[s] = fc_params.SensorCal(np.zeros(3), np.ones(3), np.eye(3), None,
                                          None if dev is None else int(dev))
    # the instance the parameters are written for
    out_inst = {}
    for s in sensors:
        if instance is not None:
            out_inst[s] = instance
        elif target == "px4":
            out_inst[s] = olds[s].slot if olds[s].slot is not None else 0
        else:
            out_inst[s] = int(log_inst) if log_inst is not None and log_fw == "ardupilot" else 0
        try:
            fc_params.check_instance(target, out_inst[s])
        except ValueError as exc:
            raise UsageProblem(str(exc)) from None
    if target == "ardupilot" and len(set(out_inst.values())) > 1:
        out_inst = {s: out_inst[sensors[0]] for s in sensors}
    dropped: dict = {}
    new: dict = {}
    shared = None
    if target == "ardupilot":  # one INS_TCALn_TMIN/TMAX for both sensors
        th = [olds[s].thermal for s in sensors if olds[s].thermal is not None]
        shared = (th[0].tmin, th[0].tmax) if th else None
    for s in sensors:
        new[s], d = compose(olds[s], target, s, cal, path, shared)
        dropped.update(d)
        if target == "ardupilot" and new[s].thermal is not None and shared is None:
            shared = (new[s].thermal.tmin, new[s].thermal.tmax)
    if target == "ardupilot" and any(new[s].thermal is not None for s in sensors):
        for s in ("accel", "gyro"):  # TCAL enables both sensors' polynomials: zeros for the other
            if s in new and new[s].thermal is None:
                new[s] = fc_params.SensorCal(
                    new[s].offset, new[s].scale, new[s].R,
                    fc_params.Thermal("ardupilot", np.zeros((3, 3)), *shared, np.nan),
                    new[s].device_id, new[s].slot)
    params = fc_params.to_params_split(target, {s: (out_inst[s], new[s]) for s in sensors})
    notes += _notes(target, mode, source, olds, new, out_inst, sensors, params_in_force,
                    in_force is not None)
    for what, size in dropped.items():
        notes.append(f"not representable, dropped: {what} = {size:.3g}")
    meta = {"mode": mode, "firmware": target, "instance": out_inst,
            "in_force": ({k: params_in_force[k] for k in sorted(params_in_force)}
                         if mode == "composed" else {}),
            "dropped": dropped}
    return params, notes, meta


def _notes(target, mode, source, olds, new, out_inst, sensors, params_in_force, given) -> list:
    notes = []
    src = source.get("stream", "")
    if mode == "composed":
        rot = "; ".join(sorted({olds[s].rotation for s in sensors if olds[s].rotation}))
        notes.append(
            f"COMPOSED: the fitted data ({source.get('format', 'log')} {src}) was already "
            f"corrected by the {target} parameters in force "
            f"({'from --in-force' if given else 'from the log'}); these values are those "
            "parameters followed by the fitted residual, an absolute calibration of the "
            f"sensor{' (' + rot + ')' if rot else ''}")
    elif mode == "residual":
        notes.append("RESIDUAL (--residual): the fit of the logged data as it is, on top of "
                     "whatever calibration the firmware applied when it was logged; NOT an "
                     "absolute calibration: loading it replaces the parameters in force")
    elif mode == "unknown":
        notes.append("the data's origin is not recorded (not imported from a flight-controller "
                     "log): written as an absolute calibration of raw samples; if the samples "
                     "were corrected by the firmware, use calib import ulog|dataflash (which "
                     "records the parameters in force) or --in-force FILE")
    else:
        notes.append(f"ABSOLUTE: the fitted data ({source.get('format', '')} {src}) is raw, "
                     "before the firmware's calibration")
    if target == "px4":
        for s in sensors:
            key = "ACC" if s == "accel" else "GYRO"
            if new[s].device_id is None:
                notes.append(f"set CAL_{key}{out_inst[s]}_ID to the sensor's device id "
                             f"(sensor_{s}.device_id in a ULog): PX4 applies a slot only to "
                             "the device it names")
            if new[s].thermal is not None and new[s].device_id is None:
                notes.append(f"set TC_{key[0]}{new[s].thermal.slot or out_inst[s]}_ID to the "
                             "same device id (TemperatureCompensation matches it)")
    else:
        notes.append("ArduPilot re-learns the gyro offsets at every boot unless INS_GYR_CAL = 0")
        th = [new[s].thermal for s in sensors if new[s].thermal is not None
              and np.isfinite(new[s].thermal.tref)]
        if th:
            t = th[0]
            notes.append(
                f"INS_TCAL: the bias-drift polynomials re-expanded about ArduPilot's fixed "
                f"35 degC reference (AP_InertialSensor_tempcal.cpp: third order, no constant "
                f"term, times 1e6), valid over TMIN..TMAX = {t.tmin:g}..{t.tmax:g} degC; the "
                f"offsets hold at CALTEMP = {t.tref:g} degC; scale terms are not held (see "
                "below)")
            if "gyro" in sensors and new["gyro"].thermal is not None:
                notes.append("with INS_GYR_CAL = 1 ArduPilot re-learns the gyro offsets at boot "
                             "and sets the gyro CALTEMP to that temperature itself")
    for s in sensors:
        t = new[s].thermal
        if target == "px4" and t is not None:
            notes.append(f"TC_{'A' if s == 'accel' else 'G'}: the {s} bias drift as PX4's "
                         f"polynomial X0 + X1 d + X2 d^2 + X3 d^3, d = T - TREF (TREF = "
                         f"{t.tref:g} degC), clamped to TMIN..TMAX = {t.tmin:g}..{t.tmax:g} "
                         "degC (TemperatureCompensation.cpp); scale terms are not held")
        if mode == "composed" and olds[s].thermal is not None and _drift_none(new, olds, s):
            notes.append(f"the {s} temperature calibration in force is kept as it is "
                         "(not written)")
    return notes


def _drift_none(new, olds, s) -> bool:
    return new[s].thermal is olds[s].thermal


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
            # MAV_PARAM_TYPE_INT32 (6) for PX4's integer parameters, REAL32 (9) otherwise
            is_int = name.endswith(fc_params.PX4_INT_SUFFIX)
            w.writerow([1, 1, name, str(int(round(value))) if is_int else repr(float(value)),
                        6 if is_int else 9])
        else:
            w.writerow([name, repr(float(value))])
    return buf.getvalue()


def export_for_tool(cal: CalibrationResult, fmt: str, source: str, path: str,
                    allan=None, raw=None, rostopic: str = "/imu0", instance: int | None = None,
                    rate: float | None = None, data_source: dict | None = None,
                    residual: bool = False, in_force: dict | None = None
                    ) -> tuple[str, list[str], dict]:
    """(text, warnings, meta) of ``fmt`` in AUTOPILOT_FORMATS. kalibr: noise
    densities and random walks from ``allan`` (an AllanResult); without it
    exit 3 naming the option (Kalibr needs all four figures)."""
    warnings: list[str] = []
    if fmt == "kalibr":
        if allan is None:
            if raw is not None:
                raise InputError("Kalibr needs the random walks too, which --raw cannot give: "
                                 "give --allan ALLAN.h5 (calib allan RAW.h5 --out ALLAN.h5, a "
                                 "record at rest)", path)
            raise InputError("a calibration holds no noise figures, which Kalibr's imu.yaml "
                             "is: give --allan ALLAN.h5 (calib allan RAW.h5 --out ALLAN.h5, a "
                             "record at rest)", path)
        d = kalibr_from_allan(allan, rostopic)
        return kalibr_yaml(d), warnings, {}
    params, notes, meta = autopilot_export(cal, fmt, instance, path, data_source, residual,
                                           in_force)
    return params_file(params, notes, fmt, source), warnings, meta
