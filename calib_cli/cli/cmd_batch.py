"""calib batch PIPELINE.toml INPUT... --out DIR: the pipeline over many inputs (docs/batch.md)."""

from __future__ import annotations

import logging
import os
import time
from pathlib import Path

import click
from rich.table import Table

from calib_cli.cli.common import Ctx, err_console, interactive, print_json
from calib_cli.cli.main import cli
from calib_cli.errors import InputError, OutputError

COMPLETE_COMMAND = True  # every subcommand lives here: loaded alone (cli/main.py)

EXIT_FAILED = 1
EXIT_TOLERANCE = 5


def _logger(path: str | None) -> logging.Logger:
    log = logging.getLogger("calib.batch")
    log.setLevel(logging.INFO)
    log.propagate = False
    for h in list(log.handlers):
        log.removeHandler(h)
        h.close()
    if path:
        h = logging.FileHandler(path, mode="a", encoding="utf-8")
        fmt = logging.Formatter("%(asctime)s %(levelname)s %(message)s", "%Y-%m-%dT%H:%M:%SZ")
        fmt.converter = time.gmtime  # timestamps in UTC
        h.setFormatter(fmt)
        log.addHandler(h)
    else:
        log.addHandler(logging.NullHandler())
    return log


def _steps_text(r: dict) -> str:
    return f"{r['steps_run']} ran, {r['steps_skipped']} up to date"


def _summary(results: list[dict]) -> dict:
    ok = [r for r in results if r["status"] != "failed"]
    return {"inputs": len(results), "ok": len(ok), "failed": len(results) - len(ok),
            "steps_run": sum(r["steps_run"] for r in results),
            "steps_up_to_date": sum(r["steps_skipped"] for r in results)}


def _summary_line(s: dict) -> str:
    head = f"{s['inputs']} inputs: {s['ok']} ok, {s['failed']} failed; "
    if s["steps_run"] == 0:
        return head + (f"nothing to do: 0 steps executed, all {s['steps_up_to_date']} outputs "
                       "up to date")
    return head + f"{s['steps_run']} steps executed, {s['steps_up_to_date']} up to date"


def _check_tolerances(out: str, results: list[dict], tols) -> dict:
    """Pass/fail per calibration made (or confirmed) by this run, and per unit."""
    from calib_cli.io.history import scan
    from calib_cli.io.tolerance import check

    entries = scan(out)
    by_rel = {e.rel: e for e in entries}
    units: dict[str, str] = {}
    for r in results:
        if r["status"] == "failed":
            continue
        checks = []
        for st in r["steps"]:
            e = by_rel.get(st["output"] or "")
            if st["step"].startswith("fit") and e is not None:
                c = check(e, entries, tols)
                checks.append({"file": e.rel, **c})
        r["tolerance"] = _worst([c["status"] for c in checks]) if checks else "n/a"
        r["tolerance_checks"] = checks
        if checks:
            u = r.get("serial") or "(no serial)"
            units[u] = _worst([r["tolerance"], units.get(u, "pass")])
    return dict(sorted(units.items()))


def _worst(statuses) -> str:
    """fail over incomplete (a rule not evaluated) over pass."""
    return next((s for s in ("fail", "incomplete") if s in statuses), "pass")


def _render(results, summary, units, tty: bool) -> None:
    con = err_console
    has_tol = units is not None
    if tty:
        t = Table(title="calib batch")
        t.add_column("input", overflow="fold")
        for col in ("unit", "status", "steps") + (("tolerance",) if has_tol else ()):
            t.add_column(col, no_wrap=True)
        for r in results:
            style = {"failed": "red", "done": "green"}.get(r["status"], "")
            row = [r["input"], r.get("serial") or "-", f"[{style}]{r['status']}[/]" if style
                   else r["status"], _steps_text(r) if r["status"] != "failed" else "-"]
            if has_tol:
                tol = r.get("tolerance", "-")
                row.append("[red]fail[/]" if tol == "fail" else tol)
            t.add_row(*row)
        con.print(t)
    else:
        for r in results:
            extra = f"  tolerance {r.get('tolerance', '-')}" if has_tol else ""
            con.print(f"{r['status']:<10}  {r.get('serial') or '-':<12}  {r['input']}  "
                      f"({_steps_text(r) if r['status'] != 'failed' else 'failed'}){extra}",
                      markup=False, highlight=False, soft_wrap=True)
    for r in results:
        if r["status"] == "failed":
            con.print(f"calib: batch: {r['error']}", markup=False, soft_wrap=True)
        for c in r.get("tolerance_checks", []):
            for line in c["failures"]:
                con.print(f"calib: tolerance: {c['file']}: {line}", markup=False,
                          soft_wrap=True)
            for line in c.get("not_evaluated", []):
                con.print(f"calib: tolerance: {c['file']}: not evaluated: {line}",
                          markup=False, soft_wrap=True)
    if has_tol and units:
        con.print("units: " + ", ".join(f"{u} {v}" for u, v in units.items()), markup=False)
    con.print(_summary_line(summary), markup=False, soft_wrap=True)


