"""Test-only writers of the log formats `calib import` reads: ROS bags through
rosbags' writers; PX4 ULog and ArduPilot DataFlash written here from their
published format specifications (pyulog and pymavlink read, they do not
write), read back by pyulog and pymavlink in the tests.

ULog (docs.px4.io "ULog File Format"): a 16-byte header (magic
``ULog\\x01\\x12\\x35``, version, uint64 start time in us), then messages of
``uint16 size, uint8 type, payload``: 'B' flag bits, 'F' formats
("name:type field;..." with uint64_t timestamp first), 'A' subscriptions
(uint8 multi_id, uint16 msg_id, name), 'D' data (uint16 msg_id, packed
little-endian fields).

DataFlash (ArduPilot "Onboard logs"; pymavlink DFReader): messages of
``0xA3 0x95 type`` then the packed payload; type 128 (FMT) defines a type:
``uint8 type, uint8 length, char[4] name, char[16] format, char[64] labels``
with format characters Q (uint64), B (uint8), I (uint32), f (float) ...
"""

from __future__ import annotations

import struct

import numpy as np

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
_CODES = {"uint64_t": "Q", "uint32_t": "I", "int32_t": "i", "uint8_t": "B", "float": "f",
          "double": "d", "int16_t": "h", "uint16_t": "H"}


def _umsg(kind: bytes, payload: bytes) -> bytes:
    return struct.pack("<HB", len(payload), kind[0]) + payload


def _ufmt(name, fields) -> bytes:
    return _umsg(b"F", (name + ":" + "".join(f"{t} {n};" for t, n in fields)).encode())


def _upack(fields):
    code = "<"
    for t, _ in fields:
        if t.endswith("]"):
            base, n = t[:-1].split("[")
            code += _CODES[base] * int(n)
        else:
            code += _CODES[t]
    return struct.Struct(code)


def write_ulog(path, t_us, accel, gyro, temp=None, combined=True, sensors=True,
               time_override=None):
    """A ULog file: sensor_combined (the corrected IMU) and sensor_accel /
    sensor_gyro instance 0 (the driver data), interleaved in time order."""
    t_us = np.asarray(t_us, dtype=np.int64)
    out = bytearray(ULOG_MAGIC + b"\x01" + struct.pack("<Q", int(t_us[0])))
    out += _umsg(b"B", bytes(8) + bytes(8) + struct.pack("<QQQ", 0, 0, 0))
    out += _umsg(b"I", bytes([len("char[9] sys_name")]) + b"char[9] sys_name" + b"calibtest")
    topics = []
    if combined:
        topics.append(("sensor_combined", SENSOR_COMBINED))
    if sensors:
        topics += [("sensor_accel", SENSOR_XYZ), ("sensor_gyro", SENSOR_XYZ)]
    for name, fields in topics:
        out += _ufmt(name, fields)
    for msg_id, (name, _) in enumerate(topics):
        out += _umsg(b"A", struct.pack("<BH", 0, msg_id) + name.encode())
    packs = [_upack(f) for _, f in topics]
    temp = np.full(len(t_us), 25.0) if temp is None else temp
    for i in range(len(t_us)):
        t = int(t_us[i])
        for msg_id, (name, _) in enumerate(topics):
            if name == "sensor_combined":
                vals = [t, *map(float, gyro[i]), 1000, 0, *map(float, accel[i]), 1000, 0, 0, 1, 1]
            elif name == "sensor_accel":
                vals = [t, t, 1234, *map(float, accel[i]), float(temp[i]), 0]
            else:
                vals = [t, t, 5678, *map(float, gyro[i]), float(temp[i]), 0]
            out += _umsg(b"D", struct.pack("<H", msg_id) + packs[msg_id].pack(*vals))
    with open(path, "wb") as fh:
        fh.write(out)


# ---------------------------------------------------------------------------
# DataFlash

FMT_STRUCT = struct.Struct("<BB4s16s64s")
_DF = {"Q": "Q", "B": "B", "I": "I", "f": "f", "h": "h", "H": "H", "i": "i", "q": "q",
       "d": "d", "n": "4s", "N": "16s", "Z": "64s"}
IMU_FMT = ("QBffffffIIfBBHH", "TimeUS,I,GyrX,GyrY,GyrZ,AccX,AccY,AccZ,EG,EA,T,GH,AH,GHz,AHz")
ACC_FMT = ("QBQfff", "TimeUS,I,SampleUS,AccX,AccY,AccZ")
GYR_FMT = ("QBQfff", "TimeUS,I,SampleUS,GyrX,GyrY,GyrZ")


def _df_fmt(msg_type, name, fmt, labels) -> bytes:
    length = 3 + struct.calcsize("<" + "".join(_DF[c] for c in fmt))
    return b"\xa3\x95\x80" + FMT_STRUCT.pack(msg_type, length, name.encode(), fmt.encode(),
                                              labels.encode())


def write_dataflash(path, t_us, accel, gyro, temp=None, instance=0, raw=True):
    """A DataFlash log: FMT for itself, IMU, ACC and GYR; IMU messages of the
    given instance (and of instance 1, which the importer must skip), ACC/GYR."""
    t_us = np.asarray(t_us, dtype=np.int64)
    temp = np.full(len(t_us), 25.0) if temp is None else temp
    out = bytearray(_df_fmt(128, "FMT", "BBnNZ", "Type,Length,Name,Format,Columns"))
    out += _df_fmt(131, "IMU", *IMU_FMT)
    out += _df_fmt(132, "ACC", *ACC_FMT)
    out += _df_fmt(133, "GYR", *GYR_FMT)
    imu = struct.Struct("<" + "".join(_DF[c] for c in IMU_FMT[0]))
    xyz = struct.Struct("<" + "".join(_DF[c] for c in ACC_FMT[0]))
    for i in range(len(t_us)):
        t = int(t_us[i])
        g, a = gyro[i], accel[i]
        for inst in (instance, instance + 1):
            out += b"\xa3\x95\x83" + imu.pack(t, inst, *map(float, g), *map(float, a), 0, 0,
                                              float(temp[i]), 1, 1, 1000, 1000)
        if raw:
            out += b"\xa3\x95\x84" + xyz.pack(t, instance, t, *map(float, a))
            out += b"\xa3\x95\x85" + xyz.pack(t, instance, t, *map(float, g))
    with open(path, "wb") as fh:
        fh.write(out)
