"""calib export CAL.h5 --format json|yaml|c-header|csv|kalibr|px4|ardupilot [--out FILE]"""

from __future__ import annotations

import sys
from pathlib import Path

import click

from calib_cli.cli.common import info, json_output_option, output_json
from calib_cli.cli.main import cli
from calib_cli.io import escape
from calib_cli.io.export import ALL_FORMATS, export_object, to_c_header, to_csv, to_json, to_yaml
from calib_cli.io.h5 import atomic_path, provenance, read_calibration, sha256_file

COMPLETE_COMMAND = True  # every subcommand lives here: loaded alone (cli/main.py)


class PrefixError(click.ClickException):
    """A bad --prefix: usage error (exit 2), one line on stderr."""

    exit_code = 2

    def show(self, file=None):
        click.echo(f"calib: error: {self.format_message()}", err=True)


@cli.command("export")
@click.argument("cal", type=click.Path(dir_okay=False))
@click.option("--format", "fmt", type=click.Choice(ALL_FORMATS), required=True,
              help="json | yaml | c-header | csv | kalibr | px4 | ardupilot (docs/export.md).")
@click.option("--out", type=click.Path(dir_okay=False), help="Output file (default: stdout).")
@click.option("--float", "single", is_flag=True, help="c-header: float instead of double.")
@click.option("--prefix", default="calib", show_default=True,
              help="c-header: prefix of the names (CALIB_ACCEL_KINV, calib_correct_accel); "
                   "a C identifier: a letter, then letters, digits or '_', at most 32.")
@click.option("--allan", "allan_path", type=click.Path(dir_okay=False),
              help="kalibr: noise densities and random walks from this 'allan' file.")
@click.option("--raw", "raw_path", type=click.Path(dir_okay=False),
              help="kalibr without --allan: noise densities from this raw file's static noise.")
@click.option("--rostopic", default="/imu0", show_default=True, help="kalibr: the IMU topic.")
@click.option("--instance", type=int,
              help="px4/ardupilot: the IMU instance the parameters are for (PX4 CAL slot 0-3; "
                   "ArduPilot 0-4 = IMUs 1-5); default: the one in force in the log, else 0.")
@click.option("--residual", is_flag=True,
              help="px4/ardupilot: write the fit of already corrected data as it is (a residual "
                   "on top of the parameters in force, labelled so), not composed with them.")
@click.option("--in-force", "in_force_path", type=click.Path(dir_okay=False),
              help="px4/ardupilot: the parameters in force when the data was logged (a "
                   "QGroundControl .params or Mission Planner .parm file), instead of the log's.")
@json_output_option
def export_cmd(cal, fmt, out, single, prefix, allan_path, raw_path, rostopic, instance,
               residual, in_force_path, as_json=False):
    """Export the correction (K^-1, biases, D) for firmware and other tools.

    px4/ardupilot: a fit on data the firmware had already corrected (imported from
    sensor_combined, IMU or ACC) is composed with the parameters in force into an
    absolute calibration, or exits 4 saying why it cannot be (docs/export.md).
    With --json (needs --out), the output object is printed instead of the export."""
    if as_json and not out:
        raise click.UsageError("--json needs --out (without it the export itself goes to stdout)")
    try:
        escape.c_identifier(prefix, "--prefix")
    except ValueError as exc:
        raise PrefixError(str(exc)) from None
    c = read_calibration(cal)
    from calib_cli.io.validate import check_calibration

    check_calibration(c, cal)
    prov = provenance(cal)
    prov["sha256"] = sha256_file(cal)
    source = Path(cal).name
    meta: dict = {}
    if fmt not in ("px4", "ardupilot") and (residual or in_force_path or instance is not None):
        raise click.UsageError("--instance, --residual and --in-force are for --format px4 "
                               "and ardupilot")
    if fmt in ("kalibr", "px4", "ardupilot"):
        from calib_cli.io.export_autopilot import export_for_tool
        from calib_cli.io.h5 import read_source

        in_force = None
        if in_force_path:
            from calib_cli.io.fc_params import read_params_file

            fw, in_force = read_params_file(in_force_path)
            if fw is not None and fw != fmt:
                from calib_cli.errors import InputError

                raise InputError(f"holds {fw} parameters, not {fmt} ones", in_force_path)
        allan = raw = None
        if allan_path:
            from calib_cli.io.allan_h5 import read_allan

            allan = read_allan(allan_path)
        if raw_path:
            from calib_cli.io.h5 import read_raw

            raw = read_raw(raw_path)
        text, warnings, meta = export_for_tool(c, fmt, source, cal, allan, raw, rostopic,
                                               instance, data_source=read_source(cal),
                                               residual=residual, in_force=in_force)
        warnings = list(warnings)
        if meta.get("mode") == "composed":
            info(f"composed with the {fmt} parameters in force "
                 f"({len(meta['in_force'])} read) into an absolute calibration")
        elif meta.get("mode") == "residual":
            info("warning: --residual: the values are a residual on top of the parameters "
                 "in force, not an absolute calibration")
        for w in warnings:
            info(f"warning: {w}")
    else:
        warnings = []
    if fmt == "c-header":
        text = to_c_header(c, prov, source, single=single, prefix=prefix)
    elif fmt not in ("kalibr", "px4", "ardupilot"):
        obj = export_object(c, prov, source)
        text = {"json": to_json, "yaml": to_yaml}[fmt](obj) if fmt != "csv" else to_csv(c, obj)
    if out:
        with atomic_path(out) as tmp, open(tmp, "w", encoding="utf-8") as fh:
            fh.write(text)
        info(f"-> {out}")
        if as_json:
            output_json(out, fmt, warnings, {"export": meta} if meta else None)
    else:
        sys.stdout.write(text)
    return 0