@cli.command("batch")
@click.argument("pipeline", type=click.Path(dir_okay=False))
@click.argument("inputs", nargs=-1, required=True, type=click.Path())
@click.option("--out", "out", required=True, type=click.Path(file_okay=False),
              help="Output directory (created; one sub-directory per input).")
@click.option("--workers", default=1, show_default=True, type=click.IntRange(1, 256),
              help="Local worker processes.")
@click.option("--force", is_flag=True, help="Re-run every step, even when up to date.")
@click.option("--json", "as_json", is_flag=True, help="One JSON object on stdout.")
@click.option("--log", "log_path", type=click.Path(dir_okay=False),
              help="Append a line per input (UTC timestamps) to this file.")
@click.option("--tolerances", "tol_path", type=click.Path(dir_okay=False),
              help="Tolerance file (TOML): pass/fail per unit, exit 5 on a fail.")
@click.option("--scheduler", default=None, metavar="tcp://HOST:PORT",
              help="Run on a Dask distributed cluster (extra calib-cli[dask]).")
def batch_cmd(pipeline, inputs, out, workers, force, as_json, log_path, tol_path, scheduler):
    """Run PIPELINE over every INPUT (CSV, raw.h5, or a directory), like make.

    Exit 0 all done, 1 some inputs failed, 5 a unit is out of tolerance.
    """
    from calib_cli.batch.paths import discover, vanished
    from calib_cli.batch.pipeline import load_pipeline
    from calib_cli.batch.runner import output_lock, run_tasks
    from calib_cli.io.outpath import drop_if_empty
    from calib_cli.io.tolerance import load_tolerances

    pipe = load_pipeline(pipeline)
    tols = load_tolerances(tol_path) if tol_path else None
    if scheduler and not scheduler.startswith(("tcp://", "tls://", "ucx://", "inproc://")):
        raise click.BadParameter("expected tcp://HOST:PORT", param_hint="--scheduler")
    created = not os.path.isdir(out)  # removed again on a failure that leaves it empty
    try:
        os.makedirs(out, exist_ok=True)
    except OSError as exc:
        raise InputError(f"cannot create the output directory: {exc.strerror}", out) from None
    out = str(Path(out).resolve())
    log = _logger(log_path)
    with drop_if_empty(out, created), output_lock(out):
        found = discover(inputs, pipe.globs, exclude=out)
        found += vanished(inputs, out, found)  # deleted from a directory: reported failed
        if not found:
            raise InputError(f"no input files (globs {', '.join(pipe.globs)})",
                             " ".join(inputs))
        log.info("batch %s: %d inputs -> %s (pipeline %s, workers %s)", pipe.name, len(found),
                 out, pipe.sha256()[:12], scheduler or workers)
        tasks = [{"input": b.path, "key": b.key, "out": out, "pipeline": pipe.to_dict(),
                  "force": force} for b in found]
        results = []
        tty = interactive() and not as_json
        from calib_cli.cli.progress import track

        for r in track(run_tasks(tasks, workers, scheduler), "calib batch", len(tasks)):
            if r.get("exit_code") == 2:  # a full disk (issue 37): stop, exit 2 naming it
                raise OutputError(r.get("error_message") or r["error"], r.get("error_path"))
            results.append(r)
            if r["status"] == "failed":
                log.error("%s: failed: %s", r["input"], r["error"])
            else:
                log.info("%s: %s (%s)", r["input"], r["status"], _steps_text(r))
        order = {t["key"]: i for i, t in enumerate(tasks)}
        results.sort(key=lambda r: order[r["key"]])
        units = _check_tolerances(out, results, tols) if tols else None
    summary = _summary(results)
    for r in results:
        r["outputs"] = {k: os.path.relpath(v, out) for k, v in r["outputs"].items()
                        if k != "source" and Path(v).is_relative_to(out)}
        for c in r.get("tolerance_checks", []):
            for line in c["failures"]:
                log.warning("%s: tolerance: %s: %s", r["input"], c["file"], line)
    tol_fail = bool(units) and any(v == "fail" for v in units.values())
    code = EXIT_TOLERANCE if tol_fail else EXIT_FAILED if summary["failed"] else 0
    log.info("%s; exit %d", _summary_line(summary), code)
    if as_json:
        print_json({"pipeline": pipe.name, "pipeline_sha256": pipe.sha256(), "out": out,
                    "inputs": results, "summary": summary, "units": units, "exit_code": code})
    elif not Ctx.quiet or code:
        _render(results, summary, units, tty)
    return code
