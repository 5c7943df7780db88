"""A tolerance failure is printed in the unit its limit was written in."""

from __future__ import annotations

import numpy as np

from calib_cli.batch.history import CalEntry
from calib_cli.batch.tolerance import check, load_tolerances


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
