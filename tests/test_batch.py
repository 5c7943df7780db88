"""calib batch: make-like pipeline over an archive, failures isolated,
tolerances, history, safe output paths (issue 10). Fast: 10 recordings."""

from __future__ import annotations

import contextlib
import io
import json
import os
import re
from pathlib import Path

import h5py
import numpy as np
import pytest

from calib_cli.batch.paths import discover, inside, output_key
from calib_cli.cli.main import main
from calib_cli.errors import InputError
from calib_cli.validation.archive import make_archive, scalar_plan, unit_serial, write_recording


def run_cli(*args) -> tuple[int, str, str]:
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            main([str(a) for a in args])
            code = 0
        except SystemExit as exc:
            code = exc.code if isinstance(exc.code, int) else 0
    return code, out.getvalue(), err.getvalue()


def batch_json(pipe, inputs, out, *extra):
    code, so, se = run_cli("batch", pipe, *inputs, "--out", out, "--json", *extra)
    return code, (json.loads(so) if so.strip() else None), se


@pytest.fixture(scope="module")
def arch(tmp_path_factory):
    root = tmp_path_factory.mktemp("batch")
    a = make_archive(root, n=10, n_broken=3)
    out = root / "out"
    code, obj, err = batch_json(a["pipeline"], [a["archive"]], out, "--log", root / "run.log")
    return {**a, "root": root, "out": out, "first": (code, obj, err)}


def by_input(obj):
    return {r["input"]: r for r in obj["inputs"]}


def test_first_run_processes_good_reports_bad(arch):
    code, obj, _ = arch["first"]
    assert code == 1
    s = obj["summary"]
    assert (s["inputs"], s["ok"], s["failed"]) == (10, 7, 3)
    n_raw = sum(g.endswith(".h5") for g in arch["good"])
    assert n_raw == 3
    assert s["steps_run"] == 7 * 4 - n_raw  # a raw.h5 input needs no import step
    res = by_input(obj)
    assert sorted(r["input"] for r in obj["inputs"] if r["status"] == "failed") == \
        sorted(arch["broken"])
    reasons = [res[b]["error"] for b in arch["broken"]]
    assert "not a number: 'ERR'" in reasons[0] and arch["broken"][0] in reasons[0]
    assert "not an HDF5 file" in reasons[1] and arch["broken"][1] in reasons[1]
    assert "needs >= 4 static positions" in reasons[2] and arch["broken"][2] in reasons[2]
    assert res[arch["broken"][2]]["exit_code"] == 4
    for g in arch["good"]:
        r = res[g]
        assert r["status"] == "done" and r["serial"].startswith("SN-")
        cal = arch["out"] / r["outputs"]["calibration"]
        with h5py.File(cal) as h5:
            assert h5.attrs["kind"].decode() == "calibration"
            assert len(h5.attrs["batch_fingerprint"]) == 64
            assert json.loads(h5.attrs["input_sha256"].decode())
        exp = json.loads((arch["out"] / r["outputs"]["export"]).read_text())
        assert exp["params"]["accel_K"] and exp["batch"]["batch_fingerprint"]
    # no calibration is left for a failed input; no temporary files anywhere
    for b in arch["broken"]:
        assert res[b]["outputs"] == {}
    assert not [p for p in arch["out"].rglob("*.tmp")]
    # several units and both accel methods
    methods = {json.loads((arch["out"] / r["outputs"]["export"]).read_text())["method"]
               for r in obj["inputs"] if r["status"] != "failed"}
    assert methods == {"vector", "scalar"}
    assert len({r["serial"] for r in obj["inputs"] if r["serial"]}) == 4


def test_log_has_utc_lines(arch):
    lines = (arch["root"] / "run.log").read_text().splitlines()
    assert len(lines) == 12
    assert all(len(ln) > 21 and ln[19] == "Z" and ln[10] == "T" for ln in lines)
    assert sum(" ERROR " in ln for ln in lines) == 3


def test_second_run_executes_nothing(arch):
    code, so, se = run_cli("batch", arch["pipeline"], arch["archive"], "--out", arch["out"])
    assert code == 1
    assert "nothing to do: 0 steps executed" in se
    assert "\x1b[" not in se and "━" not in se  # plain lines off a terminal
    assert se.count("calib: batch: ") == 3
    code, obj, _ = batch_json(arch["pipeline"], [arch["archive"]], arch["out"])
    assert obj["summary"]["steps_run"] == 0 and obj["summary"]["steps_up_to_date"] == 25


