"""calib simulate PLAN --out RAW.h5|LOG.csv [--seed N] [--truth TRUTH.toml]"""

from __future__ import annotations

import click

from calib_cli.cli.common import info
from calib_cli.cli.main import cli
from calib_cli.io.csvlog import write_csv
from calib_cli.io.h5 import write_raw
from calib_cli.io.plan import load_plan
from calib_cli.sim.simulate import plan_layout, simulate
from calib_cli.sim.truth import load_truth


@cli.command("simulate")
@click.argument("plan", type=click.Path(dir_okay=False))
@click.option("--out", "out", required=True, type=click.Path(dir_okay=False),
              help="raw.h5, or a .csv log in the contract's columns.")
@click.option("--seed", default=0, show_default=True, type=int, help="Random seed.")
@click.option("--truth", "truth_path", type=click.Path(dir_okay=False),
              help="Truth model TOML (docs/simulate.md); default: a random MEMS unit.")
def simulate_cmd(plan, out, seed, truth_path):
    """Simulate the experiment of PLAN from a truth model, with noise."""
    p = load_plan(plan)
    truth = load_truth(truth_path, plan_layout(p)) if truth_path else None
    rec = simulate(p, truth, seed)
    inputs = [plan] + ([truth_path] if truth_path else [])
    if out.lower().endswith(".csv"):
        write_csv(out, rec)
    else:
        write_raw(out, rec, inputs)
    info(f"simulated {len(rec)} samples, {len(rec.segments)} segments -> {out}")
