"""End to end over the real transports: the emulator on a pty (pyserial) or
the python-can virtual bus, the recorder following a 12-position plan, the
accelerometer fit against the emulator's truth; fault injection with exact
counts; a recorder killed with SIGKILL and its journal recovered."""

import dataclasses
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from calib_cli.acquire.emulator import Emulator, Faults
from calib_cli.acquire.journal import read_journal
from calib_cli.acquire.profile import load_imu_profile, load_table_profile
from calib_cli.acquire.session import Session, SettleConfig, free_run_plan, journal_to_recording
from calib_cli.acquire.table import SerialTable
from calib_cli.acquire.transport import CanTransport, SerialTransport
from calib_cli.io.h5 import read_raw, write_raw
from calib_cli.io.plan import parse_plan
from calib_cli.methods.accel_lsq import fit_accel

ROOT = Path(__file__).resolve().parents[1]
ATT = [(0, 0, 0), (180, 0, 0), (0, -90, 0), (0, 90, 0), (90, 0, 0), (-90, 0, 0),
       (0, 0, 90), (180, 0, 90), (0, -90, 90), (0, 90, 90), (90, 0, 90), (-90, 0, 90)]


def plan12(duration=0.3, n=12):
    return ('name = "twelve"\nkind = "static"\n[site]\nlatitude_deg = 50.45\nheight_m = 180\n'
            '[unit]\nserial = "EMU-1"\n' + "".join(
                f'[[segment]]\nlabel = "p{i}"\nattitude_deg = [{a[0]}, {a[1]}, {a[2]}]\n'
                f'duration_s = {duration}\n' for i, a in enumerate(ATT[:n])))


def table_profile():
    return dataclasses.replace(load_table_profile("generic-3axis"), speed_dps=1800.0)


SETTLE = SettleConfig(window_s=0.1, timeout_s=20.0, poll_s=0.05)


def run_plan(tmp_path, imu, rate, faults=None, seed=0, duration=0.25):
    prof = load_imu_profile(imu)
    plan = parse_plan(plan12(duration))
    tab = table_profile()
    em = Emulator(prof, tab, site=plan.site, rate=rate, faults=faults, seed=seed,
                  link_dir=str(tmp_path)).start()
    try:
        if prof.format == "can":
            transport = CanTransport("virtual", em.paths["can"])
        else:
            transport = SerialTransport(em.paths["imu"], prof.transport)
        s = Session(dataclasses.replace(prof, rate_hz=rate), transport, plan,
                    str(tmp_path / "j.journal"), table=SerialTable(tab, em.paths["table"]),
                    settle=SETTLE)
        s.start()
        s.run_plan()
        counts = s.close()
    finally:
        em.stop()
    rec = journal_to_recording(str(tmp_path / "j.journal"))
    write_raw(tmp_path / "raw.h5", rec)  # and back through the file
    return em, counts, read_raw(tmp_path / "raw.h5")


def zscores(rec, truth):
    res = fit_accel(rec)
    z = []
    for k in ("accel_bias", "accel_K"):
        sig = res.sigma[k]
        ok = np.isfinite(sig) & (sig > 0)
        z.append(((res.params[k] - truth.params[k]) / np.where(ok, sig, 1))[ok])
    return np.concatenate(z)


def check_fit(z):
    """One fit of 12 parameters: the house's hard bound for fast tests (4.5)
    and a pooled RMS that a wrong recording (a lost, shifted or mis-tagged
    sample block) would blow up. The 3-sigma statement over many runs is
    test_many_runs_within_3_sigma (slow)."""
    assert np.max(np.abs(z)) < 4.5
    assert np.sqrt(np.mean(z**2)) < 1.8


def test_serial_binary_12_positions_fit_within_3_sigma(tmp_path):
    em, counts, rec = run_plan(tmp_path, "generic-bin6", 2000)
    assert [s.label for s in rec.segments] == [f"p{i}" for i in range(12)]
    assert all(abs(s.n - 500) <= 1 for s in rec.segments)
    assert counts["checksum_errors"] == counts["gaps"] == 0 and em.injected.overflow == 0
    assert rec.counters["frames"] == len(rec) and rec.serial == "EMU-1"
    z = zscores(rec, em.truth)
    print("binary z:", np.round(z, 2))
    check_fit(z)


