"""Issue 15, recording: locks, journals never truncated, truthful and
resynchronising recovery, the no-data watchdog, the gravity check of
positions. Real subprocesses against the emulator where a process must die."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

from calib_cli.acquire.emulator import Emulator
from calib_cli.acquire.journal import read_journal
from calib_cli.acquire.profile import load_imu_profile
from calib_cli.acquire.session import Session, SettleConfig, journal_to_recording
from calib_cli.acquire.transport import SerialTransport
from calib_cli.io.plan import parse_plan
from tests.test_acquire_e2e import _cli, _start_record, _wait_rows, plan12, table_profile

ROOT = Path(__file__).resolve().parents[1]


def _emulator(tmp_path, plan):
    return Emulator(load_imu_profile("generic-bin6"), table_profile(), site=plan.site,
                    rate=1000, link_dir=str(tmp_path)).start()


def test_sigkill_then_second_record_keeps_journal_and_recover_rebuilds(tmp_path):
    plan_path = tmp_path / "plan.toml"
    plan_path.write_text(plan12(duration=200.0, n=3).replace("duration_s = 200.0",
                                                             "duration_s = 1.0", 1))
    plan = parse_plan(plan_path.read_text())
    em = _emulator(tmp_path, plan)
    journal = tmp_path / "rec.journal"
    try:
        proc = _start_record(tmp_path, em, plan_path)
        _wait_rows(str(journal), 100)
        time.sleep(0.3)
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(10)
        size = journal.stat().st_size
        # the same command again: refused, the journal untouched
        proc2 = _start_record(tmp_path, em, plan_path)
        _, err = proc2.communicate(timeout=60)
    finally:
        em.stop()
    assert proc2.returncode == 3, err
    assert "calib recover" in err and "--force" in err
    assert journal.stat().st_size == size
    r = _cli("recover", str(journal), "--out", str(tmp_path / "first.h5"))
    assert r.exit_code == 0, r.output
    assert "cut short" in r.output or "not closed" in r.output
    from calib_cli.io.h5 import read_raw

    rec = read_raw(tmp_path / "first.h5")
    assert rec.counters["journal_complete"] == 0 and len(rec) >= 100


def test_two_recorders_on_one_out(tmp_path):
    plan_path = tmp_path / "plan.toml"
    plan_path.write_text(plan12(duration=200.0, n=3).replace("duration_s = 200.0",
                                                             "duration_s = 1.0", 1))
    plan = parse_plan(plan_path.read_text())
    em = _emulator(tmp_path, plan)
    try:
        a = _start_record(tmp_path, em, plan_path)
        _wait_rows(str(tmp_path / "rec.journal"), 50)
        b = _start_record(tmp_path, em, plan_path)
        _, err = b.communicate(timeout=60)
        assert b.returncode == 3, err
        assert f"pid {a.pid}" in err and "another recorder" in err
        a.send_signal(signal.SIGINT)
        _, err_a = a.communicate(timeout=30)
    finally:
        em.stop()
    assert a.returncode == 130, err_a
    assert (tmp_path / "raw.h5").exists()
    assert not list(tmp_path.glob("*.lock"))
    # an existing recording is not replaced without --force
    r = _cli("record", "--imu", "generic-bin6", "--port", "/dev/null", "--duration", "1",
             "--out", str(tmp_path / "raw.h5"))
    assert getattr(r.exception, "exit_code", None) == 3 and "--force" in str(r.exception)


def _journal(tmp_path, n_batches=30):
    """A closed journal of a short free-running recording (in-process)."""
    from calib_cli.acquire.journal import JournalWriter

    path = tmp_path / "j.journal"
    w = JournalWriter(str(path), {"channels": ["ax", "ay", "az", "gx", "gy", "gz"],
                                  "plan_text": 'name = "f"\nkind = "static"\n'
                                               '[[segment]]\nlabel = "log"\n'})
    rng = np.random.default_rng(0)
    k = 0
    for _ in range(n_batches):
        rows = np.zeros((100, 9))
        rows[:, 0] = (k + np.arange(100)) / 100.0
        rows[:, 1] = k + np.arange(100)
        rows[:, 2] = 0
        rows[:, 3:] = rng.normal(size=(100, 6)) * 0.01 + [0, 0, 9.8, 0, 0, 0]
        w.append(rows)
        k += 100
    w.close({"frames": k, "plan_finished": 1})
    return path


def test_recover_skips_a_damaged_record_and_resynchronises(tmp_path, capsys):
    path = _journal(tmp_path)
    _, rows, _, complete = read_journal(str(path))
    assert complete and len(rows) == 3000
    b = bytearray(path.read_bytes())
    b[len(b) // 3] ^= 0x5A  # one flipped byte a third of the way in
    path.write_bytes(bytes(b))
    _, rows, counters, complete = read_journal(str(path))
    assert not complete
    assert len(rows) == 2900  # everything but the one damaged record of 100 rows
    assert counters["journal_records_skipped"] == 1
    r = _cli("recover", str(path), "--out", str(tmp_path / "r.h5"))
    assert r.exit_code == 0, r.output
    assert "1 damaged record" in r.output and "2900" in r.output


def test_recover_of_a_closed_journal_says_complete(tmp_path):
    path = _journal(tmp_path, 3)
    r = _cli("recover", str(path), "--out", str(tmp_path / "r.h5"))
    assert r.exit_code == 0 and "complete" in r.output and "cut short" not in r.output
    rec = journal_to_recording(str(path))
    assert rec.counters["journal_complete"] == 1


def test_no_data_watchdog_names_port_and_baud(tmp_path):
    master, slave = os.openpty()  # a port on which nothing arrives
    try:
        t0 = time.monotonic()
        env = dict(os.environ, PYTHONPATH=str(ROOT))
        p = subprocess.run([sys.executable, "-m", "calib_cli", "record", "--imu", "generic-bin6",
                            "--port", os.ttyname(slave), "--duration", "30", "--out",
                            str(tmp_path / "raw.h5")], capture_output=True, text=True, env=env,
                           timeout=60)
        dt = time.monotonic() - t0
    finally:
        os.close(master)
        os.close(slave)
    assert p.returncode == 3, p.stderr
    assert "no valid frame" in p.stderr and "921600 baud" in p.stderr
    assert dt < 20
    assert not list(tmp_path.iterdir())  # no journal, no lock, no output


def test_misplaced_position_is_refused_and_asked_again(tmp_path):
    from scipy.spatial.transform import Rotation

    from calib_cli.acquire.table import ManualTable

    prof = load_imu_profile("generic-bin6")
    plan = parse_plan('name = "m"\nkind = "static"\n'
                      '[[segment]]\nlabel = "x-up"\nattitude_deg = [0, -90, 0]\nduration_s = 0.3\n'
                      '[[segment]]\nlabel = "z-up"\nattitude_deg = [0, 0, 0]\nduration_s = 0.3\n')
    em = Emulator(prof, rate=1000, link_dir=str(tmp_path))
    em.unit.speed = np.radians(1440.0)
    em.start()
    prompts = []
    # the operator puts x-down first (wrong), then x-up, then z-up
    places = [Rotation.from_euler("ZYX", [0, 90, 0], degrees=True),
              Rotation.from_euler("ZYX", [0, -90, 0], degrees=True),
              Rotation.from_euler("ZYX", [0, 0, 0], degrees=True)]

    def operator(msg):
        prompts.append(msg)
        em.unit.move_to(places.pop(0), em.k)
        time.sleep(0.1)
        return ""

    try:
        s = Session(prof, SerialTransport(em.paths["imu"], prof.transport), plan,
                    str(tmp_path / "j.journal"), table=ManualTable(operator),
                    settle=SettleConfig(window_s=0.1, timeout_s=20.0, poll_s=0.05))
        s.gravity_tol_deg = 10.0
        s.start()
        s.run_plan()
        s.close()
    finally:
        em.stop()
    assert len(prompts) == 3 and "180 deg away" in prompts[1], prompts
    rec = journal_to_recording(str(tmp_path / "j.journal"))
    assert rec.accel[rec.segments[0].slice].mean(0)[0] > 9.0  # x-up, as planned


def test_settle_timeout_says_measured_std_and_option(tmp_path):
    import pytest

    from calib_cli.errors import InputError

    prof = load_imu_profile("generic-bin6")
    plan = parse_plan('name = "m"\nkind = "static"\n'
                      '[[segment]]\nlabel = "z-up"\nattitude_deg = [0, 0, 0]\nduration_s = 0.3\n')
    em = Emulator(prof, rate=1000, link_dir=str(tmp_path)).start()
    try:
        s = Session(prof, SerialTransport(em.paths["imu"], prof.transport), plan,
                    str(tmp_path / "j.journal"),
                    settle=SettleConfig(window_s=0.1, timeout_s=1.0, accel_std=1e-9,
                                        gyro_std=1e-9))
        s.start()
        with pytest.raises(InputError) as e:
            s.run_plan()
        s.close()
    finally:
        em.stop()
    msg = str(e.value)
    assert "measured std accel" in msg and "--accel-still" in msg and "--gyro-still" in msg


def test_profile_noise_sets_stillness_limits():
    import tomllib

    text = load_imu_profile("rimu18").raw_text
    noise = tomllib.loads(text)["noise"]
    assert 5 * noise["gyro_std"] > 0.05  # above the unit's own noise, unlike 0.01 rad/s
