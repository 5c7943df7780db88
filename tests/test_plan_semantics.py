"""Plan semantics of CONTRACT.md section 3: rotating segments need no rate key,
labels may repeat. Driven through the CLI on plans written from the contract."""

from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner

from calib_cli.cli.main import cli
from calib_cli.io.plan import parse_plan
from calib_cli.methods.cycle_detect import detect_cycles, trim_intervals

# a turntable plan as a user writes it from the contract alone: attitude and table
# axis per cycle, no rate key, no simulation key
CONTRACT_TT = """
name = "three-cycles"
kind = "turntable"
[site]
latitude_deg = 50.45
height_m = 180.0
[unit]
serial = "SN-TT-C"
[[segment]]
label = "x-axis"
attitude_deg = [0, 0, 0]
table_axis_enu = [1, 0, 0]
duration_s = 100.0
[[segment]]
label = "y-axis"
attitude_deg = [0, 0, -90]
table_axis_enu = [1, 0, 0]
duration_s = 100.0
[[segment]]
label = "z-axis"
attitude_deg = [0, 90, 0]
table_axis_enu = [1, 0, 0]
duration_s = 100.0
"""


def _run(args):
    res = CliRunner().invoke(cli, args, catch_exceptions=False)
    return res


def test_table_axis_makes_a_rotating_segment():
    plan = parse_plan(CONTRACT_TT)
    assert [s.kind for s in plan.segments] == ["rotating"] * 3
    still = parse_plan(CONTRACT_TT.replace('duration_s = 100.0\n[[segment]]\nlabel = "y-axis"',
                                           'table_rate_dps = 0\nduration_s = 100.0\n[[segment]]\n'
                                           'label = "y-axis"', 1))
    assert [s.kind for s in still.segments] == ["static", "rotating", "rotating"]


def test_repeated_labels_are_kept_apart():
    text = CONTRACT_TT.replace('label = "z-axis"', 'label = "x-axis"')
    plan = parse_plan(text)
    assert plan.visit_labels == ("x-axis#1", "y-axis", "x-axis#2")


@pytest.fixture(scope="module")
def contract_log(tmp_path_factory):
    d = tmp_path_factory.mktemp("tt_contract")
    (d / "plan.toml").write_text(CONTRACT_TT)
    res = _run(["simulate", str(d / "plan.toml"), "--out", str(d / "log.csv"), "--seed", "4"])
    assert res.exit_code == 0, res.output
    lines = (d / "log.csv").read_text().splitlines()
    hdr = next(i for i, line in enumerate(lines) if not line.startswith("#"))
    cols = lines[hdr].split(",")
    j = cols.index("segment")
    keep = lines[:hdr] + [",".join(p for k, p in enumerate(line.split(",")) if k != j)
                          for line in lines[hdr:]]
    (d / "noseg.csv").write_text("\n".join(keep) + "\n")
    # and without the table channels either: the cycles come from the gyros alone
    ja, jr = cols.index("table_angle"), cols.index("table_rate")
    bare = lines[:hdr] + [",".join(p for k, p in enumerate(line.split(",")) if k not in (j, ja, jr))
                          for line in lines[hdr:]]
    (d / "bare.csv").write_text("\n".join(bare) + "\n")
    return d


@pytest.mark.parametrize("log", ["log.csv", "noseg.csv", "bare.csv"])
def test_contract_turntable_plan_imports_and_fits(contract_log, log, tmp_path):
    d = contract_log
    raw = tmp_path / "raw.h5"
    res = _run(["import", "csv", str(d / log), "--plan", str(d / "plan.toml"), "--out", str(raw)])
    assert res.exit_code == 0, res.output
    shown = json.loads(_run(["show", str(raw), "--json"]).output)
    kinds = [s["kind"] for s in shown["segments"]]
    assert kinds == ["rotating"] * 3, kinds
    cal = tmp_path / "cal.h5"
    res = _run(["fit", "turntable", str(raw), "--out", str(cal), "--json"])
    assert res.exit_code == 0, res.output
    out = json.loads(res.output)
    assert out["stats"]["n_cycles"] == 3