@pytest.mark.slow
def test_serial_ascii_nmea_12_positions(tmp_path):
    em, counts, rec = run_plan(tmp_path, "nmea-imu", 1000, seed=1, duration=0.4)
    assert len(rec.segments) == 12 and counts["gaps"] == 0
    z = zscores(rec, em.truth)
    print("ascii z:", np.round(z, 2))
    check_fit(z)


def test_can_virtual_bus_12_positions(tmp_path):
    em, counts, rec = run_plan(tmp_path, "can-imu", 1000, seed=2)
    assert len(rec.segments) == 12 and counts["gaps"] == 0 and counts["checksum_errors"] == 0
    z = zscores(rec, em.truth)
    print("can z:", np.round(z, 2))
    check_fit(z)


@pytest.mark.slow
def test_many_runs_within_3_sigma(tmp_path):
    """Pooled over 12 runs (144 normalized errors): RMS near 1, and the fit
    recovers the truth within 3 sigma for at least 98 % of the entries."""
    zs = []
    for seed in range(12):
        d = tmp_path / f"run{seed}"
        d.mkdir()
        faults = Faults(corrupt=0.01, drop=0.005, seed=seed) if seed % 2 else None
        em, _, rec = run_plan(d, "generic-bin6", 2000, faults=faults, seed=100 + seed)
        zs.append(zscores(rec, em.truth))
    z = np.concatenate(zs)
    rms = np.sqrt(np.mean(z**2))
    print(f"pooled: n {len(z)}, RMS {rms:.3f}, max {np.abs(z).max():.2f}, "
          f"within 3 sigma {np.mean(np.abs(z) < 3):.3f}")
    assert 0.75 <= rms <= 1.3
    assert np.mean(np.abs(z) < 3.0) >= 0.98


def _expected(em, tmp_path):
    """Injected faults among the frames between the first and last the
    recorder accepted (before and after, it was not listening)."""
    _, rows, _, _ = read_journal(str(tmp_path / "j.journal"))
    first, last = rows[0, 1], rows[-1, 1]
    inside = lambda seqs: sum(1 for k in seqs if first < k < last)  # noqa: E731
    return inside(em.injected.corrupted_seq), inside(em.injected.dropped_seq), rows


def test_faults_payload_corruption_and_drops_counted_exactly(tmp_path):
    f = Faults(corrupt=0.01, corrupt_where="payload", drop=0.005, seed=11)
    em, counts, rec = run_plan(tmp_path, "generic-bin6", 2000, faults=f, seed=3)
    n_corrupt, n_drop, rows = _expected(em, tmp_path)
    print("injected", n_corrupt, n_drop, "reported", counts)
    assert n_corrupt > 30 and n_drop > 15 and em.injected.overflow == 0
    assert counts["checksum_errors"] == n_corrupt
    assert counts["gaps"] == n_drop
    assert counts["spurious_rejects"] == 0
    assert len(rows) + n_corrupt + n_drop == rows[-1, 1] - rows[0, 1] + 1
    z = zscores(rec, em.truth)
    check_fit(z)


def test_faults_anywhere_and_garbage_total_lost_equals_injected(tmp_path):
    f = Faults(corrupt=0.01, corrupt_where="anywhere", drop=0.005, garbage=0.01, seed=12)
    em, counts, rec = run_plan(tmp_path, "generic-bin6", 2000, faults=f, seed=4)
    n_corrupt, n_drop, rows = _expected(em, tmp_path)
    print("injected", n_corrupt, n_drop, em.injected.garbage_bursts, "reported", counts)
    assert em.injected.garbage_bursts > 30 and em.injected.overflow == 0
    assert counts["checksum_errors"] + counts["gaps"] == n_corrupt + n_drop
    assert len(rows) == rows[-1, 1] - rows[0, 1] + 1 - n_corrupt - n_drop
    z = zscores(rec, em.truth)
    check_fit(z)


