"""calib fit turntable RAW --out CAL: rotating-table calibration (docs/turntable.md)."""

from __future__ import annotations

import click
from click import UsageError

from calib_cli.cli.cmd_fit import fit_group, need_raw_out, run_with, save, with_options
from calib_cli.cli.common import info
from calib_cli.io.h5 import read_raw


def _auto_or_number(text: str, name: str):
    """'auto' or a number (a bad value is a usage error naming the option)."""
    if str(text).strip().lower() == "auto":
        return "auto"
    try:
        return float(text)
    except ValueError:
        raise UsageError(f"{name} must be auto or a number, got {text!r}") from None


@fit_group.command("turntable")
@click.argument("raw", required=False, type=click.Path(dir_okay=False))
@click.option("--out", type=click.Path(dir_okay=False),
              help="Calibration file to write (CAL.h5; required unless --list-effects).")
@click.option("--lever-arm", "lever_arm", type=click.Choice(["off", "known", "estimate"]),
              default="estimate", show_default=True,
              help="off: no centripetal terms; known: each cycle's lever_arm_m from the plan; "
                   "estimate: two components per cycle (the axial one is unobservable).")
@click.option("--proof-mass", "proof_mass", type=click.Choice(["auto", "off", "estimate"]),
              default="auto", show_default=True,
              help="Proof-mass offsets p_ij (best with tilted cycles, docs/turntable.md). auto: "
                   "estimated, entries the record cannot determine reported with sigma null; "
                   "off: held at 0.")
@click.option("--tangential", type=click.Choice(["on", "off"]), default="on", show_default=True,
              help="dw/dt x r term from the differentiated gyros (off: blocks in which the table "
                   "accelerates are left out of the accelerometer measurements).")
@click.option("--block", "block_s", type=float, default=0.2, show_default=True,
              help="Measurement block length (s): the data are averaged over blocks.")
@click.option("--axis-sigma-mrad", default="auto", show_default=True,
              help="How well the table axis stays fixed (per block, 1-sigma, mrad), or "
                   "auto: estimated from the data (stats.table_axis_noise_mrad).")
@click.option("--runout-mrad", type=float, default=0.5, show_default=True,
              help="Prior 1-sigma of the table bearing's twice-per-revolution rocking of the "
                   "axis (estimated per cycle); 0: none.")
@click.option("--table-tilt-deg", type=float, default=0.05, show_default=True,
              help="Prior 1-sigma of the table axis's tilt from the plan's direction "
                   "(estimated, one per table axis); 0: take the plan's axis as exact.")
@click.option("--grade", type=click.Choice(["mems", "tactical", "navigation"]), default="mems",
              show_default=True,
              help="Prior widths of the parameters for this grade of unit (docs/turntable.md).")
@click.option("--prior", "priors", multiple=True, metavar="KEY=SIGMA",
              help="Override one prior 1-sigma (SI), e.g. --prior lever_arm=0.1; keys: "
                   "accel_bias accel_K gyro_bias gyro_K gyro_D lever_arm proof_mass_offsets.")
@click.option("--noise", "noise_spec", metavar="accel=SIGMA,gyro=SIGMA",
              help="Per-sample white noise (SI: m/s^2, rad/s) instead of the estimate from the "
                   "data; one value for all axes of a sensor.")
@click.option("--table-encoder", "table_encoder",
              type=click.Choice(["auto", "off", "angle", "rate", "both"]),
              default="auto", show_default=True,
              help="The table's angle and/or rate channels as measurements (angle: zero, "
                   "once-per-revolution error and clock offset estimated; rate: scale error "
                   "and offset estimated): auto uses those the log has that pass the checks.")
@click.option("--json", "as_json", is_flag=True,
              help="Print the result as JSON (docs/contract.md section 5) on stdout.")
@click.option("--plot", type=click.Path(dir_okay=False),
              help="Write the sigma history of the lever arms and proof-mass offsets (PNG).")
@with_options
def fit_turntable_cmd(raw, out, lever_arm, proof_mass, tangential, block_s, axis_sigma_mrad,
                      runout_mrad, table_tilt_deg, grade, priors, noise_spec, table_encoder, as_json, plot,
                      with_text, list_effects, with_base, with_noise):
    """Accelerometer b, K (lower triangular), gyro d, G, D, lever arms and proof-mass
    offsets from rotation cycles on a single-axis table of imprecise angle and rate."""
    from calib_cli.methods import registry

    if run_with("turntable", raw, out, with_text, list_effects, with_base, with_noise, as_json):
        return
    need_raw_out(raw, out)
    from calib_cli.methods.turntable import PRIOR_KEYS

    prior = _key_values(priors, "--prior")
    unknown = sorted(set(prior) - set(PRIOR_KEYS))
    if unknown:
        raise UsageError(f"--prior: unknown key {unknown[0]!r}; expected one of "
                         f"{', '.join(PRIOR_KEYS)}")
    noise = None
    if noise_spec:
        kv = _key_values(noise_spec.split(","), "--noise")
        if set(kv) != {"accel", "gyro"}:
            raise UsageError("--noise needs accel=SIGMA,gyro=SIGMA")
        noise = kv
    opt = registry.options_from("turntable", lever_arm=lever_arm, proof_mass=proof_mass,
                                tangential=tangential, block_s=block_s,
                                axis_sigma_mrad=_auto_or_number(axis_sigma_mrad,
                                                                "--axis-sigma-mrad"),
                                runout_mrad=runout_mrad, table_tilt_deg=table_tilt_deg,
                                grade=grade, prior=prior or None, noise=noise,
                                table_encoder=table_encoder)
    rec = read_raw(raw)
    from calib_cli.cli.progress import bar

    with bar("fit turntable") as cb:
        res = registry.run("turntable", rec, opt, raw, progress=cb)
    clipped = res.stats.get("accel_clipped_samples") or []
    if any(clipped):
        info(f"[yellow]warning:[/] {sum(clipped)} accelerometer samples sit at full scale "
             "(saturated?): the centripetal and tangential terms may exceed the range; the fit "
             "does not model clipping")
    if res.stats.get("accel_noise_inflation", 1.0) > 1.0:
        info(f"[yellow]the model does not explain the accelerometer data:[/] noise widened "
             f"x{res.stats['accel_noise_inflation']:.1f} (lever arms or proof masses missing?)")
    if as_json:
        from calib_cli.cli.cmd_show import calibration_json
        from calib_cli.cli.common import print_json
        from calib_cli.io.h5 import write_calibration

        write_calibration(out, res, [raw])
        print_json(calibration_json(out))
    else:
        save(res, raw, out)
    if plot:
        from calib_cli.report.sections_turntable import sigma_history_plot

        sigma_history_plot(res, plot)
        info(f"sigma history -> {plot}")


def _key_values(items, option: str) -> dict:
    """KEY=NUMBER items -> {key: float}; a malformed one is a usage error."""
    import math

    out = {}
    for item in items:
        key, sep, val = item.partition("=")
        try:
            num = float(val)
        except ValueError:
            num = math.nan
        if not sep or not key.strip() or not math.isfinite(num) or num <= 0:
            raise UsageError(f"{option} expects KEY=POSITIVE_NUMBER, got {item!r}")
        out[key.strip()] = num
    return out
