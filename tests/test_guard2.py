"""Issue 15, the remaining guard rails, driven through the CLI: numbers in
messages, huge values, concurrent writers of one output, a full disk in the
middle of a streamed write."""

from __future__ import annotations

import errno
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
SAMPLE = ROOT / "sample_data"
PLAN = SAMPLE / "twelve_position.toml"
CSV = SAMPLE / "twelve_position.csv"


@pytest.fixture(scope="module")
def logcsv(tmp_path_factory):
    """The shipped plan simulated: a contract CSV with a segment column."""
    from calib_cli.cli.main import main

    p = tmp_path_factory.mktemp("g2log") / "log.csv"
    with pytest.raises(SystemExit) as e:
        main(["-q", "simulate", str(PLAN), "--out", str(p), "--seed", "1"])
    assert e.value.code in (0, None)
    return p


def _edit_csv(src, tmp_path, name, row, col, value):
    lines = src.read_text().splitlines()
    body = [i for i, ln in enumerate(lines) if ln and not ln.startswith("#")][1:]
    i = body[row]
    cells = lines[i].split(",")
    cells[col] = value
    lines[i] = ",".join(cells)
    p = tmp_path / name
    p.write_text("\n".join(lines) + "\n")
    return p


def _one_line(err):
    lines = [ln for ln in err.splitlines() if ln.strip()]
    assert len(lines) == 1, err
    assert "Traceback" not in err and "np." not in err, err
    return lines[0]


@pytest.mark.parametrize("row,col,value,words", [
    (98, 0, "1e20", ["1e+20"]),            # a time far beyond any recording
    (-1, 0, "1e20", ["1e+20", "beyond"]),  # ... even as the last, increasing, time
    (98, 0, "-1e20", ["-1e+20"]),
    (98, -1, "1e20", ["segment index 1e+20"]),
    (98, -1, "-1e20", ["segment index -1e+20"]),
    (5, 0, "0.5", ["0.5 then", "not increasing"]),
])
def test_numbers_in_import_messages(logcsv, run_cli, tmp_path, row, col, value, words):
    src = _edit_csv(logcsv, tmp_path, "x.csv", row, col, value)
    code, _, err = run_cli("import", "csv", src, "--plan", PLAN, "--out", tmp_path / "o.h5")
    line = _one_line(err)
    assert code == 3 and "x.csv" in line, err
    for w in words:
        assert w in line, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["x.csv"]
    # the same through batch (the non-streaming reader)
    pipe = tmp_path / "pipe.toml"
    pipe.write_text(f'name = "p"\n[[step]]\nstep = "import"\nplan = "{PLAN}"\n')
    code, _, err = run_cli("batch", pipe, src, "--out", tmp_path / "out")
    assert code == 1, err
    assert "-9223372036854775808" not in err and "np.float64" not in err, err
    for w in words[:1]:
        assert w in err, err


def test_numbers_in_text_import_messages(logcsv, run_cli, tmp_path):
    lines = [ln for ln in logcsv.read_text().splitlines() if ln and not ln.startswith("#")][1:]
    rows = [ln.split(",") for ln in lines]
    rows[-1][0] = "1e20"
    (tmp_path / "t.txt").write_text("\n".join(" ".join(r) for r in rows) + "\n")
    code, _, err = run_cli("import", "text", tmp_path / "t.txt", "--plan", PLAN, "--out",
                           tmp_path / "o.h5", "--columns",
                           "time=1,ax=2,ay=3,az=4,gx=5,gy=6,gz=7,segment=8")
    line = _one_line(err)
    assert code == 3 and "1e+20" in line and "--time-unit" in line
    rows[-1][0] = rows[-3][0]
    (tmp_path / "t.txt").write_text("\n".join(" ".join(r) for r in rows) + "\n")
    code, _, err = run_cli("import", "text", tmp_path / "t.txt", "--plan", PLAN, "--out",
                           tmp_path / "o.h5", "--columns",
                           "time=1,ax=2,ay=3,az=4,gx=5,gy=6,gz=7,segment=8")
    line = _one_line(err)
    assert code == 3 and "not increasing" in line and "152." in line, err


