"""calib's log writers and readers against the independent readers (issue 34):
what calib_cli/io/log_writers.py writes, pyulog, pymavlink and rosbags read
back bit-exactly; what pyulog and pymavlink read from a file, calib's
streaming readers (io/ulog_reader.py, io/dataflash_reader.py) read too, also
from damaged, truncated and awkward files, and in blocks of any size."""

from __future__ import annotations

import struct

import numpy as np
import pytest
from log_writers import write_dataflash, write_mcap, write_ros1_bag, write_ulog

from calib_cli.io.dataflash_reader import DataFlashReader
from calib_cli.io.ulog_reader import ULogReader

N = 3000
T_US = 5_000_000 + np.arange(N, dtype=np.int64) * 1000


def _vals(seed=0):
    rng = np.random.default_rng(seed)
    a = rng.normal(0, 3, (N, 3)).astype(np.float32)
    g = rng.normal(0, 0.3, (N, 3)).astype(np.float32)
    # floats whose bytes hold the DataFlash header pair 0xA3 0x95 (false candidates)
    a[::7, 1] = np.frombuffer(b"\xa3\x95\x10\x3f", np.float32)[0]
    g[::11, 2] = np.frombuffer(b"\x00\xa3\x95\x3f", np.float32)[0]
    return a, g


def _pymavlink(path, types):
    from pymavlink import DFReader

    log = DFReader.DFReader_binary(str(path), zero_time_base=True)
    out = {}
    while True:
        m = log.recv_match(type=types)
        if m is None:
            return out
        out.setdefault(m.get_type(), []).append(m.to_dict())


def _ours_df(path, names, block):
    r = DataFlashReader(str(path))
    out = {}
    for blk in r.scan(names, block=block):
        for k, v in blk.items():
            out.setdefault(k, []).append(v)
    return r, {k: np.concatenate(v) for k, v in out.items()}


@pytest.mark.parametrize("block", [1000, 4099, 1 << 20])
@pytest.mark.parametrize("legacy", [False, True])
def test_dataflash_same_as_pymavlink(tmp_path, block, legacy):
    a, g = _vals()
    p = tmp_path / "x.bin"
    prm = {"INS_ACCOFFS_X": 0.12, "AHRS_ORIENTATION": 2.0}
    write_dataflash(p, T_US, a, g, temp=np.linspace(20, 40, N), legacy=legacy, params=prm,
                    param_changes=[(int(T_US[100]), "INS_ACCOFFS_X", 0.2)])
    imu = ["IMU", "IMU2"] if legacy else ["IMU"]
    acc = ["ACC1", "ACC2"] if legacy else ["ACC"]
    ref = _pymavlink(p, imu + acc + ["PARM"])
    r, ours = _ours_df(p, set(imu + acc + ["PARM"]), block)
    assert r.skipped_bytes == 0 and r.truncated_bytes == 0
    for name in imu + acc:
        rec = ours[name]
        assert len(rec) == len(ref[name]) == (N if legacy else 2 * N)
        for col in ("TimeUS", "AccX", "AccY", "AccZ"):
            assert np.array_equal(rec[col].astype(float), [m[col] for m in ref[name]]), (name, col)
    names = [n.split(b"\0")[0].decode() for n in ours["PARM"]["Name"]]
    assert names == [m["Name"] for m in ref["PARM"]] == ["INS_ACCOFFS_X", "AHRS_ORIENTATION",
                                                          "INS_ACCOFFS_X"]
    assert np.allclose(ours["PARM"]["Value"], [0.12, 2.0, 0.2])
    # the written values are the given float32 values (pymavlink reads them so)
    i0 = np.array([m["AccY"] for m in ref[imu[0]] if m.get("I", 0) == 0])
    assert np.array_equal(i0, a[:, 1].astype(float))


def test_dataflash_damage_and_truncation(tmp_path):
    """Bytes overwritten in the middle and a file cut inside a message: calib
    skips what pymavlink skips and keeps every whole message it keeps."""
    a, g = _vals(1)
    p = tmp_path / "d.bin"
    write_dataflash(p, T_US, a, g)
    data = bytearray(p.read_bytes())
    k = len(data) // 2
    data[k:k + 201] = b"\x55" * 201  # damage over several messages
    data = data[:-20]  # cut inside the last message
    p.write_bytes(bytes(data))
    ref = _pymavlink(p, ["IMU", "ACC", "GYR"])
    for block in (777, 1 << 20):
        r, ours = _ours_df(p, {"IMU", "ACC", "GYR"}, block)
        for name in ("IMU", "ACC", "GYR"):
            assert np.array_equal(ours[name]["TimeUS"].astype(float),
                                  [m["TimeUS"] for m in ref[name]]), (name, block)
        assert r.skipped_bytes > 0 and r.truncated_bytes > 0


