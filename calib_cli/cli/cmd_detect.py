"""calib detect RAW.h5|LOG.csv [--plot PNG]: show the static intervals the detector finds."""

from __future__ import annotations

import click
import numpy as np
from rich.table import Table

from calib_cli.cli.common import Ctx, err_console, out_console, print_json
from calib_cli.cli.main import cli

COMPLETE_COMMAND = True  # every subcommand lives here: loaded alone (cli/main.py)

AUTO_PLAN = 'name = "detect"\nkind = "static"\n[[segment]]\nlabel = "pos"\nrepeat = "auto"\n'


def _load(path: str, gyro_path=None, text_opts=None):
    """(time, accel, gyro, segments or None, units) from a raw.h5, a contract CSV, or a
    text log read as `import text` reads it (with its options); units: the recorded
    units of accel and gyro (counts stay counts)."""
    if path.lower().endswith(".h5"):
        from calib_cli.io.h5 import read_raw

        rec = read_raw(path)
        return rec.time, rec.accel, rec.gyro, rec.segments, dict(rec.units)
    if path.lower().endswith(".csv") and gyro_path is None and not text_opts:
        from calib_cli.errors import InputError
        from calib_cli.io.csvlog import read_columns
        from calib_cli.model.effects import Layout

        try:
            t, accel, gyro, _, _ = read_columns(path, Layout())
            return t, accel, gyro, None, {"accel": "m/s^2", "gyro": "rad/s"}
        except InputError:
            pass  # not the contract's columns: read it as a text log
    from calib_cli.io.plan import parse_plan
    from calib_cli.io.textlog import import_text

    rec = import_text(path, parse_plan(AUTO_PLAN), gyro_path, **(text_opts or {}))
    return rec.time, rec.accel, rec.gyro, None, dict(rec.units)


@cli.command("detect")
@click.argument("file", type=click.Path(dir_okay=False))
@click.argument("gyro", required=False, type=click.Path(dir_okay=False))
@click.option("--columns", help="Text logs: column map, as for `import text`.")
@click.option("--gyro-columns", help="Text logs: column map of the GYRO file.")
@click.option("--rate", type=float, help="Text logs: sample rate, Hz.")
@click.option("--time-unit", type=click.Choice(["s", "ms", "us", "ns", "sample"]), default=None,
              help="Text logs: unit of the time column.")
@click.option("--accel-units", type=click.Choice(["count", "m/s^2", "g"]), default=None,
              help="Text logs: units of the accelerometer columns (as `import text`; m/s^2).")
@click.option("--gyro-units", type=click.Choice(["count", "rad/s", "deg/s"]), default=None,
              help="Text logs: units of the gyro columns (as `import text`; rad/s).")
@click.option("--window", "window_s", default=1.0, show_default=True, type=float,
              help="Moving window, s.")
@click.option("--threshold", "multiplier", default=3.0, show_default=True, type=float,
              help="Multiple of the noise floor.")
@click.option("--min-static", "min_static_s", default=1.0, show_default=True, type=float,
              help="Shortest static interval, s.")
@click.option("--expect", type=int, help="The number of static positions you expect: say which "
              "threshold finds it.")
@click.option("--json", "as_json", is_flag=True, help="One JSON object on stdout.")
@click.option("--plot", "plot_path", type=click.Path(dir_okay=False),
              help="PNG of the signal with the detected intervals marked and the detector's "
                   "statistic against the threshold.")
def detect_cmd(file, gyro, columns, gyro_columns, rate, time_unit, accel_units, gyro_units,
               window_s, multiplier, min_static_s, expect, as_json, plot_path):
    """Static-interval detection as `import` does it, without importing: the
    intervals, the noise floors, and how many intervals other thresholds find.
    FILE is a raw.h5, a contract CSV, or a text log (with an optional GYRO file
    and the reading options of `import text`; docs/import.md)."""
    from calib_cli.methods.static_detect import detect_static

    opts = {k: v for k, v in (("columns", columns), ("gyro_columns", gyro_columns),
                              ("rate", rate), ("time_unit", time_unit),
                              ("accel_units", accel_units), ("gyro_units", gyro_units))
            if v is not None}
    t, accel, gyro_data, segs, units = _load(file, gyro, opts)
    rep = detect_static(t, accel, gyro_data, window_s, multiplier, min_static_s)
    rows = [{"start": int(a), "stop": int(b), "t_start": float(t[a]), "t_stop": float(t[b - 1]),
             "duration": float(t[b - 1] - t[a] + np.median(np.diff(t)))}
            for a, b in rep.intervals]
    explain = rep.explain(expect)
    if plot_path:
        from pathlib import Path

        from calib_cli.io.h5 import atomic_path
        from calib_cli.report.figures import detection_figure, png_bytes

        data = png_bytes(detection_figure(t, accel, gyro_data, rep, f"Static detection of "
                                                                    f"{Path(file).name}",
                                          units=units))
        with atomic_path(plot_path) as tmp:
            Path(tmp).write_bytes(data)
    if as_json:
        print_json({"file": file, "intervals": rows, "threshold": multiplier,
                    "window_s": window_s, "min_static_s": min_static_s,
                    "counts": {f"{k:g}": v for k, v in rep.counts.items()},
                    "floor_accel": rep.floor_accel, "floor_gyro": rep.floor_gyro,
                    "units": {k: units.get(k) for k in ("accel", "gyro")},
                    "explain": explain,
                    "segments_in_file": None if segs is None else
                    sum(1 for s in segs if s.kind == "static")})
        return
    tab = Table(title=f"static intervals in {file}")
    for c in ("#", "start s", "end s", "duration s", "samples"):
        tab.add_column(c, justify="right")
    for i, r in enumerate(rows):
        tab.add_row(str(i + 1), f"{r['t_start']:.2f}", f"{r['t_stop']:.2f}",
                    f"{r['duration']:.2f}", str(r["stop"] - r["start"]))
    out_console.print(tab)
    if not Ctx.quiet:
        err_console.print(explain, markup=False, soft_wrap=True)
        if segs is not None:
            err_console.print(f"(the file's own segmentation has "
                              f"{sum(1 for s in segs if s.kind == 'static')} static segments)",
                              markup=False)

