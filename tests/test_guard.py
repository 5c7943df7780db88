"""Issue 15: guard rails on outputs, inputs and recordings, driven through the CLI."""

from __future__ import annotations

import os
import stat
from pathlib import Path

import pytest

SAMPLE = Path(__file__).resolve().parent.parent / "sample_data"


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """raw.h5 and cal.h5 from the shipped twelve-position log."""
    from calib_cli.cli.main import main

    d = tmp_path_factory.mktemp("guard")
    raw, cal = d / "raw.h5", d / "cal.h5"
    for args in (["-q", "import", "csv", SAMPLE / "twelve_position.csv", "--plan",
                  SAMPLE / "twelve_position.toml", "--out", raw],
                 ["-q", "fit", "accel", raw, "--out", cal]):
        with pytest.raises(SystemExit) as e:
            main([str(a) for a in args])
        assert e.value.code in (0, None)
    return d


def _snapshot(d):
    return {p.name: (p.stat().st_size, p.stat().st_mtime_ns) for p in Path(d).iterdir()}


def test_output_equal_to_input_is_exit_2(files, run_cli, tmp_path):
    raw, cal = files / "raw.h5", files / "cal.h5"
    link, hard = tmp_path / "link.h5", tmp_path / "hard.h5"
    link.symlink_to(raw)
    os.link(raw, hard)
    before = _snapshot(files)
    for args in (["fit", "accel", raw, "--out", raw], ["fit", "accel", raw, "--out", link],
                 ["fit", "accel", raw, "--out", hard], ["apply", cal, raw, "--out", raw],
                 ["apply", cal, raw, "--out", cal], ["fit", "gyro", raw, "--out", raw],
                 ["diagnose", raw, "--method", "accel", "--out", hard]):
        code, _, err = run_cli(*args)
        assert code == 2, (args, err)
        assert "input" in err and err.count("\n") == 1, err
    assert _snapshot(files) == before
    csv = tmp_path / "x.csv"
    csv.write_bytes((SAMPLE / "twelve_position.csv").read_bytes())
    code, _, err = run_cli("import", "csv", csv, "--plan", SAMPLE / "twelve_position.toml",
                           "--out", csv)
    assert code == 2 and csv.stat().st_size > 1000


def test_unwritable_outputs(files, run_cli, tmp_path):
    raw = files / "raw.h5"
    for out in ("/proc/x.h5", str(tmp_path / "missing" / "x.h5")):
        code, _, err = run_cli("fit", "accel", raw, "--out", out)
        assert code == 2, err
        assert out in err and err.count("\n") == 1 and "Traceback" not in err
    code, _, err = run_cli("fit", "accel", raw, "--out", tmp_path)
    assert code == 3 and "directory" in err
    code, _, err = run_cli("fit", "accel", tmp_path, "--out", tmp_path / "c.h5")
    assert code == 3 and "directory" in err


def test_umask_and_stale_temps(files, run_cli, tmp_path):
    raw = files / "raw.h5"
    stale = tmp_path / ".c.h5.calib-999999999-1.tmp"  # a killed run's leftover (no such pid)
    stale.write_bytes(b"x" * 100)
    old = os.umask(0o022)
    try:
        code, _, err = run_cli("fit", "accel", raw, "--out", tmp_path / "c.h5")
    finally:
        os.umask(old)
    assert code == 0, err
    assert stat.S_IMODE((tmp_path / "c.h5").stat().st_mode) == 0o644
    assert not stale.exists()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c.h5"]


def test_report_directory_replaced_whole(files, run_cli, tmp_path):
    rep = tmp_path / "rep"
    rep.mkdir()
    (rep / "old_figure.png").write_bytes(b"old")
    code, _, err = run_cli("report", files / "cal.h5", files / "raw.h5", "--out", rep)
    assert code == 0, err
    assert not (rep / "old_figure.png").exists() and (rep / "report.html").exists()
    assert [p.name for p in tmp_path.iterdir()] == ["rep"]


def test_emulate_link_dir_created_and_ranges(run_cli, tmp_path):
    code, _, err = run_cli("emulate", "--imu", "generic-binary", "--corrupt", "2",
                           "--duration", "0.1")
    assert code == 2, err
