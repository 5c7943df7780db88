"""Writers of the flight-controller and robotics log formats ``calib import``
reads, for ``calib simulate --out LOG.ulg|.bin|.mcap|.bag`` and the tests
(docs/simulate.md). pyulog and pymavlink read but do not write; these follow
the published specifications and are checked against both readers
(tests/test_log_formats.py). Bags go through rosbags' own writers.

ULog (docs.px4.io "ULog File Format"): a 16-byte header (magic
``ULog\\x01\\x12\\x35``, version 1, start time in us), flag bits 'B',
information 'I', formats 'F' (``name:type field;...``), initial parameters
'P' (``int32_t NAME``/``float NAME``), then subscriptions 'A' (uint8
multi_id, uint16 msg_id, name) and data 'D' (uint16 msg_id, packed
little-endian fields), in time order. Topics as PX4 logs them
(msg/SensorCombined.msg, SensorAccel.msg, SensorGyro.msg, SensorSelection.msg).

DataFlash (ArduPilot "Onboard logs", pymavlink DFReader): messages
``0xA3 0x95 type payload``; FMT (type 128) defines each type; PARM
(``QNff``: TimeUS, Name, Value, Default) holds the parameters; IMU, ACC, GYR
as libraries/AP_InertialSensor/LogStructure.h has them (``IMU``
``QBffffffIIfBBHH`` with the instance field I since ArduPilot 4.1; before
that ``IMU``/``IMU2``/``IMU3`` and ``ACC1..3``/``GYR1..3`` without it).

Records are built as numpy structured arrays and interleaved in time order
block by block, so hours of samples write in seconds with flat memory.
"""

from __future__ import annotations

import struct

import numpy as np

from calib_cli.io.fc_params import PX4_INT_SUFFIX

BLOCK = 200_000  # samples per block

# ---------------------------------------------------------------------------
# interleaving records of several streams in time order


def _interleave(streams) -> bytes:
    """streams: [(t (n,) int64, rows (n,) structured array)] -> their bytes in time
    order (a stable sort: equal times keep the streams' order)."""
    streams = [(np.asarray(t, np.int64), r) for t, r in streams if len(t)]
    if not streams:
        return b""
    t_all = np.concatenate([t for t, _ in streams])
    which = np.concatenate([np.full(len(t), k) for k, (t, _) in enumerate(streams)])
    sizes = np.array([r.dtype.itemsize for _, r in streams])
    order = np.argsort(t_all, kind="stable")
    start = np.zeros(len(order) + 1, np.int64)
    np.cumsum(sizes[which[order]], out=start[1:])
    out = np.empty(int(start[-1]), np.uint8)
    pos_of = np.empty(len(order), np.int64)
    pos_of[order] = start[:-1]
    off = 0
    for k, (t, r) in enumerate(streams):
        p = pos_of[off:off + len(t)]
        size = sizes[k]
        out[p[:, None] + np.arange(size)] = r.view(np.uint8).reshape(len(t), size)
        off += len(t)
    return out.tobytes()


# ---------------------------------------------------------------------------
# ULog

ULOG_MAGIC = b"ULog\x01\x12\x35"
SENSOR_COMBINED = [("uint64_t", "timestamp"), ("float[3]", "gyro_rad"),
                   ("uint32_t", "gyro_integral_dt"),
                   ("int32_t", "accelerometer_timestamp_relative"),
                   ("float[3]", "accelerometer_m_s2"), ("uint32_t", "accelerometer_integral_dt"),
                   ("uint8_t", "accelerometer_clipping"), ("uint8_t", "gyro_clipping"),
                   ("uint8_t", "accel_calibration_count"), ("uint8_t", "gyro_calibration_count")]
SENSOR_XYZ = [("uint64_t", "timestamp"), ("uint64_t", "timestamp_sample"),
              ("uint32_t", "device_id"), ("float", "x"), ("float", "y"), ("float", "z"),
              ("float", "temperature"), ("uint32_t", "error_count")]