def test_changed_input_reruns_only_its_chain(arch, tmp_path):
    target = Path(arch["good"][1])  # SN-0002 rec-01.csv (scalar unit)
    before = target.read_bytes()
    write_recording(target, (target.parent / "plan.toml").read_text(), 1, seed=999)
    assert target.read_bytes() != before
    code, obj, _ = batch_json(arch["pipeline"], [arch["archive"]], arch["out"])
    ran = {r["input"]: r["steps_run"] for r in obj["inputs"] if r["steps_run"]}
    assert ran == {str(target): 4}
    # a pipeline change re-runs only the changed step and what follows it
    pipe = tmp_path / "p.toml"
    pipe.write_text(Path(arch["pipeline"]).read_text().replace(
        'step = "export"', 'step = "export"\ncovariance = true'))
    code, obj, _ = batch_json(pipe, [arch["archive"]], arch["out"])
    assert obj["summary"]["steps_run"] == 7
    assert all(s["action"] != "ran" or s["step"] == "export"
               for r in obj["inputs"] for s in r["steps"])
    code, obj, _ = batch_json(pipe, [arch["archive"]], arch["out"], "--force")
    assert obj["summary"]["steps_run"] == 25


def test_tolerances_range_and_change(arch, tmp_path):
    tol = tmp_path / "tol.toml"
    tol.write_text("[param.accel_bias]\nmin_mg = -100\nmax_mg = 100\nmax_change_sigma = 6\n"
                   "[param.accel_K]\nmin = 0.9\nmax = 1.1\n")
    good = arch["good"]
    # accel_K off-diagonals lie far below 0.9: a range failure on every unit
    code, obj, se = batch_json(arch["pipeline"], good, tmp_path / "o1", "--tolerances", tol)
    assert code == 5
    assert set(obj["units"].values()) == {"fail"}
    assert any("accel_K[0,1]" in f and "below min 0.9" in f
               for r in obj["inputs"] for c in r["tolerance_checks"] for f in c["failures"])
    tol.write_text("[param.accel_bias]\nmin_mg = -100\nmax_mg = 100\nmax_change_sigma = 6\n"
                   "[param.accel_K]\nmin = -0.1\nmax = 1.1\n")
    code, obj, se = batch_json(arch["pipeline"], good, tmp_path / "o1", "--tolerances", tol)
    assert code == 0, se
    assert obj["units"] == {unit_serial(u): "pass" for u in range(4)}
    assert obj["summary"]["steps_run"] == 0  # the gate re-checks up-to-date outputs
    # unit SN-0002 drifts: its next calibration moved by many sigma
    d = Path(arch["archive"]) / "SN-0002"
    drift = tmp_path / "drift" / "SN-0002"
    drift.mkdir(parents=True)
    (drift / "plan.toml").write_text(scalar_plan("SN-0002"))
    write_recording(drift / "rec-99.csv", (d / "plan.toml").read_text(), 1, seed=7,
                    truth_scale=1.5)
    code, obj, se = batch_json(arch["pipeline"], [*good, drift / "rec-99.csv"], tmp_path / "o1",
                               "--tolerances", tol)
    assert code == 5, se
    assert obj["units"]["SN-0002"] == "fail"
    assert [u for u, v in obj["units"].items() if v == "fail"] == ["SN-0002"]
    fails = [f for r in obj["inputs"] for c in r["tolerance_checks"] for f in c["failures"]]
    assert fails and all("accel_bias" in f and "sigma since " in f for f in fails)
    # text mode names the failing file and parameter
    code, so, se = run_cli("batch", arch["pipeline"], *good, drift / "rec-99.csv", "--out",
                           tmp_path / "o1", "--tolerances", tol)
    assert code == 5 and "calib: tolerance: " in se and "SN-0002 fail" in se
    # one evaluator (io/tolerance.py): `calib report --tolerances --history OUT` gives every
    # unit's latest calibration the verdict the batch gave the unit, the drifting one too
    _report_agrees(obj, tol, tmp_path / "o1", tmp_path / "rep")
    tol_range = tmp_path / "range.toml"  # a range failure on every unit
    tol_range.write_text("[param.accel_K]\nmin = 0.9\nmax = 1.1\n")
    code, obj2, _ = batch_json(arch["pipeline"], [*good, drift / "rec-99.csv"], tmp_path / "o1",
                               "--tolerances", tol_range)
    assert code == 5 and set(obj2["units"].values()) == {"fail"}
    _report_agrees(obj2, tol_range, tmp_path / "o1", tmp_path / "rep2")
    # without the history the report cannot evaluate max_change_sigma and says so: not PASS
    last = _latest_calibrations(obj, tmp_path / "o1")["SN-0002"]
    code, _, se = run_cli("report", last, "--out", tmp_path / "nohist", "--tolerances", tol)
    md = (tmp_path / "nohist" / "report.md").read_text()
    assert code == 0 and re.search(r"^Verdict: INCOMPLETE against the tolerances", md, re.M)
    assert "param.accel_bias.max_change_sigma" in md and "--history" in md


