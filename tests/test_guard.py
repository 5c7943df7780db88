"""Issue 15: guard rails on outputs, inputs and recordings, driven through the CLI."""

from __future__ import annotations

import json
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


def test_report_directory_keeps_what_calib_did_not_write(files, run_cli, tmp_path):
    """Issue 37 (was: the directory replaced whole, deleting the user's files): a
    file calib did not write stays; a figure of calib's previous report that the
    new one does not write goes (calib-manifest.json lists what calib wrote)."""
    rep = tmp_path / "rep"
    rep.mkdir()
    (rep / "old_figure.png").write_bytes(b"old")
    code, _, err = run_cli("report", files / "cal.h5", files / "raw.h5", "--out", rep)
    assert code == 0, err
    assert (rep / "old_figure.png").read_bytes() == b"old" and (rep / "report.html").exists()
    first = json.loads((rep / "calib-manifest.json").read_text())["files"]
    assert "report.html" in first and "old_figure.png" not in first
    code, _, err = run_cli("report", files / "cal.h5", "--out", rep)  # no RAW: fewer figures
    assert code == 0, err
    second = json.loads((rep / "calib-manifest.json").read_text())["files"]
    assert all((rep / f).exists() == (f in second) for f in first)
    assert (rep / "old_figure.png").read_bytes() == b"old"
    assert [p.name for p in tmp_path.iterdir()] == ["rep"]


def test_emulate_link_dir_created_and_ranges(run_cli, tmp_path):
    code, _, err = run_cli("emulate", "--imu", "generic-binary", "--corrupt", "2",
                           "--duration", "0.1")
    assert code == 2, err


# ---------------------------------------------------------------------------
# item 2: HDF5 content validated before use


def _copy(src, dst):
    Path(dst).write_bytes(Path(src).read_bytes())
    return dst


def _edit(path, fn):
    import h5py

    with h5py.File(path, "r+") as h5:
        fn(h5)
    return path


def _replace(h5, name, data):
    del h5[name]
    h5.create_dataset(name, data=data)


def _raw_mutants(raw, d):
    import h5py
    import numpy as np

    out = {}

    def mut(name, fn):
        out[name] = _edit(_copy(raw, d / f"{name}.h5"), fn)

    mut("reversed_time", lambda h: _replace(h, "samples/time", h["samples/time"][()][::-1]))
    mut("short_time", lambda h: _replace(h, "samples/time", h["samples/time"][()][:-10]))

    def nan(h):
        a = h["samples/accel"][()]
        a[100, 1] = np.nan
        _replace(h, "samples/accel", a)

    def inf(h):
        a = h["samples/gyro"][()]
        a[50, 0] = np.inf
        _replace(h, "samples/gyro", a)

    mut("nan_accel", nan)
    mut("inf_gyro", inf)
    mut("no_accel", lambda h: h["samples"].__delitem__("accel"))
    mut("version_abc", lambda h: h.attrs.__setitem__("format_version", "abc"))
    mut("version_future", lambda h: h.attrs.__setitem__("format_version", 99))
    mut("segments_ragged", lambda h: _replace(h, "segments/start", h["segments/start"][()][:-1]))
    # flipped bytes inside the (checksummed) accel data
    p = _copy(raw, d / "flipped.h5")
    with h5py.File(p, "r") as h5:
        info = h5["samples/accel"].id.get_chunk_info(0)
    b = bytearray(Path(p).read_bytes())
    for i in range(info.byte_offset + 1000, info.byte_offset + 1000 + 4096):
        b[i] ^= 0x5A
    Path(p).write_bytes(bytes(b))
    out["flipped"] = p
    # 17 KB declaring 1e11 samples
    p = d / "huge.h5"
    with h5py.File(raw, "r") as src, h5py.File(p, "w") as h5:
        for k, v in src.attrs.items():
            h5.attrs[k] = v
        s = h5.create_group("samples")
        s.create_dataset("time", shape=(10**11,), dtype="f8", chunks=(65536,))
        s.create_dataset("accel", shape=(10**11, 3), dtype="f8", chunks=(65536, 3))
        s.create_dataset("gyro", shape=(10**11, 3), dtype="f8", chunks=(65536, 3))
        src.copy("segments", h5)
        src.copy("site", h5)
    out["huge"] = p
    return out


