"""calib rimu-check RAW CAL (parity-space FDI); `calib fit rimu` is made from the method
table (cli/cmd_fit.py)."""

from __future__ import annotations

import click
import numpy as np
from rich.table import Table

from calib_cli.cli.common import Ctx, err_console, out_console, print_json
from calib_cli.cli.main import cli
from calib_cli.errors import FaultDetected, InputError
from calib_cli.io.h5 import read_calibration, read_raw

R2D = 180.0 / np.pi
_SHOW = {"accel": (1e3 / 9.80665, "mg"), "gyro": (R2D, "deg/s")}


def _render_report(s: dict) -> None:
    f, unit = _SHOW[s["sensor"]]
    t = Table(title=f"{s['sensor']}: parity test, {s['n_sensors']} sensors, chi-square "
                    f"{s['dof']} dof, window {s['window_s']:.3g} s")
    t.add_column("item")
    t.add_column("value")
    t.add_row("false-alarm rate (stated)", f"{s['false_alarm_rate_per_hour']:g} per hour "
              f"(alpha {s['alpha_per_window']:.3g} per window)")
    t.add_row("threshold", f"{s['threshold']:.2f}")
    t.add_row("windows / alarms", f"{s['windows']} / {s['alarms']}")
    t.add_row("statistic mean / max", f"{s['stat_mean']:.2f} / {s['stat_max']:.2f} "
              f"(expected mean {s['dof']})")
    if s["fault"]:
        t.add_row("FAULT", f"sensor {s['faulty_sensor']} from t = {s['first_alarm_time']:.3f} s"
                  + ("" if s["isolable"] else " (not isolable from another sensor)"))
        t.add_row("rest consistent", str(s["rest_consistent"]))
        xa = ", ".join(f"{v * f:.4g}" for v in s["x_all_mean"])
        xe = ", ".join(f"{v * f:.4g}" for v in s["x_excluded_mean"])
        t.add_row(f"estimate, all sensors ({unit})", xa)
        t.add_row(f"estimate, without {s['faulty_sensor']} ({unit})", xe)
    out_console.print(t)


@cli.command("rimu-check")
@click.argument("raw", type=click.Path(dir_okay=False))
@click.argument("cal", type=click.Path(dir_okay=False))
@click.option("--window", "window_s", default=0.5, show_default=True, type=float,
              help="Test window, s (non-overlapping averages).")
@click.option("--false-alarm-rate", "rate", default=0.1, show_default=True, type=float,
              help="Stated false-alarm rate per hour of fault-free data.")
@click.option("--sensor", type=click.Choice(["both", "accel", "gyro"]), default="both",
              show_default=True)
@click.option("--cal-uncertainty/--no-cal-uncertainty", default=True, show_default=True,
              help="Add the calibration's own uncertainty at each window's motion to the "
                   "noise covariance.")
@click.option("--json", "as_json", is_flag=True, help="One JSON object on stdout.")
def rimu_check_cmd(raw, cal, window_s, rate, sensor, cal_uncertainty, as_json):
    """Parity-space fault detection and isolation; exit 6 when a fault is found."""
    from calib_cli.methods.rimu_fdi import noise_sigma, parity_check, sensor_cov_blocks

    if window_s <= 0 or rate <= 0:
        raise click.BadParameter("--window and --false-alarm-rate must be positive")
    c = read_calibration(cal)
    if not c.layout.redundant:
        raise InputError("not a redundant-unit calibration (calib fit rimu)", cal)
    rec = read_raw(raw, kinds=("raw",))  # a corrected file would be corrected twice
    if rec.layout.n != c.layout.n:
        raise InputError(f"the recording has {rec.layout.n} sensors, the calibration "
                         f"{c.layout.n}", raw)
    if rec.layout.redundant and not (np.allclose(rec.layout.el0, c.layout.el0)
                                     and np.allclose(rec.layout.az0, c.layout.az0)):
        raise InputError("the recording's nominal geometry (el0/az0) differs from the "
                         "calibration's", raw)
    for s in ("accel", "gyro"):
        if rec.units.get(s) != c.raw_units.get(s, rec.units.get(s)):
            raise InputError(f"{s} data is in {rec.units.get(s)!r} but the calibration was "
                             f"fitted on {c.raw_units.get(s)!r}", raw)
    wanted = ("accel", "gyro") if sensor == "both" else (sensor,)
    reports = []
    for s in wanted:
        data = rec.accel if s == "accel" else rec.gyro
        if data is None or f"{s}_bias" not in c.params:
            continue
        sig = noise_sigma(c.stats, s, rec.sample_rate, c.layout.n)
        cov = sensor_cov_blocks(c, s) if cal_uncertainty else None
        reports.append(parity_check(c.params, c.layout, s, rec.time, data, sig, window_s, rate,
                                    cov))
    if not reports:
        raise InputError("no channel both recorded and calibrated", raw)
    summaries = [r.summary() for r in reports]
    if as_json:
        print_json({"method": "rimu-check", "unit": {"serial": rec.serial or c.serial},
                    "fault": any(r.fault for r in reports), "checks": summaries})
    elif not Ctx.quiet:
        for s in summaries:
            _render_report(s)
    faults = [s for s in summaries if s["fault"]]
    if faults:
        msg = "; ".join(f"{s['sensor']} sensor {s['faulty_sensor']} faulty from t = "
                        f"{s['first_alarm_time']:.3f} s ({s['alarms']} of {s['windows']} "
                        f"windows above {s['threshold']:.1f})" for s in faults)
        raise FaultDetected(msg, raw)
    if not as_json and not Ctx.quiet:
        err_console.print("no fault detected")
    return 0
