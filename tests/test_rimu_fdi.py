"""Parity-space FDI of a redundant unit: detection delay, isolation, the
estimate without the faulty sensor, and the statistic's distribution on
fault-free data (fast tests; the long goodness-of-fit run is marked slow)."""

from __future__ import annotations

from functools import lru_cache
from pathlib import Path

import numpy as np
import pytest
from scipy import stats

from calib_cli.io.plan import load_plan, parse_plan
from calib_cli.methods.rimu import fit_rimu, segment_kinematics
from calib_cli.methods.rimu_fdi import noise_sigma, parity_check, sensor_cov_blocks
from calib_cli.model.imu_model import ImuModel
from calib_cli.model.truth import Truth
from calib_cli.sim.simulate import plan_layout, simulate
from calib_cli.validation.rimu_truth import rimu_truth

ROOT = Path(__file__).resolve().parents[1]
PLAN = ROOT / "sample_data" / "rimu_six_position.toml"
D2R = np.pi / 180


def check_plan(static_s: float, rotating_s: float, cycles: int = 1) -> str:
    """Operational data for the check: rest, then turning at 10 deg/s, repeated."""
    head = PLAN.read_text().split("[[segment]]")[0].replace('transition_s = 4.0',
                                                             'transition_s = 2.0')
    segs = []
    for k in range(cycles):
        segs.append(f'[[segment]]\nlabel = "rest-{k}"\nattitude_deg = [10, 20, {30 + k}]\n'
                    f'duration_s = {static_s}\n')
        segs.append(f'[[segment]]\nlabel = "turn-{k}"\nattitude_deg = [10, 20, {30 + k}]\n'
                    f'table_axis_enu = [0, 0, 1]\ntable_rate_dps = 10.0\n'
                    f'duration_s = {rotating_s}\n')
    return head + "".join(segs)


@lru_cache(maxsize=1)
def calibrated():
    plan = load_plan(PLAN)
    truth = rimu_truth(plan_layout(plan), np.random.default_rng(42))
    cal = fit_rimu(simulate(plan, truth, 42))
    return truth, cal


def check(rec, cal, sensor, window_s=0.5, rate=0.1, with_cal=True):
    data = rec.accel if sensor == "accel" else rec.gyro
    sig = noise_sigma(cal.stats, sensor, rec.sample_rate, cal.layout.n)
    cov = sensor_cov_blocks(cal, sensor) if with_cal else None
    return parity_check(cal.params, cal.layout, sensor, rec.time, data, sig, window_s, rate, cov)


def operational(seed, static_s=15.0, rotating_s=15.0, cycles=1):
    truth, cal = calibrated()
    plan = parse_plan(check_plan(static_s, rotating_s, cycles), str(PLAN))
    # the same unit in the check plan's layout (Layout with arrays does not compare with ==)
    truth = Truth(ImuModel(truth.model.effects, plan_layout(plan)), truth.params, truth.noise)
    return simulate(plan, truth, seed), truth, cal


@pytest.mark.parametrize("k, t_fault", [(4, 7.37), (2, 24.81), (6, 16.02)])
def test_step_fault_detected_within_one_second(k, t_fault):
    rec, truth, cal = operational(11 + k)
    clean = check(rec, cal, "gyro")
    assert not clean.fault
    faulty = rec.gyro.copy()
    faulty[rec.time >= t_fault, k] += 1.0 * D2R  # 1 deg/s step
    rep = check(rec.with_(gyro=faulty), cal, "gyro")
    assert rep.fault and rep.faulty_sensor == k
    detected = rep.t[rep.alarm] + rep.window_s  # the moment each alarmed window completes
    assert detected[0] > t_fault and detected[0] - t_fault <= 1.0
    s = rep.summary()
    assert s["isolable"] and s["rest_consistent"]
    # the estimate without the faulty sensor is back on the truth; with it, it is not
    sel = rep.alarm & (rep.isolated == k)
    t0, t1 = rep.t, rep.t + rep.window_s
    errs = []
    for seg in rec.segments:  # windows inside a segment: compare with its true mean rate
        inside = sel & (t0 >= rec.time[seg.start]) & (t1 <= rec.time[seg.stop - 1])
        if inside.sum() >= 4:
            w_true = segment_kinematics(rec, seg).w.mean(0)
            errs.append((np.abs(rep.x_excl[inside].mean(0) - w_true).max(),
                         np.abs(rep.x_all[inside].mean(0) - w_true).max()))
    assert errs
    err_excl, err_all = np.max(errs, axis=0)
    assert err_excl < 0.05 * D2R < err_all