SENSOR_SELECTION = [("uint64_t", "timestamp"), ("uint32_t", "accel_device_id"),
                    ("uint32_t", "gyro_device_id")]
_NP = {"uint64_t": "<u8", "uint32_t": "<u4", "int32_t": "<i4", "uint8_t": "u1", "float": "<f4",
       "double": "<f8", "int16_t": "<i2", "uint16_t": "<u2", "int8_t": "i1"}


def _umsg(kind: bytes, payload: bytes) -> bytes:
    return struct.pack("<HB", len(payload), kind[0]) + payload


def _payload_dtype(fields):
    out = []
    for t, name in fields:
        if t.endswith("]"):
            base, n = t[:-1].split("[")
            out += [(f"{name}[{i}]", _NP[base]) for i in range(int(n))]
        else:
            out.append((name, _NP[t]))
    return out


def _data_dtype(fields):
    return np.dtype([("size", "<u2"), ("type", "u1"), ("msg_id", "<u2")]
                    + _payload_dtype(fields))


def _ulog_param(name: str, value: float) -> bytes:
    if name.endswith(PX4_INT_SUFFIX):
        key, raw = f"int32_t {name}", struct.pack("<i", int(round(value)))
    else:
        key, raw = f"float {name}", struct.pack("<f", float(value))
    return _umsg(b"P", bytes([len(key)]) + key.encode() + raw)


