"""calib rimu-geometry (issue 22 item 5): figures of merit of a layout."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
from click.testing import CliRunner
from scipy import stats

from calib_cli.cli.main import cli
from calib_cli.io.plan import load_plan
from calib_cli.methods.rimu_geometry import geometry_report

ROOT = Path(__file__).resolve().parents[1]
D2R = np.pi / 180


def _main(args):
    from calib_cli.cli.main import main

    try:
        main(args)
    except SystemExit as e:
        return e.code
    return 0


def _json(*args):
    r = CliRunner().invoke(cli, ["rimu-geometry", *map(str, args), "--json"])
    assert r.exit_code == 0, r.output
    return json.loads(r.output)


def test_tetrahedron_profile_gain_and_subsets():
    js = _json(ROOT / "profiles" / "rimu" / "tetrahedron.toml")
    assert round(js["accuracy_gain"], 3) == 1.732  # H^T H = 3 I: three orthonormal triads
    np.testing.assert_allclose(js["HtH"], 3 * np.eye(3), atol=1e-4)
    assert js["subsets"]["total"] == 466 and js["subsets"]["spanning"] == 450
    assert js["collinear_groups"] == [[1, 3]]
    assert [1, 3, 0] not in js["subsets"]["not_spanning"]
    assert [0, 1, 3] in js["subsets"]["not_spanning"]
    assert js["single_faults"]["tolerated"] == 9 and js["single_faults"]["isolable"] == 9
    assert js["double_faults"]["tolerated"] == 36
    # detection power: non-central chi-square, |v_i|^2 = 1 - h_i^T (H^T H)^-1 h_i = 2/3
    d = js["detection"]
    thr = stats.chi2.isf(1e-3, 6)
    np.testing.assert_allclose(d["per_sensor"], stats.ncx2.sf(thr, 6, 25 * 2 / 3), rtol=1e-4)
    assert _json("tetrahedron", "--fault", "8")["detection"]["min_power"] > d["min_power"]


def test_triad_and_minimal_layouts():
    triad = geometry_report([0, 0, 90 * D2R], [0, 90 * D2R, 0])
    assert np.isclose(triad["accuracy_gain"], 1.0)
    assert triad["subsets"]["spanning"] == 1 and triad["detection"]["threshold"] is None
    assert triad["single_faults"]["tolerated"] == 0
    # four sensors: one parity equation, every fault detected, none isolated
    el = np.full(4, np.arcsin(1 / 3))
    el[0] = 90 * D2R
    tet = geometry_report(-el, [0, 0, 120 * D2R, 240 * D2R])
    assert tet["single_faults"]["detectable"] == 4 and tet["single_faults"]["isolable"] == 0
    # x, y, y, z: the collinear pair only detects (their parity directions are
    # opposite), the x and z sensors are not even checked
    xyyz = geometry_report([0, 0, 0, 90 * D2R], [0, 90 * D2R, 90 * D2R, 0])
    assert xyyz["single_faults"]["detectable"] == 2
    assert xyyz["single_faults"]["isolable"] == 0
    assert xyyz["single_faults"]["not_isolable_pairs"] == [[1, 2]]


def test_paper_plan_and_bad_input(tmp_path, capsys):
    plan = load_plan(ROOT / "sample_data" / "rimu_paper_1s.toml")
    stat = [s for s in plan.segments if s.table_rate is not None]
    assert len(stat) == 6
    assert all(s.duration == 1.0 and np.isclose(s.table_rate, 10 * D2R) for s in stat)
    js = _json(ROOT / "sample_data" / "rimu_paper_1s.toml")
    assert js["subsets"]["spanning"] == 450
    assert _main(["rimu-geometry", str(tmp_path / "none.toml")]) == 3
    assert "none.toml" in capsys.readouterr().err
    assert _main(["rimu-geometry", "tetrahedron", "--alpha", "2"]) == 3
    assert "alpha" in capsys.readouterr().err
