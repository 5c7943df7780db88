"""calib apply CAL.h5 RAW.h5 --out CORRECTED.h5 (chunked)."""

from __future__ import annotations

import click
import numpy as np

from calib_cli.cli.common import info, json_output_option, output_json
from calib_cli.cli.main import cli
from calib_cli.io.apply_file import CHUNK, apply_file  # noqa: F401  (CHUNK re-exported)

COMPLETE_COMMAND = True  # every subcommand lives here: loaded alone (cli/main.py)


@cli.command("apply")
@click.argument("cal", type=click.Path(dir_okay=False))
@click.argument("raw", type=click.Path(dir_okay=False))
@click.option("--out", required=True, type=click.Path(dir_okay=False))
@click.option("--temp", "temp_c", type=float, default=None,
              help="Constant temperature (degC) for a thermal calibration when the recording "
                   "has no temperature column.")
@click.option("--extrapolate", is_flag=True,
              help="Correct data outside the calibrated temperature range (docs/thermal.md).")
@json_output_option
def apply_cmd(cal, raw, out, temp_c=None, extrapolate=False, as_json=False):
    """Correct a recording with a calibration: f = K^-1 (A - b), w = G^-1 (W - d - D f).

    A redundant-unit (RIMU) calibration gives the corrected single-axis outputs
    (m - b) / (1 + ks) and the body-frame estimates samples/accel_body and
    samples/gyro_body, x = (H^T H)^-1 H^T c (docs/rimu.md). A thermal calibration
    uses the temperature column (or --temp) and refuses data outside its
    range by more than 5 degC unless --extrapolate (docs/thermal.md)."""
    from calib_cli.cli.progress import bar

    _check_order(cal, raw)
    with bar("apply") as cb:
        n, chans = apply_file(cal, raw, out, temp_c, extrapolate, progress=cb)
    info(f"corrected {n} samples ({', '.join(chans)}) -> {out}")
    if as_json:
        output_json(out, "corrected")
    return 0


def corrected_norms(path):
    """|f| of each static segment of a corrected file (for checks and reports)."""
    from calib_cli.io.h5 import read_raw

    rec = read_raw(path, kinds=("corrected",))
    return {s.label: float(np.linalg.norm(rec.accel[s.slice].mean(0)))
            for s in rec.static_segments()}


def _check_order(cal: str, raw: str) -> None:
    """CAL first, then RAW: say so when the two are the other way round."""
    from pathlib import Path

    from calib_cli.errors import InputError
    from calib_cli.io.h5 import file_kind

    def kind(p):
        try:
            return file_kind(p) if Path(p).is_file() else None
        except Exception:  # noqa: BLE001 - not a calib file: apply's own check says so
            return None

    if kind(cal) in ("raw", "corrected") and kind(raw) in ("calibration", "diagnosis"):
        raise InputError(f"a recording where the calibration belongs: the calibration comes "
                         f"first: calib apply {raw} {cal} --out CORRECTED.h5", cal)
