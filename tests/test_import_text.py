"""calib import text / import csv units / calib detect: foreign layouts and raw counts."""

from __future__ import annotations

import json

import numpy as np
import pytest
from gyro_sim import simulated

from calib_cli.errors import InputError
from calib_cli.io.csvlog import import_csv, write_csv
from calib_cli.io.h5 import read_raw
from calib_cli.io.plan import parse_plan
from calib_cli.io.textlog import import_text, parse_column_map
from calib_cli.methods.static_detect import detect_static

AUTO_PLAN = parse_plan('name = "hand"\nkind = "static"\n[[segment]]\nlabel = "pos"\n'
                       'repeat = "auto"\n')


@pytest.fixture(scope="module")
def sim():
    rec, _ = simulated(7, False)
    return rec


def _write(path, cols, header=None, sep=" ", fmt="%.9g"):
    with open(path, "w") as fh:
        if header:
            fh.write(sep.join(header) + "\n")
        np.savetxt(fh, np.column_stack(cols), delimiter=sep, fmt=fmt)


def test_separate_whitespace_files_in_counts(tmp_path, sim):
    """imu_tk layout: t ax ay az / t gx gy gz, no header, raw counts."""
    acc = np.round(sim.accel * 400 + 32768)
    gyr = np.round(sim.gyro * 4000 + 32768)
    _write(tmp_path / "acc.txt", [sim.time, acc])
    _write(tmp_path / "gyr.txt", [sim.time, gyr])
    rec = import_text(tmp_path / "acc.txt", AUTO_PLAN, tmp_path / "gyr.txt",
                      accel_units="count", gyro_units="count")
    assert rec.units == {"accel": "count", "gyro": "count"}
    assert np.array_equal(rec.accel, acc) and np.array_equal(rec.gyro, gyr)
    assert len(rec.static_segments()) == 12  # the 12 simulated positions


def test_header_column_map_and_units(tmp_path, sim):
    """CSV with its own names, g and deg/s converted to SI, time in ms."""
    names = ["ms", "Gx", "Gy", "Gz", "Ax", "Ay", "Az"]
    _write(tmp_path / "log.csv", [sim.time * 1e3, np.degrees(sim.gyro), sim.accel / 9.80665],
           header=names, sep=",")
    rec = import_text(tmp_path / "log.csv", AUTO_PLAN,
                      columns="time=ms,ax=Ax,ay=Ay,az=Az,gx=Gx,gy=Gy,gz=Gz",
                      accel_units="g", gyro_units="deg/s", time_unit="ms")
    assert rec.units == {"accel": "m/s^2", "gyro": "rad/s"}
    assert np.allclose(rec.accel, sim.accel, rtol=1e-8, atol=1e-9)
    assert np.allclose(rec.gyro, sim.gyro, rtol=1e-8, atol=1e-9)
    assert np.allclose(rec.time, sim.time)


def test_positions_and_rate(tmp_path, sim):
    """No time column: columns by position (from 1) and --rate."""
    _write(tmp_path / "log.txt", [sim.gyro, sim.accel])
    rec = import_text(tmp_path / "log.txt", AUTO_PLAN, columns="gx=1,gy=2,gz=3,ax=4,ay=5,az=6",
                      rate=100.0)
    assert np.allclose(rec.time, np.arange(len(sim.time)) / 100.0)
    with pytest.raises(InputError, match="--rate"):
        import_text(tmp_path / "log.txt", AUTO_PLAN, columns="gx=1,gy=2,gz=3,ax=4,ay=5,az=6")


