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
    """raw.h5 -> cal.h5 through a registered fit function. The built-in methods go
    through the fit registry (methods/registry.py), exactly as `calib fit METHOD`."""
    from calib_cli.io.h5 import read_raw, write_calibration

    raw = run.inputs["raw"]
    rec = read_raw(raw)
    extra = {f"{k}_path": v for k, v in run.inputs.items() if k not in ("raw", "source")}
    if getattr(fn, "registry_method", None):
        res = fn(rec, path=raw, **run.options)
    else:  # a fit registered from outside (registry.py's conventions)
        res = fn(rec, **run.options, **extra)
        from calib_cli.methods.gross import check_result, screen_fit

        screen_fit(res, rec, lambda r: fn(r, **run.options, **extra))
        check_result(res, rec)  # an impossible calibration is exit 4, not "done"
    write_calibration(run.out, res, [raw, *extra.values()])


def registry_fit(method: str):
    """The batch's fit function of a method of the fit registry: options as in a
    pipeline's step table (the command line's names), checked by the registry."""

    def fit(rec, path=None, **options):
        from calib_cli.methods import registry

        return registry.run(method, rec, dict(options), path)

    fit.registry_method = method
    fit.__name__ = f"fit_{method}"
    return fit


def fit_auto(rec, path=None, **options):
    """Pick the fit from the recording's plan kind (an archive of mixed experiments
    runs through one pipeline); options go to that fit unchanged."""
    from calib_cli.errors import EstimationError
    from calib_cli.methods import registry

    method = registry.METHOD_OF_PLAN.get(rec.plan_kind)
    if method not in registry.FITS:
        raise EstimationError(f"no batch fit for plan kind {rec.plan_kind!r} (known: "
                              f"{', '.join(registry.METHOD_OF_PLAN)})")
    bad = sorted(set(options) - set(registry.FITS[method].option_names()))
    if bad:
        raise EstimationError(f"fit {method} (plan kind {rec.plan_kind}) takes no option {bad[0]!r}")
    return registry.run(method, rec, dict(options), path)


fit_auto.registry_method = "auto"


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

# fit methods: every method of the fit registry (methods/registry.py), with its options
def _register_fits() -> None:
    from calib_cli.methods.registry import FITS

    names = set()
    for name, m in FITS.items():
        register_fit(name, registry_fit(name), options=m.option_names())
        names |= set(m.option_names())
    # any option name is passed on: the chosen fit checks it
    register_fit("auto", fit_auto, options=tuple(sorted(names)))


_register_fits()