def test_message_numbers_safety_net():
    from calib_cli.errors import InputError, num

    e = InputError("a (np.float64(20.02) then np.int64(3)) np.True_", "f.csv")
    assert e.line() == "f.csv: a (20.02 then 3) True"
    assert num(1e20) == "1e+20" and num(3.0) == "3" and num(float("nan")) == "nan"


# ---------------------------------------------------------------------------
# two commands writing one output at once


@pytest.fixture(scope="module")
def raw(tmp_path_factory):
    from calib_cli.cli.main import main

    d = tmp_path_factory.mktemp("g2")
    with pytest.raises(SystemExit) as e:
        main(["-q", "import", "csv", str(CSV), "--plan", str(PLAN), "--out", str(d / "raw.h5")])
    assert e.value.code in (0, None)
    return d / "raw.h5"


HOLD = """
import sys, time
from calib_cli.io.outpath import atomic_file
with atomic_file(sys.argv[1]) as tmp:
    open(tmp, "w").write("partial")
    print("held", flush=True)
    time.sleep(float(sys.argv[2]))
"""


def test_second_writer_of_one_output_fails_naming_the_holder(raw, run_cli, tmp_path):
    out = tmp_path / "c.h5"
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    holder = subprocess.Popen([sys.executable, "-c", HOLD, str(out), "30"], env=env,
                              stdout=subprocess.PIPE, text=True)
    try:
        assert holder.stdout.readline().strip() == "held"
        code, _, err = run_cli("fit", "accel", raw, "--out", out)
        line = _one_line(err)
        assert code == 3 and f"pid {holder.pid}" in line and "c.h5" in line, err
        assert not out.exists()
    finally:
        holder.kill()
        holder.wait(10)
    # the holder was killed: its lock is released, its temp and lock files are cleaned
    code, _, err = run_cli("fit", "accel", raw, "--out", out)
    assert code == 0, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c.h5"]


def test_two_fits_at_once_never_a_mixed_file(raw, tmp_path):
    out = tmp_path / "c.h5"
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    cmd = [sys.executable, "-m", "calib_cli", "-q", "fit", "accel", str(raw), "--out", str(out)]
    procs = [subprocess.Popen(cmd, env=env, stderr=subprocess.PIPE, text=True)
             for _ in range(2)]
    res = [(p.wait(120), p.stderr.read()) for p in procs]
    for code, err in res:
        assert code in (0, 3), err
        if code == 3:
            assert "another command is writing this output" in err and err.count("\n") == 1
    assert any(code == 0 for code, _ in res)
    from calib_cli.io.h5 import read_calibration

    assert read_calibration(out).params["accel_K"].shape == (3, 3)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["c.h5"]


# ---------------------------------------------------------------------------
# a full disk in the middle of a streamed write


def test_disk_full_mid_import_leaves_nothing(run_cli, tmp_path, monkeypatch):
    import calib_cli.io.stream_import as si

    calls = {"n": 0}
    orig = si._Sink.append

    def append(self, name, arr):
        calls["n"] += 1
        if calls["n"] >= 3:  # time and accel have data in the temp file: gyro fails
            raise OSError(errno.ENOSPC, "No space left on device")
        return orig(self, name, arr)

    monkeypatch.setattr(si._Sink, "append", append)
    code, _, err = run_cli("import", "csv", CSV, "--plan", PLAN, "--out", tmp_path / "raw.h5")
    line = _one_line(err)
    assert code == 2 and "disk full" in line and "raw.h5" in line, err
    assert calls["n"] >= 3
    assert list(tmp_path.iterdir()) == []