def test_ascii_faults_anywhere(tmp_path):
    """Free-running ASCII log: corrupting any byte of a sentence ($, commas,
    digits, *, checksum) and garbage bursts lose exactly the injected sentences."""
    prof = load_imu_profile("nmea-imu")
    f = Faults(corrupt=0.02, corrupt_where="anywhere", drop=0.005, garbage=0.02, seed=5)
    em = Emulator(prof, rate=2000, faults=f, link_dir=str(tmp_path)).start()
    try:
        s = Session(dataclasses.replace(prof, rate_hz=2000),
                    SerialTransport(em.paths["imu"], prof.transport),
                    parse_plan(free_run_plan(2.0)), str(tmp_path / "j.journal"))
        s.start()
        s.run_free(2.0)
        counts = s.close()
    finally:
        em.stop()
    n_corrupt, n_drop, rows = _expected(em, tmp_path)
    print("ascii injected", n_corrupt, n_drop, "reported", counts)
    assert n_corrupt > 20
    assert counts["checksum_errors"] + counts["gaps"] == n_corrupt + n_drop


def test_disconnect_reconnects_and_marks_gap(tmp_path):
    prof = load_imu_profile("generic-bin6")
    f = Faults(disconnect_at=0.8, disconnect_for=0.5)
    em = Emulator(prof, rate=1000, faults=f, link_dir=str(tmp_path)).start()
    try:
        s = Session(prof, SerialTransport(em.paths["imu"], prof.transport),
                    parse_plan(free_run_plan(2.0)), str(tmp_path / "j.journal"),
                    settle=SettleConfig(reconnect_s=5.0))
        s.start()
        s.run_free(2.0)
        counts = s.close()
    finally:
        em.stop()
    assert counts["disconnects"] == 1
    assert counts["gaps"] >= em.injected.disconnect_frames >= 450
    rec = journal_to_recording(str(tmp_path / "j.journal"))
    dt = np.diff(rec.time)
    assert dt.max() >= 0.45 and rec.time[-1] >= 1.9  # the gap shows in the time axis


def _calib(*args, **kw):
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    return subprocess.run([sys.executable, "-m", "calib_cli", *args], capture_output=True,
                          text=True, env=env, timeout=60, **kw)


def _cli(*args):
    """The real command line, in this process (faster than a subprocess)."""
    from click.testing import CliRunner

    from calib_cli.cli.main import cli

    return CliRunner().invoke(cli, list(args))


def _default_sigint():
    """In the child: Ctrl-C's default disposition. A test run started in the background
    of a non-interactive shell (a CI script, `cmd &`) inherits SIGINT ignored, and so
    would the recorder, which then never sees the Ctrl-C the test sends."""
    signal.signal(signal.SIGINT, signal.SIG_DFL)


def _start_record(tmp_path, em, plan_path, extra=()):
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    return subprocess.Popen(
        [sys.executable, "-m", "calib_cli", "record", "--imu", "generic-bin6", "--port",
         em.paths["imu"], "--table", "generic-3axis", "--table-port", em.paths["table"],
         "--plan", str(plan_path), "--out", str(tmp_path / "raw.h5"), "--journal",
         str(tmp_path / "rec.journal"), "--settle-window", "0.1", *extra],
        env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        preexec_fn=_default_sigint)


def _wait_rows(journal, n, timeout=90):  # a busy machine starts the recorder slowly
    t_end = time.time() + timeout
    while time.time() < t_end:
        try:
            _, rows, _, _ = read_journal(journal)
            if len(rows) >= n and (rows[:, 2] >= 1).any():
                return rows
        except Exception:  # noqa: BLE001 - not written yet
            pass
        time.sleep(0.1)
    raise AssertionError("the recorder did not get going")


