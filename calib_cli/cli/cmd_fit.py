"""calib fit METHOD RAW --out CAL: one subcommand per method of the method table
(methods/registry.py), its options generated from the method's declarations.

Every subcommand reads its files (the recording, calibrations given as options:
io/fit_inputs.py) and hands them to ``registry.run``, the one way a fit runs (the
batch and the Python API call it too). Start-up: this module imports click and the
method table only; h5py, numpy and the estimators are imported when a fit runs
(``calib fit --help`` stays fast)."""

from __future__ import annotations

import click

from calib_cli.cli.main import cli
from calib_cli.cli.method_options import click_option, parse_cli_value
from calib_cli.methods.registry import FITS, Method

COMPLETE_COMMAND = True  # every `calib fit` subcommand is made here (cli/main.py)


@cli.group("fit")
def fit_group():
    """Fit a calibration to a raw recording."""


json_option = click.option(
    "--json", "as_json", is_flag=True,
    help="Print the calibration as `calib show --json` does (docs/contract.md section 5) on "
         "stdout and nothing else there (status stays on stderr).")


def save(res, raw, out, extra_inputs=(), rec=None, as_json: bool = False):
    """Write the calibration (its inputs' hashes in it) and print it."""
    from calib_cli.cli.common import info
    from calib_cli.cli.render import render_summary
    from calib_cli.io.h5 import write_calibration

    write_calibration(out, res, [raw, *extra_inputs])
    if as_json:
        from calib_cli.cli.cmd_show import calibration_json
        from calib_cli.cli.common import print_json

        print_json(calibration_json(out))
        return
    render_summary(res)
    info(f"-> {out}")


# ---------------------------------------------------------------------------
# --with


def with_options(f):
    """--with, --list-effects, --base, --noise-floor: a method's base model plus catalogue
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
    return with_option(f)


def with_option(f, help_text: str = "Add catalogue effects to the base model (contract names, "
                                     "optionally sensor-qualified: accel.temperature_drift)."):
    return click.option("--with", "with_text", metavar="EFFECT[,EFFECT...]", help=help_text)(f)


def _list_effects(m: Method, raw, options, base, noise) -> None:
    from calib_cli.io.h5 import read_raw
    from calib_cli.methods import fit_with as fw

    if m.with_engine == "filter":
        from calib_cli.methods.method import resolve

        lines = resolve(m.with_lines)(read_raw(raw) if raw else None, base)
    elif m.with_engine == "gyro":
        acc = options.get("accel")
        lines = (fw.gyro_lines(read_raw(raw), None if acc is None else acc.value, base) if raw
                 else fw.effect_lines(None, m.name, base))
    else:
        pb = None
        if raw:
            from calib_cli.methods.diagnose_problem import build_problem

            pb = build_problem(read_raw(raw), m.name, noise=noise)
        lines = fw.effect_lines(pb, m.name, base)
    for e in lines:
        if e["excited"] is None:
            click.echo(f"{e['with']}: {e['excites']}")
        elif e["excited"]:
            click.echo(f"{e['with']}: excited by this record ({e['excites']})")
        else:
            click.echo(f"{e['with']}: not excited ({e['why']}); record {e['record']}")


def _run(m: Method, raw, out, as_json, with_text, list_effects, base, noise, outputs, values):
    from calib_cli.methods import registry

    engine = m.with_engine in ("engine", "gyro")
    if not with_text and not list_effects and (base != "full" or noise != "auto"):
        raise click.UsageError("--base and --noise-floor apply to --with")
    given = {k: parse_cli_value(m.option(k), v) for k, v in values.items()}
    given = {k: v for k, v in given.items() if v is not None or m.option(k).optional}
    if list_effects:
        from calib_cli.io.fit_inputs import read_file_options

        _list_effects(m, raw, read_file_options(m.name, given, raw)[0], base, noise)
        return
    if not raw:
        raise click.UsageError("Missing argument 'RAW'.")
    if not out:
        raise click.UsageError("Missing option '--out'.")
    req = None
    if with_text:
        if engine:
            changed = [m.option(k).cli_flag for k, v in given.items()
                       if k not in m.with_uses and v != m.option(k).default]
            if changed:
                raise click.UsageError(f"{changed[0]} applies to the plain fit, not to --with "
                                       "(the base model of --with is the method's own)")
        try:
            req = registry.parse_with(m.name, with_text, base, noise)
        except ValueError as exc:
            raise click.BadParameter(str(exc), param_hint="--with") from None
    from calib_cli.cli.common import info
    from calib_cli.cli.progress import bar
    from calib_cli.io.fit_inputs import read_file_options
    from calib_cli.io.h5 import read_raw

    given, extra = read_file_options(m.name, given, raw)
    rec = read_raw(raw)
    opts = registry.options_from(m.name, given)
    with bar(f"fit {m.name}") as cb:
        res = registry.run(m.name, rec, opts, raw, progress=cb, with_=req)
    save(res, raw, out, extra, rec=rec, as_json=as_json)
    if m.notes is not None:
        from calib_cli.methods.method import resolve

        for line in resolve(m.notes)(res, registry.options_from(m.name, given)):
            info(line)
    for o, writer, words in m.cli_outputs:
        if outputs.get(o.name):
            from calib_cli.methods.method import resolve

            resolve(writer)(res, outputs[o.name])
            info(f"{words} -> {outputs[o.name]}")


def make_fit_command(m: Method) -> click.Command:
    """``calib fit NAME``, from the method's declaration."""
    engine = m.with_engine in ("engine", "gyro")
    cli_opts = [o for o in m.options if o.cli]

    def callback(raw, out, as_json, with_text=None, list_effects=False, with_base="full",
                 with_noise="auto", **values):
        outputs = {o.name: values.pop(o.name, None) for o, _, _ in m.cli_outputs}
        _run(m, raw, out, as_json, with_text, list_effects, with_base, with_noise, outputs,
             values)

    f = callback
    for o, _, _ in reversed(m.cli_outputs):
        f = click.option(o.cli_flag, o.name, type=click.Path(dir_okay=False), help=o.help,
                         metavar=o.metavar)(f)
    f = json_option(f)
    if engine:
        f = with_options(f)
    elif m.with_engine == "own":
        f = with_option(f, f"Extra catalogue effects: {', '.join(m.with_effects)}.")
    elif m.with_engine == "filter":  # catalogue effects on the method's own rows
        f = click.option("--base", "with_base", type=click.Choice(["full", "diagonal"]),
                         default="full", show_default=True,
                         help="With --with: the base model's scale factors (diagonal: "
                              "needed by --with misalignment).")(f)
        f = click.option("--list-effects", is_flag=True,
                         help="List the effects --with accepts, one a line (with RAW: the ones "
                              "this record can excite, and why not the others).")(f)
        f = with_option(f, "Catalogue effects on the base model (accel b, K; gyro d, G), "
                           "optionally sensor-qualified: lever_arm, gyro.g_sensitivity, "
                           "time_offset, gyro.scale_asymmetry (docs/diagnose.md).")
    for o in reversed(cli_opts):
        f = click_option(o)(f)
    f = click.option("--out", type=click.Path(dir_okay=False),
                     help="The calibration file to write (HDF5).")(f)
    f = click.argument("raw", required=False, type=click.Path(dir_okay=False))(f)
    return click.command(m.name, help=m.help or m.summary, short_help=m.summary)(f)


for _m in FITS.values():
    fit_group.add_command(make_fit_command(_m))
