"""calib import csv|text|bag|ulog|dataflash: logs in -> raw.h5 (docs/import.md)"""

from __future__ import annotations

import click

from calib_cli.cli.common import info, json_output_option, output_json
from calib_cli.cli.main import cli
from calib_cli.cli.progress import bar, track
from calib_cli.io.plan import load_plan

COMPLETE_COMMAND = True  # every `calib import` subcommand lives here (cli/main.py)


def _started(*modules) -> None:
    """The command's modules imported (those that import themselves later too,
    ``modules``, when installed): the cyclic garbage collector, which the
    entry point keeps off while an import starts up (``calib_cli.__main__``:
    a few 10^5 objects of numpy, h5py, pyarrow and click that live as long as
    the process, over which it would otherwise run again and again), is on
    again, with those objects frozen out of its passes."""
    import gc
    import importlib

    import calib_cli.cli as pkg

    for name in modules:
        try:
            importlib.import_module(name)
        except ImportError:  # an optional extra: its command says so itself
            pass
    if getattr(pkg, "GC_DEFERRED", False):
        pkg.GC_DEFERRED = False
        gc.freeze()
        gc.enable()


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
@click.option("--sample-kind", type=click.Choice(["instant", "interval-mean"]), default="instant",
              show_default=True,
              help="instant: each sample is the value at its time stamp; interval-mean: the mean "
                   "over the sample period ending at the stamp (filtered MEMS output).")
@json_output_option
def import_csv_cmd(log, plan_path, out, window_s, multiplier, min_static_s, accel_units,
                   gyro_units, sample_kind, as_json=False):
    """Import a CSV log (contract columns) with its plan.

    Without a `segment` column, static intervals are detected and matched to
    the plan's static segments in order (docs/import.md).
    """
    from calib_cli.io.csvlog import import_csv_stream

    _started("calib_cli.io.stream_import", "pyarrow.csv")

    plan = load_plan(plan_path)
    with bar("import csv") as cb:
        res = import_csv_stream(log, plan, out, [log, plan_path], window_s, multiplier,
                                min_static_s, accel_units, gyro_units, sample_kind=sample_kind,
                                progress=cb)
    n_static = sum(1 for s in res.segments if s.kind == "static")
    info(f"imported {res.n} samples, {len(res.segments)} segments ({n_static} static) -> {out}")
    if as_json:
        output_json(out, "raw")


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
@click.option("--sample-kind", type=click.Choice(["instant", "interval-mean"]), default="instant",
              show_default=True,
              help="instant: each sample is the value at its time stamp; interval-mean: the mean "
                   "over the sample period ending at the stamp (filtered MEMS output).")
@json_output_option
def import_text_cmd(acc, gyro, plan_path, out, columns, gyro_columns, accel_units, gyro_units,
                    rate, time_unit, delimiter, header, sort, segments_json, window_s,
                    multiplier, min_static_s, sample_kind, as_json=False):
    """Import a text log in another layout: whitespace or CSV, with or without a
    header, raw counts or other units, accelerometer and gyro in one file or in
    two files sharing timestamps (docs/import.md)."""
    from calib_cli.io.textlog import import_text_to_raw

    _started("calib_cli.io.stream_import", "pyarrow.csv")

    plan = load_plan(plan_path)
    inputs = [acc] + ([gyro] if gyro else []) + [plan_path] + ([segments_json] if segments_json
                                                             else [])
    # streamed when the layout allows it, else in memory (the same data and errors)
    with bar("import text"):
        n, units, segments = import_text_to_raw(
            out, acc, plan, gyro, columns, gyro_columns, accel_units, gyro_units, rate, time_unit,
            delimiter, header, sort, segments_json, window_s, multiplier, min_static_s, inputs,
            sample_kind)
    n_static = sum(1 for s in segments if s.kind == "static")
    info(f"imported {n} samples ({units['accel']}, {units['gyro']}), "
         f"{len(segments)} segments ({n_static} static) -> {out}")
    if as_json:
        output_json(out, "raw")


def _detection_options(f):
    for opt in reversed([
        click.option("--plan", "plan_path", type=click.Path(dir_okay=False),
                     help="The experiment plan (TOML)."),
        click.option("--out", type=click.Path(dir_okay=False), help="raw.h5 to write."),
        click.option("--window", "window_s", default=1.0, show_default=True, type=float,
                     help="Static detection: moving window, s."),
        click.option("--threshold", "multiplier", default=3.0, show_default=True, type=float,
                     help="Static detection: multiple of the noise floor."),
        click.option("--min-static", "min_static_s", default=1.0, show_default=True, type=float,
                     help="Static detection: shortest static interval, s."),
        click.option("--json", "as_json", is_flag=True,
                     help='The listing as JSON; when importing, {"output", "kind", "sha256", '
                          '"warnings"} of the written file on stdout and nothing else there.'),
    ]):
        f = opt(f)
    return f


def _list_streams(rows, as_json, what):
    import json

    if as_json:
        click.echo(json.dumps(rows))
        return
    if not rows:
        click.echo(f"no IMU {what} found")
        return
    width = max(len(r["topic"]) for r in rows)
    for r in rows:
        click.echo(f"{r['topic']:{width}s}  {r['count']:9d} messages  {r['rate_hz']:9.2f} Hz")