def _latest_calibrations(obj, out) -> dict:
    """serial -> the last calibration (in history order) the batch checked of that unit."""
    from calib_cli.io.history import scan

    made = {c["file"] for r in obj["inputs"] for c in r.get("tolerance_checks", [])}
    latest = {}
    for e in scan(out):
        if e.rel in made:
            latest[e.serial] = e.path
    return latest


def _report_agrees(obj, tol, out, rep):
    """Each unit's latest calibration: the report's verdict is the batch's unit verdict."""
    words = {"pass": "PASS", "fail": "FAIL", "incomplete": "INCOMPLETE"}
    rep.mkdir(parents=True, exist_ok=True)
    latest = _latest_calibrations(obj, out)
    assert set(latest) == set(obj["units"])
    for serial, cal in latest.items():
        code, _, se = run_cli("report", cal, "--out", rep / serial, "--tolerances", tol,
                              "--history", out)
        assert code == 0, se
        md = (rep / serial / "report.md").read_text()
        want = words[obj["units"][serial]]
        assert re.search(rf"^Verdict: {want} against the tolerances", md, re.M), (serial, md)


def test_history_table_json_plot(arch, tmp_path):
    code, so, se = run_cli("history", arch["out"], "--unit", "SN-0001", "--json")
    assert code == 0, se
    obj = json.loads(so)
    cals = obj["calibrations"]
    assert [c["file"].split("/")[1] for c in cals] == ["rec-01-csv", "rec-02-h5"]
    assert np.shape(cals[0]["params"]["accel_K"]) == (3, 3)
    png = tmp_path / "h.png"
    code, so, se = run_cli("history", arch["out"], "--unit", "SN-0001", "--plot", png)
    assert code == 0 and png.read_bytes()[:4] == b"\x89PNG"
    assert "accel_bias[2]" in so and "mg" in so
    code, so, se = run_cli("history", arch["out"], "--unit", "SN-9999")
    assert code == 3 and "no calibration of unit 'SN-9999'" in se


def test_lock_keeps_two_runs_apart(arch, tmp_path):
    from calib_cli.batch.runner import output_lock

    out = tmp_path / "locked"
    out.mkdir()
    with output_lock(str(out.resolve())):
        code, so, se = run_cli("batch", arch["pipeline"], arch["good"][0], "--out", out)
    assert code == 3 and "another calib batch is running" in se and "pid" in se
    code, so, se = run_cli("batch", arch["pipeline"], arch["good"][0], "--out", out)
    assert code == 0, se  # the lock is gone with its holder


def test_process_pool_gives_identical_parameters(arch, tmp_path):
    inputs = arch["good"][:4]
    code, obj, _ = batch_json(arch["pipeline"], inputs, tmp_path / "pool", "--workers", "2")
    assert code == 0 and obj["summary"]["ok"] == 4
    first = by_input(arch["first"][1])
    for r in obj["inputs"]:
        a = tmp_path / "pool" / r["outputs"]["calibration"]
        b = arch["out"] / first[r["input"]]["outputs"]["calibration"]
        if r["input"] == arch["good"][1]:
            continue  # re-simulated by another test
        with h5py.File(a) as ha, h5py.File(b) as hb:
            for g in ("params", "sigma"):
                for k in ha[g]:
                    assert ha[g][k][()].tobytes() == hb[g][k][()].tobytes()