def write_ulog(path, t_us, accel, gyro, temp=None, combined=True, sensors=True,
               corrected=None, params=None, device_ids=(1234, 5678), multi_id=0,
               gyro_t_us=None, gyro_raw=None, selection=None, param_changes=(),
               dropouts=(), start_us=None, other_instance=False, sample_t_us=None):
    """A ULog file. ``sensor_accel``/``sensor_gyro`` (instance ``multi_id``,
    device ids ``device_ids``) hold the driver's samples ``accel``/``gyro``
    (the gyro at ``gyro_t_us`` when given, values ``gyro_raw``);
    ``sensor_combined`` holds ``corrected`` = (accel, gyro) when given, else the
    same values. ``params``: {name: value} in the definitions section;
    ``param_changes``: [(t_us, name, value)]; ``dropouts``: [(t_us, ms)];
    ``selection``: write ``sensor_selection`` (default: when ``combined``);
    ``other_instance``: also an instance ``multi_id + 1`` (which the importer must
    skip) with other values; ``sample_t_us``: the accelerometer's
    ``timestamp_sample`` when it differs from its publication time ``t_us``."""
    t_us = np.asarray(t_us, dtype=np.int64)
    n = len(t_us)
    accel = np.asarray(accel, dtype=np.float32).reshape(n, 3)
    gyro = np.asarray(gyro, dtype=np.float32).reshape(n, 3)
    temp = np.full(n, 25.0, np.float32) if temp is None else np.asarray(temp, np.float32)
    tg = t_us if gyro_t_us is None else np.asarray(gyro_t_us, np.int64)
    graw = gyro if gyro_raw is None else np.asarray(gyro_raw, np.float32).reshape(len(tg), 3)
    ca, cg = (accel, gyro) if corrected is None else (
        np.asarray(corrected[0], np.float32).reshape(n, 3),
        np.asarray(corrected[1], np.float32).reshape(n, 3))
    selection = combined if selection is None else selection
    t0 = int(t_us[0]) if start_us is None else int(start_us)
    head = bytearray(ULOG_MAGIC + b"\x01" + struct.pack("<Q", t0))
    head += _umsg(b"B", bytes(16) + struct.pack("<QQQ", 0, 0, 0))
    for key, val in (("char[9] sys_name", b"calibtest"), ("char[3] ver_hw", b"SIM")):
        head += _umsg(b"I", bytes([len(key)]) + key.encode() + val)
    topics = []  # (name, fields, multi_id)
    if combined:
        topics.append(("sensor_combined", SENSOR_COMBINED, 0))
    if selection:
        topics.append(("sensor_selection", SENSOR_SELECTION, 0))
    if sensors:
        topics += [("sensor_accel", SENSOR_XYZ, multi_id), ("sensor_gyro", SENSOR_XYZ, multi_id)]
        if other_instance:
            topics += [("sensor_accel", SENSOR_XYZ, multi_id + 1),
                       ("sensor_gyro", SENSOR_XYZ, multi_id + 1)]
    for name, fields in {t[0]: t[1] for t in topics}.items():
        head += _umsg(b"F", (name + ":" + "".join(f"{t} {f};" for t, f in fields)).encode())
    for k, v in (params or {}).items():
        head += _ulog_param(k, v)
    for msg_id, (name, _, multi) in enumerate(topics):
        head += _umsg(b"A", struct.pack("<BH", multi, msg_id) + name.encode())
    dts = [_data_dtype(f) for _, f, _ in topics]
    with open(path, "wb") as fh:
        fh.write(head)
        extra = [(int(t), _ulog_param(k, v)) for t, k, v in param_changes]
        extra += [(int(t), _umsg(b"O", struct.pack("<H", int(ms)))) for t, ms in dropouts]
        extra.sort(key=lambda e: e[0])
        for i in range(0, n, BLOCK):
            sl = slice(i, i + BLOCK)
            last = i + BLOCK >= n
            # the gyro's samples up to this block's last accelerometer time
            g0 = 0 if i == 0 else int(np.searchsorted(tg, t_us[i - 1], side="right"))
            g1 = len(tg) if last else int(np.searchsorted(tg, t_us[sl][-1], side="right"))
            gsl = slice(g0, g1)
            streams = []
            for msg_id, (name, _, multi) in enumerate(topics):
                dt = dts[msg_id]
                tt = tg[gsl] if name == "sensor_gyro" else t_us[sl]
                if name == "sensor_selection":
                    tt = t_us[:1] if i == 0 else t_us[:0]
                r = np.zeros(len(tt), dt)
                r["size"], r["type"], r["msg_id"] = dt.itemsize - 3, ord("D"), msg_id
                r["timestamp"] = tt
                if name == "sensor_combined":
                    for j in range(3):
                        r[f"gyro_rad[{j}]"] = cg[sl, j]
                        r[f"accelerometer_m_s2[{j}]"] = ca[sl, j]
                    r["gyro_integral_dt"] = r["accelerometer_integral_dt"] = 1000
                    r["accel_calibration_count"] = r["gyro_calibration_count"] = 1
                elif name == "sensor_selection":
                    r["accel_device_id"], r["gyro_device_id"] = device_ids
                else:
                    acc = name == "sensor_accel"
                    vals = accel[sl] if acc else graw[gsl]
                    if multi != multi_id:
                        vals = vals * 0.5 + 0.25
                    r["timestamp_sample"] = tt if not acc or sample_t_us is None else \
                        np.asarray(sample_t_us, np.int64)[sl]
                    r["device_id"] = device_ids[0 if acc else 1] + (multi - multi_id)
                    r["x"], r["y"], r["z"] = vals[:, 0], vals[:, 1], vals[:, 2]
                    r["temperature"] = temp[sl] if acc or gyro_t_us is None else 25.0
                streams.append((tt, r))
            hi = None if last else int(t_us[sl][-1])
            while extra and (hi is None or extra[0][0] <= hi):
                t, raw = extra.pop(0)
                streams.append((np.array([t]), np.frombuffer(raw, np.dtype(
                    [("b", "u1", (len(raw),))]))))
            fh.write(_interleave(streams))


# ---------------------------------------------------------------------------
# DataFlash