def test_corrupt_raw_files_are_exit_3(files, run_cli, tmp_path):
    import time

    muts = _raw_mutants(files / "raw.h5", tmp_path)
    cal = files / "cal.h5"
    for name, p in muts.items():
        for args in (["fit", "accel", p, "--out", tmp_path / "o.h5"],
                     ["apply", cal, p, "--out", tmp_path / "o.h5"],
                     ["show", p]):
            t0 = time.monotonic()
            code, _, err = run_cli(*args)
            if name == "segments_ragged" and args[0] == "show":
                continue  # show does not read the segments
            assert code == 3, (name, args, err)
            assert str(p) in err and err.count("\n") == 1 and "Traceback" not in err, err
            assert not (tmp_path / "o.h5").exists()
            if name == "huge":
                assert time.monotonic() - t0 < 1.0
    assert "checksum" in run_cli("fit", "accel", muts["flipped"], "--out", tmp_path / "o.h5")[2]
    assert sorted(x.name for x in tmp_path.iterdir() if x.name.startswith(".")) == []


def test_bad_calibration_parameters(files, run_cli, tmp_path):
    import numpy as np

    cal, raw = files / "cal.h5", files / "raw.h5"

    def setp(key, val):
        return lambda h: _replace(h, f"params/{key}", val)

    cases = {"K_nan": setp("accel_K", np.full((3, 3), np.nan)),
             "b_inf": setp("accel_bias", np.array([np.inf, 0, 0])),
             "K_singular": setp("accel_K", np.zeros((3, 3))),
             "K_shape": setp("accel_K", np.eye(2)),
             "empty": lambda h: [h["params"].__delitem__(k) for k in list(h["params"])],
             "no_cov": lambda h: h.__delitem__("covariance")}
    for name, fn in cases.items():
        p = _edit(_copy(cal, tmp_path / f"{name}.h5"), fn)
        for args in (["apply", p, raw, "--out", tmp_path / "o.h5"],
                     ["export", p, "--format", "json"]):
            code, _, err = run_cli(*args)
            assert code == 3, (name, args, err)
            assert str(p) in err and err.count("\n") == 1
        assert not (tmp_path / "o.h5").exists()


def test_calibration_where_recording_expected_and_back(files, run_cli, tmp_path):
    code, _, err = run_cli("fit", "accel", files / "cal.h5", "--out", tmp_path / "o.h5")
    assert code == 3 and "calibration" in err
    code, _, err = run_cli("apply", files / "raw.h5", files / "raw.h5", "--out", tmp_path / "o.h5")
    assert code == 3 and "raw" in err


# ---------------------------------------------------------------------------
# item 3: schemas from one key registry


def _plan(tmp_path, extra_seg="", extra_top="", site="latitude_deg = 50.0"):
    text = (f"name = 't'\nkind = 'static'\n{extra_top}\n[site]\n{site}\n"
            + "".join(f"[[segment]]\nlabel = 'p{i}'\nattitude_deg = {a}\nduration_s = 2.0\n"
                      for i, a in enumerate(([0, 0, 0], [0, 180, 0], [0, 90, 0]))))
    text += "[[segment]]\nlabel = 'last'\nduration_s = 2.0\n" + extra_seg
    p = tmp_path / "plan.toml"
    p.write_text(text)
    return p


@pytest.mark.parametrize("key,known", [("atitude_deg", "attitude_deg"),
                                       ("durration_s", "duration_s"),
                                       ("Attitude_Deg", "attitude_deg"),
                                       ("lable", "label"), ("tabel_rate_dps", "table_rate_dps")])
