"""Climatic chamber in the loop (issue 21, docs/thermal.md): Modbus RTU framing
against the specification's example frames, chamber profiles, the soak rule,
and `calib record` against `calib emulate --imu ... --chamber ...` running a
3-temperature soak plan end to end, the thermal fit recovering the truth."""

import dataclasses
import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from calib_cli.acquire import modbus
from calib_cli.acquire.chamber import (
    ManualChamber,
    Soak,
    check_plan,
    load_chamber_profile,
    open_chamber,
    parse_chamber_profile,
    soak_rule,
)
from calib_cli.errors import InputError
from calib_cli.io.plan import parse_plan
from calib_cli.validation.thermal_cases import POSITIONS

ROOT = Path(__file__).resolve().parents[1]
GROUPS = ("accel_bias", "accel_K", "accel_temp_bias", "accel_temp_scale", "gyro_bias",
          "gyro_temp_bias")


def soak_plan(temps=(0, 25, 50), hold=0.4, positions=POSITIONS, extra=""):
    text = ('name = "chamber-3"\nkind = "static"\nchamber_ramp_dpm = 1500\nunit_tau_s = 0.3\n'
            'chamber_soak_tol_degC = 0.02\nchamber_soak_s = 0.5\nchamber_soak_timeout_s = 30\n'
            + extra + '[site]\nlatitude_deg = 50.45\nheight_m = 180\n[unit]\nserial = "CH-1"\n')
    for T in temps:
        for i, (lab, att) in enumerate(positions.items()):
            text += (f'[[segment]]\nlabel = "{lab}@{T}"\nattitude_deg = {att}\n'
                     f'duration_s = {hold}\n' + (f"chamber_temp_degC = {T}\n" if i == 0 else ""))
    return text


# -- Modbus RTU framing ---------------------------------------------------------


def test_modbus_frames_match_the_specification_examples():
    # read 10 holding registers from address 0 of slave 1; write register 1 = 3
    assert modbus.read_request(1, 0, 10).hex() == "01030000000ac5cd"
    assert modbus.write_request(1, 1, 3).hex() == "010600010003980b"
    # a negative setpoint goes as its two's complement
    assert modbus.write_request(1, 300, -400)[4:6] == (0x10000 - 400).to_bytes(2, "big")
    reply = modbus.frame(1, 3, bytes([2, 0x01, 0x2C]))
    assert modbus.parse_reply(reply, 1, 3) == [300]
    assert modbus.to_signed(0xFE70) == -400
    with pytest.raises(modbus.ModbusError, match="exception 2"):
        modbus.parse_reply(modbus.frame(1, 0x83, bytes([2])), 1, 3)
    bad = bytearray(reply)
    bad[3] ^= 1
    with pytest.raises(modbus.ModbusError, match="CRC"):
        modbus.parse_reply(bytes(bad), 1, 3)
    with pytest.raises(modbus.ModbusError, match="slave"):
        modbus.parse_reply(modbus.frame(2, 3, bytes([2, 0, 1])), 1, 3)


# -- profiles and plans ------------------------------------------------------------


def test_shipped_profiles_and_bad_profiles():
    for name in ("generic-scpi", "generic-modbus", "manual"):
        assert load_chamber_profile(name).name == name
    with pytest.raises(InputError, match="temp_degC"):
        parse_chamber_profile('kind = "scpi"\n[commands]\nset_temp = "T {t}"\nquery_temp = "T?"\n'
                              '[responses]\ntemp = "(?P<temp_degC>.*)"\n', "c.toml")
    with pytest.raises(InputError, match="setpoint_register"):
        parse_chamber_profile('kind = "modbus"\n[modbus]\ntemp_register = 1\n', "c.toml")
    with pytest.raises(InputError, match="did you mean"):
        parse_chamber_profile('kind = "modbus"\nmax_ramp_dmp = 3\n', "c.toml")
    with pytest.raises(InputError, match="no chamber profile named"):
        load_chamber_profile("nope")


def test_plan_keys_soak_rule_and_range_checks():
    plan = parse_plan(soak_plan(temps=(-20, 40)))
    rule = soak_rule(plan, plan.segments[0])
    assert rule == {"chamber_soak": True, "chamber_soak_tol_degC": 0.02, "chamber_soak_s": 0.5,
                    "chamber_soak_timeout_s": 30.0, "chamber_ramp_dpm": 1500.0}
    prof = load_chamber_profile("generic-scpi")
    w = check_plan(plan, prof)  # 1500 degC/min is above the profile's 5
    assert len(w) == 1 and "limit 5" in w[0]
    with pytest.raises(InputError, match="--chamber"):
        check_plan(plan, None)
    with pytest.raises(InputError, match="outside the chamber's range"):
        check_plan(parse_plan(soak_plan(temps=(-90,))), prof)
    with pytest.raises(InputError, match="chamber_soak_s must be a number > 0"):
        parse_plan(soak_plan().replace("chamber_soak_s = 0.5", "chamber_soak_s = -1"))


