"""calib detect RAW.h5|LOG.csv: show the static intervals the detector finds."""

from __future__ import annotations

import click
import numpy as np
from rich.table import Table

from calib_cli.cli.common import Ctx, err_console, out_console, print_json
from calib_cli.cli.main import cli


def _load(path: str):
    """(time, accel, gyro, segments or None) from a raw.h5 or a contract CSV."""
    if path.lower().endswith(".csv"):
        from calib_cli.io.csvlog import read_columns
        from calib_cli.model.effects import Layout

        t, accel, gyro, _, _ = read_columns(path, Layout())
        return t, accel, gyro, None
    from calib_cli.io.h5 import read_raw

    rec = read_raw(path)
    return rec.time, rec.accel, rec.gyro, rec.segments


@cli.command("detect")
@click.argument("file", type=click.Path(dir_okay=False))
@click.option("--window", "window_s", default=1.0, show_default=True, type=float,
              help="Moving window, s.")
@click.option("--threshold", "multiplier", default=3.0, show_default=True, type=float,
              help="Multiple of the noise floor.")
@click.option("--min-static", "min_static_s", default=1.0, show_default=True, type=float,
              help="Shortest static interval, s.")
@click.option("--expect", type=int, help="The number of static positions you expect: say which "
              "threshold finds it.")
@click.option("--json", "as_json", is_flag=True, help="One JSON object on stdout.")
def detect_cmd(file, window_s, multiplier, min_static_s, expect, as_json):
    """Static-interval detection as `import` does it, without importing: the
    intervals, the noise floors, and how many intervals other thresholds find
    (docs/import.md)."""
    from calib_cli.methods.static_detect import detect_static

    t, accel, gyro, segs = _load(file)
    rep = detect_static(t, accel, gyro, window_s, multiplier, min_static_s)
    rows = [{"start": int(a), "stop": int(b), "t_start": float(t[a]), "t_stop": float(t[b - 1]),
             "duration": float(t[b - 1] - t[a] + np.median(np.diff(t)))}
            for a, b in rep.intervals]
    explain = rep.explain(expect)
    if as_json:
        print_json({"file": file, "intervals": rows, "threshold": multiplier,
                    "window_s": window_s, "min_static_s": min_static_s,
                    "counts": {f"{k:g}": v for k, v in rep.counts.items()},
                    "floor_accel": rep.floor_accel, "floor_gyro": rep.floor_gyro,
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