def test_disk_full_mid_report_leaves_nothing(raw, run_cli, tmp_path, monkeypatch):
    """A report directory: a figure that cannot be written (ENOSPC) leaves
    neither the directory nor its temp."""
    from calib_cli.cli.main import main

    cal = tmp_path / "cal.h5"
    with pytest.raises(SystemExit):
        main(["-q", "fit", "accel", str(raw), "--out", str(cal)])
    import matplotlib.figure

    def full(*a, **k):
        raise OSError(errno.ENOSPC, "No space left on device")

    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", full)
    code, _, err = run_cli("-q", "report", cal, raw, "--out", tmp_path / "rep")
    line = _one_line(err)
    assert code == 2 and "disk full" in line, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cal.h5"]


# ---------------------------------------------------------------------------
# fit align: the gross-error screen (methods/gross.py, _screen_align)


def _align_files(run_cli, d, stated, true, seed=3):
    """A recording simulated with the turns ``true`` and imported with a plan
    stating ``stated`` (a misplaced position, as far as the plan knows)."""
    from calib_cli.validation.align_cases import plan_text

    (d / "true.toml").write_text(plan_text(true, duration=20.0))
    (d / "stated.toml").write_text(plan_text(stated, duration=20.0))
    assert run_cli("-q", "simulate", d / "true.toml", "--out", d / "log.csv", "--seed",
                   str(seed))[0] == 0
    assert run_cli("-q", "import", "csv", d / "log.csv", "--plan", d / "stated.toml", "--out",
                   d / "raw.h5")[0] == 0
    return d / "raw.h5"


def test_align_misplaced_position_named(run_cli, tmp_path):
    z, x = (0, 0, 1), (1, 0, 0)
    raw = _align_files(run_cli, tmp_path, [(z, 90.0), (x, 120.0), (x, -120.0)],
                       [(z, 90.0), (x, 90.0), (x, -90.0)])
    code, _, err = run_cli("-q", "fit", "align", raw, "--rotation", "plan", "--out",
                           tmp_path / "cal.h5")
    line = _one_line(err)
    assert code == 4 and "gross error at position 3 ('position-3')" in line, err
    assert "turn" in line and "mg off" in line
    assert not (tmp_path / "cal.h5").exists()
    # the gyros integrated through the recorded turns measure the real rotation: no error
    code, _, err = run_cli("-q", "fit", "align", raw, "--rotation", "gyro", "--out",
                           tmp_path / "cal.h5")
    assert code == 0, err
    # batch: the same screen in the fit step
    pipe = tmp_path / "pipe.toml"
    pipe.write_text('name = "p"\n[[step]]\nstep = "fit"\nmethod = "align"\n'
                    'options = { rotation = "plan" }\n')
    code, _, err = run_cli("-q", "batch", pipe, raw, "--out", tmp_path / "out")
    assert code == 1 and "position-3" in err, err


def test_align_two_positions_misstated_turn_exit_4(run_cli, tmp_path):
    """Two positions leave no leave-one-out; the misfit (the gyros see the
    earth rate turn 40 deg less than stated) is exit 4, not 60 mg biases."""
    z = (0, 0, 1)
    raw = _align_files(run_cli, tmp_path, [(z, 130.0)], [(z, 90.0)])
    code, _, err = run_cli("-q", "fit", "align", raw, "--rotation", "plan", "--out",
                           tmp_path / "cal.h5")
    line = _one_line(err)
    assert code == 4 and "far beyond the noise" in line and "rotation_angle_deg" in line, err
    assert run_cli("-q", "fit", "align", raw, "--out", tmp_path / "cal.h5")[0] == 0


def test_align_on_a_twelve_position_file_exit_4(run_cli, tmp_path):
    """The issue's case: fit align on the shipped 12-position MEMS recording
    gave biases of 42, -42, 122 mg with exit 0 (the unit's scale factors)."""
    raw = tmp_path / "raw.h5"
    assert run_cli("-q", "import", "csv", CSV, "--plan", PLAN, "--out", raw)[0] == 0
    code, _, err = run_cli("-q", "fit", "align", raw, "--out", tmp_path / "cal.h5")
    line = _one_line(err)
    assert code == 4 and "calib fit accel" in line and "sigma" in line, err
    assert not (tmp_path / "cal.h5").exists()