class _FakeSession:
    """pump() returns rows whose temperature column follows an exponential."""

    def __init__(self, temps):
        self.temps = list(temps)
        self.t = 0.0
        self.state = ""

    def pump(self, dt=0.02):
        if not self.temps:
            return np.empty((0, 3))
        v = self.temps.pop(0)
        self.t += 0.1
        return np.array([[self.t, 0.0, v]])


def test_manual_chamber_prompts_then_waits_for_the_unit():
    said = []
    ch = ManualChamber(lambda m: said.append(m) or "")
    temps = 40 - 15 * np.exp(-np.arange(200) * 0.1 / 0.5)  # tau 0.5 s towards 40 degC
    s = _FakeSession(temps)
    rule = {"chamber_soak_tol_degC": 0.05, "chamber_soak_s": 0.5, "chamber_soak_timeout_s": 60,
            "chamber_ramp_dpm": 2.0}
    soak = Soak(s, ch, load_chamber_profile("manual"), 40.0, rule, 2, "hot")
    soak.run()
    assert said == ["[hot] set the chamber to 40 degC at no more than 2 degC/min, then press "
                    "Enter"]
    last = soak.hist[-1][1]
    assert abs(40 - last) < 0.1 and len(s.temps) > 50  # waited for the soak, not longer
    # a unit that never settles: one line naming the segment and the timeout
    rule["chamber_soak_timeout_s"] = 0.05
    with pytest.raises(InputError, match="did not soak at 40 degC within 0.05 s"):
        Soak(_FakeSession(np.linspace(0, 100, 400)), ch, load_chamber_profile("manual"), 40.0,
             rule, 2, "hot").run()


# -- end to end over ptys ------------------------------------------------------------


def _cli(*args):
    from click.testing import CliRunner

    from calib_cli.cli.main import cli

    return CliRunner().invoke(cli, list(args))


def _zscores(res, truth):
    z = {}
    for k in GROUPS:
        e, s = np.asarray(res.params[k]), np.asarray(res.sigma[k])
        t = np.asarray(truth[k], float).reshape(e.shape)
        z[k] = ((e - t) / s).ravel()
    return z


def test_record_against_emulated_chamber_3_temperature_soak_fit_recovers_truth(tmp_path):
    """`calib emulate --chamber` (the shipped SCPI profile ramping at 1500 degC/min,
    the unit's time constant 0.3 s) and `calib record --chamber ...` run the
    plan; `calib fit thermal` recovers the emulator's truth (order 2)."""
    from calib_cli.io.h5 import read_calibration, read_raw

    plan_path = tmp_path / "plan.toml"
    plan_path.write_text(soak_plan())
    cham = tmp_path / "fast-chamber.toml"  # the shipped profile, ramping at 1500 degC/min
    cham.write_text((ROOT / "profiles/chamber/generic-scpi.toml").read_text().replace(
        "max_ramp_dpm = 5.0", "max_ramp_dpm = 1500.0"))
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    em = subprocess.Popen(
        [sys.executable, "-m", "calib_cli", "emulate", "--imu", "generic-bin6", "--rate", "500",
         "--table", "generic-3axis", "--speed-dps", "1800", "--chamber", str(cham),
         "--chamber-tau", "0.3", "--seed", "7", "--plan", str(plan_path),
         "--link-dir", str(tmp_path / "ports"), "--truth-out", str(tmp_path / "truth.json"),
         "--duration", "240"], env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
        text=True)
    try:
        paths = json.loads(em.stdout.readline())
        r = _cli("record", "--imu", "generic-bin6", "--rate", "500", "--port", paths["imu"],
                 "--table", "generic-3axis", "--table-port", paths["table"],
                 "--chamber", str(cham), "--chamber-port", paths["chamber"],
                 "--plan", str(plan_path), "--out", str(tmp_path / "raw.h5"),
                 "--settle-window", "0.1")
        assert r.exit_code == 0, r.output
    finally:
        em.send_signal(signal.SIGTERM)
        out, err = em.communicate(timeout=20)
    rec = read_raw(tmp_path / "raw.h5")
    assert len(rec.segments) == 18 and rec.serial == "CH-1"
    for s in rec.segments:  # every position recorded soaked at its setpoint
        T = float(s.label.split("@")[1])
        assert np.all(np.abs(rec.temp[s.slice] - T) < 0.03), s.label
    r = _cli("fit", "thermal", str(tmp_path / "raw.h5"), "--order", "2", "--out",
             str(tmp_path / "cal.h5"))
    assert r.exit_code == 0, r.output
    res = read_calibration(tmp_path / "cal.h5")
    truth = json.loads((tmp_path / "truth.json").read_text())
    z = np.concatenate(list(_zscores(res, truth).values()))
    print("z:", np.round(z, 2))
    assert np.max(np.abs(z)) < 4.5 and np.sqrt(np.mean(z ** 2)) < 1.8
    assert res.stats["temp_range_degC"] == pytest.approx([0.0, 50.0], abs=0.03)


