"""Flight-controller calibration parameters as PX4 and ArduPilot have them
(docs/export.md): their names per IMU instance, their board rotations, their
parameter files, and each firmware's correction equation, written out here
once (the export composes with it, ``calib simulate --out LOG`` applies it,
the tests check exports through it).

PX4 (src/lib/sensor_calibration/Accelerometer.hpp ``Correct()``,
Gyroscope.hpp ``Correct()``)::

    y = R ((x - thermal(T) - CAL_ACCn_{X,Y,Z}OFF) .* CAL_ACCn_{X,Y,Z}SCALE)
    y = R (x - thermal(T) - CAL_GYROn_{X,Y,Z}OFF)              (no gyro scale)

with R = Euler(SENS_BOARD_X_OFF, _Y_OFF, _Z_OFF) * rot(r) (Accelerometer.cpp
``set_rotation``: "always apply board level adjustments"), r = SENS_BOARD_ROT
for an internal sensor (CAL_ACCn_ROT = -1), CAL_ACCn_ROT for an external
one; rot() is src/lib/conversion/rotation.h ``rot_lookup`` (roll, pitch, yaw
in degrees, Dcm of the 3-2-1 Euler angles). The slot n is the one whose
CAL_ACCn_ID is the sensor's device id (Utilities.cpp
``FindCurrentCalibrationIndex``, slots 0-3); a device without a slot is not
corrected (``Reset()``), only rotated. thermal(T) = X0 + X1 d + X2 d^2 + X3 d^3
per axis, d = clamp(T, TMIN, TMAX) - TREF
(src/modules/temperature_compensation/TemperatureCompensation.cpp
``calc_thermal_offsets_3D``), parameters TC_A_ENABLE, TC_Aj_ID (the device
id), TC_Aj_X{0..3}_{0..2}, TC_Aj_TREF, _TMIN, _TMAX (temp_comp_params_accel_0.yaml)
and TC_G* for gyros.

ArduPilot (libraries/AP_InertialSensor/AP_InertialSensor_Backend.cpp
``_rotate_and_correct_accel``/``_gyro``)::

    y = R (((x - P(T) + P(CALTEMP)) - INS_ACCOFFS) .* INS_ACCSCAL)
    y = R ((x - P(T) + P(CALTEMP)) - INS_GYROFFS)

with R = rot(AHRS_ORIENTATION) (libraries/AP_Math/rotations.h) and P the
temperature polynomial of AP_InertialSensor_tempcal.cpp (INS_TCALn_*). Names
(AP_InertialSensor.cpp ``var_info``, AP_InertialSensor_Params.cpp): IMUs 1-3
``INS_ACCOFFS_X``/``INS_ACC2OFFS_X``/``INS_ACC3OFFS_X``, ``INS_ACC_ID``/
``INS_ACC2_ID``..., ``INS_ACC1_CALTEMP``..., ``INS_TCAL1_*``...; IMUs 4-5 the
groups ``INS4_``/``INS5_``: ``INS4_ACCOFFS_X``, ``INS4_ACC_ID``,
``INS4_ACC_CALTEMP``, ``INS4_TCAL_*``.

x is the driver's sample in the sensor frame (PX4 ``sensor_accel``; ArduPilot
after the driver's own orientation), y what ``sensor_combined`` / ``IMU`` /
``ACC`` log.
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

import numpy as np

from calib_cli.errors import EstimationError, InputError

FIRMWARES = ("px4", "ardupilot")
AXES = "XYZ"
# instances the parameter tables hold: PX4 Accelerometer.hpp MAX_SENSOR_COUNT = 4;
# ArduPilot INS_ACC*, INS_ACC2*, INS_ACC3* and the INS4_, INS5_ groups
INSTANCES = {"px4": range(0, 4), "ardupilot": range(0, 5)}

# PX4 src/lib/conversion/rotation.h rot_lookup (roll, pitch, yaw), deg; index = enum value
PX4_ROTATIONS = (
    (0, 0, 0), (0, 0, 45), (0, 0, 90), (0, 0, 135), (0, 0, 180), (0, 0, 225), (0, 0, 270),
    (0, 0, 315), (180, 0, 0), (180, 0, 45), (180, 0, 90), (180, 0, 135), (0, 180, 0),
    (180, 0, 225), (180, 0, 270), (180, 0, 315), (90, 0, 0), (90, 0, 45), (90, 0, 90),
    (90, 0, 135), (270, 0, 0), (270, 0, 45), (270, 0, 90), (270, 0, 135), (0, 90, 0),
    (0, 270, 0), (270, 0, 270), (180, 270, 0), (0, 90, 180), (90, 90, 0), (90, 68, 293),
    (270, 90, 0), (0, 9, 180), (0, 45, 0), (0, 315, 0), (90, 0, 270))
# ArduPilot libraries/AP_Math/rotations.h enum Rotation, from the names (roll, pitch,
# yaw); 38 (ROLL_90_PITCH_68_YAW_293, approximate angles in its code) and 100
# (CUSTOM, CUST_ROT_* parameters) are not taken
AP_ROTATIONS = {i: r for i, r in enumerate(PX4_ROTATIONS[:26])}
AP_ROTATIONS.update({26: (0, 180, 90), 27: (0, 180, 270), 28: (90, 90, 0), 29: (180, 90, 0),
                     30: (270, 90, 0), 31: (90, 180, 0), 32: (270, 180, 0), 33: (90, 270, 0),
                     34: (180, 270, 0), 35: (270, 270, 0), 36: (90, 180, 90), 37: (90, 0, 270),
                     39: (0, 315, 0), 40: (90, 315, 0), 41: (0, 7, 0), 42: (45, 0, 0),
                     43: (315, 0, 0)})
AP_TEMP_REFERENCE = 35.0  # degC, AP_InertialSensor_tempcal.cpp TEMP_REFERENCE
AP_SCALE_FACTOR = 1.0e6  # its SCALE_FACTOR: coefficients are stored times 1e6
TCAL_ORDER = 3  # both firmwares: third order at most


class CompositionError(EstimationError):
    """The parameters in force cannot be composed with a fit (exit 4)."""


def euler_dcm(roll_deg: float, pitch_deg: float, yaw_deg: float) -> np.ndarray:
    """Dcm of 3-2-1 Euler angles, R = Rz(yaw) Ry(pitch) Rx(roll) (PX4 matrix::Dcm(Euler),
    ArduPilot Matrix3::from_euler): maps sensor-frame vectors into the body frame."""
    r, p, y = (math.radians(v) for v in (roll_deg, pitch_deg, yaw_deg))
    cr, sr, cp, sp, cy, sy = math.cos(r), math.sin(r), math.cos(p), math.sin(p), \
        math.cos(y), math.sin(y)
    return np.array([[cp * cy, sr * sp * cy - cr * sy, cr * sp * cy + sr * sy],
                     [cp * sy, sr * sp * sy + cr * cy, cr * sp * sy - sr * cy],
                     [-sp, sr * cp, cr * cp]])


def rotation_matrix(firmware: str, value, what: str) -> np.ndarray:
    """The board rotation of an enum value; CompositionError when the table lacks it."""
    table = PX4_ROTATIONS if firmware == "px4" else AP_ROTATIONS
    try:
        i = int(value)
        if float(value) != i:
            raise ValueError
        rpy = table[i] if firmware != "px4" or 0 <= i < len(table) else None
    except (KeyError, ValueError, TypeError, IndexError):
        rpy = None
    if rpy is None:
        raise CompositionError(f"{what} = {value!r}: a rotation calib does not know (custom or "
                               "new in this firmware), so the parameters in force cannot be "
                               "composed with the fit")
    return euler_dcm(*rpy)


def is_axis_permutation(R: np.ndarray, tol: float = 1e-9) -> bool:
    a = np.abs(np.asarray(R))
    return bool(np.all((np.abs(a - 1) < tol) | (a < tol)))


# ---------------------------------------------------------------------------
# names


def check_instance(firmware: str, instance: int) -> None:
    """ValueError naming the valid range when ``instance`` has no parameters."""
    rng = INSTANCES[firmware]
    if instance not in rng:
        if firmware == "px4":
            raise ValueError(f"--instance {instance}: PX4 has calibration slots 0-3 "
                             "(CAL_ACC0..3, CAL_GYRO0..3)")
        raise ValueError(f"--instance {instance}: ArduPilot holds IMUs 1-5 as --instance 0-4 "
                         "(INS_ACC*, INS_ACC2*, INS_ACC3*, INS4_*, INS5_*)")


def names(firmware: str, instance: int) -> dict:
    """Parameter names of one IMU instance (0-based, as the logs' instance fields):
    {"accel_off": [x, y, z], "accel_scale": [...], "gyro_off": [...],
    "accel_id", "gyro_id", "accel_rot", "accel_tc": {...}, "gyro_tc": {...}}.
    accel_tc/gyro_tc: "enable", "id", "tref" (PX4) or "caltemp" (ArduPilot), "tmin",
    "tmax", "coef": [[name per axis] per power] (PX4 powers 0-3, ArduPilot 1-3)."""
    check_instance(firmware, instance)
    n = instance
    if firmware == "px4":
        out = {"accel_off": [f"CAL_ACC{n}_{a}OFF" for a in AXES],
               "accel_scale": [f"CAL_ACC{n}_{a}SCALE" for a in AXES],
               "gyro_off": [f"CAL_GYRO{n}_{a}OFF" for a in AXES],
               "accel_id": f"CAL_ACC{n}_ID", "gyro_id": f"CAL_GYRO{n}_ID",
               "accel_rot": f"CAL_ACC{n}_ROT", "gyro_rot": f"CAL_GYRO{n}_ROT"}
        for s, c in (("accel", "A"), ("gyro", "G")):
            out[f"{s}_tc"] = {"enable": f"TC_{c}_ENABLE", "id": f"TC_{c}{n}_ID",
                              "tref": f"TC_{c}{n}_TREF", "tmin": f"TC_{c}{n}_TMIN",
                              "tmax": f"TC_{c}{n}_TMAX",
                              "coef": [[f"TC_{c}{n}_X{k}_{i}" for i in range(3)]
                                       for k in range(TCAL_ORDER + 1)]}
        return out
    if n < 3:
        num = "" if n == 0 else str(n + 1)
        m = n + 1
        out = {"accel_off": [f"INS_ACC{num}OFFS_{a}" for a in AXES],
               "accel_scale": [f"INS_ACC{num}SCAL_{a}" for a in AXES],
               "gyro_off": [f"INS_GYR{num}OFFS_{a}" for a in AXES],
               "accel_id": f"INS_ACC{num}_ID", "gyro_id": f"INS_GYR{num}_ID",
               "accel_caltemp": f"INS_ACC{m}_CALTEMP", "gyro_caltemp": f"INS_GYR{m}_CALTEMP"}
        tc = f"INS_TCAL{m}_"
    else:
        g = f"INS{n + 1}_"
        out = {"accel_off": [f"{g}ACCOFFS_{a}" for a in AXES],
               "accel_scale": [f"{g}ACCSCAL_{a}" for a in AXES],
               "gyro_off": [f"{g}GYROFFS_{a}" for a in AXES],
               "accel_id": f"{g}ACC_ID", "gyro_id": f"{g}GYR_ID",
               "accel_caltemp": f"{g}ACC_CALTEMP", "gyro_caltemp": f"{g}GYR_CALTEMP"}
        tc = f"{g}TCAL_"
    for s, c in (("accel", "ACC"), ("gyro", "GYR")):
        out[f"{s}_tc"] = {"enable": f"{tc}ENABLE", "tmin": f"{tc}TMIN", "tmax": f"{tc}TMAX",
                          "caltemp": out[f"{s}_caltemp"],
                          "coef": [[f"{tc}{c}{k}_{a}" for a in AXES]
                                   for k in range(1, TCAL_ORDER + 1)]}
    return out


# parameters that belong to the IMU calibration (kept in a raw file's /source)
_RELEVANT = {"px4": re.compile(r"^(CAL_(ACC|GYRO)\d_|SENS_BOARD_|TC_[AG])"),
             "ardupilot": re.compile(r"^(INS\d?_|AHRS_ORIENTATION$|AHRS_CUSTOM_|CUST_ROT)")}


def relevant(firmware: str, params: dict) -> dict:
    """The IMU-calibration parameters of a full parameter set."""
    rx = _RELEVANT[firmware]
    return {k: float(v) for k, v in params.items() if rx.match(k)}


# ---------------------------------------------------------------------------
# one sensor's calibration in force


@dataclass(frozen=True)
class Thermal:
    """A firmware temperature polynomial. px4: coef (3, 4) = X0..X3, offset
    X0 + X1 d + ... with d = clamp(T) - tref. ardupilot: coef (3, 3) as stored
    (times 1e6), offset P(clamp T) - P(clamp tref), tref = CALTEMP."""

    kind: str
    coef: np.ndarray
    tmin: float
    tmax: float
    tref: float
    slot: int | None = None  # PX4 TC_?j slot (matched by TC_?j_ID), ArduPilot: the IMU

    def offset(self, temp) -> np.ndarray:
        """(N, 3) offset the firmware subtracts at temperatures ``temp`` (degC)."""
        t = np.atleast_1d(np.asarray(temp, dtype=float))
        c = np.asarray(self.coef, dtype=float)
        if self.kind == "px4":
            d = np.clip(t, self.tmin, self.tmax) - self.tref
            return (c[:, 0][:, None] + d * (c[:, 1][:, None] + d * (c[:, 2][:, None]
                    + d * c[:, 3][:, None]))).T
        return ap_poly(c, t, self.tmin, self.tmax) - ap_poly(c, [self.tref], self.tmin,
                                                               self.tmax)


def ap_poly(stored: np.ndarray, temp, tmin: float, tmax: float) -> np.ndarray:
    """ArduPilot's polynomial_eval at clamp(temp) (AP_InertialSensor_tempcal.cpp):
    (c1 + (c2 + c3 d) d) d * 1e-6, d = clamp(T) - 35; stored (3, 3). Returns (N, 3)."""
    d = np.clip(np.asarray(temp, float), tmin, tmax) - AP_TEMP_REFERENCE
    c = np.asarray(stored, float) / AP_SCALE_FACTOR
    return ((c[:, 0][:, None] + (c[:, 1][:, None] + c[:, 2][:, None] * d) * d) * d).T


@dataclass(frozen=True)
class SensorCal:
    """One sensor's calibration as the firmware applies it: offset (3,), scale
    (3,) (ones for gyros), R (3, 3) sensor -> logged frame, thermal or None."""

    offset: np.ndarray
    scale: np.ndarray
    R: np.ndarray
    thermal: Thermal | None = None
    device_id: int | None = None
    slot: int | None = None  # PX4 CAL slot / ArduPilot instance whose parameters these are
    rotation: str = ""  # which parameters make R, for messages

    def correct(self, x, temp=None) -> np.ndarray:
        """The firmware's equation (module docstring): x (N, 3) sensor frame -> y."""
        x = np.asarray(x, dtype=float)
        v = x - self.offset
        if self.thermal is not None:
            if temp is None:
                raise ValueError("a thermal correction needs the temperature")
            v = v - self.thermal.offset(temp)
        return (v * self.scale) @ self.R.T

    def uncorrect(self, y, temp=None) -> np.ndarray:
        """The inverse of ``correct``: the sensor sample the firmware turned into y."""
        v = np.asarray(y, dtype=float) @ self.R / self.scale + self.offset
        if self.thermal is not None:
            v = v + self.thermal.offset(temp)
        return v


def identity(slot: int | None = None) -> SensorCal:
    return SensorCal(np.zeros(3), np.ones(3), np.eye(3), slot=slot)


def _get(params: dict, name: str, default=None, required=True):
    if name in params:
        return float(params[name])
    if default is not None or not required:
        return default
    raise CompositionError(f"the parameter {name} is not in the log, so the calibration in "
                           "force is not known")


def px4_slot(params: dict, sensor: str, device_id: int | None) -> int | None:
    """The CAL slot whose CAL_{ACC,GYRO}n_ID is ``device_id`` (None: no slot)."""
    key = "ACC" if sensor == "accel" else "GYRO"
    if device_id is None:
        return None
    for n in INSTANCES["px4"]:
        v = params.get(f"CAL_{key}{n}_ID")
        if v is not None and int(v) & 0xFFFFFFFF == int(device_id) & 0xFFFFFFFF:
            return n
    return None


def in_force(firmware: str, params: dict, sensor: str, instance: int | None = None,
             device_id: int | None = None) -> SensorCal:
    """The calibration of one sensor that ``params`` (a log's parameters) put in
    force. PX4: the slot of ``device_id`` (``instance`` when no id is known);
    ArduPilot: ``instance`` (the log's I field). CompositionError when the log lacks
    what the firmware uses."""
    if not params:
        raise CompositionError("the log carries no parameters, so the calibration in force "
                               "is not known")
    if firmware == "px4":
        return _px4_in_force(params, sensor, instance, device_id)
    return _ap_in_force(params, sensor, instance or 0)


def _px4_in_force(params, sensor, instance, device_id):
    key = "ACC" if sensor == "accel" else "GYRO"
    if not any(k.startswith(f"CAL_{key}") for k in params):
        raise CompositionError(f"the log carries no CAL_{key}* parameters, so the "
                               "calibration in force is not known")
    slot = px4_slot(params, sensor, device_id) if device_id is not None else instance
    if slot is None and not any(f"CAL_{key}{n}_ID" in params for n in INSTANCES["px4"]):
        slot = instance or 0  # a parameter file without device ids: the slot given
    lvl = euler_dcm(*(_get(params, f"SENS_BOARD_{a}_OFF", 0.0) for a in AXES))
    board = _get(params, "SENS_BOARD_ROT", 0.0)
    rot_name, rot_val = "SENS_BOARD_ROT", board
    if slot is not None:
        nm = names("px4", slot)
        r = _get(params, nm[f"{sensor}_rot"], -1.0)
        if r >= 0:  # external sensor: its own rotation (Accelerometer.cpp ParametersUpdate)
            rot_name, rot_val = nm[f"{sensor}_rot"], r
    R = lvl @ rotation_matrix("px4", rot_val, rot_name)
    rtxt = f"{rot_name} = {int(rot_val)}" + "".join(
        f", SENS_BOARD_{a}_OFF = {params[f'SENS_BOARD_{a}_OFF']:g}" for a in AXES
        if params.get(f"SENS_BOARD_{a}_OFF", 0.0))
    if slot is None:  # PX4 Reset(): no offsets, no scales, rotation only
        return SensorCal(np.zeros(3), np.ones(3), R, None, device_id, None, rtxt)
    nm = names("px4", slot)
    off = np.array([_get(params, k) for k in nm[f"{sensor}_off"]])
    scale = (np.array([_get(params, k) for k in nm["accel_scale"]]) if sensor == "accel"
             else np.ones(3))
    thermal = None
    tc = nm[f"{sensor}_tc"]
    if _get(params, tc["enable"], 0.0) == 1 and device_id is not None:
        # TemperatureCompensation::set_sensor_id: the TC slot whose TC_?j_ID is the device
        for j in INSTANCES["px4"]:
            tj = names("px4", j)[f"{sensor}_tc"]
            if tj["id"] in params and int(params[tj["id"]]) & 0xFFFFFFFF == device_id:
                coef = np.array([[_get(params, k) for k in row] for row in tj["coef"]]).T
                thermal = Thermal("px4", coef, _get(params, tj["tmin"]), _get(params, tj["tmax"]),
                                  _get(params, tj["tref"]))
                break
    elif _get(params, tc["enable"], 0.0) == 1:
        raise CompositionError(f"{tc['enable']} = 1 but the sensor's device id is not in the "
                               "log, so which TC_* slot corrects it is not known")
    return SensorCal(off, scale, R, thermal, device_id, slot, rtxt)


def _ap_in_force(params, sensor, instance):
    check_instance("ardupilot", instance)
    nm = names("ardupilot", instance)
    if nm[f"{sensor}_off"][0] not in params:
        raise CompositionError(f"the log carries no {nm[f'{sensor}_off'][0]}, so the "
                               "calibration in force is not known")
    orient = _get(params, "AHRS_ORIENTATION")
    R = rotation_matrix("ardupilot", orient, "AHRS_ORIENTATION")
    off = np.array([_get(params, k) for k in nm[f"{sensor}_off"]])
    scale = (np.array([_get(params, k) for k in nm["accel_scale"]]) if sensor == "accel"
             else np.ones(3))
    tc = nm[f"{sensor}_tc"]
    enable = _get(params, tc["enable"], 0.0)
    thermal = None
    if enable == 2:
        raise CompositionError(f"{tc['enable']} = 2: ArduPilot was learning its temperature "
                               "calibration during the log, so the data's correction changed")
    if enable == 1:
        coef = np.array([[_get(params, k) for k in row] for row in tc["coef"]]).T
        thermal = Thermal("ardupilot", coef, _get(params, tc["tmin"]), _get(params, tc["tmax"]),
                          _get(params, tc["caltemp"]))
    dev = params.get(nm[f"{sensor}_id"])
    return SensorCal(off, scale, R, thermal, None if dev is None else int(dev), instance,
                     f"AHRS_ORIENTATION = {int(orient)}")


# ---------------------------------------------------------------------------
# writing a calibration as parameters


PX4_INT_SUFFIX = ("_ID", "_ROT", "_PRIO", "_ENABLE")  # PX4's int32 parameters (the rest float)


def to_params(firmware: str, instance: int, accel: SensorCal | None, gyro: SensorCal | None
              ) -> list[tuple[str, float]]:
    """[(name, value)] of offsets, scales, device ids and temperature terms."""
    cals = {s: (instance, c) for s, c in (("accel", accel), ("gyro", gyro)) if c is not None}
    return to_params_split(firmware, cals)


def to_params_split(firmware: str, cals: dict) -> list[tuple[str, float]]:
    """As ``to_params`` with an instance per sensor: {sensor: (instance, SensorCal)}
    (PX4 keeps accelerometer and gyro calibrations in separate slots). A Thermal
    with a NaN reference writes zero coefficients and no reference (ArduPilot's
    shared INS_TCALn_ENABLE turns on both sensors' polynomials)."""
    out: list[tuple[str, float]] = []
    for sensor in ("accel", "gyro"):
        if sensor not in cals:
            continue
        inst, cal = cals[sensor]
        nm = names(firmware, inst)
        out += list(zip(nm[f"{sensor}_off"], map(float, cal.offset)))
        if sensor == "accel":
            out += list(zip(nm["accel_scale"], map(float, cal.scale)))
        if cal.device_id is not None:
            out.append((nm[f"{sensor}_id"], float(cal.device_id)))
    for sensor in ("accel", "gyro"):
        if sensor not in cals or cals[sensor][1].thermal is None:
            continue
        inst, cal = cals[sensor]
        th = cal.thermal
        if firmware == "px4":
            tc = names(firmware, th.slot if th.slot is not None else inst)[f"{sensor}_tc"]
            out.append((tc["enable"], 1.0))
            if cal.device_id is not None:
                out.append((tc["id"], float(cal.device_id)))
            out += [(tc["tref"], th.tref), (tc["tmin"], th.tmin), (tc["tmax"], th.tmax)]
        else:
            tc = names(firmware, inst)[f"{sensor}_tc"]
            out += [(tc["enable"], 1.0), (tc["tmin"], th.tmin), (tc["tmax"], th.tmax)]
        for k, row in enumerate(tc["coef"]):
            out += [(row[i], float(th.coef[i, k])) for i in range(3)]
    for sensor in ("accel", "gyro"):  # ArduPilot: the offsets hold at CALTEMP
        if firmware == "ardupilot" and sensor in cals and cals[sensor][1].thermal is not None:
            inst, cal = cals[sensor]
            if np.isfinite(cal.thermal.tref):
                out.append((names(firmware, inst)[f"{sensor}_tc"]["caltemp"], cal.thermal.tref))
    seen, uniq = set(), []
    for k, v in out:  # ArduPilot's TCAL ENABLE/TMIN/TMAX are shared by accel and gyro
        if k not in seen:
            seen.add(k)
            uniq.append((k, v))
    return uniq


# ---------------------------------------------------------------------------
# parameter files (QGroundControl .params, Mission Planner .parm)


def read_params_file(path: str) -> tuple[str | None, dict]:
    """(firmware guessed from the names or None, {name: value}) of a
    QGroundControl ``.params`` (``vehicle component name value type``, tabs) or
    Mission Planner ``.parm`` (``NAME,VALUE`` or ``NAME VALUE``) file; ``#``
    starts a comment."""
    try:
        with open(path, encoding="utf-8") as fh:
            lines = fh.read().splitlines()
    except FileNotFoundError:
        raise InputError("no such file", path) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"cannot read the parameter file: {exc}", path) from None
    params: dict[str, float] = {}
    for i, line in enumerate(lines, 1):
        s = line.split("#", 1)[0].strip()
        if not s:
            continue
        parts = [p for p in re.split(r"[\t, ]+", s) if p]
        if len(parts) >= 4 and re.fullmatch(r"\d+", parts[0]) and re.fullmatch(r"\d+", parts[1]):
            name, value = parts[2], parts[3]  # QGroundControl: vehicle component name value type
        elif len(parts) >= 2:
            name, value = parts[0], parts[1]
        else:
            raise InputError(f"line {i}: expected NAME,VALUE or a QGroundControl row", path)
        try:
            params[name] = float(value)
        except ValueError:
            raise InputError(f"line {i}: {name}: {value!r} is not a number", path) from None
    fw = guess_firmware(params)
    return fw, params


def guess_firmware(params: dict) -> str | None:
    if any(k.startswith(("CAL_ACC", "CAL_GYRO", "SENS_BOARD_", "TC_A", "TC_G")) for k in params):
        return "px4"
    if any(k.startswith("INS") or k == "AHRS_ORIENTATION" for k in params):
        return "ardupilot"
    return None