# ---------------------------------------------------------------------------
# leftovers of killed runs, umask, report directories


def test_killed_runs_leftovers_cleaned_by_the_next_run(raw, run_cli, tmp_path):
    """A real SIGKILL while a report is written leaves its temp directory and
    the output lock; the next run of the same command removes both, replaces
    the report whole and leaves only its own files."""
    import signal

    from calib_cli.cli.main import main

    cal = tmp_path / "cal.h5"
    with pytest.raises(SystemExit):
        main(["-q", "fit", "accel", str(raw), "--out", str(cal)])
    rep = tmp_path / "rep"
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    # the report's figure step is made to hang, so the kill lands mid-write
    hang = ("import sys, time, matplotlib.figure\n"
            "def slow(self, *a, **k):\n"
            "    open(sys.argv[-1] + '.started', 'w').close(); time.sleep(300)\n"
            "matplotlib.figure.Figure.savefig = slow\n"
            "from calib_cli.cli.main import main\n"
            "main(sys.argv[1:-1])\n")
    p = subprocess.Popen([sys.executable, "-c", hang, "-q", "report", str(cal), str(raw),
                          "--out", str(rep), str(tmp_path / "k")], env=env)
    t_end = time.time() + 120
    while not (tmp_path / "k.started").exists() and time.time() < t_end:
        time.sleep(0.1)
    os.kill(p.pid, signal.SIGKILL)
    p.wait(30)
    (tmp_path / "k.started").unlink()
    left = sorted(x.name for x in tmp_path.iterdir())
    # issue 37: the report is made in a temporary directory inside DIR (then moved
    # file by file, so that DIR's other files stay)
    inside = sorted(x.name for x in rep.iterdir())
    assert any(n.startswith("..calib-out.calib-") and n.endswith(".tmpdir") for n in inside), \
        inside
    assert ".rep.calib-lock" in left, left
    old = os.umask(0o027)
    try:
        code, _, err = run_cli("-q", "report", cal, raw, "--out", rep)
    finally:
        os.umask(old)
    assert code == 0, err
    assert sorted(x.name for x in tmp_path.iterdir()) == ["cal.h5", "rep"]
    assert not [x.name for x in rep.iterdir() if x.name.startswith(".")]
    import stat

    # (rep itself was made by the killed run: an existing directory keeps its mode)
    assert all(stat.S_IMODE(f.stat().st_mode) == 0o640 for f in rep.iterdir() if f.is_file())


@pytest.mark.parametrize("mask,mode", [(0o002, 0o664), (0o077, 0o600)])
def test_outputs_follow_the_umask(raw, run_cli, tmp_path, mask, mode):
    import stat

    old = os.umask(mask)
    try:
        outs = {"c.h5": ("fit", "accel", raw, "--out", tmp_path / "c.h5")}
        for name, args in outs.items():
            code, _, err = run_cli("-q", *args)
            assert code == 0, err
            assert stat.S_IMODE((tmp_path / name).stat().st_mode) == mode
        code, _, err = run_cli("-q", "apply", tmp_path / "c.h5", raw, "--out",
                               tmp_path / "corr.h5")
        assert code == 0, err
        assert stat.S_IMODE((tmp_path / "corr.h5").stat().st_mode) == mode
        code, _, err = run_cli("-q", "export", tmp_path / "c.h5", "--format", "json", "--out",
                               tmp_path / "c.json")
        assert code == 0, err
        assert stat.S_IMODE((tmp_path / "c.json").stat().st_mode) == mode
    finally:
        os.umask(old)