_DF = {"Q": "<u8", "B": "u1", "I": "<u4", "f": "<f4", "h": "<i2", "H": "<u2", "i": "<i4",
       "q": "<i8", "d": "<f8", "n": "S4", "N": "S16", "Z": "S64"}
IMU_FMT = ("QBffffffIIfBBHH", "TimeUS,I,GyrX,GyrY,GyrZ,AccX,AccY,AccZ,EG,EA,T,GH,AH,GHz,AHz")
IMU_FMT_OLD = ("QffffffIIfBBHH", "TimeUS,GyrX,GyrY,GyrZ,AccX,AccY,AccZ,EG,EA,T,GH,AH,GHz,AHz")
ACC_FMT = ("QBQfff", "TimeUS,I,SampleUS,AccX,AccY,AccZ")
GYR_FMT = ("QBQfff", "TimeUS,I,SampleUS,GyrX,GyrY,GyrZ")
ACC_FMT_OLD = ("QQfff", "TimeUS,SampleUS,AccX,AccY,AccZ")
GYR_FMT_OLD = ("QQfff", "TimeUS,SampleUS,GyrX,GyrY,GyrZ")
PARM_FMT = ("QNff", "TimeUS,Name,Value,Default")
FMT_STRUCT = struct.Struct("<BB4s16s64s")


def _df_dtype(fmt, cols):
    return np.dtype([("h1", "u1"), ("h2", "u1"), ("type", "u1")]
                    + [(c, _DF[f]) for f, c in zip(fmt, cols.split(","))])


def _df_fmt(msg_type, name, fmt, labels) -> bytes:
    length = _df_dtype(fmt, labels).itemsize
    return b"\xa3\x95\x80" + FMT_STRUCT.pack(msg_type, length, name.encode(), fmt.encode(),
                                              labels.encode())


def _df_records(mtype, fmt, n):
    r = np.zeros(n, _df_dtype(*fmt))
    r["h1"], r["h2"], r["type"] = 0xA3, 0x95, mtype
    return r


def _parm(t, name, value) -> bytes:
    r = _df_records(130, PARM_FMT, 1)
    r["TimeUS"], r["Name"], r["Value"], r["Default"] = t, name.encode()[:16], value, value
    return r.tobytes()


