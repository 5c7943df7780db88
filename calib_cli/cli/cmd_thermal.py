"""calib fit thermal RAW --out CAL [--order N] [--temp-ref DEGC] [--sensor ...] [--base CAL]
[--with thermal_lag] (docs/thermal.md)"""

from __future__ import annotations

import click

from calib_cli.cli.cmd_fit import fit_group, json_option, save
from calib_cli.cli.common import info
from calib_cli.io.h5 import read_calibration, read_raw

THERMAL_EFFECTS = ("thermal_lag",)


@fit_group.command("thermal")
@click.argument("raw", type=click.Path(dir_okay=False))
@click.option("--out", required=True, type=click.Path(dir_okay=False))
@click.option("--order", type=click.IntRange(1, 3), default=None,
              help="Polynomial order in T - T_ref (default: by BIC over 1..3).")
@click.option("--temp-ref", type=float, default=25.0, show_default=True,
              help="Reference temperature T_ref, degC.")
@click.option("--sensor", type=click.Choice(["accel", "gyro", "both"]), default="both",
              show_default=True)
@click.option("--base", "base_path", type=click.Path(dir_okay=False),
              help="A room-temperature calibration whose K (and gyro G) are held.")
@click.option("--with", "with_", default="",
              help="Extra catalogue effects: thermal_lag (first-order lag, tau estimated).")
@json_option
def fit_thermal_cmd(raw, out, order, temp_ref, sensor, base_path, with_, as_json):
    """Bias and scale factor polynomial in temperature on top of the static
    model, from soak steps and/or ramps in known positions (docs/thermal.md)."""
    from calib_cli.errors import InputError
    from calib_cli.methods.thermal import fit_thermal

    effects = [e.strip() for e in with_.split(",") if e.strip()]
    bad = [e for e in effects if e not in THERMAL_EFFECTS]
    if bad:
        raise click.UsageError(f"--with {bad[0]}: the thermal fit takes "
                               f"{', '.join(THERMAL_EFFECTS)}")
    rec = read_raw(raw)
    if rec.temp is None:
        raise InputError("no temperature column (samples/temp): a thermal fit needs the "
                         "unit's temperature", raw)
    base = read_calibration(base_path) if base_path else None
    if base is not None and "accel_K" not in base.params and "gyro_K" not in base.params:
        raise InputError("the base calibration holds no accel_K or gyro_K", base_path)
    sensors = ("accel", "gyro") if sensor == "both" else (sensor,)
    from calib_cli.cli.progress import bar

    with bar("fit thermal"):
        res = fit_thermal(rec, order=order, temp_ref=temp_ref, sensors=sensors, base=base,
                          lag="thermal_lag" in effects)
    save(res, raw, out, [base_path] if base_path else [], as_json=as_json)
    st = res.stats
    info(f"order {st['temp_order']} (T_ref {st['temp_ref_degC']:g} degC, range "
         f"{st['temp_range_degC'][0]:.1f}..{st['temp_range_degC'][1]:.1f} degC)")
