"""calib diagnose RAW --method METHOD --out DIAG.h5 [--json] [--report DIR]

Find the effect the model lacks, name it, add it and show the gap shrink
(docs/diagnose.md)."""

from __future__ import annotations

import click
import numpy as np
from rich.table import Table

from calib_cli.cli.common import Ctx, info, out_console, print_json, to_jsonable
from calib_cli.cli.main import cli
from calib_cli.io.h5 import read_raw
from calib_cli.methods.registry import diagnosable, method_of_plan_kind

COMPLETE_COMMAND = True  # every subcommand lives here: loaded alone (cli/main.py)


def _render(j: dict) -> None:
    t = Table(title=f"calib diagnose ({j['method']}): base model {', '.join(j['base_model'])}")
    for c in ("step", "effect", "score", "threshold", "RMS before", "RMS after"):
        t.add_column(c)
    t.add_row("0", "(base model)", "", "", "", f"{j['residual_rms_initial']:.3f}")
    for i, s in enumerate(j["steps"]):
        t.add_row(str(i + 1), s.get("with") or f"{s['sensor']} {s['effect']}".strip(),
                  f"{s['score']:.1f}",
                  f"{s['threshold']:.1f}", f"{s['residual_rms_before']:.3f}",
                  f"{s['residual_rms_after']:.3f}")
    out_console.print(t)
    for i, s in enumerate(j["steps"]):
        out_console.print(f"step {i + 1}: {s['evidence']}")
    out_console.print(f"noise floor {j['noise_rms']:.3f}; final residual "
                      f"{j['residual_rms_final']:.3f} ({j['gap_left']:.2f}x the floor)")
    if not j["steps"]:
        out_console.print("no candidate passed its threshold: the base model explains the data "
                          "down to the noise")
    for k, v in j["untested"].items():
        out_console.print(f"not tested: {k}: {v}")
    for n in j["notes"]:
        out_console.print(f"note: {n}")
    if j.get("fit_command"):
        out_console.print(f"the calibration with these effects: {j['fit_command']}")


@cli.command("diagnose")
@click.argument("raw", type=click.Path(dir_okay=False))
@click.option("--method", required=True, type=click.Choice(diagnosable()),
              help="The method whose base model is diagnosed (its fit's own model).")
@click.option("--out", required=True, type=click.Path(dir_okay=False))
@click.option("--base", type=click.Choice(["full", "diagonal"]), default="full",
              show_default=True, help="diagonal: start from diagonal scale factors "
                                      "(misalignment becomes a candidate).")
@click.option("--alpha", type=float, default=0.01, show_default=True,
              help="False-alarm probability per round (shared over its candidates).")
@click.option("--noise", type=click.Choice(["auto", "hf"]), default="auto", show_default=True,
              help="Noise floor: hf = white noise from the high-frequency content; auto = the "
                   "same, raised to the within-segment scatter of 0.5 s means where that is "
                   "significantly larger (coloured or drifting noise).")
@click.option("--json", "as_json", is_flag=True, help="One JSON object (docs/contract.md section 5).")
@click.option("--report", "report_dir", type=click.Path(file_okay=False),
              help="Write PNG plots and summary.md to this directory.")
@click.option("--calibration", "cal_out", type=click.Path(dir_okay=False),
              help="Also write the final model as an ordinary calibration file (DIAG.h5 "
                   "holds the same calibration).")
def diagnose_cmd(raw, method, out, base, alpha, noise, as_json, report_dir, cal_out):
    """Find the missing effect, name it, add it and show the gap shrink."""
    from calib_cli.io.diag_h5 import write_diagnosis
    from calib_cli.methods.registry import FITS
    from calib_cli.methods.registry import diagnose as run_diagnose

    if not 0 < alpha < 1:
        raise click.BadParameter("--alpha must be in (0, 1)")
    if cal_out:
        import os

        if os.path.abspath(cal_out) == os.path.abspath(out):
            raise click.UsageError("--calibration and --out name the same file (DIAG.h5 holds "
                                   "the calibration already)")
    rec = read_raw(raw)
    if method != "gyro":  # static positions that do not see gravity: exit 3 (issue 37)
        __import__("calib_cli.methods.segstats").methods.segstats.check_gravity_seen(rec, raw)
    from calib_cli.cli.progress import bar
    from calib_cli.errors import CalibError

    own = FITS[method].diagnose.own  # the method's own equations (gyro), not bins
    with bar("diagnose"):
        try:
            d = run_diagnose(method, rec, base=base, alpha=alpha, noise=noise)
        except CalibError as exc:  # the core does not know the file: name it, and the
            exc.path = exc.path or raw  # method the recording's plan is for
            right = method_of_plan_kind(rec.plan_kind)
            if right and right != method and f"--method {right}" not in exc.message:
                exc.message += f" (a {rec.plan_kind} plan: --method {right})"
            raise
    if own and noise != "auto":
        info(f"--noise does not apply to --method {method} (the {method} fit's own noise "
             "estimate)")
    j = to_jsonable(d.to_json())
    j["fit_command"] = d.fit_command(str(raw), str(cal_out or "CAL.h5"))
    cal = d.calibration(rec)
    if own:
        residuals = {("initial" if i == 0 else f"step{i}"):
                     {k: np.asarray(v, float).reshape(-1, 1) for k, v in r.residuals.items()}
                     for i, r in enumerate(d.results)}
        bins = {"time": np.zeros(0), "segment": np.zeros(0, int), "count": np.zeros(0)}
        noise_sigma = {"gyro": np.asarray(cal.stats.get("gyro_noise_sigma", []), float)}
    else:
        pb = d.problem
        residuals = {"initial": d.fits[0].residual_blocks(pb)}
        for i, f in enumerate(d.fits[1:]):
            residuals[f"step{i + 1}"] = f.residual_blocks(pb)
        bins = {"time": pb.bin_t, "segment": pb.bin_seg, "count": pb.counts}
        noise_sigma = d.noise_sigma
    write_diagnosis(out, j, bins, residuals, noise_sigma, [raw], rec.serial, calibration=cal)
    if cal_out:
        from calib_cli.io.h5 import write_calibration

        write_calibration(cal_out, cal, [raw])
    if report_dir:
        from calib_cli.io.outpath import atomic_dir
        from calib_cli.report.diagnose_report import write_gyro_report, write_report

        with atomic_dir(report_dir) as tmp:
            (write_gyro_report if own else write_report)(d, tmp, source=str(raw))
        info(f"report -> {report_dir}")
    if as_json:
        print_json(j)
    elif not Ctx.quiet:
        _render(j)
    info(f"-> {out}")
    return 0


def show_diagnosis(files, as_json, covariance):
    """The calibration of the final model, with the diagnosis's keys added."""
    from calib_cli.io.diag_h5 import read_diagnosis

    j = read_diagnosis(files[0])
    if as_json:
        from calib_cli.cli.cmd_show import calibration_json
        from calib_cli.errors import InputError

        try:
            obj = calibration_json(files[0], covariance)
        except InputError:  # an older diagnosis file: no calibration in it
            obj = {}
        obj.update(j)
        print_json(obj)
    else:
        _render(j)
    return 0


def _register():
    from calib_cli.cli.cmd_show import SHOWERS

    SHOWERS["diagnosis"] = show_diagnosis


_register()