def test_sigkill_mid_segment_then_recover(tmp_path):
    plan_path = tmp_path / "plan.toml"
    # positions long enough that the signal lands mid-plan even on a loaded machine
    plan_path.write_text(plan12(duration=5.0, n=3))
    plan = parse_plan(plan_path.read_text())
    em = Emulator(load_imu_profile("generic-bin6"), table_profile(), site=plan.site, rate=1000,
                  link_dir=str(tmp_path)).start()
    try:
        proc = _start_record(tmp_path, em, plan_path)
        _wait_rows(str(tmp_path / "rec.journal"), 100)  # in segment p1
        time.sleep(0.7)
        k_sent = em.k  # samples the emulator has produced by now
        os.kill(proc.pid, signal.SIGKILL)
        proc.wait(10)
    finally:
        em.stop()
    assert not (tmp_path / "raw.h5").exists()
    r = _cli("recover", str(tmp_path / "rec.journal"), "--out", str(tmp_path / "rec.h5"))
    assert r.exit_code == 0, r.output
    assert _cli("show", str(tmp_path / "rec.h5")).exit_code == 0
    rec = read_raw(tmp_path / "rec.h5")
    _, rows, _, complete = read_journal(str(tmp_path / "rec.journal"))
    seq = rows[:, 1]
    assert len(rec) == len(rows) and np.all(np.diff(seq) == 1)  # every sample, in order
    lost = k_sent - seq[-1]
    print("samples lost to SIGKILL:", lost, "of", k_sent, "complete:", complete)
    assert lost <= 1000  # at most the last second (1 kHz)
    assert [s.label for s in rec.segments][:2] == ["p0", "p1"]
    assert rec.counters["journal_complete"] in (0, 1)


def test_ctrl_c_keeps_valid_file_and_exits_130(tmp_path):
    plan_path = tmp_path / "plan.toml"
    # positions so long that the signal lands mid-plan however loaded the machine is
    # (the signal is sent as soon as 100 rows are in; the plan would take 10 minutes)
    plan_path.write_text(plan12(duration=200.0, n=3).replace("duration_s = 200.0",
                                                             "duration_s = 1.0", 1))
    plan = parse_plan(plan_path.read_text())
    em = Emulator(load_imu_profile("generic-bin6"), table_profile(), site=plan.site, rate=1000,
                  link_dir=str(tmp_path)).start()
    try:
        proc = _start_record(tmp_path, em, plan_path)
        _wait_rows(str(tmp_path / "rec.journal"), 100)
        assert proc.poll() is None  # mid-plan: 2 x 200 s positions remain
        proc.send_signal(signal.SIGINT)
        _, err = proc.communicate(timeout=120)  # writing raw.h5 may be slow when busy
    finally:
        em.stop()
    assert proc.returncode == 130, err
    rec = read_raw(tmp_path / "raw.h5")
    assert rec.segments[0].label == "p0" and rec.counters["plan_finished"] == 0
    assert not (tmp_path / "rec.journal").exists()


def test_emulate_cli_prints_paths_and_faults(tmp_path):
    r = _calib("emulate", "--imu", "generic-bin6", "--duration", "0.5", "--drop", "0.1",
               "--link-dir", str(tmp_path))
    assert r.returncode == 0, r.stderr
    lines = [json.loads(x) for x in r.stdout.splitlines()]
    assert lines[0]["imu"] == str(tmp_path / "imu")
    assert lines[1]["dropped"] > 10


def test_manual_table_prompts():
    from calib_cli.acquire.table import ManualTable, describe_attitude

    d2r = np.pi / 180
    assert describe_attitude(np.array([0, -90, 0]) * d2r) == "put +x up"
    assert describe_attitude(np.array([180, 0, 0]) * d2r) == "put -z up"
    said = []
    ManualTable(lambda m: said.append(m) or "").move(np.array([90, 0, 0]) * d2r, "y-up")
    assert said == ["[y-up] put +y up, hold it still, then press Enter"]


def _record_with_table(prof, plan, tmp_path):
    """Run the plan against the emulator's IMU and motorised table; the recovered recording."""
    tab = table_profile()
    em = Emulator(prof, tab, site=plan.site, rate=1000, link_dir=str(tmp_path)).start()
    try:
        s = Session(prof, SerialTransport(em.paths["imu"], prof.transport), plan,
                    str(tmp_path / "j.journal"), table=SerialTable(tab, em.paths["table"]),
                    settle=SETTLE)
        s.start()
        s.run_plan()
        s.close()
    finally:
        em.stop()
    return journal_to_recording(str(tmp_path / "j.journal"))