def test_revisited_positions_import_fit_and_report(tmp_path):
    text = (tmp_path / "p.toml")
    src = open("sample_data/twelve_position.toml").read()
    # visit x-up again at the end (repeatability)
    src += '\n[[segment]]\nlabel = "x-up"\nattitude_deg = [0, -90, 0]\nduration_s = 10.0\n'
    text.write_text(src)
    raw, cal = tmp_path / "raw.h5", tmp_path / "cal.h5"
    assert _run(["simulate", str(text), "--out", str(tmp_path / "log.csv"), "--seed", "2"]).exit_code == 0
    res = _run(["import", "csv", str(tmp_path / "log.csv"), "--plan", str(text), "--out", str(raw)])
    assert res.exit_code == 0, res.output
    res = _run(["fit", "accel", str(raw), "--out", str(cal)])
    assert res.exit_code == 0, res.output
    shown = json.loads(_run(["show", str(raw), "--json"]).output)
    labels = [s["label"] for s in shown["segments"]]
    assert labels.count("x-up#1") == 1 and labels.count("x-up#2") == 1
    rep = tmp_path / "rep"
    res = _run(["report", str(cal), "--out", str(rep)])
    assert res.exit_code == 0, res.output
    md = next(rep.glob("*.md")).read_text()
    assert "x-up#1" in md and "x-up#2" in md  # every visit reported, told apart


def test_cycle_detection_keeps_holds_inside_a_cycle():
    fs = 50.0
    t = np.arange(0, 200, 1 / fs)
    w = np.zeros((len(t), 3))
    # cycle 1 about x: turn, hold at 0 for 20 s, turn again; remount slew about z;
    # cycle 2 about y
    w[(t > 5) & (t < 40), 0] = 1.0
    w[(t > 60) & (t < 90), 0] = -1.0
    w[(t > 100) & (t < 102), 2] = 0.5  # a remount: 1 rad, less than a revolution
    w[(t > 110) & (t < 190), 1] = 2.0
    rng = np.random.default_rng(0)
    det = detect_cycles(t, w + rng.standard_normal(w.shape) * 1e-3)
    assert len(det.cycles) == 2
    (a0, b0), (a1, b1) = det.cycles
    assert t[a0] < 5 and t[b0 - 1] > 90 and t[a1] < 110 and t[b1 - 1] > 189
    assert len(det.short_runs) == 1
    trimmed = trim_intervals([(0, 300)], det.cycles, 10)
    assert trimmed == [] or trimmed[0][1] <= a0


def test_simulate_warns_beyond_the_unit_range(tmp_path):
    text = CONTRACT_TT.replace('serial = "SN-TT-C"', 'serial = "SN-TT-C"\naccel_range_g = 1.2')
    text = text.replace('table_axis_enu = [1, 0, 0]\nduration_s = 100.0',
                        'table_axis_enu = [1, 0, 0]\nlever_arm_m = [0, 0.5, 0]\nduration_s = 60.0', 1)
    (tmp_path / "p.toml").write_text(text)
    res = CliRunner().invoke(cli, ["simulate", str(tmp_path / "p.toml"), "--out",
                                   str(tmp_path / "r.h5")])
    assert res.exit_code == 0, res.output
    assert "beyond the unit's range" in res.output


def test_clipped_accelerometers_are_reported(contract_log, tmp_path):
    from calib_cli.io.h5 import read_raw
    from calib_cli.methods.turntable import TurntableOptions, fit_turntable

    raw = tmp_path / "raw.h5"
    assert _run(["import", "csv", str(contract_log / "log.csv"), "--plan",
                 str(contract_log / "plan.toml"), "--out", str(raw)]).exit_code == 0
    rec = read_raw(raw)
    top = np.quantile(rec.accel[:, 0], 0.99)
    rec = rec.with_(accel=np.column_stack([np.minimum(rec.accel[:, 0], top), rec.accel[:, 1:]]))
    res = fit_turntable(rec, TurntableOptions(table_encoder="off"))
    assert res.stats["accel_clipped_samples"][0] > 100


@pytest.mark.parametrize("bad", ['rate_jerk_dps3 = "steep"', "rate_jerk_dps3 = -5",
                                 'x_dummy = 1\nsim_table_encoder_counts = "many"'])
def test_bad_simulation_keys_are_one_line(tmp_path, bad, capsys):
    text = CONTRACT_TT.replace('duration_s = 100.0\n[[segment]]\nlabel = "y-axis"',
                               f'duration_s = 100.0\nrate_shape = "scurve"\n{bad}\n'
                               'rate_profile = [[0, 0], [3, 0], [5, 100], [20, 100], [22, 0]]\n'
                               '[[segment]]\nlabel = "y-axis"', 1)
    if "encoder" in bad:
        text = bad.split("\n")[1] + "\n" + CONTRACT_TT
    (tmp_path / "p.toml").write_text(text)
    from calib_cli.cli.main import main

    with pytest.raises(SystemExit) as ex:
        main(["simulate", str(tmp_path / "p.toml"), "--out", str(tmp_path / "r.h5")])
    assert ex.value.code == 3
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert "p.toml" in err and ("rate_jerk_dps3" in err or "sim_table_encoder_counts" in err)
    assert not (tmp_path / "r.h5").exists()