def test_modbus_chamber_software_ramp_and_soak(tmp_path):
    """generic-modbus has no ramp register: calib steps the setpoint at the
    ramp-rate limit; the emulated Modbus slave follows; each segment soaked."""
    from calib_cli.acquire.emulator import Emulator
    from calib_cli.acquire.profile import load_imu_profile
    from calib_cli.acquire.session import Session, SettleConfig, journal_to_recording
    from calib_cli.acquire.transport import SerialTransport

    prof = dataclasses.replace(load_imu_profile("generic-bin6"), rate_hz=500)
    cprof = dataclasses.replace(load_chamber_profile("generic-modbus"), max_ramp_dpm=600.0)
    plan = parse_plan(soak_plan(temps=(15, 35), positions={"z-up": [0, 0, 0]}))
    em = Emulator(prof, None, site=plan.site, rate=500, link_dir=str(tmp_path),
                  chamber=cprof, chamber_tau=0.2).start()
    try:
        s = Session(prof, SerialTransport(em.paths["imu"], prof.transport), plan,
                    str(tmp_path / "j.journal"), settle=SettleConfig(window_s=0.1, timeout_s=20))
        s.chamber, s.chamber_profile = open_chamber(cprof, em.paths["chamber"], None), cprof
        s.start()
        s.run_plan()
        s.close()
    finally:
        em.stop()
    rec = journal_to_recording(str(tmp_path / "j.journal"))
    for seg, T in zip(rec.segments, (15, 35), strict=True):
        assert np.all(np.abs(rec.temp[seg.slice] - T) < 0.03)
    sps = [v * 0.1 for fn, a, v in [x for x in em.chamber.log if x[0] != "bad"]
           if fn == 6 and a == 300]
    assert sps[-1] == pytest.approx(35.0) and len(sps) > 5  # stepped, not jumped
    steps = np.abs(np.diff(sps))
    assert steps.max() <= 600 / 60 * 0.5 + 0.1  # at most the rate over a poll (0.2 s + slack)
    assert not [x for x in em.chamber.log if x[0] == "bad"]


def test_ramp_segment_sets_the_chamber_going_without_waiting():
    """chamber_soak = false (a ramp design): the ramp rate and setpoint are sent
    and the segment is recorded at once; a chamber that cannot ramp by itself
    is refused before anything starts."""

    class Chamber:
        motorised = True

        def __init__(self, ramps):
            self.ramps, self.sent = ramps, []

        def set_ramp(self, r):
            self.sent.append(("ramp", r))
            return self.ramps

        def set_temp(self, t):
            self.sent.append(("temp", t))

    text = soak_plan(temps=(-20, 60), positions={"z-up": [0, 0, 0]}).replace(
        "chamber_temp_degC = 60\n", "chamber_temp_degC = 60\nchamber_soak = false\n")
    plan = parse_plan(text)
    seg = plan.segments[1]
    rule = soak_rule(plan, seg)
    assert rule["chamber_soak"] is False
    prof = dataclasses.replace(load_chamber_profile("generic-scpi"), max_ramp_dpm=2.0)
    ch = Chamber(True)
    Soak(_FakeSession([]), ch, prof, 60.0, rule, 2, seg.label).run()
    assert ch.sent == [("ramp", 2.0), ("temp", 60.0)]
    with pytest.raises(InputError, match="ramp by itself"):
        Soak(_FakeSession([]), Chamber(False), prof, 60.0, rule, 2, seg.label).run()
    with pytest.raises(InputError, match="ramp by itself"):
        check_plan(plan, load_chamber_profile("generic-modbus"))


def test_record_refuses_chamber_problems_before_starting(tmp_path, capsys):
    """One line, exit 3 (2 for usage), nothing written: a thermal plan without
    --chamber, a setpoint the chamber cannot reach, a chamber port that does
    not open, a serial chamber without --chamber-port."""
    from calib_cli.cli.main import main

    plan = tmp_path / "plan.toml"
    base = ["record", "--imu", "generic-bin6", "--port", str(tmp_path / "imu"), "--plan",
            str(plan), "--out", str(tmp_path / "raw.h5"), "--no-check"]
    scpi = ["--chamber", "generic-scpi", "--chamber-port"]
    cases = [((-20, 40), [], 3, "give --chamber PROFILE"),
             ((-20, 40), scpi + [str(tmp_path / "nope")], 3, "cannot open chamber port"),
             ((-20, 40), ["--chamber", "generic-scpi"], 2, "needs --chamber-port"),
             ((-90, 40), scpi + ["x"], 3, "outside the chamber's range -70..180")]
    for temps, extra, code, msg in cases:
        plan.write_text(soak_plan(temps=temps))
        with pytest.raises(SystemExit) as e:
            main([*base, *extra])
        err = capsys.readouterr().err
        assert e.value.code == code and msg in err, (extra, err)
        assert len([ln for ln in err.splitlines() if not ln.startswith("calib: warning")]) == 1
    assert sorted(p.name for p in tmp_path.iterdir()) == ["plan.toml"]