def test_rotating_segment_commands_table_rate(tmp_path):
    prof = load_imu_profile("generic-bin6")
    plan = parse_plan('name = "rot"\nkind = "turntable"\n[site]\nlatitude_deg = 45\n'
                      '[[segment]]\nlabel = "still"\nattitude_deg = [0, 0, 0]\nduration_s = 0.3\n'
                      '[[segment]]\nlabel = "spin"\nattitude_deg = [0, 0, 0]\n'
                      'table_axis_enu = [0, 0, 1]\ntable_rate_dps = 90\nduration_s = 0.5\n')
    rec = _record_with_table(prof, plan, tmp_path)
    spin = rec.segments[1]
    assert spin.kind == "rotating" and abs(spin.n - 500) <= 1
    gz = rec.gyro[spin.slice, 2].mean()
    assert abs(gz - np.pi / 2) < 0.02  # the virtual table turned at 90 deg/s
    assert rec.table_rate[spin.start] == pytest.approx(np.pi / 2)
    assert np.isnan(rec.table_angle[0])


def test_rimu18_redundant_unit_records_18_channels(tmp_path):
    from scipy.spatial.transform import Rotation

    from calib_cli.model import kinematics as kn

    el = [35.26] * 3 + [-35.26] * 3 + [0, 90, -90]
    az = [0, 120, 240, 60, 180, 300, 45, 0, 0]
    plan = parse_plan('name = "r"\nkind = "rimu"\n[site]\nlatitude_deg = 45\n'
                      f'[rimu]\nel0_deg = {el}\naz0_deg = {az}\n'
                      '[[segment]]\nlabel = "level"\nattitude_deg = [0, 0, 0]\nduration_s = 0.4\n')
    from calib_cli.sim.simulate import plan_layout

    prof = load_imu_profile("rimu18")
    tab = table_profile()
    em = Emulator(prof, tab, site=plan.site, rate=1000, layout=plan_layout(plan),
                  link_dir=str(tmp_path)).start()
    try:
        s = Session(prof, SerialTransport(em.paths["imu"], prof.transport), plan,
                    str(tmp_path / "j.journal"), table=SerialTable(tab, em.paths["table"]),
                    settle=SETTLE)
        s.start()
        s.run_plan()
        s.close()
    finally:
        em.stop()
    rec = journal_to_recording(str(tmp_path / "j.journal"))
    assert rec.accel.shape[1] == rec.gyro.shape[1] == 9 and rec.layout.redundant
    seg = rec.segments[0]
    kin = kn.from_attitude(np.zeros(1), Rotation.identity(1), plan.site)
    want = em.truth.model.predict(em.truth.params, kin)
    np.testing.assert_allclose(rec.accel[seg.slice].mean(0), want["accel"][0], atol=2e-3)
    np.testing.assert_allclose(rec.gyro[seg.slice].mean(0), want["gyro"][0], atol=5e-4)


