"""Avrutov et al.'s figures of merit of an accelerometer triad (issue 22
item 4): std of |g| over the positions and |mean |g| - g|, before and after
correction, in stats, `calib show` and the report."""

from __future__ import annotations

import json

import numpy as np
from click.testing import CliRunner

from calib_cli.cli.main import cli
from calib_cli.io.h5 import write_calibration, write_raw
from calib_cli.io.plan import parse_plan
from calib_cli.methods.accel_lsq import fit_accel, g_figures
from calib_cli.sim.simulate import simulate

try:
    from samples_9 import PLAN
except ImportError:  # pragma: no cover
    from tests.samples_9 import PLAN


def test_g_figures_split_the_rms():
    g = 9.8
    v = np.array([9.81, 9.79, 9.805, 9.83])
    fig = g_figures(v, v - 0.01, g)
    rms = np.sqrt(np.mean((v - g) ** 2))
    assert np.isclose(fig["g_norm_std_before"] ** 2 + fig["g_mean_error_before"] ** 2, rms**2)
    assert np.isclose(fig["g_norm_std_after"], fig["g_norm_std_before"])
    assert np.isclose(fig["g_mean_error_after"], abs(np.mean(v) - 0.01 - g))
    assert g_figures(None, v, g)["g_norm_std_before"] is None


def test_fit_show_and_report_carry_both_figures(tmp_path):
    rec = simulate(parse_plan(PLAN), None, seed=5)
    res = fit_accel(rec, "vector")
    st = res.stats
    for tag in ("before", "after"):
        assert np.isclose(st[f"g_norm_std_{tag}"] ** 2 + st[f"g_mean_error_{tag}"] ** 2,
                          st[f"g_error_rms_{tag}"] ** 2)
    assert st["g_norm_std_after"] < st["g_norm_std_before"]
    write_calibration(tmp_path / "cal.h5", res, [])
    write_raw(tmp_path / "raw.h5", rec)
    r = CliRunner().invoke(cli, ["show", str(tmp_path / "cal.h5"), "--json"])
    js = json.loads(r.output)
    assert {"g_norm_std_before", "g_norm_std_after", "g_mean_error_before",
            "g_mean_error_after", "g_error_rms_before", "g_error_rms_after"} <= set(js["stats"])
    r = CliRunner().invoke(cli, ["show", str(tmp_path / "cal.h5")])
    assert "|g| over the positions: std" in r.output
    r = CliRunner().invoke(cli, ["report", str(tmp_path / "cal.h5"), "--out",
                                 str(tmp_path / "rep")])
    assert r.exit_code == 0, r.output
    assert "Avrutov" in (tmp_path / "rep" / "report.md").read_text()
