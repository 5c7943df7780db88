"""Check positions of the turntable fit (issue 22 item 2, the rough-stand paper's
verification): static segments the fit does not use, |f| - g and the vertical rate
against the earth rate, with sigma; the estimate history beside the sigma history."""

from __future__ import annotations

import numpy as np
import pytest
from click.testing import CliRunner

from calib_cli.cli.main import cli
from calib_cli.data import CalibrationResult
from calib_cli.io.h5 import write_raw
from calib_cli.io.plan import parse_plan
from calib_cli.methods.check_positions import check_positions
from calib_cli.methods.turntable import TurntableOptions, fit_turntable
from calib_cli.model.effects import Layout
from calib_cli.sim.simulate import simulate
from calib_cli.sim.turntable_plans import turntable_plan_text

CHECKS = ([0, 0, 0], [0, -90, 0], [90, 0, 0])  # +z, +x, +y up (roll, pitch, yaw deg)


def _plan(duration=90.0):
    txt = turntable_plan_text(4, duration_s=duration)
    for k, att in enumerate(CHECKS):
        txt += f"[[segment]]\nlabel = 'check-{k + 1}'\nattitude_deg = {att}\nduration_s = 20.0\n"
    return parse_plan(txt, "<check>")


@pytest.fixture(scope="module")
def fitted():
    rec = simulate(_plan(), None, 4)
    return rec, fit_turntable(rec, TurntableOptions())


def _truth_cal(rec, cov_scale=0.0):
    p = {k: np.asarray(v, float) for k, v in rec.truth["params"].items() if k != "lever_arm"}
    keys = ["accel_bias", "gyro_bias"]
    order = [(k, i) for k in keys for i in range(3)]
    return CalibrationResult(method="turntable", params=p, sigma={k: np.zeros(3) for k in keys},
                             units={}, covariance=np.eye(6) * cov_scale, cov_order=order,
                             stats={}, model=[{"name": "bias", "sensor": "accel"},
                                              {"name": "scale_misalignment", "sensor": "accel",
                                               "structure": "lower"},
                                              {"name": "bias", "sensor": "gyro"},
                                              {"name": "scale_misalignment", "sensor": "gyro",
                                               "structure": "full"},
                                              {"name": "g_sensitivity", "sensor": "gyro"}],
                             layout=Layout(n_cycles=0))


def test_exact_calibration_leaves_only_the_noise():
    rec = simulate(_plan(60.0), None, 5)
    cp = check_positions(rec, _truth_cal(rec))
    assert cp["n"] == 3 and [p["label"] for p in cp["positions"]] == ["check-1", "check-2",
                                                                        "check-3"]
    assert [p["vertical_axis"] for p in cp["positions"]] == ["+z", "+x", "+y"]
    for p in cp["positions"]:
        assert p["axis_near_vertical"] and p["axis_tilt_deg"] < 1.0
        assert abs(p["g_error_z"]) < 4 and abs(p["earth_rate_up_error_z"]) < 4
        assert p["g_error_sigma_calibration"] == 0.0  # no covariance given
    # a calibration covariance widens the sigma (bias variance 1e-4 (m/s^2)^2 -> ~1e-2)
    wide = check_positions(rec, _truth_cal(rec, 1e-4))
    assert wide["positions"][0]["g_error_sigma"] > 5e-3
    # a wrong bias along the vertical axis fails the check
    bad = _truth_cal(rec)
    bad.params["accel_bias"] = bad.params["accel_bias"] + np.array([0.0, 0.0, 0.05])
    assert check_positions(rec, bad)["verdict"] == "fail"


def test_noise_free_exact_calibration_has_no_verdict():
    from calib_cli.sim.turntable_plans import turntable_truth

    plan = _plan(30.0)
    t = turntable_truth(plan, np.random.default_rng(1), noise={"accel_white": 0.0,
                                                               "gyro_white": 0.0})
    rec = simulate(plan, t, 1)
    cp = check_positions(rec, _truth_cal(rec))
    assert cp["verdict"] == "none" and cp["positions"][0]["g_error_z"] is None
    assert abs(cp["positions"][0]["g_error"]) < 1e-9


def test_turntable_fit_reports_check_positions(fitted):
    rec, res = fitted
    cp = res.stats["check_positions"]
    assert cp["n"] == 3 and cp["verdict"] in ("pass", "fail")
    z = np.array([[p["g_error_z"], p["earth_rate_up_error_z"]] for p in cp["positions"]])
    assert np.all(np.isfinite(z)) and np.abs(z).max() < 4.5
    assert all(p["g_error_sigma_calibration"] > 0 for p in cp["positions"])


def test_no_static_segment_is_said(fitted):
    rec, res = fitted
    from dataclasses import replace

    rot = replace(rec, segments=tuple(s for s in rec.segments if s.kind == "rotating"))
    cp = check_positions(rot, res)
    assert cp["verdict"] == "none" and "no static segment" in cp["note"]


def test_estimate_history_beside_sigma_history(fitted):
    _rec, res = fitted
    est, sig = res.tables["estimate_history"], res.tables["sigma_history"]
    assert est.shape == sig.shape and est.shape[1] == len(res.tables["sigma_history_labels"])
    # the running proof-mass estimate ends near the final one (within a few sigma)
    labels = list(res.tables["sigma_history_labels"])
    k = labels.index("p_xy")
    assert abs(est[-1, k] - res.params["proof_mass_offsets"][0, 1]) < 5 * sig[-1, k] + 1e-3


def test_report_has_check_table_and_estimate_history(fitted, tmp_path):
    rec, res = fitted
    from calib_cli.io.h5 import write_calibration

    write_raw(tmp_path / "raw.h5", rec)
    write_calibration(tmp_path / "cal.h5", res, [])
    r = CliRunner().invoke(cli, ["report", str(tmp_path / "cal.h5"), str(tmp_path / "raw.h5"),
                                 "--out", str(tmp_path / "rep")])
    assert r.exit_code == 0, r.output
    md = (tmp_path / "rep" / "report.md").read_text()
    assert "Check positions" in md and "check-2" in md
    assert "estimate-history" in md
