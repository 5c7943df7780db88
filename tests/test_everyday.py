"""Everyday use (issue 35): one display of values, sigmas and units (counts stay
counts, thermal powers, "fixed"), full-width tables off a terminal, plan check
printed as fit prints, every option with a help line, tidy numbers."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from calib_cli.model import display as D

ROOT = Path(__file__).resolve().parent.parent


def test_thermal_columns_carry_their_power():
    assert D.display_of("accel_temp_bias", "m/s^2/degC^k", (0, 0))[1] == "mg/degC"
    assert D.display_of("accel_temp_bias", "m/s^2/degC^k", (2, 1))[1] == "mg/degC^2"
    assert D.display_of("accel_temp_bias", "m/s^2/degC^k", (1,))[1] == "mg/degC"  # order 1
    assert D.display_of("gyro_temp_bias", "rad/s/degC^k", (0, 2))[1] == "deg/h/degC^3"
    assert D.display_of("accel_temp_scale", "1/degC^k", (0, 1)) == (1e6, "ppm/degC^2")
    assert D.display_of("accel_temp_bias", "count/degC^k", (0, 1)) == (1.0, "count/degC^2")


def test_counts_stay_counts_and_si_gets_engineering_units():
    assert D.display_of("accel_bias", "count") == (1.0, "count")
    assert D.display_of("gyro_K", "count/(rad/s)") == (1.0, "count/(rad/s)")
    assert D.display_of("accel_bias", "m/s^2")[1] == "mg"
    # an SI unit no table names (a toy method's key): engineering units by its quantity
    assert D.display_of("toy_offset", "rad/s")[1] == "deg/h"
    assert D.display_of("toy_offset", "m/s^2/sqrt(s)")[1] == "mg/sqrt(s)"
    su = D.StatUnits("gyro", D.data_units({"accel_bias": "count", "gyro_bias": "count"}))
    assert su("gyro_noise_sigma") == (1.0, "count")
    assert su("accel_residual_rms") == (1.0, "count")
    assert su("g_error_rms_after")[1] == "mg"  # after correction: SI
    assert su("gyro_residual_rms")[1] == "deg"  # the gyro fit's angle residuals
    si = D.StatUnits("vector", D.data_units({"accel_bias": "m/s^2"}))
    assert si("accel_noise_sigma")[1] == "mg"
    assert D.value_text("gyro_noise_sigma", [4.4, 4.5], units=su) == "4.4, 4.5 count"


def test_entries_print_fixed_unobservable_and_matrix_sigma_in_ppm():
    e = D.entries({"accel_K": np.eye(3), "accel_bias": np.zeros(3)},
                  {"accel_K": np.diag([5e-6, 5e-6, 5e-6]),  # off-diagonal 0: fixed
                   "accel_bias": np.array([1e-5, np.nan, 0.0])},
                  {"accel_K": "-", "accel_bias": "m/s^2"})
    by = {x.name: x for x in e}
    assert by["accel_K[0,0]"].sigma == "5 ppm" and by["accel_K[0,0]"].unit == "-"
    assert by["accel_K[0,1]"].sigma == "fixed"
    assert by["accel_bias[1]"].sigma == "unobservable" and by["accel_bias[2]"].sigma == "fixed"
    assert by["accel_bias[0]"].unit == "mg" and by["accel_bias[0]"].value_sigma().startswith("0.")


def test_tables_are_full_width_in_a_pipe(tmp_path):
    """`calib show A B | cat`: every name and value whole, never cut to 80 columns."""
    from calib_cli.data import CalibrationResult
    from calib_cli.io.h5 import write_calibration

    long = "x" * 150
    for name in ("a", "b"):
        write_calibration(tmp_path / f"{name}.h5", CalibrationResult(
            method="vector", params={"accel_bias": np.array([0.01, 0.02, 0.03])},
            sigma={"accel_bias": np.full(3, 1e-4)}, units={"accel_bias": "m/s^2"},
            covariance=np.diag(np.full(3, 1e-8)), cov_order=[("accel_bias", i) for i in range(3)],
            stats={"method": "vector", "note": long}, serial="SN-0004",
            model=[{"name": "bias", "sensor": "accel"}]))
    env = {"COLUMNS": "", "PATH": str(Path(sys.executable).parent)}
    r = subprocess.run([sys.executable, "-m", "calib_cli", "show", str(tmp_path / "a.h5")],
                       capture_output=True, text=True, timeout=120, env=env)
    assert r.returncode == 0, r.stderr
    assert long in r.stdout and "…" not in r.stdout
    r = subprocess.run([sys.executable, "-m", "calib_cli", "show", str(tmp_path / "a.h5"),
                        str(tmp_path / "b.h5")], capture_output=True, text=True, timeout=120,
                       env=env)
    assert "accel_bias[0]" in r.stdout and "…" not in r.stdout


def test_every_option_has_a_help_line():
    from calib_cli.cli.tree import tree

    missing = []

    def walk(d, path):
        for n, sub in d.get("commands", {}).items():
            if "commands" in sub:
                walk(sub, path + [n])
                continue
            missing.extend(f"{' '.join(path + [n])} {o}" for o, h in sub["records"]
                           if not h.strip())

    walk(tree(), [])
    assert not missing, missing


def test_plan_check_prints_as_fit_prints(tmp_path, run_cli):
    plan = ROOT / "sample_data" / "twelve_position.toml"
    code, out, err = run_cli("plan", "check", plan, "--no-suggest")
    assert code == 0, err
    assert "accel_bias[0]" in err and "mg" in err and "ppm" in err
    assert "null" not in err and "m/s^2 " not in err.split("noise per sample")[0]
    assert "correlation of the determined entries: condition number" in err
    code, out, _ = run_cli("plan", "check", plan, "--no-suggest", "--json")
    import json

    cd = json.loads(out)["condition_details"]
    assert cd["dependencies"] == 0 and cd["condition_determined"] > 0


def test_condition_details_leave_exact_dependencies_out():
    from calib_cli.data import CalibrationResult
    from calib_cli.design import condition_details

    # three lever-arm components of one free pair (the third their combination) and a bias
    A = np.array([[1.0, 0.0], [0.0, 1.0], [0.6, 0.8]])
    C2 = np.diag([1e-8, 2e-8])
    C = np.zeros((4, 4))
    C[:3, :3] = A @ C2 @ A.T
    C[3, 3] = 1e-6
    res = CalibrationResult(method="toy", params={"lever_arm": np.zeros((1, 3)),
                                                   "accel_bias": np.zeros(1)},
                            sigma={}, units={}, covariance=C,
                            cov_order=[("lever_arm", 0), ("lever_arm", 1), ("lever_arm", 2),
                                       ("accel_bias", 0)], stats={})
    cd = condition_details(res)
    assert cd["condition"] > 1e12 and cd["dependencies"] == 1
    assert cd["dependent_keys"] == ["lever_arm"] and cd["condition_determined"] < 10
    from calib_cli.cli.cmd_plan import condition_line

    line = condition_line(cd)
    assert "1 exact linear dependencies among lever_arm left out" in line


def test_rates_and_windows_are_tidy_numbers():
    from calib_cli.data import Recording
    from calib_cli.io.export_autopilot import kalibr_dict

    t = np.arange(1000) * 0.01 + 1234.56  # float steps: 1/median(dt) = 100.0000000002
    rec = Recording(time=t, accel=np.zeros((1000, 3)), gyro=None, segments=())
    assert rec.sample_rate == 100.0
    assert kalibr_dict(1e-3, None, 1e-4, None, "/imu0", 100.00000000000213)["update_rate"] == 100.0


@pytest.mark.parametrize("n,word", [(1, "figure ->"), (2, "figures ->")])
def test_report_says_figure_in_the_singular(n, word, monkeypatch, tmp_path, run_cli):
    import calib_cli.report.builder as b

    monkeypatch.setattr(b, "write_report", lambda *a, **k: {"figures": [{}] * n})
    from calib_cli.data import CalibrationResult
    from calib_cli.io.h5 import write_calibration

    write_calibration(tmp_path / "c.h5", CalibrationResult(
        method="vector", params={"accel_bias": np.zeros(3)}, sigma={"accel_bias": np.ones(3)},
        units={"accel_bias": "m/s^2"}, covariance=np.eye(3),
        cov_order=[("accel_bias", i) for i in range(3)], stats={},
        model=[{"name": "bias", "sensor": "accel"}]))
    code, _, err = run_cli("report", tmp_path / "c.h5", "--out", tmp_path / "r")
    assert code == 0 and f"report with {n} {word}" in err
