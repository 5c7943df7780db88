"""calib fit gyro RAW --out CAL [--accel ACCEL_CAL]"""

from __future__ import annotations

import json

import click

from calib_cli.cli.cmd_fit import fit_group, json_option, need_raw_out, run_with, save, with_options
from calib_cli.cli.common import info
from calib_cli.io.h5 import read_calibration, read_raw


@fit_group.command("gyro")
@click.argument("raw", required=False, type=click.Path(dir_okay=False))
@click.option("--out", type=click.Path(dir_okay=False),
              help="Calibration file to write (CAL.h5; required unless --list-effects).")
@click.option("--accel", "accel_path", type=click.Path(dir_okay=False),
              help="Accelerometer calibration to take the gravity directions from "
                   "(default: fit it from RAW, `fit accel --method auto`).")
@click.option("--g-sensitivity", type=click.Choice(["auto", "on", "off"]), default="auto",
              show_default=True, help="Fit gyro_D (auto: when the static positions make it "
                                      "observable).")
@with_options
@json_option
def fit_gyro_cmd(raw, out, accel_path, g_sensitivity, with_text, list_effects, with_base,
                 with_noise, as_json):
    """Gyro bias, scale factors and misalignments (and g-sensitivity) from the
    rotations between static positions and turns of known angle (docs/gyro.md)."""
    from calib_cli.errors import InputError
    from calib_cli.methods import registry

    registry.options_from("gyro", g_sensitivity=g_sensitivity)
    acc = read_calibration(accel_path) if accel_path else None
    if acc is not None and "accel_K" not in acc.params:
        raise InputError("not an accelerometer calibration (no accel_K)", accel_path)
    independent = False
    if acc is not None and raw:
        from calib_cli.io.h5 import provenance, sha256_file

        try:
            used = json.loads(provenance(accel_path).get("input_sha256", "{}")).values()
        except ValueError:
            used = ()
        # fitted on other data: its errors are independent of RAW's and are propagated
        independent = sha256_file(raw) not in set(used)
        info("accelerometer calibration " + ("from other data: its uncertainty is propagated "
                                             "into the gyro parameters" if independent else
                                             "from this recording"))
    if run_with("gyro", raw, out, with_text, list_effects, with_base, with_noise, as_json,
                accel=acc, accel_independent=independent,
                extra_inputs=[accel_path] if accel_path else []):
        return
    need_raw_out(raw, out)
    rec = read_raw(raw)
    from calib_cli.cli.progress import bar

    opts = registry.GyroOptions(g_sensitivity, acc, independent)
    with bar("fit gyro"):
        res = registry.run("gyro", rec, opts, raw)
    save(res, raw, out, [accel_path] if accel_path else [], rec=rec, as_json=as_json)
    st = res.stats
    for w in st.get("warnings", []):
        info(f"[yellow]warning:[/] {w}")
    tr = st["transition_residual_rms_rad"]
    info(f"{st['n_transitions']} transitions, {st['n_turns']} turns, {st['n_positions']} "
         f"static positions; transition residual RMS "
         f"{'n/a' if tr is None else f'{tr * 180 / 3.141592653589793:.3f} deg'}")