def test_batch_reports_a_csv_deleted_from_a_directory(logcsv, run_cli, tmp_path, monkeypatch):
    arch = tmp_path / "arch"
    arch.mkdir()
    for n in ("a.csv", "b.csv"):
        (arch / n).write_bytes(logcsv.read_bytes())
    (arch / "plan.toml").write_text(PLAN.read_text())
    pipe = tmp_path / "pipe.toml"
    pipe.write_text('name = "p"\nglob = ["*.csv"]\n[[step]]\nstep = "import"\n'
                    'plan = "{dir}/plan.toml"\n')
    monkeypatch.chdir(tmp_path)
    code, _, err = run_cli("-q", "batch", pipe, "arch", "--out", "out")
    assert code == 0, err
    (arch / "b.csv").unlink()
    code, _, err = run_cli("-q", "batch", pipe, "arch", "--out", "out")
    assert code == 1, err
    assert "arch/b.csv: no such file" in err, err
    assert (tmp_path / "out" / "b-csv" / "raw.h5").exists()  # old outputs left alone


def test_recorded_file_cut_short_is_not_told_to_reimport(run_cli, tmp_path):
    """A recording made by `calib record` and stopped after 3 of 12 positions:
    the fit says the plan was not finished, not 're-import ... calib detect'."""
    import h5py

    from calib_cli.io.h5 import read_raw, write_raw

    raw = tmp_path / "raw.h5"
    assert run_cli("-q", "import", "csv", CSV, "--plan", PLAN, "--out", raw)[0] == 0
    rec = read_raw(raw)
    import dataclasses

    cut = rec.segments[2].stop
    short = dataclasses.replace(
        rec, time=rec.time[:cut], accel=rec.accel[:cut], gyro=rec.gyro[:cut],
        segments=tuple(rec.segments[:3]),
        counters={"plan_finished": 0, "journal_complete": 1, "frames": cut})
    write_raw(tmp_path / "rec.h5", short, [])
    with h5py.File(tmp_path / "rec.h5") as h5:
        assert h5["counters"].attrs["plan_finished"] == 0
    code, _, err = run_cli("-q", "fit", "accel", tmp_path / "rec.h5", "--out", tmp_path / "c.h5")
    line = _one_line(err)
    assert code == 4 and "stopped before its plan ended" in line, err
    assert "3 of the plan's 12 segments" in line and "re-import" not in line, err


def test_plan_parsing_is_linear_in_the_segments(run_cli, tmp_path):
    """20k segments were 4.8 s and 10^5 did not finish in 120 s (quadratic):
    4x the segments must cost well under 16x the time (best of two)."""
    from calib_cli.io.plan import parse_plan

    def text(n):
        return 'name = "big"\nkind = "static"\nsample_rate_hz = 10\n' + "".join(
            f'[[segment]]\nlabel = "p{i}"\nattitude_deg = [0, 0, 0]\nduration_s = 1.0\n'
            for i in range(n))

    def best(n):
        t = text(n)
        out = []
        for _ in range(2):
            t0 = time.perf_counter()
            assert len(parse_plan(t).segments) == n
            out.append(time.perf_counter() - t0)
        return min(out)

    small, large = best(1000), best(4000)
    assert large < 8 * small + 0.2, (small, large)


def test_report_with_nan_samples_is_exit_3(raw, run_cli, tmp_path):
    """The report turned every Allan failure into a note: damaged samples are
    exit 3 there too (an uneven or short record stays a note)."""
    import h5py
    import numpy as np

    from calib_cli.cli.main import main

    cal = tmp_path / "cal.h5"
    with pytest.raises(SystemExit):
        main(["-q", "fit", "accel", str(raw), "--out", str(cal)])
    bad = tmp_path / "nan.h5"
    bad.write_bytes(raw.read_bytes())
    with h5py.File(bad, "r+") as h5:
        a = h5["samples/accel"][()]
        a[100, 1] = np.nan
        del h5["samples/accel"]
        h5.create_dataset("samples/accel", data=a)
    code, _, err = run_cli("-q", "report", cal, bad, "--out", tmp_path / "rep")
    line = _one_line(err)
    assert code == 3 and "NaN or infinite" in line and "nan.h5" in line, err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["cal.h5", "nan.h5"]
    code, _, err = run_cli("-q", "report", cal, raw, "--out", tmp_path / "rep")
    assert code == 0, err
