"""One fit registry (methods/registry.py) behind `calib fit`, the batch and the
Python API: for each precondition the command line and a batch give the same exit
code and the same message (CONTRACT.md section 5), and the batch exits 1."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest

from calib_cli.io.h5 import read_raw, write_raw

FIX = Path(__file__).parent / "fixtures" / "v0.1.0"


def _cli_vs_batch(run_cli, tmp_path, raw, method, cli_opts=(), batch_opts=""):
    tmp_path.mkdir(parents=True, exist_ok=True)
    code, _, err = run_cli("fit", method, raw, "--out", tmp_path / "c.h5", *cli_opts)
    assert err.startswith("calib: error: ") and err.count("\n") == 1, err
    line = err[len("calib: error: "):].strip()
    pipe = tmp_path / "pipe.toml"
    pipe.write_text(f'[[step]]\nstep = "fit"\nmethod = "{method}"\n{batch_opts}\n')
    bcode, so, _ = run_cli("batch", pipe, raw, "--out", tmp_path / "out", "--json")
    row = json.loads(so)["inputs"][0]
    assert bcode == 1 and row["status"] == "failed"
    assert row["exit_code"] == code, (row, line)
    assert line in row["error"], (row["error"], line)
    assert not (tmp_path / "c.h5").exists()
    return code, line


def _variant(tmp_path, src, **changes):
    rec = dataclasses.replace(read_raw(src), **changes)
    out = tmp_path / "variant.h5"
    write_raw(out, rec, [str(src)])
    return out


def test_redundant_recording_to_a_triad_fit_is_3(run_cli, tmp_path):
    for method in ("accel", "gyro", "align", "turntable"):
        code, line = _cli_vs_batch(run_cli, tmp_path / method, FIX / "raw_rimu.h5", method)
        assert code == 3 and "use `calib fit rimu`" in line and str(FIX / "raw_rimu.h5") in line


def test_triad_recording_to_fit_rimu_is_3(run_cli, tmp_path):
    code, line = _cli_vs_batch(run_cli, tmp_path, FIX / "raw_static.h5", "rimu")
    assert code == 3 and "use `calib fit accel`" in line


def test_no_rotating_segment_is_4(run_cli, tmp_path):
    code, line = _cli_vs_batch(run_cli, tmp_path, FIX / "raw_static.h5", "turntable")
    assert code == 4 and "rotating" in line


def test_too_few_static_positions_is_4(run_cli, tmp_path):
    rec = read_raw(FIX / "raw_static.h5")
    raw = _variant(tmp_path, FIX / "raw_static.h5", segments=rec.segments[:1])
    code, line = _cli_vs_batch(run_cli, tmp_path, raw, "align")
    assert code == 4 and ">= 2 static positions" in line


def test_counts_where_si_is_needed_is_3(run_cli, tmp_path):
    raw = _variant(tmp_path, FIX / "raw_static.h5", units={"accel": "count", "gyro": "count"})
    code, line = _cli_vs_batch(run_cli, tmp_path, raw, "turntable")
    assert code == 3 and "SI units" in line


def test_missing_sensor_is_3(run_cli, tmp_path):
    raw = _variant(tmp_path, FIX / "raw_static.h5", gyro=None)
    code, line = _cli_vs_batch(run_cli, tmp_path, raw, "gyro")
    assert code == 3 and "needs gyro data" in line


@pytest.mark.parametrize("method,cli,batch,needle", [
    ("turntable", ("--table-tilt-deg", "20.5"), "table_tilt_deg = 20.5", "--table-tilt-deg"),
    ("align", ("--turn-sigma-deg", "-1.5"), "turn_sigma_deg = -1.5", "--turn-sigma-deg"),
])
def test_bad_option_value_is_3(run_cli, tmp_path, method, cli, batch, needle):
    code, line = _cli_vs_batch(run_cli, tmp_path, FIX / "raw_static.h5", method, cli, batch)
    assert code == 3 and needle in line


def test_registry_is_what_batch_and_api_offer():
    from calib_cli.api import FITS as api_fits
    from calib_cli.batch.registry import FITS as batch_fits
    from calib_cli.batch.steps import registry_fit  # noqa: F401  (registers the built-ins)
    from calib_cli.methods.registry import FITS

    assert set(FITS) <= set(batch_fits) and set(batch_fits) - set(FITS) == {"auto"}
    assert "table_tilt_deg" in batch_fits["turntable"].options
    assert api_fits is FITS
