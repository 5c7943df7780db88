"""calib simulate PLAN --out RAW.h5|LOG.csv [--seed N] [--truth TRUTH.toml]"""

from __future__ import annotations

import click

from calib_cli.cli.common import info, json_output_option, output_json
from calib_cli.cli.main import cli
from calib_cli.errors import InputError
from calib_cli.io.csvlog import write_csv
from calib_cli.io.h5 import write_raw
from calib_cli.io.plan import load_plan
from calib_cli.io.truth import load_truth
from calib_cli.plan import plan_layout
from calib_cli.sim.simulate import simulate

COMPLETE_COMMAND = True  # every subcommand lives here: loaded alone (cli/main.py)


@cli.command("simulate")
@click.argument("plan", type=click.Path(dir_okay=False))
@click.option("--out", "out", required=True, type=click.Path(dir_okay=False),
              help="raw.h5, a .csv log in the contract's columns, or a flight-controller or "
                   "ROS log: .ulg (PX4), .bin (ArduPilot), .mcap, .bag (docs/simulate.md).")
@click.option("--seed", default=0, show_default=True, type=int, help="Random seed.")
@click.option("--truth", "truth_path", type=click.Path(dir_okay=False),
              help="Truth model TOML (docs/simulate.md); default: a random MEMS unit.")
@click.option("--in-force", "in_force_path", type=click.Path(dir_okay=False),
              help=".ulg/.bin: the calibration parameters the firmware applies before logging "
                   "(a QGroundControl .params or Mission Planner .parm file; default: the "
                   "plan's [autopilot] table, else none).")
@json_output_option
def simulate_cmd(plan, out, seed, truth_path, in_force_path, as_json=False):
    """Simulate the experiment of PLAN from a truth model, with noise."""
    from pathlib import Path

    from calib_cli.io.log_writers import LOG_SUFFIXES

    suffix = Path(out).suffix.lower()
    if in_force_path and suffix not in (".ulg", ".bin"):
        raise click.UsageError("--in-force is for --out LOG.ulg or LOG.bin")
    p = load_plan(plan)
    in_force = None
    if suffix in LOG_SUFFIXES:
        in_force = _in_force(p, in_force_path)
    truth = load_truth(truth_path, plan_layout(p)) if truth_path else None
    from calib_cli.cli.progress import bar

    try:
        with bar("simulate") as cb:
            rec = simulate(p, truth, seed, progress=cb)
    except InputError as exc:  # a bad simulation key: the line names the plan
        exc.path = exc.path or plan
        raise
    inputs = [plan] + ([truth_path] if truth_path else [])
    if suffix in LOG_SUFFIXES:
        from calib_cli.io.log_writers import write_sim_log

        write_sim_log(out, rec, in_force, in_force_path or plan)
    elif out.lower().endswith(".csv"):
        write_csv(out, rec)
    else:
        write_raw(out, rec, inputs)
    warnings = range_warnings(p, rec)
    for line in warnings:
        info(f"[yellow]warning:[/] {line}")
    info(f"simulated {len(rec)} samples, {len(rec.segments)} segments -> {out}")
    if as_json:
        kind = suffix[1:] if suffix in LOG_SUFFIXES else \
            ("csv" if out.lower().endswith(".csv") else "raw")
        output_json(out, kind, warnings)


def _in_force(plan, path) -> dict | None:
    """The parameters in force: --in-force FILE, else the plan's [autopilot] table
    ({NAME = value}), else None (a board without calibration)."""
    if path:
        from calib_cli.io.fc_params import read_params_file

        return read_params_file(path)[1]
    table = plan.extra.get("autopilot")
    if table is None:
        return None
    if not isinstance(table, dict) or not all(
            isinstance(v, (int, float)) and not isinstance(v, bool) for v in table.values()):
        raise InputError("[autopilot] must hold parameter names with numbers "
                         "(CAL_ACC0_XOFF = 0.12)", plan.path)
    return {str(k): float(v) for k, v in table.items()}


def range_warnings(plan, rec) -> list[str]:
    """Lines for sensor outputs beyond the unit's range (plan [unit] accel_range_g,
    default 16 g; gyro_range_dps, default 2000 deg/s): on a rotating table the
    centripetal and tangential terms at the lever arms add to gravity."""
    import tomllib

    import numpy as np

    if rec.units.get("accel") != "m/s^2":
        return []
    unit = tomllib.loads(plan.text).get("unit", {}) if plan.text else {}
    unit = unit if isinstance(unit, dict) else {}
    out = []
    def rng_key(key, default):
        v = unit.get(key, default)
        if isinstance(v, bool) or not isinstance(v, (int, float)) or not v > 0:
            raise InputError(f"[unit] {key} must be a positive number, got {v!r}", plan.path)
        return float(v)

    a_rng = rng_key("accel_range_g", 16.0)
    peak_a = float(np.max(np.abs(rec.accel))) / 9.80665 if len(rec.accel) else 0.0
    if peak_a > a_rng:
        out.append(f"the accelerometers would read up to {peak_a:.1f} g, beyond the unit's range "
                   f"+-{a_rng:g} g (gravity plus the centripetal and tangential terms at the lever "
                   "arms): lower the table rate, the ramp rate or the lever arm")
    g_rng = rng_key("gyro_range_dps", 2000.0)
    if rec.gyro is not None and len(rec.gyro):
        peak_g = float(np.degrees(np.max(np.abs(rec.gyro))))
        if peak_g > g_rng:
            out.append(f"the gyros would read up to {peak_g:.0f} deg/s, beyond the unit's range "
                       f"+-{g_rng:g} deg/s")
    return out