def test_segment_labels_and_sort(tmp_path):
    """imucal layout: parts listed by label, out of time order."""
    plan = parse_plan('name = "f"\nkind = "static"\n[[segment]]\nlabel = "a"\n'
                      '[[segment]]\nlabel = "b"\n')
    rows = ["part,samples,acc_x,acc_y,acc_z,gyr_x,gyr_y,gyr_z"]
    rows += [f"b,{i},1,2,3,4,5,6" for i in range(5, 10)]
    rows += [f"a,{i},1,2,3,4,5,6" for i in range(0, 5)]
    (tmp_path / "s.csv").write_text("\n".join(rows) + "\n")
    cmap = "time=samples,ax=acc_x,ay=acc_y,az=acc_z,gx=gyr_x,gy=gyr_y,gz=gyr_z,segment=part"
    with pytest.raises(InputError, match="--sort"):
        import_text(tmp_path / "s.csv", plan, columns=cmap, rate=10, time_unit="sample")
    rec = import_text(tmp_path / "s.csv", plan, columns=cmap, rate=10, time_unit="sample",
                      sort=True, accel_units="count", gyro_units="count")
    assert [(s.label, s.start, s.stop) for s in rec.segments] == [("a", 0, 5), ("b", 5, 10)]
    # the default map finds these names too, and takes `samples` for a sample counter
    rec2 = import_text(tmp_path / "s.csv", plan, rate=10, sort=True)
    assert np.array_equal(rec2.accel, rec.accel) and np.allclose(rec2.time, rec.time)
    with pytest.raises(InputError, match="time in samples: give the sample rate"):
        import_text(tmp_path / "s.csv", plan, sort=True)


def test_segments_json(tmp_path, sim):
    plan = parse_plan('name = "f"\nkind = "static"\n[[segment]]\nlabel = "a"\n'
                      '[[segment]]\nlabel = "b"\n')
    _write(tmp_path / "log.txt", [sim.time, sim.accel, sim.gyro])
    (tmp_path / "seg.json").write_text(json.dumps({"a": {"start": 10, "end": 500},
                                                   "b": [900, 1500]}))
    rec = import_text(tmp_path / "log.txt", plan, segments_json=str(tmp_path / "seg.json"))
    assert [(s.label, s.start, s.stop) for s in rec.segments] == [("a", 10, 500), ("b", 900, 1500)]
    (tmp_path / "bad.json").write_text(json.dumps({"c": [0, 5]}))
    with pytest.raises(InputError, match="'c' is not in the plan"):
        import_text(tmp_path / "log.txt", plan, segments_json=str(tmp_path / "bad.json"))


@pytest.mark.parametrize("content,match", [
    ("1 2 3 4\n1 2 3\n", "line 2: 3 cells, expected 4"),
    ("1 2 3 4\n2 2 x 4\n", "line 2, column 3: not a number"),
    ("1 2 3 4\n1 2 3 4\n", "time is not increasing at line 2"),
])
def test_bad_text_names_line(tmp_path, content, match):
    (tmp_path / "a.txt").write_text(content)
    with pytest.raises(InputError, match=match) as exc:
        import_text(tmp_path / "a.txt", AUTO_PLAN, columns="time=1,ax=2,ay=3,az=4")
    assert exc.value.path == str(tmp_path / "a.txt")


def test_gyro_file_must_share_timestamps(tmp_path, sim):
    _write(tmp_path / "acc.txt", [sim.time, sim.accel])
    _write(tmp_path / "gyr.txt", [sim.time + 0.001, sim.gyro])
    with pytest.raises(InputError, match="must share timestamps") as exc:
        import_text(tmp_path / "acc.txt", AUTO_PLAN, tmp_path / "gyr.txt")
    assert exc.value.path == str(tmp_path / "gyr.txt")
    _write(tmp_path / "gyr2.txt", [sim.time[:-1], sim.gyro[:-1]])
    with pytest.raises(InputError, match="rows"):
        import_text(tmp_path / "acc.txt", AUTO_PLAN, tmp_path / "gyr2.txt")


def test_column_map_errors():
    assert parse_column_map("time=t, ax=3") == {"time": "t", "ax": 3}
    with pytest.raises(InputError, match="unknown field"):
        parse_column_map("foo=1")
    with pytest.raises(InputError, match="FIELD=COLUMN"):
        parse_column_map("ax")


