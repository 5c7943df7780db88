"""A tolerance failure is printed in the unit its limit was written in."""

from __future__ import annotations

import numpy as np
import pytest

from calib_cli.io.history import CalEntry
from calib_cli.io.tolerance import check, load_tolerances


def _entry():
    return CalEntry("a.h5", "a.h5", "SN1", "accel", "t", "t",
                    {"accel_bias": np.array([0.05, 0.0, 0.0]), "accel_K": np.eye(3)},
                    {"accel_bias": np.full(3, 1e-4), "accel_K": np.full((3, 3), 1e-5)},
                    {"accel_bias": "m/s^2", "accel_K": "1"})


def test_failure_in_the_limits_unit(tmp_path):
    tol = tmp_path / "tol.toml"
    tol.write_text("[param.accel_bias]\nmin_mg = -2\nmax_mg = 2\n"
                   "[param.accel_K]\nmax = 0.5\n")
    res = check(_entry(), [], load_tolerances(tol))
    assert res["status"] == "fail"
    line = next(f for f in res["failures"] if f.startswith("accel_bias"))
    # 0.05 m/s^2 = 5.09858 mg, against the limit as written: 2 mg
    assert "= 5.09858 mg above max 2 mg" in line, line
    assert any(f.startswith("accel_K") and "above max 0.5" in f for f in res["failures"])


@pytest.mark.parametrize("line,key", [
    ("min_mg = inf", "min_mg"), ("max_mg = -inf", "max_mg"), ("max_mg = 1e400", "max_mg"),
    ("max_change_sigma = nan", "max_change_sigma"), ("max_change_sigma = inf", "max_change_sigma"),
    ("max = true", "max"), ('max = "1"', "max"), ("max_change_sigma = true", "max_change_sigma"),
    ("min = [1, 2, inf]", "min"), ('min = [1, "2", 3]', "min"), ("min = [[1, 2], [3]]", "min"),
])
def test_tolerance_values_typed_and_finite(tmp_path, line, key):
    """Issue 37 point 14: a bound that is not a finite number (or an array of them) is
    exit 3 naming the file and the key, never a gate that passes everything."""
    from calib_cli.errors import InputError

    tol = tmp_path / "tol.toml"
    tol.write_text(f"[param.accel_bias]\n{line}\n")
    with pytest.raises(InputError) as exc:
        load_tolerances(tol)
    assert exc.value.exit_code == 3 and exc.value.path == str(tol)
    assert f"param.accel_bias.{key}" in exc.value.line()


def test_tolerance_cli_exit_3_and_nan_array_entry_is_no_bound(tmp_path, run_cli):
    tol = tmp_path / "tol.toml"
    tol.write_text("[param.accel_bias]\nmax_mg = 1e400\n")
    pipe = tmp_path / "p.toml"
    pipe.write_text('[[step]]\nstep = "fit"\nmethod = "accel"\n')
    code, _, err = run_cli("batch", pipe, tmp_path, "--out", tmp_path / "o", "--tolerances", tol)
    assert code == 3 and str(tol) in err and "max_mg" in err
    tol.write_text("[param.accel_bias]\nmax = [nan, 0.01, 0.01]\n")  # nan: no bound there
    res = check(_entry(), [], load_tolerances(tol))
    assert res["failures"] == [] and res["status"] == "pass"


def test_a_rule_not_evaluated_is_named():
    """max_change_sigma without the unit's earlier calibrations: "incomplete", naming the
    rule; a key the calibration does not report is listed."""
    from calib_cli.io.tolerance import ParamTolerance, evaluate

    tols = {"accel_bias": ParamTolerance("accel_bias", None, None, 5.0),
            "gyro_K": ParamTolerance("gyro_K", None, np.asarray(2.0), None)}
    res = evaluate(_entry(), None, tols)
    assert res["status"] == "incomplete" and res["not_reported"] == ["gyro_K"]
    assert res["not_evaluated"][0].startswith("param.accel_bias.max_change_sigma: needs")
    assert evaluate(_entry(), [], tols)["status"] == "pass"  # a first calibration: nothing to compare
