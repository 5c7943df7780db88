"""`calib plan check PLAN --like RAW` against the fit of RAW (issue 33): the median
predicted / fitted sigma of every parameter group within [0.87, 1.15] and the same
unobservable list, on plans written from the contract alone (attitudes unknown, no g,
a navigation-grade alignment with its turn recorded) and on the methods' example plans.
The prediction is the method's own information (methods/registry.py) on the plan's
noise-free record, with the attitudes the plan leaves unknown taken from RAW
(design.attitudes_like): the positions' directions are what a fit's information
depends on."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from calib_cli import api
from calib_cli.design import check, noise_like

ROOT = Path(__file__).resolve().parents[1]

SCALAR = ('name = "scalar18"\nkind = "static"\nsample_rate_hz = 100.0\ntransition_s = 3.0\n'
          "[site]\nlatitude_deg = 45.0\n"
          + "".join(f'[[segment]]\nlabel = "p{i}"\nduration_s = 10.0\n' for i in range(18)))
ALIGN = ('name = "align-contract"\nkind = "align"\nsample_rate_hz = 100.0\ntransition_s = 4.0\n'
         "[site]\nlatitude_deg = 48.0\n"
         '[[segment]]\nlabel = "position-1"\nduration_s = 120.0\n'
         '[[segment]]\nlabel = "turn"\nrotation_axis_body = [0.0, 0.0, 1.0]\n'
         "rotation_angle_deg = 90.0\nduration_s = 10.0\n"
         '[[segment]]\nlabel = "position-2"\nduration_s = 120.0\n')


def _ratios(plan, method, seeds):
    rat, unobs = {}, []
    for seed in seeds:
        rec = api.simulate(plan, seed=seed)
        res = api.fit(method, rec)
        pr = check(plan, "auto", noise_like(rec), suggestions=False)
        unobs.append((sorted(pr.unobservable), sorted(res.stats.get("unobservable", []))))
        for k, s in res.sigma.items():
            a = np.asarray(pr.result.sigma[k], float).ravel()
            b = np.asarray(s, float).ravel()
            ok = np.isfinite(a) & np.isfinite(b) & (b > 0)
            rat.setdefault(k, []).extend((a[ok] / b[ok]).tolist())
    return {k: float(np.median(v)) for k, v in rat.items()}, unobs


@pytest.mark.parametrize("name,method", [
    ("scalar-contract", "accel"), ("align-contract", "align"),
    ("twelve_position", "accel"), ("ferraris", "gyro"), ("rimu", "rimu"),
])
def test_prediction_agrees_with_the_fit(name, method, tmp_path):
    if name == "scalar-contract":
        plan = api.parse_plan(SCALAR, "scalar.toml")
    elif name == "align-contract":
        plan = api.parse_plan(ALIGN, "align.toml")
    elif name == "twelve_position":
        plan = api.load_plan(ROOT / "sample_data" / "twelve_position.toml")
    else:
        plan = api.load_plan(ROOT / "sample_data" / "plans" / f"{name}.toml")
    med, unobs = _ratios(plan, method, (11, 12))
    assert all(0.87 <= v <= 1.15 for v in med.values()), med
    assert all(p == f for p, f in unobs), unobs


def test_like_through_the_command_line(run_cli, tmp_path):
    """The same through `calib plan check --like --json` and `calib fit`, for the plan
    without attitudes (which the simulator would draw at random)."""
    plan = tmp_path / "plan.toml"
    plan.write_text(SCALAR)
    assert run_cli("simulate", plan, "--out", tmp_path / "raw.h5", "--seed", 4)[0] == 0
    code, so, err = run_cli("plan", "check", plan, "--like", tmp_path / "raw.h5", "--json",
                            "--no-suggest")
    assert code == 0, err
    pred = json.loads(so)
    assert run_cli("fit", "accel", tmp_path / "raw.h5", "--out", tmp_path / "cal.h5")[0] == 0
    code, so, _ = run_cli("show", tmp_path / "cal.h5", "--json")
    fit = json.loads(so)
    assert pred["method"] == "scalar"
    for k in ("accel_bias", "accel_K"):
        a, b = np.asarray(pred["sigma"][k], float), np.asarray(fit["sigma"][k], float)
        ok = np.isfinite(b) & (b > 0)
        assert 0.87 <= np.median(a[ok] / b[ok]) <= 1.15, (k, a, b)
    assert pred["unobservable"] == fit["stats"]["unobservable"]
