"""Progress bars (cli/progress.py): drawn on a terminal, silent in pipes and with
--quiet; the core reports through a callback (fit_turntable per cycle and pass,
simulate per segment)."""

from __future__ import annotations

import io
import json

from click.testing import CliRunner

from calib_cli.cli import common, progress
from calib_cli.cli.main import cli
from calib_cli.io.plan import parse_plan
from calib_cli.sim.simulate import simulate
from calib_cli.sim.turntable_plans import turntable_plan_text


def _runner():
    try:
        return CliRunner(mix_stderr=False)
    except TypeError:  # click >= 8.2
        return CliRunner()


def test_bar_on_a_terminal_only(monkeypatch):
    from rich.console import Console

    buf = io.StringIO()
    monkeypatch.setitem(common._CONSOLES, "err_console",
                        Console(file=buf, force_terminal=True, width=100))
    monkeypatch.setattr(progress.sys.stdout, "isatty", lambda: True, raising=False)
    monkeypatch.setattr(progress.sys.stderr, "isatty", lambda: True, raising=False)
    monkeypatch.setattr(common.Ctx, "quiet", False)
    assert progress.enabled()
    with progress.bar("fit demo", 4) as cb:
        cb(2)
        with progress.bar("inner") as inner:  # one bar at a time: the inner one is silent
            inner(1, 1)
    assert "fit demo" in buf.getvalue() and "inner" not in buf.getvalue()
    assert list(progress.track(iter([1, 2, 3]), "items", 3)) == [1, 2, 3]
    monkeypatch.setattr(common.Ctx, "quiet", True)
    assert not progress.enabled()
    buf.truncate(0)
    with progress.bar("quiet one") as cb:
        cb(1, 2)
    assert "quiet one" not in buf.getvalue()


def test_not_a_terminal_is_silent(monkeypatch):
    monkeypatch.setattr(common.Ctx, "quiet", False)
    assert not progress.enabled()  # pytest captures: no TTY
    calls = []
    with progress.bar("x") as cb:
        cb(1, 2)
        calls.append(1)
    assert calls == [1]


def test_core_reports_progress_through_a_callback():
    plan = parse_plan(turntable_plan_text(3, duration_s=120.0))
    seen = []
    rec = simulate(plan, None, 1, progress=lambda d, t: seen.append((d, t)))
    n = len(plan.segments) + 2
    assert seen[-1] == (n, n) and all(d <= t for d, t in seen)
    from calib_cli.methods.turntable import TurntableOptions, fit_turntable

    ticks = []
    fit_turntable(rec, TurntableOptions(), progress=lambda d, t: ticks.append((d, t)))
    assert len(ticks) >= 3  # the start windows and the passes
    assert [d for d, _ in ticks] == list(range(1, len(ticks) + 1))
    assert ticks[-1][0] == ticks[-1][1]  # ends full


def test_json_output_object_of_simulate_apply_export_import(tmp_path):
    r = _runner()
    plan = tmp_path / "p.toml"
    assert r.invoke(cli, ["-q", "plan", "make", "static", "--out", str(plan)]).exit_code == 0
    res = r.invoke(cli, ["simulate", str(plan), "--out", str(tmp_path / "raw.h5"), "--json"])
    assert res.exit_code == 0, res.output
    obj = json.loads(res.stdout)  # stdout is the object alone; no bar, no status there
    assert set(obj) == {"output", "kind", "sha256", "warnings"} and obj["kind"] == "raw"
    from calib_cli.io.h5 import sha256_file

    assert obj["sha256"] == sha256_file(tmp_path / "raw.h5")
    assert "\x1b" not in (res.stderr or "")  # not a terminal: no progress bar drawn
    res = r.invoke(cli, ["simulate", str(plan), "--out", str(tmp_path / "log.csv"), "--json"])
    assert json.loads(res.stdout)["kind"] == "csv"
    res = r.invoke(cli, ["import", "csv", str(tmp_path / "log.csv"), "--plan", str(plan),
                         "--out", str(tmp_path / "imp.h5"), "--json"])
    assert res.exit_code == 0, res.output
    assert json.loads(res.stdout)["kind"] == "raw"
    assert r.invoke(cli, ["-q", "fit", "accel", str(tmp_path / "raw.h5"), "--out",
                          str(tmp_path / "cal.h5")]).exit_code == 0
    res = r.invoke(cli, ["apply", str(tmp_path / "cal.h5"), str(tmp_path / "raw.h5"), "--out",
                         str(tmp_path / "cor.h5"), "--json"])
    assert res.exit_code == 0 and json.loads(res.stdout)["kind"] == "corrected"
    res = r.invoke(cli, ["export", str(tmp_path / "cal.h5"), "--format", "c-header", "--out",
                         str(tmp_path / "cal.h"), "--json"])
    obj = json.loads(res.stdout)
    assert obj["kind"] == "c-header" and obj["output"] == str(tmp_path / "cal.h")
    res = r.invoke(cli, ["export", str(tmp_path / "cal.h5"), "--format", "json", "--json"])
    assert res.exit_code == 2  # --json needs --out: stdout would hold the export itself