def test_stale_outputs_removed_when_input_breaks(arch, tmp_path):
    src = Path(arch["good"][0])
    d = tmp_path / "arch"
    d.mkdir()
    (d / "plan.toml").write_text((src.parent / "plan.toml").read_text())
    csv = d / "rec.csv"
    csv.write_bytes(src.read_bytes())
    out = tmp_path / "o"
    code, obj, _ = batch_json(arch["pipeline"], [d], out)
    assert code == 0 and (out / "rec-csv" / "cal-accel.h5").exists()
    csv.write_text(csv.read_text().replace("\n1,", "\nx,"), encoding="utf-8")
    lines = csv.read_text().splitlines()
    lines[5] = "1,2"
    csv.write_text("\n".join(lines) + "\n")
    code, obj, _ = batch_json(arch["pipeline"], [d], out)
    assert code == 1
    assert not (out / "rec-csv" / "cal-accel.h5").exists()
    assert not (out / "rec-csv" / "export.json").exists()


# ---------------------------------------------------------------------------
# paths derived from hostile names stay inside OUT


@pytest.mark.parametrize("rel", ["../../etc/passwd", "/etc/passwd", "..", ".", "a/../../b.csv",
                                 ".hidden.csv", "-rf .csv", "x;rm -rf ~.csv", "ünï.csv",
                                 "new\nline.csv", "a\\..\\..\\b.csv", "....csv", "",
                                 "x" * 300 + ".csv"])
def test_output_key_cannot_escape(rel, tmp_path):
    key = output_key(rel)
    assert key and not key.startswith(("/", ".", "-"))
    assert all(c not in ("", ".", "..") for c in key.split("/"))
    out = tmp_path / "out"
    out.mkdir()
    p = Path(inside(str(out), key, "raw.h5"))
    assert p.is_relative_to(out.resolve())


def test_hostile_file_names_end_up_inside(arch, tmp_path):
    d = tmp_path / "hostile"
    d.mkdir()
    src = Path(arch["good"][0])
    (d / "plan.toml").write_text((src.parent / "plan.toml").read_text())
    names = ["..csv", "-rf.csv", "a b;$(id).csv", "x'\"`.csv", "a_b.csv", "a b.csv"]
    for n in names:
        (d / n).write_bytes(src.read_bytes())
    out = tmp_path / "out"
    # a directory skips hidden names ("..csv"); given by itself, it is processed
    code, obj, se = batch_json(arch["pipeline"], [d, d / "..csv"], out)
    assert code == 0, se
    assert obj["summary"]["ok"] == len(names)
    keys = [r["key"] for r in obj["inputs"]]
    assert len(set(keys)) == len(names)  # "a b" and "a_b" stay apart
    for f in Path(tmp_path).rglob("*.h5"):
        assert f.resolve().is_relative_to(out.resolve())
    # a symlink planted in OUT that points outside is refused, not followed
    outside = tmp_path / "elsewhere"
    outside.mkdir()
    os.symlink(outside, out / "evil")
    with pytest.raises(InputError, match="would leave the output directory"):
        inside(str(out), "evil", "raw.h5")


def test_discover_skips_hidden_and_output_dir(tmp_path):
    (tmp_path / "a.csv").write_text("x")
    (tmp_path / ".b.csv").write_text("x")
    (tmp_path / "out").mkdir()
    (tmp_path / "out" / "c.h5").write_text("x")
    found = discover([str(tmp_path)], ["**/*.csv", "**/*.h5"], exclude=str(tmp_path / "out"))
    assert [b.rel for b in found] == ["a.csv"]


# ---------------------------------------------------------------------------
# pipeline and registry errors


@pytest.mark.parametrize("body, msg", [
    ('[[step]]\nstep = "report2"\n', "unknown step 'report2'; known: apply, export, fit, import"),
    ('[[step]]\nstep = "fit"\nmethod = "warp"\n', "unknown fit method 'warp'; known: accel"),
    ('[[step]]\nstep = "fit"\n', "a fit step needs method"),
    ('[[step]]\nstep = "import"\n', "needs plan = \"FILE\""),
    ('[[step]]\nstep = "fit"\nmethod = "accel"\nspeed = 3\n', "unknown option speed"),
    ('[[step]]\nstep = "export"\n', "needs calibration, which no earlier step makes"),
    ('glob = "../*.csv"\n[[step]]\nstep = "fit"\nmethod = "accel"\n', "must stay inside"),
    ("[[step]\n", "not valid TOML"),
])
def test_pipeline_errors_are_input_errors(body, msg, tmp_path, arch):
    p = tmp_path / "bad.toml"
    p.write_text(body)
    code, so, se = run_cli("batch", p, arch["good"][0], "--out", tmp_path / "o")
    assert code == 3, se
    assert msg in se and str(p) in se


