"""calib import bag / ulog / dataflash (issue 19): files written by the tests
(tests/log_writers.py) import and fit to the same calibration as a CSV of the
same float32 values and integer time stamps; clear errors otherwise."""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import TRUTH_SI, static_plan_text
from log_writers import write_dataflash, write_ros1_bag, write_ros2_bag, write_ulog

from calib_cli.io.h5 import read_calibration, read_raw
from calib_cli.io.plan import parse_plan
from calib_cli.model.effects import Layout
from calib_cli.model.truth import truth_from_dict
from calib_cli.sim.simulate import simulate

T0_US = 1_700_000_000_000_000  # an epoch-like start, us


@pytest.fixture(scope="module")
def record(tmp_path_factory):
    """A static 12-position record: float32 values, integer us time stamps,
    its plan, and a CSV of exactly those values."""
    d = tmp_path_factory.mktemp("logs")
    text = static_plan_text(duration=8.0, rate=100.0)
    rec = simulate(parse_plan(text), truth_from_dict(TRUTH_SI, Layout()), seed=3)
    t_us = T0_US + np.round(rec.time * 1e6).astype(np.int64)
    accel = rec.accel.astype(np.float32)
    gyro = rec.gyro.astype(np.float32)
    (d / "plan.toml").write_text(text)
    t = (t_us * 1000 - t_us[0] * 1000) / 1e9  # as every importer computes it
    with open(d / "log.csv", "w") as fh:
        fh.write("time,ax,ay,az,gx,gy,gz\n")
        np.savetxt(fh, np.column_stack([t, accel.astype(float), gyro.astype(float)]),
                   delimiter=",", fmt="%.17g")
    return d, t_us, accel, gyro


def _fit(run_cli, d, raw, tag):
    cal = d / f"cal_{tag}.h5"
    code, _, err = run_cli("fit", "accel", raw, "--out", cal)
    assert code == 0, err
    gcal = d / f"gcal_{tag}.h5"
    code, _, err = run_cli("fit", "gyro", raw, "--out", gcal)
    assert code == 0, err
    return read_calibration(cal), read_calibration(gcal)


def _import(run_cli, d, fmt, t_us, accel, gyro):
    plan = d / "plan.toml"
    raw = d / f"raw_{fmt}.h5"
    if fmt in ("ros2-sqlite3", "ros2-mcap"):
        bag = d / f"bag_{fmt}"
        if not bag.exists():
            write_ros2_bag(bag, t_us * 1000, accel, gyro, storage=fmt.split("-")[1])
        args = ("import", "bag", bag, "--topic", "/imu")
    elif fmt == "mcap":
        bag = d / "bag_ros2-mcap"
        if not bag.exists():
            write_ros2_bag(bag, t_us * 1000, accel, gyro, storage="mcap")
        args = ("import", "bag", next(bag.glob("*.mcap")), "--topic", "/imu")
    elif fmt == "ros1":
        write_ros1_bag(d / "log.bag", t_us * 1000, accel, gyro)
        args = ("import", "bag", d / "log.bag", "--topic", "/imu")
    elif fmt.startswith("ulog"):
        write_ulog(d / "log.ulg", t_us, accel, gyro)
        args = ("import", "ulog", d / "log.ulg") + (("--source", "sensor") if fmt == "ulog-sensor"
                                                     else ())
    else:
        write_dataflash(d / "log.bin", t_us, accel, gyro)
        args = ("import", "dataflash", d / "log.bin") + (("--message", "ACC") if fmt == "df-acc"
                                                        else ())
    code, _, err = run_cli(*args, "--plan", plan, "--out", raw)
    assert code == 0, err
    return raw


FORMATS = ["ros2-sqlite3", "ros2-mcap", "mcap", "ros1", "ulog", "ulog-sensor", "dataflash",
           "df-acc"]


@pytest.mark.parametrize("fmt", FORMATS)
def test_same_calibration_as_csv(record, run_cli, fmt):
    d, t_us, accel, gyro = record
    csv_raw = d / "raw_csv.h5"
    if not csv_raw.exists():
        code, _, err = run_cli("import", "csv", d / "log.csv", "--plan", d / "plan.toml",
                               "--out", csv_raw)
        assert code == 0, err
    ref_a, ref_g = _fit(run_cli, d, csv_raw, "csv")
    raw = _import(run_cli, d, fmt, t_us, accel, gyro)
    rr, rc = read_raw(raw), read_raw(csv_raw)
    assert [(s.start, s.stop) for s in rr.segments] == [(s.start, s.stop) for s in rc.segments]
    cal_a, cal_g = _fit(run_cli, d, raw, fmt)
    for k, v in ref_a.params.items():
        assert np.allclose(cal_a.params[k], v, rtol=1e-12, atol=1e-12 * np.abs(v).max()), k
    for k, v in ref_g.params.items():
        assert np.allclose(cal_g.params[k], v, rtol=1e-9, atol=1e-9 * np.abs(v).max()), k


