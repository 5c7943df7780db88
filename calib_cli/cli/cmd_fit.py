"""calib fit METHOD RAW --out CAL: the estimators."""

from __future__ import annotations

import click

from calib_cli.cli.common import info
from calib_cli.cli.main import cli
from calib_cli.cli.progress import bar
from calib_cli.cli.render import render_summary
from calib_cli.io.h5 import read_raw, write_calibration


@cli.group("fit")
def fit_group():
    """Fit a calibration to a raw recording."""


json_option = click.option(
    "--json", "as_json", is_flag=True,
    help="Print the calibration as `calib show --json` does (docs/contract.md section 5) on "
         "stdout and nothing else there (status stays on stderr).")


def save(res, raw, out, extra_inputs=(), rec=None, as_json: bool = False):
    from calib_cli.methods.gross import check_result

    check_result(res, rec)  # never exit 0 with an impossible calibration (issue 15)
    write_calibration(out, res, [raw, *extra_inputs])
    if as_json:
        from calib_cli.cli.cmd_show import calibration_json
        from calib_cli.cli.common import print_json

        print_json(calibration_json(out))
        return
    render_summary(res)
    info(f"-> {out}")


def with_options(f):
    """--with, --list-effects, --base, --noise: a method's base model plus catalogue
    effects (methods/fit_with.py, docs/diagnose.md)."""
    f = click.option("--noise-floor", "with_noise", type=click.Choice(["auto", "hf"]), default="auto",
                     show_default=True,
                     help="With --with: the noise floor, as `calib diagnose --noise` (auto: raised "
                          "to the 0.5 s means' scatter where that is larger; hf: white).")(f)
    f = click.option("--base", "with_base", type=click.Choice(["full", "diagonal"]),
                     default="full", show_default=True,
                     help="With --with: the base model's scale factors (diagonal: needed by "
                          "--with misalignment).")(f)
    f = click.option("--list-effects", is_flag=True,
                     help="List the effects --with accepts, one a line (with RAW: the ones "
                          "this record can excite, and what to record for the others).")(f)
    f = click.option("--with", "with_text", metavar="EFFECT[,EFFECT...]",
                     help="Add catalogue effects to the base model (contract names, optionally "
                          "sensor-qualified: accel.temperature_drift).")(f)
    return f


def run_with(method, raw, out, with_text, list_effects, base, noise, as_json,
             accel=None, accel_independent=False, extra_inputs=()) -> bool:
    """Handle --with / --list-effects; False when neither was given (the plain fit)."""
    if not with_text and not list_effects:
        if base != "full" or noise != "auto":
            raise click.UsageError("--base and --noise-floor apply to --with")
        return False
    from calib_cli.methods import fit_with as fw

    if list_effects:
        pb = None
        if raw:
            from calib_cli.methods.diagnose_problem import build_problem

            if method == "gyro":
                lines = fw.gyro_lines(read_raw(raw), accel, base)
            else:
                pb = build_problem(read_raw(raw), method, noise=noise)
        for e in (lines if raw and method == "gyro" else fw.effect_lines(pb, method, base)):
            if e["excited"] is None:
                click.echo(f"{e['with']}: {e['excites']}")
            elif e["excited"]:
                click.echo(f"{e['with']}: excited by this record ({e['excites']})")
            else:
                click.echo(f"{e['with']}: not excited ({e['why']}); record {e['record']}")
        return True
    if not raw or not out:
        raise click.UsageError("--with needs RAW and --out")
    try:
        effects = fw.parse_with(with_text, method)
        bad = [fw.with_arg(n, s) for n, s in effects
               if method == "gyro" and (s != "gyro" or n not in fw.GYRO_WITH)]
        if bad:
            raise ValueError(f"{', '.join(bad)}: the gyro method takes "
                             f"{', '.join(fw.GYRO_WITH)} (docs/diagnose.md)")
    except ValueError as exc:
        raise click.BadParameter(str(exc), param_hint="--with") from None
    if any(n == "misalignment" for n, _ in effects) and method in ("align", "rimu"):
        raise click.BadParameter(f"the {method} method has no triad misalignment (align: K is "
                                 "the identity; rimu: each sensor's direction is in the base "
                                 "model)", param_hint="--with")
    if any(n == "misalignment" for n, _ in effects) and base != "diagonal":
        raise click.UsageError("--with misalignment needs --base diagonal (the full base model "
                               "already has every misalignment)")
    from calib_cli.errors import EstimationError

    rec = read_raw(raw)
    try:
        if method == "gyro":
            res = fw.fit_with_gyro(rec, effects, base, accel, accel_independent)
        else:
            res, _, _ = fw.fit_with(rec, method, effects, base=base, noise=noise)
    except EstimationError as exc:
        exc.path = exc.path or raw
        raise
    save(res, raw, out, list(extra_inputs), rec=rec, as_json=as_json)
    return True


@fit_group.command("accel")
@click.argument("raw", required=False, type=click.Path(dir_okay=False))
@click.option("--out", type=click.Path(dir_okay=False),
              help="Calibration file to write (CAL.h5; required unless --list-effects).")
@click.option("--method", type=click.Choice(["auto", "vector", "scalar"]), default="auto",
              show_default=True, help="vector: known attitudes; scalar: |a| = g.")
@with_options
@json_option
def fit_accel_cmd(raw, out, method, with_text, list_effects, with_base, with_noise, as_json):
    """Static multi-position accelerometer fit: A = b + K f."""
    from calib_cli.methods import registry

    if (with_text or list_effects) and method != "auto":
        raise click.UsageError("--method applies to the plain fit; with --with the positions "
                               "decide (known attitudes: bias + full K; unknown: the scalar "
                               "model)")
    if run_with("accel", raw, out, with_text, list_effects, with_base, with_noise, as_json):
        return
    need_raw_out(raw, out)
    opts = registry.options_from("accel", method=method)
    rec = read_raw(raw)
    with bar("fit accel"):
        res = registry.run("accel", rec, opts, raw)
    save(res, raw, out, rec=rec, as_json=as_json)


def need_raw_out(raw, out) -> None:
    """RAW and --out are optional only for --list-effects."""
    if not raw:
        raise click.UsageError("Missing argument 'RAW'.")
    if not out:
        raise click.UsageError("Missing option '--out'.")
