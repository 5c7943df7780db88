"""Probe for issue 22 item 2: why is the navigation-grade turntable fit's gyro-bias sigma
conservative? Runs the slow test's seed harness with option overrides and prints, per seed,
the gyro bias error, sigma and z per axis (and gyro_D, check earth rate RMS z).

  .venv/bin/python benchmarks/nav22_probe.py SEEDS [key=value ...]

keys: TurntableOptions fields (axis_sigma=1e-6, runout_sigma=0, block_s=0.1, ...),
plus sim keys: gnoise=<factor on the simulated gyro noise>, anoise=<factor on accel noise>,
fgnoise=<factor on the fit's gyro noise>, floor=<axis-noise floor rad>, walk=<floor's fraction of the
attitude walk per block (1e9: the fixed floor alone)>, wobble=<table rate wobble dps>.
Writes one JSON line per seed to stdout."""

from __future__ import annotations

import json
import sys
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "tests"))
import test_turntable_nav_slow as T  # noqa: E402


def run(seed: int, kv: dict) -> dict:
    from calib_cli.io.plan import parse_plan
    from calib_cli.methods.turntable import TurntableOptions, fit_turntable
    from calib_cli.model.truth import Truth
    from calib_cli.sim.simulate import simulate

    kv = dict(kv)
    gn = float(kv.pop("gnoise", 1.0))
    an = float(kv.pop("anoise", 1.0))
    fgn = float(kv.pop("fgnoise", 1.0))
    txt = T.plan_text(seed)
    if "wobble" in kv:
        txt = txt.replace("sim_table_wobble_dps = 0.5", f"sim_table_wobble_dps = {kv.pop('wobble')}")
    if "kind" in kv:
        txt = f"sample_kind = '{kv.pop('kind')}'\n" + txt
    plan = parse_plan(txt, "<nav-grade>")
    tr = T.nav_truth(plan, seed)
    tr = Truth(tr.model, tr.params, {"accel_white": tr.noise["accel_white"] * an,
                                     "gyro_white": tr.noise["gyro_white"] * gn})
    rec = simulate(plan, tr, seed)
    n = T.per_sample_noise()
    opts = TurntableOptions(grade="navigation",
                            noise={"accel": n["accel"] * max(an, 1e-3),
                                   "gyro": n["gyro"] * max(gn, 1e-3) * fgn})
    if "floor" in kv:  # the estimated axis noise's floor (rad), default 1e-5
        from calib_cli.methods.turntable import estimator as es
        es.AXIS_FLOOR = float(kv.pop("floor"))
    if "walk" in kv:  # the floor's fraction of the attitude walk per block, default 0.5
        from calib_cli.methods.turntable import estimator as es
        es.AXIS_FLOOR_WALK = float(kv.pop("walk"))
    conv = {}
    for k, v in kv.items():
        conv[k] = None if v == "None" else (int(v) if k in ("passes", "coarse_factor") else float(v))
    opts = replace(opts, **conv)
    t0 = time.process_time()
    res = fit_turntable(rec, opts)
    cpu = time.process_time() - t0
    truth = rec.truth["params"]
    out = {"seed": seed, "cpu_s": round(cpu, 1)}
    for k in ("gyro_bias", "gyro_D", "accel_bias"):
        e = np.asarray(res.params[k], float) - np.asarray(truth[k], float)
        s = np.asarray(res.sigma[k], float)
        out[k + "_err"] = e.ravel().tolist()
        out[k + "_sig"] = s.ravel().tolist()
    cp = res.stats["check_positions"]
    out["cer_z"] = [p["earth_rate_up_error_z"] for p in cp["positions"]]
    out["axis_noise_mrad"] = res.stats["table_axis_noise_mrad"]
    out["passes"] = res.stats["filter_passes"]
    out["runout_urad"] = res.stats["table_axis_runout_urad"]
    return out


def main():
    seeds = [int(s) for s in sys.argv[1].split(",")] if "," in sys.argv[1] else \
        list(range(*map(int, sys.argv[1].split(":"))))
    kv = dict(a.split("=", 1) for a in sys.argv[2:])
    for s in seeds:
        print(json.dumps(run(s, kv)), flush=True)


if __name__ == "__main__":
    main()
