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
    from calib_cli.methods.gross import check_result, screen_fit

    screen_fit(res, rec, lambda r: fn(r, **run.options, **extra))
    check_result(res, rec)  # an impossible calibration is exit 4, not "done"
    write_calibration(run.out, res, [run.inputs["raw"], *extra.values()])


def fit_align_step(rec, method: str = "two-position", rotation: str = "auto", gyro: str = "auto",
                   gyro_k_ppm: float | None = None, turn_sigma_deg: float = 0.0):
    """`calib fit align` with the command's options (same names, same defaults)."""
    import numpy as np

    if method == "classic":
        from calib_cli.methods.align_classic import fit_classic

        return fit_classic(rec, rotation=rotation)
    from calib_cli.methods.align import fit_align

    return fit_align(rec, rotation=rotation, gyro=gyro,
                     gyro_k_prior=None if gyro_k_ppm is None else float(gyro_k_ppm) * 1e-6,
                     turn_sigma=float(np.radians(turn_sigma_deg)))


def fit_gyro_step(rec, g_sensitivity: str = "auto"):
    """`calib fit gyro` without --accel (the accelerometers are fitted from the same recording)."""
    from calib_cli.methods.gyro import fit_gyro

    return fit_gyro(rec, None, g_sensitivity)


def fit_turntable_step(rec, lever_arm: str = "estimate", proof_mass: str = "auto",
                       tangential: str = "on", block_s: float = 0.2, axis_sigma_mrad: float = 1.0,
                       table_tilt_deg: float = 0.05, table_encoder: str = "auto"):
    """`calib fit turntable` with the command's options (same names)."""
    import numpy as np

    from calib_cli.methods.turntable import TurntableOptions, fit_turntable

    return fit_turntable(rec, TurntableOptions(lever_arm=lever_arm, proof_mass=proof_mass,
                                               tangential=tangential in ("on", True),
                                               block_s=float(block_s),
                                               axis_sigma=float(axis_sigma_mrad) * 1e-3,
                                               table_tilt_sigma=float(np.radians(table_tilt_deg)),
                                               table_encoder=table_encoder))


# plan kind -> the fit method `method = "auto"` runs for it
AUTO_METHODS = {"static": "accel", "align": "align", "rimu": "rimu", "turntable": "turntable"}


def fit_auto_step(rec, **options):
    """Pick the fit from the recording's plan kind (an archive of mixed experiments
    runs through one pipeline); options go to that fit unchanged."""
    from calib_cli.batch.registry import FITS
    from calib_cli.errors import EstimationError

    method = AUTO_METHODS.get(rec.plan_kind)
    if method not in FITS:
        raise EstimationError(f"no batch fit for plan kind {rec.plan_kind!r} "
                              f"(known: {', '.join(k for k, v in AUTO_METHODS.items() if v in FITS)})")
    d = FITS[method]
    bad = sorted(set(options) - set(d.options or ()))
    if bad:
        raise EstimationError(f"fit {method} (plan kind {rec.plan_kind}) takes no option {bad[0]!r}")
    return d.function()(rec, **options)


def apply_step(run: StepRun) -> None:
    """cal.h5 + raw.h5 -> corrected.h5: exactly `calib apply` (chunked)."""
    from calib_cli.io.apply_file import apply_file

    apply_file(run.inputs["calibration"], run.inputs["raw"], run.out)


def export_step(run: StepRun) -> None:
    """cal.h5 -> the contract's JSON object (as `calib show --json`), plus a
    "batch" key with the provenance the up-to-date check reads back."""
    from calib_cli.io.contract_json import calibration_json, to_jsonable

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
register_fit("align", "calib_cli.batch.steps:fit_align_step",
             options=("method", "rotation", "gyro", "gyro_k_ppm", "turn_sigma_deg"))
register_fit("gyro", "calib_cli.batch.steps:fit_gyro_step", options=("g_sensitivity",))
register_fit("rimu", "calib_cli.methods.rimu:fit_rimu")
register_fit("turntable", "calib_cli.batch.steps:fit_turntable_step",
             options=("lever_arm", "proof_mass", "tangential", "block_s", "axis_sigma_mrad",
                      "table_tilt_deg", "table_encoder"))
# any option name is passed on: the chosen fit checks it
register_fit("auto", "calib_cli.batch.steps:fit_auto_step",
             options=("method", "rotation", "gyro", "gyro_k_ppm", "turn_sigma_deg", "g_sensitivity",
                      "lever_arm", "proof_mass", "tangential", "block_s", "axis_sigma_mrad",
                      "table_tilt_deg", "table_encoder"))
