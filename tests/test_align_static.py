"""Static-only two-position alignment (issue 22 item 3): fast tests; the
20-seed validation is in test_align_static_slow.py (make validate)."""

from __future__ import annotations

import dataclasses
import json

import numpy as np
import pytest

from calib_cli.errors import EstimationError
from calib_cli.methods.align_static import COND_MAX, fit_align_static
from calib_cli.sim.simulate import simulate
from calib_cli.validation import align_cases as ac


def _run(args):
    from calib_cli.cli.main import main

    try:
        main(args)
    except SystemExit as e:
        return e.code
    return 0


def test_within_sigma_few_seeds_both_attitudes():
    run = ac.run_static_pair((1, 1, 1), 130.0, range(3), {"s": fit_align_static},
                             duration=120.0)["s"]
    assert not run["failed"].any()
    z = run["err"] / run["sigma"]
    assert np.all(np.isfinite(z))
    assert np.all(np.abs(z) < 4.0), np.round(z, 2)


def test_no_turn_needed_and_stats():
    p = ac.plan([((1, 1, 1), 130.0)], duration=120.0)
    truth = ac.nav_truth(np.random.default_rng(3))
    rec = simulate(p, truth, seed=3)
    # drop the turn segment: the static method never looks at it
    rec = dataclasses.replace(rec, segments=[s for s in rec.segments if s.kind == "static"])
    res = fit_align_static(rec)
    st = res.stats
    assert st["method"] == "static" and st["unobservable"] == []
    assert st["condition_number"] < COND_MAX
    assert len(st["attitude_2"]) == 3 and all(s is not None for s in st["attitude_2_sigma"])
    assert abs(np.degrees(st["rotation_angle"]) - 130.0) < 1.0


def test_turn_about_the_vertical_gives_null_sigma():
    run = ac.run_static_pair("vertical", 120.0, range(2), {"s": fit_align_static},
                             duration=120.0, start=(0.0, 0.0, 30.0))["s"]
    assert not run["failed"].any()
    assert np.isnan(run["sigma"][:, 0]).all()  # nabla_x lost with the tilt
    z = run["err"] / run["sigma"]
    fin = np.isfinite(z)
    assert fin.any() and np.all(np.abs(z[fin]) < 4.0)


def test_turn_about_the_earth_axis_is_exit_4():
    p = ac.plan([(ac.polar_axis_body(), 120.0)], duration=120.0)
    rec = simulate(p, ac.nav_truth(np.random.default_rng(1)), seed=1)
    with pytest.raises(EstimationError, match="earth's axis"):
        fit_align_static(rec)


def test_cli_static(tmp_path, capsys):
    raw, cal = tmp_path / "raw.h5", tmp_path / "cal.h5"
    assert _run(["-q", "simulate", "docs/examples/align_plan.toml", "--truth",
                 "docs/examples/align_truth.toml", "--out", str(raw), "--seed", "7"]) == 0
    assert _run(["-q", "fit", "align", str(raw), "--out", str(cal), "--method", "static"]) == 0
    capsys.readouterr()
    assert _run(["show", str(cal), "--json"]) == 0
    js = json.loads(capsys.readouterr().out)
    assert js["stats"]["method"] == "static"
    assert set(js["params"]) == {"accel_bias", "gyro_bias", "attitude"}
    assert abs(np.degrees(js["params"]["attitude"][2]) - 30.0) < 1.0
    assert "attitude_2" in js["stats"] and "attitude_2_sigma" in js["stats"]
    assert _run(["-q", "report", str(cal), "--out", str(tmp_path / "rep")]) == 0
    md = (tmp_path / "rep" / "report.md").read_text()
    assert "Static-only alignment" in md and "well conditioned" in md


def test_a_third_position_removes_the_weakness():
    p = ac.plan([((1, 1, 1), 130.0), ((0, 1, -0.6), 100.0)], duration=120.0)
    truth = ac.nav_truth(np.random.default_rng(5))
    rec = simulate(p, truth, seed=5)
    res = fit_align_static(rec)
    assert res.stats["n_positions"] == 3 and res.stats["unobservable"] == []
    assert np.all(res.sigma["accel_bias"] < 10 * ac.UG)  # vs ~1 mg from two positions
    z = (res.params["accel_bias"] - truth.params["accel_bias"]) / res.sigma["accel_bias"]
    assert np.all(np.abs(z) < 4.0)
