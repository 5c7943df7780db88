"""The built-in batch steps (registered in registry.py, which names them by strings
and never imports this module). A fit step of a method of the method table runs it
exactly as `calib fit METHOD` does."""

from __future__ import annotations

import json

from calib_cli.batch.registry import WITH_KEYS


def import_step(run) -> None:
    """CSV + plan -> raw.h5: exactly `calib import csv` (the streaming importer)."""
    from calib_cli.io.csvlog import import_csv_stream
    from calib_cli.io.plan import load_plan

    o = run.options
    plan = load_plan(o["plan"])
    import_csv_stream(run.inputs["source"], plan, run.out, [run.inputs["source"], o["plan"]],
                      float(o.get("window_s", 1.0)), float(o.get("threshold", 3.0)),
                      float(o.get("min_static_s", 1.0)))


def fit_step(run, d) -> None:
    """raw.h5 -> cal.h5 by the fit step ``d`` (a StepDef). The methods of the table (and
    "auto") go through ``registry.run`` (methods/registry.py), exactly as `calib fit
    METHOD`: the same file options read the same way (io/fit_inputs.py), the same checks."""
    from calib_cli.io.h5 import read_raw, write_calibration
    from calib_cli.methods.registry import FITS

    raw = run.inputs["raw"]
    rec = read_raw(raw)
    if d.method in FITS or d.method == "auto":
        run_fit = fit_auto if d.method == "auto" else registry_fit(d.method)
        res, files = run_fit(rec, path=raw, **run.options)
        write_calibration(run.out, res, [raw, *files])
        return
    fn = d.function()  # a fit registered from outside (registry.py's conventions)
    extra = {f"{k}_path": v for k, v in run.inputs.items() if k not in ("raw", "source")}
    res = fn(rec, **run.options, **extra)
    from calib_cli.methods.gross import check_result, screen_fit

    screen_fit(res, rec, lambda r: fn(r, **run.options, **extra))
    check_result(res, rec)  # an impossible calibration is exit 4, not "done"
    write_calibration(run.out, res, [raw, *extra.values()])


def _run_method(method: str, rec, path, options: dict):
    """The table's method on a recording, options as in a pipeline's step table (the
    command line's names; calibration options are file paths)."""
    from calib_cli.errors import InputError
    from calib_cli.io.fit_inputs import read_file_options
    from calib_cli.methods import registry

    options = dict(options)
    w = {k: options.pop(k) for k in WITH_KEYS if k in options}
    req = None
    if w.get("with"):
        try:
            req = registry.parse_with(method, str(w["with"]), w.get("with_base", "full"),
                                      w.get("with_noise_floor", "auto"))
        except ValueError as exc:
            raise InputError(f"with: {exc}") from None
    elif len(w):
        raise InputError(f"{', '.join(w)} apply to with = \"EFFECT,...\"")
    options, files = read_file_options(method, options, path)
    return registry.run(method, rec, options, path, with_=req), files


def registry_fit(method: str):
    """The batch's fit function of a method of the table."""

    def fit(rec, path=None, **options):
        return _run_method(method, rec, path, options)

    fit.registry_method = method
    fit.__name__ = f"fit_{method}"
    return fit


def fit_auto(rec, path=None, **options):
    """Pick the fit from the recording's plan kind (an archive of mixed experiments
    runs through one pipeline); options go to that fit unchanged."""
    from calib_cli.errors import EstimationError
    from calib_cli.methods import registry

    method = registry.method_of_plan_kind(rec.plan_kind)
    if method is None:
        kinds = sorted({k for m in registry.FITS.values() for k in m.plan_kinds})
        raise EstimationError(f"no batch fit for plan kind {rec.plan_kind!r} (known: "
                              f"{', '.join(kinds)})")
    bad = sorted(set(options) - set(registry.FITS[method].option_names()) - set(WITH_KEYS))
    if bad:
        raise EstimationError(f"fit {method} (plan kind {rec.plan_kind}) takes no option {bad[0]!r}")
    return _run_method(method, rec, path, options)


fit_auto.registry_method = "auto"


def apply_step(run) -> None:
    """cal.h5 + raw.h5 -> corrected.h5: exactly `calib apply` (chunked)."""
    from calib_cli.io.apply_file import apply_file

    apply_file(run.inputs["calibration"], run.inputs["raw"], run.out)


def export_step(run) -> None:
    """cal.h5 -> the contract's JSON object (as `calib show --json`), plus a
    "batch" key with the provenance the up-to-date check reads back."""
    from calib_cli.io.contract_json import calibration_json, to_jsonable

    obj = calibration_json(run.inputs["calibration"], bool(run.options.get("covariance")))
    obj["batch"] = dict(run.stamp)
    with open(run.out, "w", encoding="utf-8") as fh:
        fh.write(json.dumps(to_jsonable(obj), indent=2, sort_keys=False) + "\n")