def test_plan_typo_is_exit_3(run_cli, tmp_path, key, known):
    p = _plan(tmp_path, f"{key} = 1.0\n")
    code, _, err = run_cli("simulate", p, "--out", tmp_path / "r.h5")
    assert code == 3, err
    assert f"did you mean {known}?" in err and str(p) in err and key in err
    assert not (tmp_path / "r.h5").exists()


def test_plan_unknown_keys_one_warning(run_cli, tmp_path):
    p = _plan(tmp_path, "operator_note = 'x'\nx_atitude_deg = 1\n", "my_project = 'y'")
    code, _, err = run_cli("simulate", p, "--out", tmp_path / "r.h5")
    assert code == 0, err
    warn = [ln for ln in err.splitlines() if "warning" in ln]
    assert len(warn) == 1 and "operator_note" in warn[0] and "my_project" in warn[0]
    assert "x_atitude" not in err


@pytest.mark.parametrize("top,site,seg", [
    ("sample_rate_hz = 0", "latitude_deg = 1", ""),
    ("sample_rate_hz = -5", "latitude_deg = 1", ""),
    ("", "g = -9.8", ""), ("", "g = 1e6", ""),
    ("", "latitude_deg = 1", "duration_s = 1e12\n"),
    ("", "latitude_deg = 1", "attitude_deg = [true, false, true]\n"),
    ("", "latitude_deg = 1", "attitude_sigma_deg = -1.0\n"),
    ("transition_s = -1", "latitude_deg = 1", "")])
def test_plan_ranges(run_cli, tmp_path, top, site, seg):
    p = _plan(tmp_path, seg.replace("duration_s", "x_d") if "duration" in seg else seg, top, site)
    if "duration_s = 1e12" in seg:
        p.write_text(p.read_text().replace("duration_s = 2.0", "duration_s = 1e12", 1))
    code, _, err = run_cli("simulate", p, "--out", tmp_path / "r.h5")
    assert code == 3, err
    assert err.count("\n") == 1 and str(p) in err


def test_deeply_nested_toml(run_cli, tmp_path):
    p = tmp_path / "deep.toml"
    p.write_text("a = " + "[" * 5000 + "]" * 5000 + "\n")
    code, _, err = run_cli("simulate", p, "--out", tmp_path / "r.h5")
    assert code == 3 and str(p) in err


def test_tolerance_and_pipeline_strict(run_cli, tmp_path, files):
    tol = tmp_path / "tol.toml"
    tol.write_text("[param.accel_biass]\nmax_mg = 20\n")
    pipe = tmp_path / "pipe.toml"
    pipe.write_text("[[step]]\nstep = 'fit'\nmethod = 'accel'\n")
    code, _, err = run_cli("batch", pipe, files / "raw.h5", "--out", tmp_path / "o",
                           "--tolerances", tol)
    assert code == 3 and "did you mean accel_bias?" in err and str(tol) in err
    tol.write_text("[param.accel_bias]\nmin_mg = 20\nmax_mg = -20\n")
    code, _, err = run_cli("batch", pipe, files / "raw.h5", "--out", tmp_path / "o",
                           "--tolerances", tol)
    assert code == 3 and "min is above max" in err
    pipe.write_text("[[step]]\nstep = 'fit'\nmethod = 'accel'\noptions = 5\n")
    code, _, err = run_cli("batch", pipe, files / "raw.h5", "--out", tmp_path / "o")
    assert code == 3 and str(pipe) in err
    pipe.write_text("[[stepp]]\nstep = 'fit'\n")
    code, _, err = run_cli("batch", pipe, files / "raw.h5", "--out", tmp_path / "o")
    assert code == 3 and "did you mean step?" in err


@pytest.mark.parametrize("edit,word", [
    (("bits = 16", "bits = 0"), "sequence.bits"),
    (("baudrate = 921600", 'baudrate = "fast"'), "baudrate"),
    (('parity = "N"', 'parity = "X"'), "parity"),
    (("rate_hz", "rate_hzz = 1\nrate_hz"), "did you mean rate_hz?")])