def write_dataflash(path, t_us, accel, gyro, temp=None, instance=0, raw=True, imu=True,
                    legacy=False, params=None, param_changes=(), extra_instance=True,
                    acc_t_us=None):
    """A DataFlash log: FMT, PARM (``params`` at the first time stamp,
    ``param_changes`` [(t_us, name, value)] later), IMU messages of ``instance``
    (and of instance + 1, which the importer must skip, when ``extra_instance``),
    ACC/GYR when ``raw`` (at ``acc_t_us`` SampleUS when given). ``legacy``:
    ArduPilot <= 4.0's layout (IMU/IMU2/IMU3, ACC1..3, GYR1..3 without I)."""
    t_us = np.asarray(t_us, dtype=np.int64)
    n = len(t_us)
    temp = np.full(n, 25.0) if temp is None else np.asarray(temp, float)
    accel = np.asarray(accel, np.float32).reshape(n, 3)
    gyro = np.asarray(gyro, np.float32).reshape(n, 3)
    ts = t_us if acc_t_us is None else np.asarray(acc_t_us, np.int64)
    types = {}  # (kind, instance) -> (type id, fmt)
    out = bytearray(_df_fmt(128, "FMT", "BBnNZ", "Type,Length,Name,Format,Columns"))
    out += _df_fmt(130, "PARM", *PARM_FMT)
    insts = [instance, instance + 1] if extra_instance else [instance]
    nxt = 131
    for kind, new, old, oldname in (("IMU", IMU_FMT, IMU_FMT_OLD, "IMU"),
                                    ("ACC", ACC_FMT, ACC_FMT_OLD, "ACC"),
                                    ("GYR", GYR_FMT, GYR_FMT_OLD, "GYR")):
        if (kind == "IMU" and not imu) or (kind != "IMU" and not raw):
            continue
        if not legacy:
            out += _df_fmt(nxt, kind, *new)
            for k in insts:
                types[(kind, k)] = (nxt, new)
            nxt += 1
            continue
        for k in insts:
            name = (("IMU" if k == 0 else f"IMU{k + 1}") if kind == "IMU" else f"{oldname}{k + 1}")
            out += _df_fmt(nxt, name, *old)
            types[(kind, k)] = (nxt, old)
            nxt += 1
    for k, v in (params or {}).items():
        out += _parm(int(t_us[0]), k, v)
    extra = sorted(((int(t), _parm(int(t), k, v)) for t, k, v in param_changes),
                   key=lambda e: e[0])
    with open(path, "wb") as fh:
        fh.write(out)
        for i in range(0, n, BLOCK):
            sl = slice(i, i + BLOCK)
            m = len(t_us[sl])
            streams = []
            for (kind, k), (mtype, fmt) in types.items():
                r = _df_records(mtype, fmt, m)
                r["TimeUS"] = t_us[sl]
                if "I" in r.dtype.names:
                    r["I"] = k
                a, g = (accel[sl], gyro[sl]) if k == instance else (accel[sl] * 0.5 + 0.25,
                                                                    gyro[sl] * 0.5)
                if kind == "IMU":
                    for j, ax in enumerate("XYZ"):
                        r[f"Gyr{ax}"], r[f"Acc{ax}"] = g[:, j], a[:, j]
                    r["T"], r["GH"], r["AH"], r["GHz"], r["AHz"] = temp[sl], 1, 1, 1000, 1000
                else:
                    r["SampleUS"] = ts[sl]
                    v = a if kind == "ACC" else g
                    for j, ax in enumerate("XYZ"):
                        r[f"{kind[:3].title()[:3]}{ax}"] = v[:, j]
                streams.append((t_us[sl], r))
            hi = None if i + BLOCK >= n else int(t_us[sl][-1])
            while extra and (hi is None or extra[0][0] <= hi):
                t, raw_msg = extra.pop(0)
                streams.append((np.array([t]), np.frombuffer(raw_msg, np.dtype(
                    [("b", "u1", (len(raw_msg),))]))))
            fh.write(_interleave(streams))


# ---------------------------------------------------------------------------
# ROS


def _imu_msgs(ts, ros1, t_ns, accel, gyro, frame_id):
    Imu = ts.types["sensor_msgs/msg/Imu"]
    Header = ts.types["std_msgs/msg/Header"]
    Time = ts.types["builtin_interfaces/msg/Time"]
    V3 = ts.types["geometry_msgs/msg/Vector3"]
    Q = ts.types["geometry_msgs/msg/Quaternion"]
    cov = np.zeros(9)
    for i, t in enumerate(t_ns):
        t = int(t)
        stamp = Time(sec=t // 1_000_000_000, nanosec=t % 1_000_000_000)
        hdr = Header(seq=i, stamp=stamp, frame_id=frame_id) if ros1 else \
            Header(stamp=stamp, frame_id=frame_id)
        yield t, Imu(header=hdr, orientation=Q(x=0.0, y=0.0, z=0.0, w=1.0),
                     orientation_covariance=cov,
                     angular_velocity=V3(x=float(gyro[i, 0]), y=float(gyro[i, 1]),
                                         z=float(gyro[i, 2])),
                     angular_velocity_covariance=cov,
                     linear_acceleration=V3(x=float(accel[i, 0]), y=float(accel[i, 1]),
                                            z=float(accel[i, 2])),
                     linear_acceleration_covariance=cov)


def write_ros2_bag(path, t_ns, accel, gyro, storage="sqlite3", topic="/imu", frame_id="imu_link",
                   extra_topic=True):
    """A ROS 2 bag folder (storage sqlite3 or mcap) with one Imu topic (and a
    String topic, which the importer must skip)."""
    from rosbags.rosbag2 import StoragePlugin, Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS2_HUMBLE)
    plugin = StoragePlugin.MCAP if storage == "mcap" else StoragePlugin.SQLITE3
    with Writer(path, version=9, storage_plugin=plugin) as w:
        conn = w.add_connection(topic, "sensor_msgs/msg/Imu", typestore=ts)
        other = w.add_connection("/chatter", "std_msgs/msg/String", typestore=ts) \
            if extra_topic else None
        for i, (t, msg) in enumerate(_imu_msgs(ts, False, t_ns, accel, gyro, frame_id)):
            # received a little after the stamp
            w.write(conn, t + 250_000, ts.serialize_cdr(msg, "sensor_msgs/msg/Imu"))
            if other is not None and i % 1000 == 0:
                s = ts.types["std_msgs/msg/String"](data="hello")
                w.write(other, t, ts.serialize_cdr(s, "std_msgs/msg/String"))


