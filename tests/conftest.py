"""Shared test helpers: plans, truths and an in-process CLI runner."""

from __future__ import annotations

import os

import numpy as np
import pytest

os.environ.setdefault("MPLBACKEND", "Agg")

TWELVE = [[0, -90, 0], [0, 90, 0], [90, 0, 0], [-90, 0, 0], [0, 0, 0], [180, 0, 0],
          [45, 45, 0], [-45, 45, 30], [45, -45, 60], [135, 30, 10], [-135, -30, 80],
          [30, 60, 120]]


def static_plan_text(attitudes=TWELVE, duration=10.0, rate=100.0, known=True, serial="SN-T1",
                     lat=50.45, sigma_deg=None) -> str:
    lines = ["name = 'test'", "kind = 'static'", f"sample_rate_hz = {rate}",
             "transition_s = 3.0", "[site]", f"latitude_deg = {lat}", "height_m = 180.0",
             "[unit]", f"serial = '{serial}'"]
    for i, a in enumerate(attitudes):
        lines += ["[[segment]]", f"label = 'p{i + 1}'", f"duration_s = {duration}"]
        key = "attitude_deg" if known else "sim_attitude_deg"
        lines.append(f"{key} = {list(map(float, a))}")
        if sigma_deg is not None:
            lines.append(f"attitude_sigma_deg = {sigma_deg}")
    return "\n".join(lines) + "\n"


TRUTH_SI = {
    "params": {"accel_bias": [0.05, -0.03, 0.08],
               "accel_K": [[1.01, 0.002, -0.003], [0.001, 0.99, 0.004], [-0.002, 0.003, 1.005]],
               "gyro_bias": [0.002, -0.001, 0.003]},
    "noise": {"accel_white": 0.01, "gyro_white": 1e-3},
}


def random_unit_attitudes(n, rng):
    """Attitudes (deg) spread over the sphere of gravity directions."""
    from scipy.spatial.transform import Rotation

    return [list(np.degrees(Rotation.random(random_state=rng).as_euler("ZYX")[::-1]))
            for _ in range(n)]


def pooled_ok(z, hard=None):
    """The brief's pooled rule on normalized errors; returns (rms, frac<3.3, max)."""
    z = np.asarray(z, dtype=float).ravel()
    return float(np.sqrt(np.mean(z**2))), float(np.mean(np.abs(z) < 3.3)), float(np.abs(z).max())


@pytest.fixture
def run_cli(capsys):
    """Run `calib ARGS` in-process; returns (exit code, stdout, stderr)."""
    from calib_cli.cli.main import main

    def run(*args):
        code = 0
        try:
            main([str(a) for a in args])
        except SystemExit as exc:
            code = exc.code if isinstance(exc.code, int) else (0 if exc.code is None else 1)
        out = capsys.readouterr()
        return code, out.out, out.err

    return run
