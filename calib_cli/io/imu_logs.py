"""IMU streams from robotics and flight-controller logs (docs/import.md):
ROS bags (``rosbags``, extra ``[ros]``), PX4 ULog (io/ulog_reader.py) and
ArduPilot DataFlash (io/dataflash_reader.py), all read block by block, so
memory stays flat whatever the log's length.

Each reader turns one IMU stream into ``stream_import.Chunk`` blocks (time
relative to the stream's first sample, s, computed as an integer count of
nanoseconds divided by 1e9; accelerometer m/s^2 and gyro rad/s as logged;
temperature where logged) and goes through the same import pipeline as a
CSV log (``stream_import.import_to_raw``): streaming static detection, plan
matching, raw HDF5. Errors name the file and the stream: a missing or empty
stream, time that does not increase, a gap longer than ``MAX_GAP_PERIODS``
sample periods inside a segment. Shorter gaps are counted and reported.

Provenance (``LogStream.source``, written to the raw file's /source,
docs/file-formats.md): whether the samples are raw or already corrected by
the firmware, and by which parameters (the log's IMU-calibration parameters
at its start, those that changed during it, the sensors' device ids).

Frames: the axes are taken as logged, and that frame is the contract's body
frame of the calibration: ROS ``sensor_msgs/Imu`` in the message's
``frame_id`` (REP-145: the sensor's own frame); PX4 ``sensor_combined`` in
the vehicle frame (board rotation and PX4's calibration applied),
``sensor_accel``/``sensor_gyro`` in the driver's frame before both; ArduPilot
``IMU``/``ACC``/``GYR`` after ArduPilot's calibration and
``AHRS_ORIENTATION`` (docs/import.md has the table).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from calib_cli.errors import InputError
from calib_cli.io import fc_params
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
class LogStream:
    """One IMU stream: ``blocks()`` yields (t_ns int64 (m,), accel (m, 3), gyro
    (m, 3), temp (m,) or None) in time order; ``info`` (counters) and
    ``source`` (provenance) are complete once the blocks are exhausted."""

    name: str  # how errors name it: "topic /imu", "ULog sensor_combined", ...
    blocks: Callable[[], Iterator[tuple]]
    info: dict = field(default_factory=dict)
    source: dict = field(default_factory=dict)


def stream_chunks(path: str, s: LogStream) -> Iterator[Chunk]:
    """Chunks of BLOCK rows of a stream (the readers' blocks gathered: the
    import's detection works in whole chunks, as for a CSV log): time relative
    to its first sample; checks that it increases."""
    t0 = None
    last = None
    count = 0
    pend: list = []
    n_pend = 0

    def emit(final=False):
        nonlocal pend, n_pend
        t = np.concatenate([p[0] for p in pend])
        a = np.concatenate([p[1] for p in pend])
        g = np.concatenate([p[2] for p in pend])
        tp = None if any(p[3] is None for p in pend) else np.concatenate([p[3] for p in pend])
        k = len(t) if final else (len(t) // BLOCK) * BLOCK
        for i in range(0, k, BLOCK):
            j = slice(i, min(i + BLOCK, k))
            yield Chunk(time=t[j], accel=a[j], gyro=g[j],
                        opt={"temp": None if tp is None else tp[j]})
        pend = [] if k == len(t) else [(t[k:], a[k:], g[k:], None if tp is None else tp[k:])]
        n_pend = len(t) - k

    for t_ns, accel, gyro, temp in s.blocks():
        t_ns = np.asarray(t_ns, dtype=np.int64)
        if not len(t_ns):
            continue
        if t0 is None:
            t0 = int(t_ns[0])
        tt = t_ns if last is None else np.concatenate([[last], t_ns])
        d = np.diff(tt)
        if np.any(d <= 0):
            i = int(np.flatnonzero(d <= 0)[0])
            k = count + i + (1 if last is None else 0)  # 0-based index of the later sample
            raise InputError(f"{s.name}: time is not increasing at message {k + 1} "
                             f"({(tt[i] - t0) / 1e9:.9g} s then {(tt[i + 1] - t0) / 1e9:.9g} s "
                             "after the first sample)", path)
        count += len(t_ns)
        last = int(t_ns[-1])
        pend.append(((t_ns - t0) / 1e9, np.asarray(accel, dtype=float),
                     np.asarray(gyro, dtype=float),
                     None if temp is None else np.asarray(temp, dtype=float)))
        n_pend += len(t_ns)
        if n_pend >= BLOCK:
            yield from emit()
    if t0 is None:
        raise InputError(f"{s.name}: no messages", path)
    if n_pend:
        yield from emit(final=True)


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


class Interp:
    """The gyro of another time base interpolated linearly onto the
    accelerometer's times, block by block: accelerometer samples wait until a
    gyro sample at or after them has arrived (np.interp holds the end values
    before the first and after the last gyro sample, as the whole-array
    interpolation would)."""

    def __init__(self, gyro_name: str, path: str):
        self.name, self.path = gyro_name, path
        self.a = []  # pending accelerometer blocks (t, accel, temp)
        self.gt = np.zeros(0, np.int64)
        self.gv = np.zeros((0, 3))
        self.glast = None
        self.gcount = 0
        self.seen_gyro = False

    def feed(self, ta, va, tempa, tg, vg) -> Iterator[tuple]:
        if len(tg):
            tg = np.asarray(tg, np.int64)
            tt = tg if self.glast is None else np.concatenate([[self.glast], tg])
            d = np.diff(tt)
            if np.any(d <= 0):
                i = int(np.flatnonzero(d <= 0)[0]) + (0 if self.glast is None else -1)
                raise InputError(f"{self.name}: time is not increasing at message "
                                 f"{self.gcount + i + 2}", self.path)
            self.gcount += len(tg)
            self.glast = int(tg[-1])
            self.gt = np.concatenate([self.gt, tg])
            self.gv = np.concatenate([self.gv, np.asarray(vg, float).reshape(-1, 3)])
            self.seen_gyro = True
        if len(ta):
            self.a.append((np.asarray(ta, np.int64), np.asarray(va, float).reshape(-1, 3),
                           None if tempa is None else np.asarray(tempa, float)))
        if not self.a or not len(self.gt):
            return
        ta = np.concatenate([x[0] for x in self.a])
        k = int(np.searchsorted(ta, self.gt[-1], side="right"))  # ready: t <= last gyro time
        if k:
            yield from self._emit(k)

    def _emit(self, k):
        ta = np.concatenate([x[0] for x in self.a])
        va = np.concatenate([x[1] for x in self.a])
        temps = [x[2] for x in self.a]
        tp = None if any(t is None for t in temps) else np.concatenate(temps)
        t_out = ta[:k]
        if len(self.gt) == len(t_out) and np.array_equal(self.gt, t_out):
            g = self.gv.copy()
        else:
            g = np.column_stack([np.interp(t_out, self.gt, self.gv[:, j]) for j in range(3)])
        yield t_out, va[:k], g, None if tp is None else tp[:k]
        rest = ta[k:]
        self.a = [(rest, va[k:], None if tp is None else tp[k:])] if len(rest) else []
        # keep the gyro samples the waiting accelerometer samples need (one before them)
        keep = max(0, int(np.searchsorted(self.gt, t_out[-1], side="right")) - 1)
        self.gt, self.gv = self.gt[keep:], self.gv[keep:]

    def finish(self, acc_name: str) -> Iterator[tuple]:
        if not self.a:
            return
        if not self.seen_gyro:
            raise InputError(f"{self.name}: no messages", self.path)
        yield from self._emit(sum(len(x[0]) for x in self.a))


def _rate(count: int, first, last, unit: float) -> float:
    return (count - 1) / ((last - first) / unit) if count > 1 and last > first else 0.0


class _Counter:
    """Message counts and first/last stamps per stream, for the listings."""

    def __init__(self):
        self.rows: dict[str, list] = {}

    def add(self, key: str, t) -> None:
        if not len(t):
            return
        r = self.rows.setdefault(key, [0, int(t[0]), int(t[0])])
        r[0] += len(t)
        r[2] = int(t[-1])

    def listing(self, unit: float, extra: dict | None = None) -> list[dict]:
        out = []
        for k, (n, first, last) in sorted(self.rows.items()):
            row = {"topic": k, "count": n, "rate_hz": _rate(n, first, last, unit)}
            row.update((extra or {}).get(k, {}))
            out.append(row)
        return out


def _changed(params0: dict, changes, firmware: str) -> list[str]:
    """Names of IMU-calibration parameters whose value changed during the log."""
    rel = fc_params.relevant(firmware, {k: v for k, v in changes if v is not None})
    out = []
    for k, _ in changes:
        if k in rel and k not in out:
            vals = [v for kk, v in changes if kk == k]
            if any(float(v) != float(params0.get(k, v)) for v in vals):
                out.append(k)
    return out


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
        cnt = _Counter()
        types = {}
        for c in reader.connections:
            if c.msgtype != IMU_TYPE:
                continue
            types[c.topic] = {"type": c.msgtype}
            for _, t, _ in reader.messages(connections=[c]):
                cnt.add(c.topic, [t])
        return cnt.listing(1e9, types)
    finally:
        reader.close()


def bag_stream(path: str, topic: str, stamp: str = "header") -> LogStream:
    """The sensor_msgs/Imu messages of ``topic``: header stamps (``stamp =
    "receive"``: the bag's receive times); covariances ignored."""
    name = f"topic {topic}"
    reader = _open_bag(path)
    try:
        conns = [c for c in reader.connections if c.topic == topic]
        if not conns:
            imu = sorted({c.topic for c in reader.connections if c.msgtype == IMU_TYPE})
            raise InputError(f"no topic {topic!r} in the bag (IMU topics: "
                             f"{', '.join(imu) or 'none'})", path)
        bad = [c.msgtype for c in conns if c.msgtype != IMU_TYPE]
        if bad:
            raise InputError(f"{name} holds {bad[0]}, not {IMU_TYPE}", path)
    finally:
        reader.close()
    s = LogStream(name, lambda: None)
    s.source.update({"format": "bag", "stream": topic, "samples": "unknown"})

    def blocks():
        rd = _open_bag(path)
        try:
            cs = [c for c in rd.connections if c.topic == topic]
            t, a, g = [], [], []
            for c, t_recv, raw in rd.messages(connections=cs):
                m = rd.deserialize(raw, c.msgtype)
                t.append(int(t_recv) if stamp == "receive" else
                         int(m.header.stamp.sec) * 1_000_000_000 + int(m.header.stamp.nanosec))
                la, av = m.linear_acceleration, m.angular_velocity
                a.append((la.x, la.y, la.z))
                g.append((av.x, av.y, av.z))
                if "frame_id" not in s.info:
                    s.info["frame_id"] = m.header.frame_id
                    s.source["frame_id"] = m.header.frame_id
                if len(t) == BLOCK:
                    yield np.array(t, np.int64), np.array(a), np.array(g), None
                    t, a, g = [], [], []
            if t:
                yield np.array(t, np.int64), np.array(a), np.array(g), None
        except InputError:
            raise
        except Exception as exc:
            raise InputError(f"{name}: cannot read the messages: {exc}", path) from None
        finally:
            rd.close()

    s.blocks = blocks
    return s


# ---------------------------------------------------------------------------
# PX4 ULog

ULOG_TOPICS = ("sensor_combined", "sensor_accel", "sensor_gyro")


def _ulog(path: str):
    from calib_cli.io.ulog_reader import open_ulog

    return open_ulog(path)


def _ulog_scan(path, r, *args):
    try:
        yield from r.scan(*args)
    except InputError:
        raise
    except (ValueError, IndexError, KeyError) as exc:
        raise InputError(f"cannot read the ULog file: {exc}", path) from None


def list_ulog_streams(path: str) -> list[dict]:
    """sensor_combined, sensor_accel, sensor_gyro instances: counts and rates
    (from ``timestamp_sample`` where the topic has it, else ``timestamp``)."""
    r = _ulog(path)
    cnt = _Counter()
    for blk in _ulog_scan(path, r, ULOG_TOPICS):
        for name, multi, rec in blk:
            key = "timestamp_sample" if "timestamp_sample" in rec.dtype.names else "timestamp"
            cnt.add(f"{name}[{multi}]", rec[key])
    return cnt.listing(1e6)


def _ulog_source(r, stream: str, corrected: bool, instance: int) -> dict:
    params = fc_params.relevant("px4", {k: v for k, v in r.params.items() if v is not None})
    return {"format": "ulog", "firmware": "px4", "stream": stream, "instance": instance,
            "samples": "corrected" if corrected else "raw",
            "corrected_by": ("PX4 CAL_ACCn_*/CAL_GYROn_* offsets and scales, TC_* thermal "
                             "compensation, SENS_BOARD_* rotation") if corrected else "",
            "parameters": params, "sys_name": str(r.info.get("sys_name") or ""),
            "ver_sw": str(r.info.get("ver_sw") or "")}


def _ulog_finish(s: LogStream, r, ids: dict) -> None:
    s.source["parameters_changed"] = _changed(s.source["parameters"], r.param_changes, "px4")
    s.source["device_ids"] = ids
    if r.dropouts[0]:
        s.info["dropouts"] = r.dropouts[0]
        s.info["dropout_ms"] = r.dropouts[1]
    if r.truncated_bytes:
        s.info["truncated_bytes"] = r.truncated_bytes
    if r.corrupt_bytes:
        s.info["corrupt_bytes"] = r.corrupt_bytes


def ulog_stream(path: str, source: str = "sensor_combined", instance: int = 0) -> LogStream:
    """``sensor_combined`` (the autopilot's corrected data), or ``sensor``:
    ``sensor_accel``/``sensor_gyro`` of one instance (the drivers' data,
    before the autopilot's calibration), the gyro interpolated onto the
    accelerometer's sample times when they differ."""
    r = _ulog(path)
    if source == "sensor_combined":
        name = "ULog sensor_combined"
        if "sensor_combined" not in r.formats:
            raise InputError(f"{name}: not in the log", path)
        s = LogStream(name, lambda: None, source=_ulog_source(r, "sensor_combined", True, 0))

        def blocks():
            sel, dev = None, {}
            for blk in _ulog_scan(path, r, ["sensor_combined"],
                                  ["sensor_selection", "sensor_accel", "sensor_gyro"]):
                for nm, multi, rec in blk:
                    if nm == "sensor_combined":
                        yield (rec["timestamp"].astype(np.int64) * 1000,
                               np.column_stack([rec[f"accelerometer_m_s2[{i}]"]
                                                for i in range(3)]),
                               np.column_stack([rec[f"gyro_rad[{i}]"] for i in range(3)]), None)
                    elif nm == "sensor_selection" and sel is None:
                        sel = {"accel": int(rec["accel_device_id"][0]),
                               "gyro": int(rec["gyro_device_id"][0])}
                    elif "device_id" in rec.dtype.names:
                        dev.setdefault(nm, {})[multi] = int(rec["device_id"][0])
            # which sensors sensor_combined comes from: sensor_selection, else the only one
            ids = dict(sel or {})
            for sensor, topic in (("accel", "sensor_accel"), ("gyro", "sensor_gyro")):
                if sensor not in ids and len(dev.get(topic, {})) == 1:
                    ids[sensor] = next(iter(dev[topic].values()))
            _ulog_finish(s, r, ids)

        s.blocks = blocks
        return s
    for what in ("sensor_accel", "sensor_gyro"):
        if what not in r.formats:
            raise InputError(f"ULog {what}[{instance}]: not in the log (instances: none)", path)
    s = LogStream(f"ULog sensor_accel[{instance}]", lambda: None,
                  source=_ulog_source(r, f"sensor_accel[{instance}]", False, instance))

    def blocks_sensor():
        it = Interp(f"ULog sensor_gyro[{instance}]", path)
        ids, seen = {}, False
        for blk in _ulog_scan(path, r, ["sensor_accel", "sensor_gyro"]):
            ta = va = tg = vg = tempa = ()
            for nm, multi, rec in blk:
                if multi != instance:
                    continue
                key = "timestamp_sample" if "timestamp_sample" in rec.dtype.names else "timestamp"
                t = rec[key].astype(np.int64) * 1000
                v = np.column_stack([rec["x"], rec["y"], rec["z"]]).astype(float)
                sensor = "accel" if nm == "sensor_accel" else "gyro"
                if "device_id" in rec.dtype.names and sensor not in ids and len(rec):
                    ids[sensor] = int(rec["device_id"][0])
                if nm == "sensor_accel":
                    ta, va, seen = t, v, True
                    tempa = rec["temperature"] if "temperature" in rec.dtype.names else None
                else:
                    tg, vg = t, v
            yield from it.feed(ta, va, tempa if len(ta) else None, tg, vg)
        if not seen:
            have = sorted(m for (nm, m) in r.subscriptions if nm == "sensor_accel")
            raise InputError(f"ULog sensor_accel[{instance}]: not in the log (instances: "
                             f"{', '.join(map(str, have)) or 'none'})", path)
        yield from it.finish("sensor_accel")
        _ulog_finish(s, r, ids)

    s.blocks = blocks_sensor
    return s


# ---------------------------------------------------------------------------
# ArduPilot DataFlash


def _dataflash(path: str):
    from calib_cli.io.dataflash_reader import open_dataflash

    return open_dataflash(path)


def _df_scan(path, r, names):
    try:
        yield from r.scan(names)
    except InputError:
        raise
    except (ValueError, IndexError, KeyError) as exc:
        raise InputError(f"cannot read the DataFlash log: {exc}", path) from None


LEGACY = {"IMU": ("IMU", "IMU2", "IMU3"), "ACC": ("ACC1", "ACC2", "ACC3"),
          "GYR": ("GYR1", "GYR2", "GYR3")}


def _df_split(r, kind: str, out: dict) -> dict:
    """{instance: records} of a kind (IMU, ACC, GYR) in one block: the ``I``
    field of ArduPilot >= 4.1, or the legacy per-instance messages (IMU, IMU2,
    IMU3; ACC1..3; GYR1..3)."""
    res = {}
    f = r.formats.get(kind)
    if kind in out and f is not None and "I" in f.columns:
        rec = out[kind]
        for k in np.unique(rec["I"]).tolist():
            res[int(k)] = rec[rec["I"] == k]
        return res
    for k, name in enumerate(LEGACY[kind]):
        if name in out:
            res[k] = out[name]
    return res


def _df_time(rec) -> np.ndarray:
    key = "SampleUS" if "SampleUS" in rec.dtype.names else "TimeUS"
    return rec[key].astype(np.int64)


def _df_names(kinds) -> set:
    return {n for k in kinds for n in (k, *LEGACY[k])} | {"PARM"}


def list_dataflash_streams(path: str) -> list[dict]:
    """IMU, ACC, GYR per instance (legacy IMU2/IMU3, ACC1..3, GYR1..3 listed as
    the instances they are, with their own message names)."""
    r = _dataflash(path)
    cnt = _Counter()
    legacy = {}
    for out in _df_scan(path, r, _df_names(("IMU", "ACC", "GYR"))):
        for kind in ("IMU", "ACC", "GYR"):
            for k, rec in _df_split(r, kind, out).items():
                key = f"{kind}[{k}]"
                cnt.add(key, _df_time(rec))
                f = r.formats.get(kind)
                if f is None or "I" not in f.columns:
                    legacy[key] = {"message": LEGACY[kind][k]}
    rows = cnt.listing(1e6, legacy)
    for row in rows:
        if "message" in row:
            row["topic"] = f"{row['topic']} ({row['message']})"
    return rows


def _df_params(out, params: dict, changes: list) -> None:
    rec = out.get("PARM")
    if rec is None:
        return
    for nm, v in zip(rec["Name"].tolist(), rec["Value"].tolist()):
        k = nm.split(b"\0", 1)[0].decode("ascii", "replace")
        if k in params:
            if float(v) != params[k]:
                changes.append((k, float(v)))
        else:
            params[k] = float(v)


def dataflash_stream(path: str, message: str = "IMU", instance: int = 0) -> LogStream:
    """``IMU`` messages of one instance (``I``; legacy logs: IMU, IMU2, IMU3),
    or the unfiltered ``ACC`` and ``GYR`` messages (time: ``SampleUS``; the
    gyro interpolated onto the accelerometer's sample times when they differ;
    legacy ACC1..3, GYR1..3). ArduPilot corrects both (offsets, scales,
    temperature calibration, AHRS_ORIENTATION) before it logs them."""
    r = _dataflash(path)
    name = f"DataFlash {message}[{instance}]"
    src = {"format": "dataflash", "firmware": "ardupilot", "instance": instance,
           "stream": f"{message}[{instance}]", "samples": "corrected",
           "corrected_by": "ArduPilot INS_* offsets, scales and temperature calibration, "
                           "AHRS_ORIENTATION" + (" (and its low-pass filters)"
                                                 if message == "IMU" else "")}
    s = LogStream(name, lambda: None, source=src)
    params: dict = {}
    changes: list = []

    def finish():
        rel = fc_params.relevant("ardupilot", params)
        src["parameters"] = rel
        src["parameters_changed"] = _changed(rel, changes, "ardupilot")
        if 0 <= instance < 5:
            nm = fc_params.names("ardupilot", instance)
            src["device_ids"] = {sensor: int(params[nm[f"{sensor}_id"]])
                                 for sensor in ("accel", "gyro") if nm[f"{sensor}_id"] in params}
        for k in ("skipped_bytes", "truncated_bytes"):
            if getattr(r, k, 0):
                s.info[k] = int(getattr(r, k))

    if message == "IMU":
        def blocks():
            seen = False
            for out in _df_scan(path, r, _df_names(("IMU",))):
                _df_params(out, params, changes)
                rec = _df_split(r, "IMU", out).get(instance)
                if rec is None or not len(rec):
                    continue
                seen = True
                yield (_df_time(rec) * 1000,
                       np.column_stack([rec["AccX"], rec["AccY"], rec["AccZ"]]),
                       np.column_stack([rec["GyrX"], rec["GyrY"], rec["GyrZ"]]),
                       rec["T"] if "T" in rec.dtype.names else None)
            finish()
            if not seen:
                raise InputError(f"{name}: no messages", path)

        s.blocks = blocks
        return s
    s.name = f"DataFlash ACC[{instance}]"

    def blocks_raw():
        it = Interp(f"DataFlash GYR[{instance}]", path)
        seen = False
        for out in _df_scan(path, r, _df_names(("ACC", "GYR"))):
            _df_params(out, params, changes)
            a = _df_split(r, "ACC", out).get(instance)
            g = _df_split(r, "GYR", out).get(instance)
            ta = va = tg = vg = ()
            if a is not None and len(a):
                seen = True
                ta = _df_time(a) * 1000
                va = np.column_stack([a["AccX"], a["AccY"], a["AccZ"]])
            if g is not None and len(g):
                tg = _df_time(g) * 1000
                vg = np.column_stack([g["GyrX"], g["GyrY"], g["GyrZ"]])
            yield from it.feed(ta, va, None, tg, vg)
        finish()
        if not seen:
            raise InputError(f"DataFlash ACC[{instance}]: no messages", path)
        yield from it.finish("ACC")

    s.blocks = blocks_raw
    return s