def test_ulog_same_as_pyulog(tmp_path):
    """Topics, instances, parameters (initial and changed), dropouts, and a
    file cut inside a message: pyulog's reading, block size irrelevant."""
    import pyulog

    a, g = _vals(2)
    p = tmp_path / "x.ulg"
    prm = {"CAL_ACC0_ID": 1234, "CAL_ACC0_XOFF": 0.12, "SENS_BOARD_ROT": 2}
    write_ulog(p, T_US, a, g, temp=np.linspace(20, 40, N), params=prm, other_instance=True,
               param_changes=[(int(T_US[10]), "CAL_ACC0_XOFF", 0.3)],
               dropouts=[(int(T_US[500]), 12), (int(T_US[900]), 3)],
               gyro_t_us=T_US + 250)
    data = p.read_bytes()
    p.write_bytes(data[:-9])
    ul = pyulog.ULog(str(p))
    ref = {(d.name, d.multi_id): d.data for d in ul.data_list}
    for block in (333, 65536, 1 << 22):
        r = ULogReader(str(p))
        assert r.params == {k: pytest.approx(v) for k, v in ul.initial_parameters.items()}
        got: dict = {}
        for blk in r.scan(["sensor_combined", "sensor_accel", "sensor_gyro", "sensor_selection"],
                          block=block):
            for name, multi, rec in blk:
                got.setdefault((name, multi), []).append(rec)
        assert set(got) == set(ref)
        for key, chunks in got.items():
            rec = np.concatenate(chunks)
            for col, v in ref[key].items():
                assert np.array_equal(rec[col], v), (key, col, block)
        assert r.param_changes == [("CAL_ACC0_XOFF", pytest.approx(0.3))]
        assert [c[1] for c in ul.changed_parameters] == ["CAL_ACC0_XOFF"]
        assert r.dropouts == [2, 15] == [len(ul.dropouts), sum(d.duration for d in ul.dropouts)]
        assert r.truncated_bytes > 0


def test_ulog_nested_and_padding(tmp_path):
    """Formats with nested types, arrays of nested types and padding fields:
    pyulog's flattened names and values."""
    import pyulog

    from calib_cli.io.log_writers import ULOG_MAGIC, _umsg

    fmt_inner = b"vec:float x;float y;uint8_t[3] _padding0;"
    fmt_outer = (b"outer_topic:uint64_t timestamp;vec a;vec[2] b;int16_t k;"
                 b"uint8_t[5] _padding0;")
    inner = struct.Struct("<ff3x")
    rows = []
    out = bytearray(ULOG_MAGIC + b"\x01" + struct.pack("<Q", 0))
    out += _umsg(b"B", bytes(40))
    out += _umsg(b"F", fmt_inner) + _umsg(b"F", fmt_outer)
    out += _umsg(b"A", struct.pack("<BH", 0, 3) + b"outer_topic")
    for i in range(50):
        vals = [float(i), i + 0.5, 2.0 * i, -1.0, 3.5, float(-i)]
        rows.append(vals)
        payload = struct.pack("<Q", 1000 * i) + b"".join(inner.pack(vals[j], vals[j + 1])
                                                         for j in (0, 2, 4)) + \
            struct.pack("<h", -i)  # trailing padding not logged
        out += _umsg(b"D", struct.pack("<H", 3) + payload)
    p = tmp_path / "n.ulg"
    p.write_bytes(bytes(out))
    ref = pyulog.ULog(str(p)).data_list[0].data
    r = ULogReader(str(p))
    rec = np.concatenate([b[0][2] for b in r.scan(["outer_topic"], block=200)])
    for col, v in ref.items():
        assert np.array_equal(rec[col], v), col
    assert "b[1].y" in rec.dtype.names and np.array_equal(rec["k"], -np.arange(50))


def test_writers_read_by_rosbags_and_pyulog(tmp_path):
    """The bags and the ULog of calib simulate --out hold what was given."""
    from rosbags.highlevel import AnyReader
    from rosbags.typesys import Stores, get_typestore

    a, g = _vals(3)
    n = 200
    for path, write in ((tmp_path / "x.bag", write_ros1_bag), (tmp_path / "x.mcap", write_mcap)):
        write(path, T_US[:n] * 1000, a[:n], g[:n])
        with AnyReader([path], default_typestore=get_typestore(Stores.ROS2_HUMBLE)) as rd:
            msgs = [rd.deserialize(raw, c.msgtype) for c, _, raw in rd.messages()]
        assert len(msgs) == n
        assert [m.header.stamp.sec * 10**9 + m.header.stamp.nanosec for m in msgs] == \
            list(T_US[:n] * 1000)
        assert np.array_equal([m.linear_acceleration.y for m in msgs], a[:n, 1].astype(float))
