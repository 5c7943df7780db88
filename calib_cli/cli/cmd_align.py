"""calib fit align RAW --out CAL: two-position analytic alignment (docs/align.md)."""

from __future__ import annotations

import click

from calib_cli.cli.cmd_fit import fit_group, json_option, need_raw_out, run_with, save, with_options
from calib_cli.cli.common import info
from calib_cli.io.h5 import read_raw


@fit_group.command("align")
@click.argument("raw", required=False, type=click.Path(dir_okay=False))
@click.option("--out", type=click.Path(dir_okay=False),
              help="Calibration file to write (CAL.h5; required unless --list-effects).")
@click.option("--method", type=click.Choice(["two-position", "classic", "static"]),
              default="two-position", show_default=True,
              help="two-position: any rotation between the positions; classic: the 2- or "
                   "4-position baseline (turns of 180 or 90 deg about the vertical body z); "
                   "static: static data only, the turn neither recorded nor stated (both "
                   "attitudes and the biases from the twelve static equations).")
@click.option("--rotation", type=click.Choice(["auto", "gyro", "plan"]), default="auto",
              show_default=True,
              help="Rotation between positions: gyros integrated through the recorded "
                   "transition, or the plan's turn segments (auto: gyro when recorded).")
@click.option("--gyro", "gyro_mode", type=click.Choice(["auto", "use", "ignore"]), default="auto",
              show_default=True,
              help="Earth-rate equations: auto = grade check decides; use = fail (exit 4) "
                   "when the gyros cannot resolve the earth rate; ignore = accelerometer "
                   "biases and tilt only.")
@click.option("--gyro-k-ppm", type=float, default=None,
              help="Prior 1-sigma of the gyro scale-factor/misalignment entries (ppm, urad) "
                   "that bend the integrated turn [default: 30, or 3000 without earth rate].")
@click.option("--turn-sigma-deg", type=float, default=0.0, show_default=True,
              help="1-sigma error per axis of a plan-stated turn (with --rotation plan).")
@with_options
@json_option
def fit_align_cmd(raw, out, method, rotation, gyro_mode, gyro_k_ppm, turn_sigma_deg,
                  with_text, list_effects, with_base, with_noise, as_json):
    """Accelerometer and gyro biases and the attitude of the first position from
    two (or more) static positions related by a known rotation."""
    if run_with("align", raw, out, with_text, list_effects, with_base, with_noise, as_json):
        return
    need_raw_out(raw, out)
    from calib_cli.methods import registry

    opts = registry.options_from("align", method=method, rotation=rotation, gyro=gyro_mode,
                                 gyro_k_ppm=gyro_k_ppm, turn_sigma_deg=turn_sigma_deg)
    rec = read_raw(raw)
    from calib_cli.cli.progress import bar

    with bar("fit align"):
        res = registry.run("align", rec, opts, raw)
    if method == "static" and res.stats.get("degeneracy"):
        info(f"[yellow]degenerate positions:[/] {res.stats['degeneracy']}; not observable: "
             + ", ".join(res.stats["unobservable"]))
    if not res.stats.get("earth_rate_used", True):
        info(f"[yellow]earth rate not used:[/] {res.stats.get('grade_check')}; heading not "
             "estimated, accelerometer biases and tilt only")
    if res.stats.get("observability"):
        info(res.stats["observability"])
    save(res, raw, out, rec=rec, as_json=as_json)