def test_imu_profile_strict(run_cli, tmp_path, edit, word):
    src = (Path(__file__).resolve().parent.parent / "profiles/imu/generic-bin6.toml").read_text()
    assert edit[0] in src
    p = tmp_path / "imu.toml"
    p.write_text(src.replace(edit[0], edit[1], 1))
    code, _, err = run_cli("emulate", "--imu", p, "--duration", "0.1")
    assert code == 3 and word in err and str(p) in err, err


def test_table_template_unknown_field(run_cli, tmp_path):
    src = (Path(__file__).resolve().parent.parent / "profiles/turntable/generic-3axis.toml")
    text = src.read_text()
    p = tmp_path / "t.toml"
    p.write_text(text.replace("{roll_deg", "{rol_deg", 1))
    code, _, err = run_cli("emulate", "--imu", "generic-bin6", "--table", p, "--duration", "0.1")
    assert code == 3 and "did you mean roll_deg?" in err, err


# ---------------------------------------------------------------------------
# item 4: gross errors are named (exit 4), impossible calibrations refused


def _sample_plan_variant(tmp_path, name, fn):
    p = tmp_path / f"{name}.toml"
    p.write_text(fn((SAMPLE / "twelve_position.toml").read_text()))
    return p


def test_misplaced_position_named(run_cli, tmp_path):
    # the unit sat x-up where the plan says x-down
    mis = _sample_plan_variant(tmp_path, "mis", lambda s: s.replace(
        "attitude_deg = [0, 90, 0]", "attitude_deg = [0, -90, 0]", 1))
    raw = tmp_path / "mis.h5"
    assert run_cli("-q", "import", "csv", SAMPLE / "twelve_position.csv", "--plan", mis,
                   "--out", raw)[0] == 0
    code, _, err = run_cli("fit", "accel", raw, "--out", tmp_path / "c.h5")
    assert code == 4 and "gross error at position 2 ('x-down')" in err, err
    assert "179 deg" in err or "180 deg" in err
    assert not (tmp_path / "c.h5").exists()
    code, _, err = run_cli("fit", "gyro", raw, "--out", tmp_path / "c.h5")
    assert code == 4 and "x-down" in err


def test_swapped_positions_exit_4(run_cli, tmp_path):
    def swap(s):
        return (s.replace("attitude_deg = [0, -90, 0]", "TMP", 1)
                .replace("attitude_deg = [0, 90, 0]", "attitude_deg = [0, -90, 0]", 1)
                .replace("TMP", "attitude_deg = [0, 90, 0]"))

    raw = tmp_path / "sw.h5"
    assert run_cli("-q", "import", "csv", SAMPLE / "twelve_position.csv", "--plan",
                   _sample_plan_variant(tmp_path, "sw", swap), "--out", raw)[0] == 0
    code, _, err = run_cli("fit", "accel", raw, "--out", tmp_path / "c.h5")
    assert code == 4 and "x-up" in err and "x-down" in err, err


def test_rimu_misplaced_position_named(run_cli, tmp_path):
    p = tmp_path / "r.toml"
    p.write_text((SAMPLE / "rimu_six_position.toml").read_text().replace(
        "attitude_deg = [90, 0, 0]", "attitude_deg = [90, 0, 0]\nsim_attitude_deg = [-90, 0, 0]", 1))
    assert run_cli("-q", "simulate", p, "--out", tmp_path / "r.h5", "--seed", "1")[0] == 0
    code, _, err = run_cli("fit", "rimu", tmp_path / "r.h5", "--out", tmp_path / "c.h5")
    assert code == 4 and "gross error at position 3 ('y-up')" in err, err