def test_register_fit_one_line(arch, tmp_path):
    from calib_cli.batch.registry import FITS, register_fit
    from calib_cli.methods.accel_lsq import fit_accel

    calls = []

    def fake(rec, method="auto"):
        calls.append(rec.serial)
        return fit_accel(rec, method)

    register_fit("fake", fake, options=("method",))
    try:
        p = tmp_path / "p.toml"
        p.write_text('[[step]]\nstep = "fit"\nmethod = "fake"\noptions = { method = "vector" }\n')
        raw = [g for g in arch["good"] if g.endswith(".h5")][0]
        code, obj, se = batch_json(p, [raw], tmp_path / "o")
        assert code == 0, obj["inputs"][0]["error"]
        assert obj["inputs"][0]["steps"][0]["output"].endswith("cal-fake.h5")
        assert len(calls) == 1
        # a CSV input with no import step fails alone, with a clear line
        code, obj, se = batch_json(p, [arch["good"][0]], tmp_path / "o")
        assert code == 1 and "needs an import step" in obj["inputs"][0]["error"]
    finally:
        FITS.pop("fake")


def test_missing_input_fails_alone(arch, tmp_path):
    code, obj, _ = batch_json(arch["pipeline"], [arch["good"][0], tmp_path / "nope.csv"],
                              tmp_path / "o")
    assert code == 1
    assert [r["status"] for r in obj["inputs"]] == ["done", "failed"]
    assert "nope.csv: no such file" in obj["inputs"][1]["error"]


# ---------------------------------------------------------------------------
# the archive: 50 recordings, 3 broken (make validate)


@pytest.mark.slow
def test_archive_of_50(tmp_path):
    import time

    a = make_archive(tmp_path, n=50, n_broken=3)
    out = tmp_path / "out"
    t0 = time.monotonic()
    code, obj, se = batch_json(a["pipeline"], [a["archive"]], out, "--workers", "2")
    first_s = time.monotonic() - t0
    assert code == 1
    s = obj["summary"]
    assert (s["inputs"], s["ok"], s["failed"]) == (50, 47, 3)
    errors = sorted(r["error"] for r in obj["inputs"] if r["status"] == "failed")
    assert len(errors) == 3 and all(e for e in errors)
    assert len({r["serial"] for r in obj["inputs"] if r["serial"]}) == 4
    code, so, se = run_cli("batch", a["pipeline"], a["archive"], "--out", out)
    assert code == 1 and "nothing to do: 0 steps executed" in se
    target = Path(a["good"][17])
    write_recording(target, (target.parent / "plan.toml").read_text(), 17 % 4, seed=4242)
    code, obj, _ = batch_json(a["pipeline"], [a["archive"]], out)
    ran = {r["input"]: r["steps_run"] for r in obj["inputs"] if r["steps_run"]}
    n_steps = 3 if target.suffix == ".h5" else 4
    assert ran == {str(target): n_steps}
    tol = tmp_path / "tol.toml"
    tol.write_text("[param.accel_bias]\nmin_mg = -1\nmax_mg = 1\n")
    code, obj, se = batch_json(a["pipeline"], [a["archive"]], out, "--tolerances", tol)
    assert code == 5 and "fail" in obj["units"].values()
    print(f"50 files, 2 workers: first run {first_s:.1f} s")


def test_lock_file_symlink_is_refused(arch, tmp_path):
    out = tmp_path / "o"
    out.mkdir()
    victim = tmp_path / "victim.txt"
    victim.write_text("keep me")
    os.symlink(victim, out / ".calib-batch.lock")
    code, so, se = run_cli("batch", arch["pipeline"], arch["good"][0], "--out", out)
    assert code == 3 and "cannot open the lock file" in se
    assert victim.read_text() == "keep me"


def test_terminal_table_and_quiet(arch, tmp_path, monkeypatch):
    import calib_cli.cli.cmd_batch as cb

    good = arch["good"][:2]
    monkeypatch.setattr(cb, "interactive", lambda: True)  # as on a terminal
    code, so, se = run_cli("batch", arch["pipeline"], *good, arch["broken"][0], "--out",
                           tmp_path / "o")
    assert code == 1 and so == ""
    assert "calib batch" in se and "┃" in se and "failed" in se
    assert "calib: batch: " in se and "not a number" in se
    monkeypatch.undo()
    code, so, se = run_cli("-q", "batch", arch["pipeline"], *good, "--out", tmp_path / "o")
    assert code == 0 and so == "" and se == ""


