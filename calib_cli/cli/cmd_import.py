"""calib import csv LOG.csv --plan PLAN.toml --out RAW.h5"""

from __future__ import annotations

import click

from calib_cli.cli.common import info
from calib_cli.cli.main import cli
from calib_cli.io.csvlog import import_csv
from calib_cli.io.h5 import write_raw
from calib_cli.io.plan import load_plan


@cli.group("import")
def import_group():
    """Bring logs from other sources into raw.h5."""


@import_group.command("csv")
@click.argument("log", type=click.Path(dir_okay=False))
@click.option("--plan", "plan_path", required=True, type=click.Path(dir_okay=False),
              help="The experiment plan (TOML).")
@click.option("--out", required=True, type=click.Path(dir_okay=False), help="raw.h5 to write.")
@click.option("--window", "window_s", default=1.0, show_default=True, type=float,
              help="Static detection: moving window, s.")
@click.option("--threshold", "multiplier", default=3.0, show_default=True, type=float,
              help="Static detection: multiple of the noise floor.")
@click.option("--min-static", "min_static_s", default=1.0, show_default=True, type=float,
              help="Static detection: shortest static interval, s.")
def import_csv_cmd(log, plan_path, out, window_s, multiplier, min_static_s):
    """Import a CSV log (contract columns) with its plan.

    Without a `segment` column, static intervals are detected and matched to
    the plan's static segments in order (docs/import.md).
    """
    plan = load_plan(plan_path)
    rec = import_csv(log, plan, window_s, multiplier, min_static_s)
    write_raw(out, rec, [log, plan_path])
    n_static = len(rec.static_segments())
    info(f"imported {len(rec)} samples, {len(rec.segments)} segments ({n_static} static) -> {out}")
