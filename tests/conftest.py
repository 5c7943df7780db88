"""Shared test helpers: plans, truths and an in-process CLI runner."""

from __future__ import annotations

import os

import numpy as np
import pytest

os.environ.setdefault("MPLBACKEND", "Agg")

from calib_cli.validation.static_cases import TWELVE, static_plan_text  # noqa: E402,F401

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


def pytest_addoption(parser):
    parser.addoption("--part", default=None,
                     help="make validate K=NAME: the tests marked part(NAME); where none is, "
                          "those whose names match NAME (as -k NAME)")


@pytest.hookimpl(tryfirst=True)
def pytest_collection_modifyitems(config, items):
    """`make validate K=NAME`: a named part (an issue's acceptance run, e.g. K=turntable is
    the profile families alone) selects its marked tests; any other NAME is a -k expression
    (runs before pytest's own keyword selection, which then applies it)."""
    part = config.getoption("--part")
    if not part:
        return
    marked = [i for i in items if any(m.args and m.args[0] == part for m in i.iter_markers("part"))]
    if marked:
        config.hook.pytest_deselected(items=[i for i in items if i not in marked])
        items[:] = marked
    else:
        config.option.keyword = part