def write_ros1_bag(path, t_ns, accel, gyro, topic="/imu", frame_id="imu_link", recv_ns=None):
    """A ROS 1 bag; ``recv_ns``: receive times (default: the stamps + 0.25 ms)."""
    from rosbags.rosbag1 import Writer
    from rosbags.typesys import Stores, get_typestore

    ts = get_typestore(Stores.ROS1_NOETIC)
    with Writer(path) as w:
        conn = w.add_connection(topic, "sensor_msgs/msg/Imu", typestore=ts)
        for i, (t, msg) in enumerate(_imu_msgs(ts, True, t_ns, accel, gyro, frame_id)):
            tr = t + 250_000 if recv_ns is None else int(recv_ns[i])
            w.write(conn, tr, ts.serialize_ros1(msg, "sensor_msgs/msg/Imu"))


def write_mcap(path, t_ns, accel, gyro, topic="/imu", frame_id="imu_link"):
    """A bare ``.mcap`` file (ROS 2 serialization): rosbags writes a bag folder
    with MCAP storage, whose one ``.mcap`` file is moved to ``path``."""
    import shutil
    import tempfile
    from pathlib import Path

    with tempfile.TemporaryDirectory(dir=Path(path).parent) as tmp:
        bag = Path(tmp) / "bag"
        write_ros2_bag(bag, t_ns, accel, gyro, storage="mcap", topic=topic, frame_id=frame_id,
                       extra_topic=False)
        shutil.move(str(next(bag.glob("*.mcap"))), str(path))


# ---------------------------------------------------------------------------
# calib simulate --out LOG: a simulated record as the firmware would log it

LOG_SUFFIXES = {".ulg": "px4", ".bin": "ardupilot", ".mcap": None, ".bag": None}
SIM_DEVICE_IDS = {"accel": 2490378, "gyro": 2490634}  # as a driver on SPI bus 1 numbers them
SIM_BOOT_US = 20_000_000  # the first sample 20 s after boot (flight-controller clocks)
SIM_EPOCH_NS = 1_700_000_000_000_000_000  # ROS stamps: wall-clock time


def default_params(firmware: str) -> dict:
    """The parameters of a freshly flashed board with one IMU (no calibration,
    no rotation), its device ids as logged."""
    from calib_cli.io import fc_params

    nm = fc_params.names(firmware, 0)
    p = {nm["accel_id"]: SIM_DEVICE_IDS["accel"], nm["gyro_id"]: SIM_DEVICE_IDS["gyro"]}
    for i in range(3):
        p[nm["accel_off"][i]] = 0.0
        p[nm["accel_scale"][i]] = 1.0
        p[nm["gyro_off"][i]] = 0.0
    if firmware == "px4":
        p.update({"CAL_ACC0_ROT": -1, "CAL_GYRO0_ROT": -1, "SENS_BOARD_ROT": 0,
                  "SENS_BOARD_X_OFF": 0.0, "SENS_BOARD_Y_OFF": 0.0, "SENS_BOARD_Z_OFF": 0.0,
                  "TC_A_ENABLE": 0, "TC_G_ENABLE": 0})
    else:
        p.update({"AHRS_ORIENTATION": 0, "INS_TCAL1_ENABLE": 0, "INS_GYR_CAL": 0})
    return p