def test_impossible_calibration_refused(files, run_cli, tmp_path):
    from calib_cli.errors import EstimationError
    from calib_cli.io.h5 import read_calibration
    from calib_cli.methods.gross import check_result

    c = read_calibration(files / "cal.h5")
    check_result(c)  # the good one passes
    import dataclasses

    import numpy as np

    for params, stats in (({"accel_K": np.diag([-1e-5, 1, 1])}, {}),
                          ({"accel_bias": np.array([200.0, 0, 0])}, {}),
                          ({}, {"g_error_rms_after": 6.0})):
        bad = dataclasses.replace(c, params={**c.params, **params}, stats={**c.stats, **stats})
        with pytest.raises(EstimationError):
            check_result(bad)


def test_float_options_finite_and_positive(run_cli, tmp_path):
    for v in ("nan", "inf", "-1", "0"):
        code, _, err = run_cli("import", "csv", SAMPLE / "twelve_position.csv", "--plan",
                               SAMPLE / "twelve_position.toml", "--out", tmp_path / "r.h5",
                               "--window", v)
        assert code == 2 and "--window" in err and err.count("\n") == 1, err
    assert not (tmp_path / "r.h5").exists()


def test_device_as_input_is_exit_3(run_cli, tmp_path):
    code, _, err = run_cli("import", "csv", "/dev/zero", "--plan",
                           SAMPLE / "twelve_position.toml", "--out", tmp_path / "r.h5")
    assert code == 3 and "/dev/zero" in err


def test_csv_given_to_fit_says_import(run_cli, tmp_path):
    code, _, err = run_cli("fit", "accel", SAMPLE / "twelve_position.csv", "--out",
                           tmp_path / "c.h5")
    assert code == 3 and "calib import csv" in err


def test_damaged_calibration_under_out_does_not_fail_tolerances(files, run_cli, tmp_path):
    tol = tmp_path / "tol.toml"
    tol.write_text("[param.accel_bias]\nmin_mg = -500\nmax_mg = 500\n")
    pipe = tmp_path / "pipe.toml"
    pipe.write_text("[[step]]\nstep = 'fit'\nmethod = 'accel'\n")
    out = tmp_path / "out"
    code, _, err = run_cli("batch", pipe, files / "raw.h5", "--out", out, "--tolerances", tol)
    assert code == 0, err
    bad = out / "old" / "cal.h5"
    bad.parent.mkdir()
    _edit(_copy(files / "cal.h5", bad), lambda h: h.__delitem__("params"))
    code, _, err = run_cli("batch", pipe, files / "raw.h5", "--out", out, "--tolerances", tol)
    assert code == 0, err
    assert "skipped" in err and "cal.h5" in err


def test_unknown_profile_name_lists_shipped(run_cli, tmp_path):
    code, _, err = run_cli("record", "--imu", "nosuch", "--port", tmp_path / "p", "--duration",
                           "1", "--out", tmp_path / "r.h5")
    assert code == 3 and "generic-bin6" in err and "nosuch" in err


def test_disk_full_leaves_nothing_and_says_so(files, run_cli, tmp_path, monkeypatch):
    import errno

    import calib_cli.io.h5 as h5mod

    def full(*a, **k):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(h5mod, "write_provenance", full)
    code, _, err = run_cli("fit", "accel", files / "raw.h5", "--out", tmp_path / "c.h5")
    assert code == 2 and "disk full" in err and err.count("\n") == 1
    assert list(tmp_path.iterdir()) == []


def test_files_without_checksums_still_read(files, run_cli, tmp_path):
    """A file of the previous writer (no Fletcher-32 filter) is read as before."""
    p = _copy(files / "raw.h5", tmp_path / "old.h5")

    def plain(h):
        for k in list(h["samples"]):
            _replace(h, f"samples/{k}", h[f"samples/{k}"][()])
        assert not h["samples/accel"].fletcher32

    _edit(p, plain)
    code, _, err = run_cli("fit", "accel", p, "--out", tmp_path / "c.h5")
    assert code == 0, err
    import h5py

    with h5py.File(tmp_path / "c.h5") as h5:
        assert h5["params/accel_K"].fletcher32
    with h5py.File(files / "raw.h5") as h5:
        assert h5["samples/accel"].fletcher32 and h5["samples/time"].fletcher32