def _import_stream(path, stream, plan_path, out, window_s, multiplier, min_static_s, inputs,
                   as_json=False):
    from pathlib import Path

    from calib_cli.io.imu_logs import gap_check, stream_chunks
    from calib_cli.io.stream_import import import_to_raw

    plan = load_plan(plan_path)
    if Path(path).is_dir():  # a ROS 2 bag folder: hash every file in it
        inputs = sorted(str(p) for p in Path(path).rglob("*") if p.is_file())
    # filled in while the log is read (dropouts, device ids, parameter changes)
    counters = stream.info
    counters["source_stream"] = stream.name
    res = import_to_raw(out, track(stream_chunks(path, stream), f"import {stream.name}"), plan,
                        path, inputs + [plan_path],
                        window_s, multiplier, min_static_s, counters=counters,
                        check=gap_check(path, stream.name), provenance=stream.source)
    n_static = sum(1 for s in res.segments if s.kind == "static")
    gaps = res.counters.get("gaps", 0)
    gap_txt = (f", {gaps} short gap{'s' * (gaps != 1)} (longest "
               f"{res.counters['longest_gap_periods']:.1f} sample periods)") if gaps else ""
    from calib_cli.io.escape import term_text

    info(f"imported {res.n} samples of {term_text(stream.name)}, {len(res.segments)} segments "
         f"({n_static} static){gap_txt} -> {out}")
    warnings = [gap_txt[2:]] if gaps else []
    src = stream.source
    if src.get("samples") == "corrected":
        n_par = len(src.get("parameters") or {})
        info(f"the samples are already corrected by the firmware ({n_par} calibration "
             "parameters in force recorded): `calib export --format "
             f"{src.get('firmware')}` composes the fit with them (docs/export.md)")
    if src.get("parameters_changed"):
        w = ("calibration parameters changed during the log: "
             + ", ".join(src["parameters_changed"][:6])
             + ("..." if len(src["parameters_changed"]) > 6 else ""))
        info(f"[yellow]warning:[/] {term_text(w)}")
        warnings.append(w)
    if as_json:
        output_json(out, "raw", warnings)


def _need_plan(plan_path, out, what):
    if not plan_path or not out:
        raise click.UsageError(f"give --plan and --out to import {what} (without them the "
                               "command lists the IMU streams)")


@import_group.command("bag")
@click.argument("path", type=click.Path())
@click.option("--topic", help="The sensor_msgs/Imu topic; without it, list the IMU topics.")
@click.option("--stamp", type=click.Choice(["header", "receive"]), default="header",
              show_default=True, help="Time: the messages' header stamps or the receive times.")
@_detection_options
def import_bag_cmd(path, topic, stamp, plan_path, out, window_s, multiplier, min_static_s,
                   as_json):
    """Import sensor_msgs/Imu from a ROS 1 .bag, a ROS 2 bag folder (sqlite3 or
    MCAP) or a bare .mcap file (needs calib-cli[ros]; docs/import.md).
    Without --topic, list the IMU topics with their message counts and rates."""
    from calib_cli.io.imu_logs import bag_stream, list_bag_topics

    _started("calib_cli.io.stream_import")

    if topic is None:
        _list_streams(list_bag_topics(path), as_json, "topics")
        return
    _need_plan(plan_path, out, "a topic")
    _import_stream(path, bag_stream(path, topic, stamp), plan_path, out, window_s, multiplier,
                   min_static_s, [path], as_json)


@import_group.command("ulog")
@click.argument("path", type=click.Path(dir_okay=False))
@click.option("--source", type=click.Choice(["sensor_combined", "sensor"]),
              default="sensor_combined", show_default=True,
              help="sensor_combined (corrected by PX4's calibration) or sensor_accel/sensor_gyro "
                   "of one instance (before it).")
@click.option("--instance", default=0, show_default=True, type=int,
              help="Instance of sensor_accel/sensor_gyro (--source sensor).")
@_detection_options
def import_ulog_cmd(path, source, instance, plan_path, out, window_s, multiplier, min_static_s,
                    as_json):
    """Import the IMU of a PX4 ULog file (docs/import.md); /source of the raw file
    records whether the samples are corrected and the parameters in force.
    Without --plan, list the IMU topics with their message counts and rates."""
    from calib_cli.io.imu_logs import list_ulog_streams, ulog_stream

    _started("calib_cli.io.stream_import")

    if not plan_path and not out:
        _list_streams(list_ulog_streams(path), as_json, "topics")
        return
    _need_plan(plan_path, out, "a ULog file")
    _import_stream(path, ulog_stream(path, source, instance), plan_path, out, window_s,
                   multiplier, min_static_s, [path], as_json)


@import_group.command("dataflash")
@click.argument("path", type=click.Path(dir_okay=False))
@click.option("--message", type=click.Choice(["IMU", "ACC"]), default="IMU", show_default=True,
              help="IMU (filtered, at the logging rate) or ACC/GYR (unfiltered samples).")
@click.option("--instance", default=0, show_default=True, type=int,
              help="IMU instance: field I, or 0-2 = IMU/IMU2/IMU3 (ACC1..3) of older logs.")
@_detection_options
def import_dataflash_cmd(path, message, instance, plan_path, out, window_s, multiplier,
                         min_static_s, as_json):
    """Import the IMU of an ArduPilot DataFlash .bin log (needs
    docs/import.md; ArduPilot 4.1+ I field, or IMU/IMU2/IMU3 and ACC1..3 of older
    logs); /source records the parameters in force. Without --plan, list the IMU
    messages with their counts and rates."""
    from calib_cli.io.imu_logs import dataflash_stream, list_dataflash_streams

    _started("calib_cli.io.stream_import")

    if not plan_path and not out:
        _list_streams(list_dataflash_streams(path), as_json, "messages")
        return
    _need_plan(plan_path, out, "a DataFlash log")
    _import_stream(path, dataflash_stream(path, message, instance), plan_path, out, window_s,
                   multiplier, min_static_s, [path], as_json)
