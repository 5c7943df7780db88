"""Error messages that say what to do (issue 35, point 8): one line, naming the
file, with the command that would work."""

from __future__ import annotations

import re

import pytest


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    """A static raw.h5 and its calibration, a turntable raw.h5, the plans."""
    from calib_cli.cli.main import main

    d = tmp_path_factory.mktemp("msg")

    def run(*args):
        try:
            main([str(a) for a in args])
        except SystemExit as exc:
            assert exc.code in (0, None), args

    run("-q", "plan", "make", "static", "--positions", "6", "--duration", "2", "--out",
        d / "static.toml")
    run("-q", "simulate", d / "static.toml", "--out", d / "static.h5", "--seed", "1")
    run("-q", "fit", "accel", d / "static.h5", "--out", d / "cal.h5")
    run("-q", "plan", "make", "turntable", "--duration", "40", "--out", d / "tt.toml")
    run("-q", "simulate", d / "tt.toml", "--out", d / "tt.h5", "--seed", "1")
    return d


def _one_line(err: str) -> str:
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1, err
    assert lines[0].startswith("calib: error: "), err
    return lines[0]


def test_import_of_an_hdf5_file_says_it_needs_no_import(files, run_cli):
    for kind in ("csv", "text"):
        code, _, err = run_cli("import", kind, files / "static.h5", "--plan",
                               files / "static.toml", "--out", files / "x.h5")
        line = _one_line(err)
        assert code == 3 and "static.h5" in line and "HDF5 file, not a text log" in line
        assert "codec" not in line and "needs no import" in line


def test_apply_with_swapped_arguments_names_the_order(files, run_cli):
    code, _, err = run_cli("apply", files / "static.h5", files / "cal.h5", "--out",
                           files / "c.h5")
    line = _one_line(err)
    assert code == 3 and "the calibration comes first" in line
    assert f"calib apply {files / 'cal.h5'} {files / 'static.h5'}" in line
    assert not (files / "c.h5").exists()


def test_fit_accel_of_a_turntable_record_points_to_fit_turntable(files, run_cli):
    code, _, err = run_cli("fit", "accel", files / "tt.h5", "--out", files / "x.h5")
    line = _one_line(err)
    assert code == 4 and "tt.h5" in line and "use `calib fit turntable`" in line


def test_diagnose_turntable_of_a_static_record_names_the_file_and_the_method(files, run_cli):
    code, _, err = run_cli("diagnose", files / "static.h5", "--method", "turntable", "--out",
                           files / "d.h5")
    line = _one_line(err)
    assert code == 4 and str(files / "static.h5") in line and "--method accel" in line


def test_fit_of_a_plan_says_record_or_simulate_it_first(files, run_cli):
    code, _, err = run_cli("fit", "accel", files / "static.toml", "--out", files / "x.h5")
    line = _one_line(err)
    assert code == 3 and "it is a plan (TOML), not a recording" in line
    assert "calib simulate" in line


def test_missing_choice_option_is_one_line(files, run_cli):
    code, _, err = run_cli("diagnose", files / "static.h5", "--out", files / "d.h5")
    line = _one_line(err)
    assert code == 2 and "Missing option '--method'" in line
    assert re.search(r"Choose from: (accel|gyro|align|rimu|turntable)(, \w+){4} \(see", line)
