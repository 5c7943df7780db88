"""Issue 15 through the real commands: `calib record` against `calib emulate`
(both subprocesses). The test is the operator: it answers the recorder's
prompts on stdin and places the emulated unit through the emulator's virtual
table port, as a hand would. A misplaced position is refused and asked again;
a recording that has one anyway (the check off) makes `fit accel` name it."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
D2R = np.pi / 180
TWELVE = [(0, -90, 0), (0, 90, 0), (90, 0, 0), (-90, 0, 0), (0, 0, 0), (180, 0, 0),
          (45, 45, 0), (-45, 45, 30), (45, -45, 60), (135, 30, 10), (-135, -30, 80),
          (30, 60, 120)]


def _plan(atts, duration=0.4):
    return ('name = "m"\nkind = "static"\n[site]\nlatitude_deg = 50.45\nheight_m = 180\n'
            '[unit]\nserial = "EMU-G"\n' + "".join(
                f'[[segment]]\nlabel = "p{i + 1}"\nattitude_deg = {list(map(float, a))}\n'
                f'duration_s = {duration}\n' for i, a in enumerate(atts)))


class _Proc:
    """A subprocess whose stderr is collected by a thread (prompts have no newline)."""

    def __init__(self, args, stdin=None):
        env = dict(os.environ, PYTHONPATH=str(ROOT))
        self.p = subprocess.Popen([sys.executable, "-m", "calib_cli", *map(str, args)],
                                  env=env, stdin=stdin, stdout=subprocess.PIPE,
                                  stderr=subprocess.PIPE, text=True, bufsize=1)
        self.err = ""
        self._t = threading.Thread(target=self._read, daemon=True)
        self._t.start()

    def _read(self):
        while True:
            c = self.p.stderr.read(1)
            if not c:
                return
            self.err += c

    def wait_for(self, text, count, timeout=120.0):
        t_end = time.time() + timeout
        while self.err.count(text) < count:
            if self.p.poll() is not None:
                time.sleep(0.2)
                if self.err.count(text) >= count:
                    return
                raise AssertionError(f"ended ({self.p.returncode}) before prompt {count}: "
                                     f"{self.err}")
            if time.time() > t_end:
                raise AssertionError(f"no prompt {count}: {self.err}")
            time.sleep(0.05)

    def finish(self, timeout=120.0):
        self.p.wait(timeout)
        self._t.join(5)
        return self.p.returncode, self.err


def _emulate(tmp_path):
    em = _Proc(["emulate", "--imu", "generic-bin6", "--table", "generic-3axis", "--rate",
                "500", "--speed-dps", "1800", "--link-dir", tmp_path / "ports",
                "--attitude-deg", "0", "0", "0", "--seed", "4"])
    paths = json.loads(em.p.stdout.readline())
    return em, paths


def _hand(paths):
    from calib_cli.acquire.profile import load_table_profile
    from calib_cli.acquire.table import SerialTable

    table = SerialTable(load_table_profile("generic-3axis"), paths["table"])

    def place(att_deg):
        table.move(np.asarray(att_deg, float) * D2R)
        t_end = time.time() + 30
        while not table.settled() and time.time() < t_end:
            time.sleep(0.05)
    return table, place


def _record(tmp_path, paths, plan, extra=()):
    (tmp_path / "plan.toml").write_text(plan)
    return _Proc(["record", "--imu", "generic-bin6", "--port", paths["imu"], "--plan",
                  tmp_path / "plan.toml", "--out", tmp_path / "raw.h5", "--settle-window",
                  "0.1", "--no-check", *extra], stdin=subprocess.PIPE)


def _answer(rec, n, place, att):
    rec.wait_for("press Enter", n)
    place(att)
    rec.p.stdin.write("\n")
    rec.p.stdin.flush()


def test_record_refuses_a_misplaced_position_and_the_fit_names_one_it_let_pass(tmp_path):
    """p1: the operator puts -x up where the plan says +x up: refused, asked
    again, then placed right. p5: placed 6 deg off z-up, within the recorder's
    10 deg tolerance, so recorded; `fit accel` names p5 (exit 4)."""
    em, paths = _emulate(tmp_path)
    table = None
    places = [(0, 90, 0), *TWELVE]  # the first answer is the wrong one
    places[5] = (6, 0, 0)           # p5 (z up in the plan) tilted 6 deg about x
    try:
        table, place = _hand(paths)
        rec = _record(tmp_path, paths, _plan(TWELVE, 0.3))
        for k, att in enumerate(places):
            _answer(rec, k + 1, place, att)
        code, err = rec.finish()
    finally:
        if table is not None:
            table.ser.close()
        em.p.terminate()
        em.finish(30)
    assert code == 0, err
    assert err.count("press Enter") == 13, err
    assert "[p1] the unit reads gravity 180 deg away from this position" in err, err
    assert "[p5] the unit reads gravity" not in err, err
    from calib_cli.io.h5 import read_raw

    r = read_raw(tmp_path / "raw.h5")
    assert r.accel[r.segments[0].slice].mean(0)[0] > 9.0  # +x up, as planned
    fit = subprocess.run([sys.executable, "-m", "calib_cli", "-q", "fit", "accel",
                          str(tmp_path / "raw.h5"), "--out", str(tmp_path / "cal.h5")],
                         env=dict(os.environ, PYTHONPATH=str(ROOT)), capture_output=True,
                         text=True, timeout=300)
    assert fit.returncode == 4, fit.stderr
    assert "gross error at position 5 ('p5')" in fit.stderr, fit.stderr
    assert fit.stderr.count("\n") == 1 and not (tmp_path / "cal.h5").exists()


NOISY = """# a unit noisier than the default stillness limits (0.05 m/s^2, 0.01 rad/s)
[params]
accel_bias_mg = [6.0, -4.0, 9.0]
gyro_bias_dps = [0.15, -0.08, 0.22]
[noise]
accel_white_mg = 12.0
gyro_white_dps = 1.2
"""


def _record_motorised(tmp_path, em_paths, plan, extra=()):
    (tmp_path / "plan.toml").write_text(plan)
    return _Proc(["record", "--imu", "generic-bin6", "--port", em_paths["imu"], "--table",
                  "generic-3axis", "--table-port", em_paths["table"], "--plan",
                  tmp_path / "plan.toml", "--out", tmp_path / "raw.h5", "--settle-window",
                  "0.2", "--no-check", *extra])


def test_stillness_limits_measured_at_the_start(tmp_path):
    """generic-bin6 states no [noise]: the defaults sit below this unit's
    noise (0.118 m/s^2, 0.021 rad/s per sample), so the limits are measured
    in the first second and the plan records; with --accel-still 0.05 the
    unit never counts as still and the timeout message gives the measured
    std, the limit and the option."""
    (tmp_path / "truth.toml").write_text(NOISY)
    em = _Proc(["emulate", "--imu", "generic-bin6", "--table", "generic-3axis", "--rate",
                "500", "--speed-dps", "1800", "--link-dir", tmp_path / "ports", "--truth",
                tmp_path / "truth.toml"])
    try:
        paths = json.loads(em.p.stdout.readline())
        rec = _record_motorised(tmp_path, paths, _plan([(0, 0, 0), (0, -90, 0)], 0.3))
        code, err = rec.finish()
        assert code == 0, err
        assert "measured at the start" in err and "stillness limits" in err, err
        d = tmp_path / "again"
        d.mkdir()
        rec = _record_motorised(d, paths, _plan([(0, 0, 0)], 0.3),
                                ("--accel-still", "0.05", "--settle-timeout", "3"))
        code, err = rec.finish()
    finally:
        em.p.terminate()
        em.finish(30)
    lines = [ln for ln in err.splitlines() if ln.startswith("calib: error")]
    assert code == 3 and len(lines) == 1, err
    msg = " ".join(err.split())
    assert "did not keep still within 3 s: measured std accel" in msg, err
    assert "(limit 0.05, --accel-still)" in msg and "--gyro-still" in msg, err
    assert "measured accel" in msg and "at the start" in msg, err
    assert not (d / "raw.h5").exists()
