"""calib import csv LOG.csv --plan PLAN.toml --out RAW.h5"""

from __future__ import annotations

import click

from calib_cli.cli.common import info
from calib_cli.cli.main import cli
from calib_cli.io.h5 import write_raw
from calib_cli.io.plan import load_plan


COMPLETE_COMMAND = True  # every `calib import` subcommand lives here (cli/main.py)


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
@click.option("--accel-units", type=click.Choice(["count", "m/s^2", "g"]), default="m/s^2",
              show_default=True, help="Units of ax ay az (g: 9.80665 m/s^2).")
@click.option("--gyro-units", type=click.Choice(["count", "rad/s", "deg/s"]), default="rad/s",
              show_default=True, help="Units of gx gy gz.")
def import_csv_cmd(log, plan_path, out, window_s, multiplier, min_static_s, accel_units,
                   gyro_units):
    """Import a CSV log (contract columns) with its plan.

    Without a `segment` column, static intervals are detected and matched to
    the plan's static segments in order (docs/import.md).
    """
    from calib_cli.io.csvlog import import_csv_stream

    plan = load_plan(plan_path)
    res = import_csv_stream(log, plan, out, [log, plan_path], window_s, multiplier, min_static_s,
                            accel_units, gyro_units)
    n_static = sum(1 for s in res.segments if s.kind == "static")
    info(f"imported {res.n} samples, {len(res.segments)} segments ({n_static} static) -> {out}")


@import_group.command("text")
@click.argument("acc", type=click.Path(dir_okay=False))
@click.argument("gyro", required=False, type=click.Path(dir_okay=False))
@click.option("--plan", "plan_path", required=True, type=click.Path(dir_okay=False),
              help="The experiment plan (TOML).")
@click.option("--out", required=True, type=click.Path(dir_okay=False), help="raw.h5 to write.")
@click.option("--columns", help="Column map of ACC: FIELD=COLUMN,... with fields time ax ay az "
              "(gx gy gz temp segment); COLUMN is a header name or a position counting from 1.")
@click.option("--gyro-columns", help="Column map of the GYRO file (time gx gy gz).")
@click.option("--accel-units", type=click.Choice(["count", "m/s^2", "g"]), default="m/s^2",
              show_default=True, help="Units of the accelerometer columns (g: 9.80665 m/s^2).")
@click.option("--gyro-units", type=click.Choice(["count", "rad/s", "deg/s"]), default="rad/s",
              show_default=True, help="Units of the gyro columns.")
@click.option("--rate", type=float, help="Sample rate, Hz (no time column, or time in samples).")
@click.option("--time-unit", type=click.Choice(["s", "ms", "us", "ns", "sample"]), default="s",
              show_default=True, help="Unit of the time column.")
@click.option("--delimiter", type=click.Choice(["auto", "comma", "semicolon", "tab", "whitespace"]),
              default="auto", show_default=True)
@click.option("--header", type=click.Choice(["auto", "yes", "no"]), default="auto",
              show_default=True, help="Is the first non-comment line a header?")
@click.option("--sort", is_flag=True, help="Order the rows by time (files cut into parts).")
@click.option("--segments", "segments_json", type=click.Path(dir_okay=False),
              help="JSON {label: {start, end}} sample ranges of the plan's segments.")
@click.option("--window", "window_s", default=1.0, show_default=True, type=float,
              help="Static detection: moving window, s.")
@click.option("--threshold", "multiplier", default=3.0, show_default=True, type=float,
              help="Static detection: multiple of the noise floor.")
@click.option("--min-static", "min_static_s", default=1.0, show_default=True, type=float,
              help="Static detection: shortest static interval, s.")
def import_text_cmd(acc, gyro, plan_path, out, columns, gyro_columns, accel_units, gyro_units,
                    rate, time_unit, delimiter, header, sort, segments_json, window_s,
                    multiplier, min_static_s):
    """Import a text log in another layout: whitespace or CSV, with or without a
    header, raw counts or other units, accelerometer and gyro in one file or in
    two files sharing timestamps (docs/import.md)."""
    from calib_cli.io.textlog import import_text

    plan = load_plan(plan_path)
    rec = import_text(acc, plan, gyro, columns, gyro_columns, accel_units, gyro_units, rate,
                      time_unit, delimiter, header, sort, segments_json, window_s, multiplier,
                      min_static_s)
    inputs = [acc] + ([gyro] if gyro else []) + [plan_path] + ([segments_json] if segments_json
                                                             else [])
    write_raw(out, rec, inputs)
    n_static = len(rec.static_segments())
    info(f"imported {len(rec)} samples ({rec.units['accel']}, {rec.units['gyro']}), "
         f"{len(rec.segments)} segments ({n_static} static) -> {out}")
