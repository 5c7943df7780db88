"""The built-in batch steps. To add a step or fit method, add one line at the
bottom (see registry.py for the function conventions)."""

from __future__ import annotations

import json

from calib_cli.batch.registry import StepRun, register_fit, register_step


def import_step(run: StepRun) -> None:
    """CSV + plan -> raw.h5 (calib import csv)."""
    from calib_cli.io.csvlog import import_csv
    from calib_cli.io.h5 import write_raw
    from calib_cli.io.plan import load_plan

    o = run.options
    plan = load_plan(o["plan"])
    rec = import_csv(run.inputs["source"], plan, float(o.get("window_s", 1.0)),
                     float(o.get("threshold", 3.0)), float(o.get("min_static_s", 1.0)))
    write_raw(run.out, rec, [run.inputs["source"], o["plan"]])


def fit_step(run: StepRun, fn) -> None:
    """raw.h5 -> cal.h5 through a registered fit function."""
    from calib_cli.io.h5 import read_raw, write_calibration

    rec = read_raw(run.inputs["raw"])
    extra = {f"{k}_path": v for k, v in run.inputs.items() if k not in ("raw", "source")}
    res = fn(rec, **run.options, **extra)
    write_calibration(run.out, res, [run.inputs["raw"], *extra.values()])


def apply_step(run: StepRun) -> None:
    """cal.h5 + raw.h5 -> corrected.h5: exactly `calib apply` (chunked)."""
    from calib_cli.cli.cmd_apply import apply_cmd

    apply_cmd.callback(run.inputs["calibration"], run.inputs["raw"], run.out)


def export_step(run: StepRun) -> None:
    """cal.h5 -> the contract's JSON object (as `calib show --json`), plus a
    "batch" key with the provenance the up-to-date check reads back."""
    from calib_cli.cli.cmd_show import calibration_json
    from calib_cli.cli.common import to_jsonable

    obj = calibration_json(run.inputs["calibration"], bool(run.options.get("covariance")))
    obj["batch"] = dict(run.stamp)
    with open(run.out, "w", encoding="utf-8") as fh:
        fh.write(json.dumps(to_jsonable(obj), indent=2, sort_keys=False) + "\n")


register_step("import", "calib_cli.batch.steps:import_step", needs=("source",), makes="raw",
              options=("plan", "window_s", "threshold", "min_static_s"), file_options=("plan",),
              applies_to_raw_input=False)
register_step("apply", "calib_cli.batch.steps:apply_step", needs=("calibration", "raw"),
              makes="corrected")
register_step("export", "calib_cli.batch.steps:export_step", needs=("calibration",),
              makes="export", suffix=".json", options=("covariance",))

# fit methods: one line each
register_fit("accel", "calib_cli.methods.accel_lsq:fit_accel", options=("method",))