def test_manual_table_operator_places_unit_and_repeat_auto(tmp_path):
    """The operator (here a function that moves the virtual unit) follows the
    prompts; a repeat = "auto" segment takes positions until 'q'."""
    from scipy.spatial.transform import Rotation

    from calib_cli.acquire.table import ManualTable

    prof = load_imu_profile("generic-bin6")
    plan = parse_plan('name = "m"\nkind = "static"\n'
                      '[[segment]]\nlabel = "x-up"\nattitude_deg = [0, -90, 0]\nduration_s = 0.3\n'
                      '[[segment]]\nlabel = "free"\nrepeat = "auto"\nduration_s = 0.3\n')
    em = Emulator(prof, rate=1000, link_dir=str(tmp_path))
    em.unit.speed = np.radians(1440.0)
    em.start()
    prompts = []
    places = [Rotation.from_euler("ZYX", [0, -90, 0], degrees=True),
              Rotation.from_euler("ZYX", [0, 0, 180], degrees=True),
              Rotation.from_euler("ZYX", [30, 20, 10], degrees=True)]

    def operator(msg):
        prompts.append(msg)
        if not places:
            return "q"
        em.unit.move_to(places.pop(0), em.k)
        time.sleep(0.1)
        return ""

    try:
        s = Session(prof, SerialTransport(em.paths["imu"], prof.transport), plan,
                    str(tmp_path / "j.journal"), table=ManualTable(operator), settle=SETTLE)
        s.start()
        s.run_plan()
        s.close()
    finally:
        em.stop()
    assert prompts[0] == "[x-up] put +x up, hold it still, then press Enter"
    assert "q + Enter when done" in prompts[1] and len(prompts) == 4
    rec = journal_to_recording(str(tmp_path / "j.journal"))
    assert [x.label for x in rec.segments] == ["x-up", "free#1", "free#2"]
    f = rec.accel[rec.segments[0].slice].mean(0)
    assert f[0] > 9.0  # +x up reads +g on x
    assert rec.segments[1].attitude is None


def test_host_clock_timestamps():
    from calib_cli.acquire.codec import SampleStream

    text = load_imu_profile("nmea-imu").raw_text.replace('source = "sequence"',
                                                          'source = "host"')
    from calib_cli.acquire.profile import parse_imu_profile

    st = SampleStream(parse_imu_profile(text))
    vals = (0.0, 1, 0, 0, 9.8, 0, 0, 0, 25)
    a = st.push([vals], 100.0)
    b = st.push([(0.0, 2, 0, 0, 9.8, 0, 0, 0, 25)], 100.25)
    assert a[0, 0] == 0.0 and b[0, 0] == pytest.approx(0.25)


def test_record_bad_port_or_profile_exit_3_and_no_output(tmp_path):
    r = _cli("record", "--imu", "generic-bin6", "--port", str(tmp_path / "nope"),
             "--duration", "1", "--out", str(tmp_path / "raw.h5"))
    assert r.exit_code != 0 and "cannot open serial port" in str(r.exception)
    assert list(tmp_path.iterdir()) == []
    bad = tmp_path / "bad.toml"
    bad.write_text('format = "binary"\nrate_hz = 100\n[frame]\nsync = "ZZ"\n[[field]]\n'
                   'name = "ax"\ntype = "i16"\n')
    r = _cli("record", "--imu", str(bad), "--port", "x", "--duration", "1", "--out",
             str(tmp_path / "raw.h5"))
    assert "frame.sync" in str(r.exception) and not (tmp_path / "raw.h5").exists()


def test_rotating_segment_without_rate_runs_its_profile(tmp_path):
    """A contract-form rotating segment (no table_rate_dps): the cycle starts at rest and
    the table is commanded through the profile's holds while the segment records."""
    from calib_cli.acquire.session import rate_schedule

    prof = load_imu_profile("generic-bin6")
    plan = parse_plan('name = "rot"\nkind = "turntable"\n[site]\nlatitude_deg = 45\n'
                      '[[segment]]\nlabel = "cycle"\nattitude_deg = [0, 0, 0]\n'
                      'table_axis_enu = [0, 0, 1]\n'
                      'rate_profile = [[0, 0], [0.2, 0], [0.2, 90], [0.5, 90], [0.5, 0], [0.8, 0]]\n')
    dur, sched = rate_schedule(plan.segments[0])
    assert dur == pytest.approx(0.8) and [r for _t, r in sched] == pytest.approx([np.pi / 2, 0.0])
    rec = _record_with_table(prof, plan, tmp_path)
    cyc = rec.segments[0]
    assert cyc.kind == "rotating" and abs(cyc.n - 800) <= 5
    gz = rec.gyro[cyc.slice, 2]
    assert abs(gz[:100].mean()) < 0.05  # at rest when the cycle starts
    assert np.max(gz) == pytest.approx(np.pi / 2, abs=0.05)  # then at 90 deg/s
