"""IMU streams from robotics and flight-controller logs (docs/import.md):
ROS bags (``rosbags``, extra ``[ros]``), PX4 ULog (``pyulog``, ``[px4]``)
and ArduPilot DataFlash (``pymavlink``, ``[ardupilot]``).

Each reader turns one IMU stream into ``stream_import.Chunk`` blocks (time
relative to the stream's first sample, s, computed as an integer count of
nanoseconds divided by 1e9; accelerometer m/s^2 and gyro rad/s as logged;
temperature where logged) and goes through the same import pipeline as a
CSV log (``stream_import.import_to_raw``): streaming static detection, plan
matching, raw HDF5. Errors name the file and the stream: a missing or empty
stream, time that does not increase, a gap longer than ``MAX_GAP_PERIODS``
sample periods inside a segment. Shorter gaps are counted and reported.

Frames: the axes are taken as logged, and that frame is the contract's body
frame of the calibration: ROS ``sensor_msgs/Imu`` in the message's
``frame_id`` (REP-145: the sensor's own frame); PX4 ``sensor_combined`` in
the vehicle frame (board rotation and PX4's calibration applied),
``sensor_accel``/``sensor_gyro`` in the driver's frame before both; ArduPilot
``IMU``/``ACC``/``GYR`` after ArduPilot's calibration and
``AHRS_ORIENTATION`` (docs/import.md has the table).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from calib_cli.errors import InputError
from calib_cli.io.stream_import import Chunk

MAX_GAP_PERIODS = 5.0  # a longer gap inside a segment is an error
GAP_PERIODS = 1.5  # a step longer than this many sample periods is a gap
BLOCK = 65536
IMU_TYPE = "sensor_msgs/msg/Imu"


def _need(module: str, extra: str, path: str, what: str):
    import importlib

    try:
        return importlib.import_module(module)
    except ImportError:
        raise InputError(f"reading {what} needs the {module.split('.')[0]} package: install "
                         f"calib-cli[{extra}]", path) from None


@dataclass
class Stream:
    """One IMU stream in time order: integer time stamps (ns) and values."""

    name: str  # how errors name it: "topic /imu", "ULog sensor_combined", ...
    t_ns: list = field(default_factory=list)
    accel: list = field(default_factory=list)
    gyro: list = field(default_factory=list)
    temp: list = field(default_factory=list)
    info: dict = field(default_factory=dict)


def chunks_from_arrays(path: str, name: str, t_ns, accel, gyro, temp=None) -> Iterator[Chunk]:
    """Chunks of a stream held as arrays; checks that time increases."""
    t_ns = np.asarray(t_ns, dtype=np.int64)
    if len(t_ns) == 0:
        raise InputError(f"{name}: no messages", path)
    d = np.diff(t_ns)
    if np.any(d <= 0):
        i = int(np.flatnonzero(d <= 0)[0])
        t0 = t_ns[0]
        raise InputError(f"{name}: time is not increasing at message {i + 2} "
                         f"({(t_ns[i] - t0) / 1e9:.9g} s then {(t_ns[i + 1] - t0) / 1e9:.9g} s "
                         "after the first sample)", path)
    t = (t_ns - t_ns[0]) / 1e9
    for i in range(0, len(t), BLOCK):
        j = slice(i, i + BLOCK)
        yield Chunk(time=t[j], accel=np.asarray(accel[j], dtype=float),
                    gyro=np.asarray(gyro[j], dtype=float),
                    opt={"temp": None if temp is None else np.asarray(temp[j], dtype=float)})


def gap_check(path: str, name: str):
    """For ``import_to_raw(check=...)``: a gap longer than MAX_GAP_PERIODS
    sample periods inside a segment is an error naming its time; the others
    are counted (returned as counters)."""
    from calib_cli.methods.static_stream import stream_median_diff

    def check(sink, segments):
        times = sink.times
        dt = stream_median_diff(times, sink.n)
        starts = np.array([s.start for s in segments])
        stops = np.array([s.stop for s in segments])
        n_gaps, longest, off, last = 0, 0.0, 0, None
        for t in times():
            tt = t if last is None else np.concatenate([[last], t])
            d = np.diff(tt)
            idx = np.flatnonzero(d > GAP_PERIODS * dt)
            for k in idx.tolist():
                i = off + k + (1 if last is None else 0)  # the sample after the gap
                g = float(d[k])
                inside = np.flatnonzero((starts < i) & (i < stops))
                if g > MAX_GAP_PERIODS * dt and len(inside):
                    seg = segments[int(inside[0])]
                    raise InputError(f"{name}: gap of {g:.6g} s ({g / dt:.1f} sample periods) at "
                                     f"t = {float(tt[k]):.6f} s inside segment {seg.label!r} "
                                     f"(at most {MAX_GAP_PERIODS:g} periods)", path)
                n_gaps += 1
                longest = max(longest, g / dt)
            off += len(t)
            last = t[-1]
        return {"gaps": n_gaps, "longest_gap_periods": longest, "sample_period_s": dt}

    return check


# ---------------------------------------------------------------------------
# ROS bags


def _open_bag(path: str):
    hl = _need("rosbags.highlevel", "ros", path, "ROS bags")
    ts = _need("rosbags.typesys", "ros", path, "ROS bags")
    p = Path(path)
    if not p.exists():
        raise InputError("no such file or bag folder", path)
    try:
        reader = hl.AnyReader([p], default_typestore=ts.get_typestore(ts.Stores.ROS2_HUMBLE))
        reader.open()
    except Exception as exc:  # rosbags raises several kinds for unreadable bags
        raise InputError(f"cannot read the bag: {exc}", path) from None
    return reader


def list_bag_topics(path: str) -> list[dict]:
    """IMU topics of a bag: topic, count, rate (Hz, from the receive times)."""
    reader = _open_bag(path)
    try:
        out = []
        for c in reader.connections:
            if c.msgtype != IMU_TYPE:
                continue
            ts = [t for _, t, _ in reader.messages(connections=[c])]
            n = len(ts)
            rate = (n - 1) / ((ts[-1] - ts[0]) / 1e9) if n > 1 and ts[-1] > ts[0] else 0.0
            out.append({"topic": c.topic, "type": c.msgtype, "count": n, "rate_hz": rate})
        return out
    finally:
        reader.close()


def bag_stream(path: str, topic: str, stamp: str = "header") -> Stream:
    """The sensor_msgs/Imu messages of ``topic``: header stamps (``stamp =
    "receive"``: the bag's receive times); covariances ignored."""
    reader = _open_bag(path)
    name = f"topic {topic}"
    try:
        conns = [c for c in reader.connections if c.topic == topic]
        if not conns:
            imu = sorted({c.topic for c in reader.connections if c.msgtype == IMU_TYPE})
            raise InputError(f"no topic {topic!r} in the bag (IMU topics: "
                             f"{', '.join(imu) or 'none'})", path)
        bad = [c.msgtype for c in conns if c.msgtype != IMU_TYPE]
        if bad:
            raise InputError(f"{name} holds {bad[0]}, not {IMU_TYPE}", path)
        s = Stream(name)
        for c, t_recv, raw in reader.messages(connections=conns):
            m = reader.deserialize(raw, c.msgtype)
            if stamp == "receive":
                s.t_ns.append(int(t_recv))
            else:
                s.t_ns.append(int(m.header.stamp.sec) * 1_000_000_000 + int(m.header.stamp.nanosec))
            la, av = m.linear_acceleration, m.angular_velocity
            s.accel.append((la.x, la.y, la.z))
            s.gyro.append((av.x, av.y, av.z))
            if "frame_id" not in s.info:
                s.info["frame_id"] = m.header.frame_id
        return s
    except InputError:
        raise
    except Exception as exc:
        raise InputError(f"{name}: cannot read the messages: {exc}", path) from None
    finally:
        reader.close()


# ---------------------------------------------------------------------------
# PX4 ULog


def _ulog(path: str, names):
    pyulog = _need("pyulog", "px4", path, "PX4 ULog files")
    if not Path(path).is_file():
        raise InputError("no such file", path)
    try:
        return pyulog.ULog(path, names)
    except Exception as exc:
        raise InputError(f"cannot read the ULog file: {exc}", path) from None


def list_ulog_streams(path: str) -> list[dict]:
    ul = _ulog(path, ["sensor_combined", "sensor_accel", "sensor_gyro"])
    out = []
    for d in ul.data_list:
        t = d.data["timestamp"].astype(np.int64)
        n = len(t)
        rate = (n - 1) / ((t[-1] - t[0]) / 1e6) if n > 1 and t[-1] > t[0] else 0.0
        out.append({"topic": f"{d.name}[{d.multi_id}]", "count": n, "rate_hz": rate})
    return out


def _interp_onto(t_dst, t_src, x_src):
    if len(t_src) == len(t_dst) and np.array_equal(t_src, t_dst):
        return x_src
    return np.column_stack([np.interp(t_dst, t_src, x_src[:, j]) for j in range(x_src.shape[1])])


def ulog_stream(path: str, source: str = "sensor_combined", instance: int = 0) -> Stream:
    """``sensor_combined`` (the autopilot's corrected data), or ``sensor``:
    ``sensor_accel``/``sensor_gyro`` of one instance (the drivers' data,
    before the autopilot's calibration), the gyro interpolated onto the
    accelerometer's sample times when they differ."""
    if source == "sensor_combined":
        ul = _ulog(path, ["sensor_combined"])
        ds = [d for d in ul.data_list if d.name == "sensor_combined"]
        name = "ULog sensor_combined"
        if not ds:
            raise InputError(f"{name}: not in the log", path)
        d = ds[0].data
        s = Stream(name)
        s.t_ns = d["timestamp"].astype(np.int64) * 1000
        s.accel = np.column_stack([d[f"accelerometer_m_s2[{i}]"] for i in range(3)])
        s.gyro = np.column_stack([d[f"gyro_rad[{i}]"] for i in range(3)])
        s.temp = None
        s.info["corrected"] = True
        return s
    ul = _ulog(path, ["sensor_accel", "sensor_gyro"])
    acc = [d for d in ul.data_list if d.name == "sensor_accel" and d.multi_id == instance]
    gyr = [d for d in ul.data_list if d.name == "sensor_gyro" and d.multi_id == instance]
    for what, lst in (("sensor_accel", acc), ("sensor_gyro", gyr)):
        if not lst:
            have = sorted(d.multi_id for d in ul.data_list if d.name == what)
            raise InputError(f"ULog {what}[{instance}]: not in the log (instances: "
                             f"{', '.join(map(str, have)) or 'none'})", path)
    a, g = acc[0].data, gyr[0].data
    key = "timestamp_sample" if "timestamp_sample" in a else "timestamp"
    ta = a[key].astype(np.int64)
    tg = g[key if key in g else "timestamp"].astype(np.int64)
    s = Stream(f"ULog sensor_accel[{instance}]")
    s.t_ns = ta * 1000
    s.accel = np.column_stack([a["x"], a["y"], a["z"]])
    for nm, tt in (("sensor_gyro", tg), ("sensor_accel", ta)):
        if len(tt) and np.any(np.diff(tt) <= 0):
            i = int(np.flatnonzero(np.diff(tt) <= 0)[0])
            raise InputError(f"ULog {nm}[{instance}]: time is not increasing at message {i + 2}",
                             path)
    if len(tg) == 0:
        raise InputError(f"ULog sensor_gyro[{instance}]: no messages", path)
    s.gyro = _interp_onto(ta, tg, np.column_stack([g["x"], g["y"], g["z"]]).astype(float))
    s.temp = a.get("temperature")
    s.info["corrected"] = False
    return s


# ---------------------------------------------------------------------------
# ArduPilot DataFlash


def _dataflash_messages(path: str, types):
    DFReader = _need("pymavlink.DFReader", "ardupilot", path, "ArduPilot DataFlash logs")
    if not Path(path).is_file():
        raise InputError("no such file", path)
    try:
        log = DFReader.DFReader_binary(path, zero_time_base=True)
    except Exception as exc:
        raise InputError(f"cannot read the DataFlash log: {exc}", path) from None
    while True:
        try:
            m = log.recv_match(type=types)
        except Exception as exc:
            raise InputError(f"cannot read the DataFlash log: {exc}", path) from None
        if m is None:
            return
        yield m


def list_dataflash_streams(path: str) -> list[dict]:
    ts: dict[str, list] = {}
    for m in _dataflash_messages(path, ["IMU", "ACC", "GYR"]):
        ts.setdefault(f"{m.get_type()}[{getattr(m, 'I', 0)}]", []).append(m.TimeUS)
    out = []
    for k, t in sorted(ts.items()):
        n = len(t)
        rate = (n - 1) / ((t[-1] - t[0]) / 1e6) if n > 1 and t[-1] > t[0] else 0.0
        out.append({"topic": k, "count": n, "rate_hz": rate})
    return out


def dataflash_stream(path: str, message: str = "IMU", instance: int = 0) -> Stream:
    """``IMU`` messages of one instance (``I``), or the unfiltered ``ACC`` and
    ``GYR`` messages (time: ``SampleUS``; the gyro interpolated onto the
    accelerometer's sample times when they differ)."""
    if message == "IMU":
        s = Stream(f"DataFlash IMU[{instance}]")
        for m in _dataflash_messages(path, ["IMU"]):
            if getattr(m, "I", 0) != instance:
                continue
            s.t_ns.append(int(m.TimeUS) * 1000)
            s.accel.append((m.AccX, m.AccY, m.AccZ))
            s.gyro.append((m.GyrX, m.GyrY, m.GyrZ))
            if hasattr(m, "T"):
                s.temp.append(m.T)
        if s.temp and len(s.temp) != len(s.t_ns):
            s.temp = []
        s.temp = s.temp or None
        return s
    acc, gyr = [], []
    for m in _dataflash_messages(path, ["ACC", "GYR"]):
        if getattr(m, "I", 0) != instance:
            continue
        t = int(getattr(m, "SampleUS", m.TimeUS))
        if m.get_type() == "ACC":
            acc.append((t, m.AccX, m.AccY, m.AccZ))
        else:
            gyr.append((t, m.GyrX, m.GyrY, m.GyrZ))
    s = Stream(f"DataFlash ACC[{instance}]")
    if not acc:
        raise InputError(f"{s.name}: no messages", path)
    if not gyr:
        raise InputError(f"DataFlash GYR[{instance}]: no messages", path)
    a, g = np.array(acc, dtype=float), np.array(gyr, dtype=float)
    ta, tg = a[:, 0].astype(np.int64), g[:, 0].astype(np.int64)
    if np.any(np.diff(tg) <= 0):
        i = int(np.flatnonzero(np.diff(tg) <= 0)[0])
        raise InputError(f"DataFlash GYR[{instance}]: time is not increasing at message {i + 2}",
                         path)
    s.t_ns = ta * 1000
    s.accel = a[:, 1:]
    s.gyro = _interp_onto(ta, tg, g[:, 1:])
    s.temp = None
    return s


def stream_chunks(path: str, s: Stream) -> Iterator[Chunk]:
    temp = None if s.temp is None or len(s.temp) == 0 else np.asarray(s.temp, dtype=float)
    accel = np.asarray(s.accel, dtype=float).reshape(-1, 3)
    gyro = np.asarray(s.gyro, dtype=float).reshape(-1, 3)
    return chunks_from_arrays(path, s.name, s.t_ns, accel, gyro, temp)
