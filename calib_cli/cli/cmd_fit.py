"""calib fit METHOD RAW --out CAL: the estimators."""

from __future__ import annotations

import click

from calib_cli.cli.common import info
from calib_cli.cli.main import cli
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


@fit_group.command("accel")
@click.argument("raw", type=click.Path(dir_okay=False))
@click.option("--out", required=True, type=click.Path(dir_okay=False))
@click.option("--method", type=click.Choice(["auto", "vector", "scalar"]), default="auto",
              show_default=True, help="vector: known attitudes; scalar: |a| = g.")
@json_option
def fit_accel_cmd(raw, out, method, as_json):
    """Static multi-position accelerometer fit: A = b + K f."""
    from calib_cli.methods import registry

    opts = registry.options_from("accel", method=method)
    rec = read_raw(raw)
    res = registry.run("accel", rec, opts, raw)
    save(res, raw, out, rec=rec, as_json=as_json)