def test_drifting_and_stuck_sensors():
    rec, truth, cal = operational(21)
    t = rec.time
    drift = rec.gyro.copy()
    drift[:, 7] += np.clip(t - 10.0, 0, None) * 0.2 * D2R  # 0.2 deg/s per second
    rep = check(rec.with_(gyro=drift), cal, "gyro")
    assert rep.fault and rep.faulty_sensor == 7
    assert rep.t[rep.alarm][0] + rep.window_s < 10.0 + 5.0
    # stuck: sensor 0 freezes while at rest; the fault shows once the table turns
    # (sensor 0 sees 3.4 deg/s of the 10 deg/s turn in this attitude)
    stuck = rec.gyro.copy()
    i0 = np.searchsorted(t, 5.0)
    stuck[i0:, 0] = stuck[i0, 0]
    turn = rec.segments[1]
    rep = check(rec.with_(gyro=stuck), cal, "gyro")
    assert rep.fault and rep.faulty_sensor == 0
    assert rep.t[rep.alarm][0] <= t[turn.start] + 1.0
    # an accelerometer step of 10 mg
    acc = rec.accel.copy()
    acc[t >= 20.0, 3] += 10e-3 * 9.80665
    rep = check(rec.with_(accel=acc), cal, "accel")
    assert rep.fault and rep.faulty_sensor == 3
    assert rep.t[rep.alarm][0] + rep.window_s - 20.0 <= 1.0


def gof(rep):
    """KS test of the window statistic against chi-square(n - 3)."""
    return stats.kstest(rep.stat, stats.chi2(rep.dof).cdf).pvalue


def test_fault_free_statistic_follows_chi_square():
    """~700 windows of rest and turning: the statistic is chi-square(6)."""
    rec, truth, cal = operational(5, static_s=60.0, rotating_s=60.0, cycles=3)
    for sensor in ("gyro", "accel"):
        rep = check(rec, cal, sensor)
        assert len(rep.stat) > 600 and rep.dof == 6
        assert not rep.fault
        assert gof(rep) > 1e-3, (sensor, gof(rep), rep.stat.mean())
        assert abs(rep.stat.mean() - 6) < 4 * np.sqrt(12 / len(rep.stat))
    # the test is not blind: a doubled noise level is rejected
    rep = check(rec, cal, "gyro")
    half = parity_check(cal.params, cal.layout, "gyro", rec.time, rec.gyro,
                        rep.sigma / 2, 0.5, 0.1)
    assert gof(half) < 1e-6 and half.fault


def test_cli_rimu_check_exit_6(tmp_path, capsys, monkeypatch):
    from calib_cli.cli.main import main
    from calib_cli.io.h5 import write_calibration, write_raw

    rec, truth, cal = operational(3)
    monkeypatch.chdir(tmp_path)
    write_calibration("cal.h5", cal)
    write_raw("ok.h5", rec)
    g = rec.gyro.copy()
    g[rec.time >= 12.0, 8] += 1.0 * D2R
    write_raw("bad.h5", rec.with_(gyro=g))

    def run(*a):
        capsys.readouterr()
        with pytest.raises(SystemExit) as exc:
            main(list(a))
        return exc.value.code, *capsys.readouterr()

    code, out, err = run("rimu-check", "ok.h5", "cal.h5")
    assert code == 0
    code, out, err = run("rimu-check", "bad.h5", "cal.h5", "--json")
    assert code == 6 and "gyro sensor 8" in err and "bad.h5" in err
    import json

    js = json.loads(out)
    gy = next(c for c in js["checks"] if c["sensor"] == "gyro")
    assert js["fault"] and gy["faulty_sensor"] == 8 and gy["dof"] == 6
    assert gy["false_alarm_rate_per_hour"] == 0.1
    code, out, err = run("rimu-check", "bad.h5", "nonexistent.h5")
    assert code == 3


@pytest.mark.slow
def test_goodness_of_fit_long_run():
    """One hour of fault-free data (7200 windows of 0.5 s) per sensor kind: the
    statistic passes a KS test against chi-square(6), and the exceedances of
    looser thresholds match their rates."""
    rec, truth, cal = operational(99, static_s=600.0, rotating_s=600.0, cycles=3)
    for sensor in ("gyro", "accel"):
        rep = check(rec, cal, sensor)
        assert len(rep.stat) > 7000
        p = gof(rep)
        assert p > 1e-3, (sensor, p)
        for a in (0.1, 0.01, 0.001):
            k = int((rep.stat > stats.chi2.isf(a, rep.dof)).sum())
            lo, hi = stats.binom.interval(0.999, len(rep.stat), a)
            assert lo <= k <= hi, (sensor, a, k, lo, hi)
        assert not rep.fault
