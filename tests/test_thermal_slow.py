"""`calib fit thermal` over many seeds (`make validate`), issue 21's figures;
writes docs/validation/thermal.md. CALIB_THERMAL_N sets the seeds (20)."""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np
import pytest

from calib_cli.validation import thermal_validate as V

pytestmark = pytest.mark.slow
N = int(os.environ.get("CALIB_THERMAL_N", "20"))
DOC = Path(__file__).resolve().parent.parent / "docs" / "validation" / "thermal.md"
_R: dict = {}


@pytest.fixture(scope="module")
def results():
    if not _R:
        _R["soak"] = V.run_design("soak", range(N))
        _R["ramp"] = V.run_design("ramp", range(N))
        _R["lag"] = V.run_lag(range(N))
        DOC.write_text(V.markdown([_R["soak"], _R["ramp"]], _R["lag"]))
    return _R


@pytest.mark.parametrize("design", ["soak", "ramp"])
def test_pooled_rule(results, design):
    for k, g in results[design]["groups"].items():
        assert 0.8 <= g["rms"] <= 1.25, (k, g)
        # 99 % below 3.3: at most 1 % of the group above, rounded up (one in 60)
        assert g["n_above_3.3"] <= int(np.ceil(0.01 * g["n"])), (k, g)


@pytest.mark.parametrize("design", ["soak", "ramp"])
def test_holdout_g_error(results, design):
    for T0, h in results[design]["holdout"].items():
        assert h["ratio"] <= 1.2, (T0, h)
        if abs(T0 - 25) >= 15:
            assert h["rms_static_only"] > 10 * h["floor"], (T0, h)


def test_lag_hysteresis_and_tau(results):
    lag = results["lag"]
    assert lag["plain_min"] > 5, lag
    # below 2 sigma with the lag modelled: per axis, as a normal variable would be
    assert lag["axis_rms_lag"] <= 1.3, lag
    assert lag["axis_frac_below_2"] >= 0.9, lag
    assert 0.7 <= lag["tau_rms_z"] <= 1.3, lag