def test_history_orders_by_recorded_utc(arch, tmp_path):
    """A raw file's recorded_utc (written by a recorder) is carried onto the
    calibration and orders the unit's history before the file names do."""
    raws = [g for g in arch["good"] if g.endswith(".h5")][:1]
    d = tmp_path / "a"
    d.mkdir()
    for name, when in (("a-late.h5", "2026-06-01T00:00:00Z"), ("b-early.h5",
                                                               "2026-01-01T00:00:00Z")):
        (d / name).write_bytes(Path(raws[0]).read_bytes())
        with h5py.File(d / name, "r+") as h5:
            h5.attrs["recorded_utc"] = when
    out = tmp_path / "o"
    code, obj, se = batch_json(arch["pipeline"], [d], out)
    assert code == 0, se
    serial = obj["inputs"][0]["serial"]
    code, so, se = run_cli("history", out, "--unit", serial, "--json")
    cals = json.loads(so)["calibrations"]
    assert [c["file"].split("/")[0] for c in cals] == ["b-early-h5", "a-late-h5"]
    assert cals[0]["recorded_utc"] == "2026-01-01T00:00:00Z"


def test_missing_input_keeps_outputs_corrupt_input_drops_them(arch, tmp_path):
    raw = Path([g for g in arch["good"] if g.endswith(".h5")][0])
    d = tmp_path / "a"
    d.mkdir()
    f = d / "r.h5"
    f.write_bytes(raw.read_bytes())
    out = tmp_path / "o"
    assert batch_json(arch["pipeline"], [f], out)[0] == 0
    cal = out / "r-h5" / "cal-accel.h5"
    assert cal.exists()
    f.rename(d / "moved.h5")
    code, obj, _ = batch_json(arch["pipeline"], [f], out)
    assert code == 1 and "no such file" in obj["inputs"][0]["error"] and cal.exists()
    f.write_bytes(b"corrupt")
    code, obj, _ = batch_json(arch["pipeline"], [f], out)
    assert code == 1 and obj["inputs"][0]["error"].startswith(str(f)) and not cal.exists()


def test_auto_method_fits_each_plan_kind(tmp_path):
    """One pipeline (`method = "auto"`) over an archive of mixed experiments:
    each raw file gets the fit of its plan kind."""
    from calib_cli.io.h5 import write_raw
    from calib_cli.io.plan import load_plan
    from calib_cli.sim.simulate import simulate

    repo = Path(__file__).resolve().parents[1]
    arch = tmp_path / "archive"
    arch.mkdir()
    plans = {"static": repo / "sample_data" / "twelve_position.toml",
             "rimu": repo / "sample_data" / "rimu_six_position.toml",
             "align": repo / "docs" / "examples" / "align_plan.toml"}
    from calib_cli.sim.turntable_plans import turntable_plan_text

    plans["turntable"] = tmp_path / "turntable.toml"
    plans["turntable"].write_text(turntable_plan_text(2, duration_s=60.0))
    for kind, p in plans.items():
        write_raw(arch / f"{kind}.h5", simulate(load_plan(str(p)), seed=3))
    pipe = tmp_path / "pipeline.toml"
    pipe.write_text('glob = "*.h5"\n[[step]]\nstep = "fit"\nmethod = "auto"\n\n'
                    '[[step]]\nstep = "export"\n')
    code, obj, err = batch_json(pipe, [arch], tmp_path / "out")
    assert code == 0, err
    rows = {Path(r["input"]).stem: r for r in obj["inputs"]}
    assert {k: r["status"] for k, r in rows.items()} == {k: "done" for k in plans}
    keys = {k: json.loads((tmp_path / "out" / r["outputs"]["export"]).read_text())["params"].keys()
            for k, r in rows.items()}
    assert "accel_K" in keys["static"]
    assert {"accel_bias", "gyro_bias", "attitude"} <= set(keys["align"])
    assert "gyro_scale_error" in keys["rimu"] and "accel_dEl" in keys["rimu"]
    assert {"lever_arm", "gyro_D", "accel_K"} <= set(keys["turntable"])
