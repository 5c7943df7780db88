"""The example plans of every method (sample_data/plans/, docs/plans.md) load,
are of the method's kind and are all run by `make demo-all`."""

from __future__ import annotations

from pathlib import Path

import pytest

from calib_cli.io.plan import load_plan

ROOT = Path(__file__).resolve().parent.parent
PLANS = {"ferraris.toml": ("static", 9), "align.toml": ("align", 3), "rimu.toml": ("rimu", 6),
         "turntable_3cycle.toml": ("turntable", 3), "turntable_9cycle.toml": ("turntable", 9),
         "thermal.toml": ("static", 35)}
TRUTHS = {"thermal_truth.toml": "thermal.toml"}  # a truth file beside the plan it goes with


@pytest.mark.parametrize("name", sorted(PLANS))
def test_example_plan_loads(name):
    p = load_plan(ROOT / "sample_data" / "plans" / name)
    kind, n = PLANS[name]
    assert p.kind == kind and len(p.segments) == n
    if kind == "turntable":
        assert sum(s.kind == "rotating" for s in p.segments) == n


def test_demo_all_runs_every_example_plan():
    script = (ROOT / "sample_data" / "demo_all.sh").read_text(encoding="utf-8")
    on_disk = {f.name for f in (ROOT / "sample_data" / "plans").glob("*.toml")} - set(TRUTHS)
    assert on_disk == set(PLANS)
    for name in TRUTHS:
        assert f"$plans/{name}" in script, name
    for name in on_disk:
        assert f"$plans/{name}" in script, name
    assert "demo-all:" in (ROOT / "Makefile").read_text(encoding="utf-8")
    docs = (ROOT / "docs" / "plans.md").read_text(encoding="utf-8")
    assert all(f"sample_data/plans/{n}" in docs for n in on_disk)


@pytest.mark.parametrize("name", sorted(TRUTHS))
def test_example_truth_loads_with_its_plan(name):
    from calib_cli.io.truth import load_truth
    from calib_cli.plan import plan_layout

    plan = load_plan(ROOT / "sample_data" / "plans" / TRUTHS[name])
    truth = load_truth(ROOT / "sample_data" / "plans" / name, plan_layout(plan))
    assert {"accel_temp_bias", "accel_temp_scale", "gyro_temp_bias"} <= set(truth.params)
    assert sum("chamber_temp_degC" in s.extra for s in plan.segments) == 5