def test_listing(record, run_cli, tmp_path):
    d, t_us, accel, gyro = record
    write_ros2_bag(tmp_path / "b", t_us[:500] * 1000, accel[:500], gyro[:500])
    code, out, err = run_cli("import", "bag", tmp_path / "b")
    assert code == 0, err
    assert "/imu" in out and "500 messages" in out and "100.00 Hz" in out and "chatter" not in out
    code, out, _ = run_cli("import", "bag", tmp_path / "b", "--json")
    assert json.loads(out)[0]["count"] == 500
    write_ulog(tmp_path / "x.ulg", t_us[:300], accel[:300], gyro[:300])
    code, out, _ = run_cli("import", "ulog", tmp_path / "x.ulg")
    assert code == 0 and "sensor_combined[0]" in out and "300 messages" in out
    write_dataflash(tmp_path / "x.bin", t_us[:300], accel[:300], gyro[:300])
    code, out, _ = run_cli("import", "dataflash", tmp_path / "x.bin")
    assert code == 0 and "IMU[1]" in out and "ACC[0]" in out


def _err(run_cli, *args):
    code, _, err = run_cli(*args)
    lines = err.strip().splitlines()
    assert code == 3 and len(lines) == 1, err
    return lines[0]


def test_errors_name_file_and_stream(record, run_cli, tmp_path):
    d, t_us, accel, gyro = record
    plan = d / "plan.toml"
    out = tmp_path / "raw.h5"
    n = len(t_us)
    write_ros2_bag(tmp_path / "b", t_us * 1000, accel, gyro)
    line = _err(run_cli, "import", "bag", tmp_path / "b", "--topic", "/nope", "--plan", plan,
                "--out", out)
    assert str(tmp_path / "b") in line and "'/nope'" in line and "/imu" in line
    line = _err(run_cli, "import", "bag", tmp_path / "b", "--topic", "/chatter", "--plan", plan,
                "--out", out)
    assert "topic /chatter" in line and "std_msgs/msg/String" in line
    # time going backwards
    tb = t_us.copy()
    tb[500], tb[501] = tb[501], tb[500]
    write_ros1_bag(tmp_path / "back.bag", tb * 1000, accel, gyro, recv_ns=t_us * 1000)
    line = _err(run_cli, "import", "bag", tmp_path / "back.bag", "--topic", "/imu", "--plan",
                plan, "--out", out)
    assert "topic /imu" in line and "not increasing at message 502" in line
    # a long gap inside a static position: error naming its time; a short one is counted
    keep = np.ones(n, bool)
    keep[300:310] = False  # 10 periods, inside p1 (0..8 s at 100 Hz)
    write_ulog(tmp_path / "gap.ulg", t_us[keep], accel[keep], gyro[keep])
    line = _err(run_cli, "import", "ulog", tmp_path / "gap.ulg", "--plan", plan, "--out", out)
    assert "ULog sensor_combined" in line and "gap of 0.11 s" in line and "t = 2.990000 s" in line
    keep = np.ones(n, bool)
    keep[300:302] = False
    write_dataflash(tmp_path / "short.bin", t_us[keep], accel[keep], gyro[keep])
    code, _, err = run_cli("import", "dataflash", tmp_path / "short.bin", "--plan", plan, "--out",
                           out)
    assert code == 0 and "1 short gap" in err, err
    assert read_raw(out).counters["gaps"] == 1
    # empty stream, missing instance
    write_dataflash(tmp_path / "noraw.bin", t_us[:50], accel[:50], gyro[:50], raw=False)
    line = _err(run_cli, "import", "dataflash", tmp_path / "noraw.bin", "--message", "ACC",
                "--plan", plan, "--out", out)
    assert "DataFlash ACC[0]: no messages" in line
    write_ulog(tmp_path / "nos.ulg", t_us[:50], accel[:50], gyro[:50], sensors=False)
    line = _err(run_cli, "import", "ulog", tmp_path / "nos.ulg", "--source", "sensor", "--plan",
                plan, "--out", out)
    assert "sensor_accel[0]: not in the log" in line
    line = _err(run_cli, "import", "ulog", tmp_path / "missing.ulg", "--plan", plan, "--out", out)
    assert "no such file" in line
    assert not out.exists() or read_raw(out).counters["gaps"] == 1


def test_missing_extra_is_one_line(record, run_cli, tmp_path, monkeypatch):
    import builtins

    real = builtins.__import__

    def fake(name, *a, **k):
        if name.split(".")[0] in ("rosbags", "pyulog", "pymavlink"):
            raise ImportError(name)
        return real(name, *a, **k)

    monkeypatch.setattr(builtins, "__import__", fake)
    import importlib

    monkeypatch.setattr(importlib, "import_module", lambda n, *a: fake(n))
    d = record[0]
    line = _err(run_cli, "import", "bag", d / "log.csv", "--plan", d / "plan.toml", "--out",
                tmp_path / "r.h5", "--topic", "/imu")
    assert "install calib-cli[ros]" in line
    # ULog and DataFlash are read by calib itself (io/ulog_reader.py, io/dataflash_reader.py)
    for cmd, what in (("ulog", "not a ULog file"), ("dataflash", "not a DataFlash log")):
        line = _err(run_cli, "import", cmd, d / "log.csv", "--plan", d / "plan.toml", "--out",
                    tmp_path / "r.h5")
        assert what in line and "install" not in line