def test_contract_csv_unchanged_and_units_option(tmp_path, sim, capsys):
    """The contract CSV path keeps working; --gyro-units converts at import."""
    from test_gyro_fit import run_cli

    write_csv(tmp_path / "log.csv", sim)
    rec = import_csv(tmp_path / "log.csv", parse_plan(sim.plan_text))
    assert rec.units == {"accel": "m/s^2", "gyro": "rad/s"}
    assert [s.start for s in rec.segments] == [s.start for s in sim.segments]
    plan = tmp_path / "p.toml"
    plan.write_text(sim.plan_text)
    code, _, err = run_cli(["-q", "import", "csv", str(tmp_path / "log.csv"), "--plan", str(plan),
                            "--out", str(tmp_path / "r.h5"), "--accel-units", "count"], capsys)
    assert code == 0, err
    assert read_raw(tmp_path / "r.h5").units == {"accel": "count", "gyro": "rad/s"}
    code, _, err = run_cli(["-q", "import", "text", str(tmp_path / "log.csv"), "--plan",
                            str(plan), "--out", str(tmp_path / "r2.h5"), "--gyro-units",
                            "deg/s"], capsys)
    assert code == 0, err
    r2 = read_raw(tmp_path / "r2.h5")
    assert np.allclose(r2.gyro, np.radians(rec.gyro))


def test_detection_explains_too_few(sim):
    """Too few intervals: the message says how many, why, and which threshold helps."""
    rep = detect_static(sim.time, sim.accel, sim.gyro, min_duration_s=9.0)
    msg = rep.explain(12)
    assert "found 0 static intervals" in msg
    assert "shorter than --min-static 9 s" in msg
    assert "check --min-static" in msg
    rep = detect_static(sim.time, sim.accel, sim.gyro)
    assert "--threshold 3 finds 12" in rep.explain(12)
    assert "finds 12" in rep.explain(10, at_least=True)


def test_import_count_mismatch_message(tmp_path, sim):
    plan = parse_plan('name = "f"\nkind = "static"\n' +
                      "".join(f'[[segment]]\nlabel = "p{i}"\n' for i in range(14)))
    write_csv(tmp_path / "log.csv", sim)
    text = (tmp_path / "log.csv").read_text().splitlines()
    # drop the segment column: detection instead
    rows = [",".join(r.split(",")[:-1]) for r in text[1:]]
    (tmp_path / "nos.csv").write_text("\n".join(rows) + "\n")
    with pytest.raises(InputError) as exc:
        import_csv(tmp_path / "nos.csv", plan)
    msg = str(exc.value)
    assert "detected 12 static intervals but the plan has 14" in msg
    assert "no threshold finds that many" in msg


def test_detect_command(tmp_path, sim, capsys):
    from test_gyro_fit import run_cli

    write_csv(tmp_path / "log.csv", sim)
    code, out, _ = run_cli(["detect", str(tmp_path / "log.csv"), "--json", "--expect", "12"],
                           capsys)
    assert code == 0
    d = json.loads(out)
    assert len(d["intervals"]) == 12 and "finds 12" in d["explain"]


def test_fit_too_few_positions_says_which_threshold(sim):
    """A recording segmented with only 5 positions: the scalar fit's error says
    what detection finds in it and the threshold that finds >= 9."""
    from calib_cli.errors import EstimationError
    from calib_cli.methods.accel_lsq import fit_accel

    few = sim.with_(segments=tuple(s if i < 5 else s.__class__(s.label, "turn", s.start, s.stop)
                                   for i, s in enumerate(sim.segments)))
    with pytest.raises(EstimationError) as exc:
        fit_accel(few, "scalar")
    msg = str(exc.value)
    assert "the recording has 5" in msg and "--threshold 3 finds 12" in msg


def test_detect_command_on_text_logs(tmp_path, sim, capsys):
    """Separate whitespace files without header, as `import text` reads them."""
    from test_gyro_fit import run_cli

    _write(tmp_path / "acc.txt", [sim.time, sim.accel])
    _write(tmp_path / "gyr.txt", [sim.time, sim.gyro])
    code, out, err = run_cli(["detect", str(tmp_path / "acc.txt"), str(tmp_path / "gyr.txt"),
                              "--json"], capsys)
    assert code == 0, err
    assert len(json.loads(out)["intervals"]) == 12
