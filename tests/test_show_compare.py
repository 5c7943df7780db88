"""calib show A.h5 B.h5: parameter differences in sigma."""

from __future__ import annotations

import json

import numpy as np
import pytest
from click.testing import CliRunner

from calib_cli.cli.main import cli
from calib_cli.io.h5 import write_calibration
from calib_cli.io.plan import parse_plan
from calib_cli.methods.accel_lsq import fit_accel
from calib_cli.methods.compare import compare
from calib_cli.model.truth import truth_from_dict
from calib_cli.sim.simulate import plan_layout, simulate

try:  # tests/ as rootdir-inserted path (no __init__.py) or as a package
    from samples_9 import PLAN
except ImportError:  # pragma: no cover
    from tests.samples_9 import PLAN

TRUTH = {"params": {"accel_bias": [0.02, -0.01, 0.03],
                    "accel_K": [[1.002, 0.001, 0.0], [0.0, 0.998, 0.002], [0.001, 0.0, 1.001]]},
         "noise": {"accel_white": 3e-3, "gyro_white": 1e-3}}


def _fit(seed, bias_shift=0.0):
    plan = parse_plan(PLAN)
    raw = dict(TRUTH, params=dict(TRUTH["params"]))
    raw["params"]["accel_bias"] = list(np.array(raw["params"]["accel_bias"]) + bias_shift)
    truth = truth_from_dict(raw, plan_layout(plan))
    return fit_accel(simulate(plan, truth, seed), "vector")


def test_same_unit_differences_are_within_sigma():
    zs = []
    for s in range(3):
        r = compare(_fit(10 + s), _fit(20 + s))
        zs += [np.ravel(z) for z in r["z"].values()]
    z = np.concatenate(zs)
    assert np.all(np.abs(z) < 4.5)
    assert 0.4 < np.sqrt(np.mean(z**2)) < 1.8


def test_changed_bias_is_flagged_and_cli(tmp_path):
    a, b = _fit(1), _fit(2, bias_shift=5e-3)  # 0.5 mg shift, sigma ~ 0.05 mg
    r = compare(a, b)
    assert r["worst"].startswith("accel_bias") and r["max_abs_z"] > 10
    write_calibration(tmp_path / "a.h5", a)
    write_calibration(tmp_path / "b.h5", b)
    res = CliRunner().invoke(cli, ["show", str(tmp_path / "a.h5"), str(tmp_path / "b.h5"),
                                   "--json"])
    assert res.exit_code == 0, res.output
    obj = json.loads(res.stdout)
    assert obj["kind"] == "comparison"
    np.testing.assert_allclose(obj["params"]["accel_bias"],
                               b.params["accel_bias"] - a.params["accel_bias"])
    res = CliRunner().invoke(cli, ["show", str(tmp_path / "a.h5"), str(tmp_path / "b.h5")])
    assert res.exit_code == 0 and "largest change" in res.stdout
    # one file still shows as before
    res = CliRunner().invoke(cli, ["show", str(tmp_path / "a.h5"), "--json"])
    assert json.loads(res.stdout)["method"] == "vector"


def test_unit_mismatch_is_input_error():
    from dataclasses import replace

    from calib_cli.errors import InputError

    a = _fit(1)
    b = replace(a, units={**a.units, "accel_bias": "count"})
    with pytest.raises(InputError):
        compare(a, b)