def write_sim_log(path, rec, firmware_params: dict | None, where: str) -> dict:
    """Write ``rec`` (a simulated record: the sensor's own samples) as the log
    of ``path``'s suffix: ULog (``sensor_accel``/``sensor_gyro`` the samples,
    ``sensor_combined`` corrected by the PX4 parameters in force), DataFlash
    (``IMU``, ``ACC``, ``GYR`` corrected by the ArduPilot parameters in force,
    as ArduPilot logs them), ``.mcap``/``.bag`` (``sensor_msgs/Imu`` on
    ``/imu``, the samples as a ROS driver publishes them). Returns the
    parameters written. ``where`` names the input in errors."""
    import os
    from pathlib import Path

    from calib_cli.errors import InputError
    from calib_cli.io import fc_params
    from calib_cli.io.h5 import atomic_path

    suffix = Path(path).suffix.lower()
    firmware = LOG_SUFFIXES[suffix]
    if rec.units.get("accel") != "m/s^2" or rec.units.get("gyro") != "rad/s" or \
            rec.gyro is None or rec.accel.shape[1] != 3:
        raise InputError("a flight-controller or ROS log holds one triad of accelerometers and "
                         "gyros in SI units: this simulation is not one (counts, a redundant "
                         "unit, or no gyro)", where)
    if firmware is None and firmware_params:
        raise InputError(f"parameters in force are for flight-controller logs: a {suffix} "
                         "bag holds what the driver publishes", where)
    t_us = SIM_BOOT_US + np.round(np.asarray(rec.time) * 1e6).astype(np.int64)
    x, w = rec.accel, rec.gyro
    temp = rec.temp if rec.temp is not None else np.full(len(t_us), 25.0)
    prm = {}
    if firmware is not None:
        guess = fc_params.guess_firmware(firmware_params or {})
        if guess is not None and guess != firmware:
            raise InputError(f"the parameters in force are {guess} parameters, the output "
                             f"{suffix} is a {firmware} log", where)
        prm = {**default_params(firmware), **(firmware_params or {})}
        try:
            cal_a = fc_params.in_force(firmware, prm, "accel", 0, SIM_DEVICE_IDS["accel"]
                                       if firmware == "px4" else None)
            cal_g = fc_params.in_force(firmware, prm, "gyro", 0, SIM_DEVICE_IDS["gyro"]
                                       if firmware == "px4" else None)
        except fc_params.CompositionError as exc:
            raise InputError(str(exc), where) from None
        # float32 as the drivers deliver them, corrected as the firmware does in float
        x = np.asarray(x, np.float32).astype(float)
        w = np.asarray(w, np.float32).astype(float)
        y, yg = cal_a.correct(x, temp), cal_g.correct(w, temp)
    with atomic_path(path) as tmp:
        if suffix == ".ulg":
            ids = (SIM_DEVICE_IDS["accel"], SIM_DEVICE_IDS["gyro"])
            write_ulog(tmp, t_us, x, w, temp, corrected=(y, yg), params=prm, device_ids=ids)
        elif suffix == ".bin":
            write_dataflash(tmp, t_us, y, yg, temp, params=prm, extra_instance=False)
        else:
            os.unlink(tmp)  # rosbags' writers make the file themselves
            t_ns = SIM_EPOCH_NS + np.round(np.asarray(rec.time) * 1e9).astype(np.int64)
            if suffix == ".mcap":
                write_mcap(tmp, t_ns, x, w)
            else:
                write_ros1_bag(tmp, t_ns, x, w)
    return prm
