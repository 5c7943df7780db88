"""The rough-stand paper's navigation-grade setting over 20 seeds (issue 22 item 2,
make validate K=nav_grade): a unit drawn from the navigation grade's prior (gyro
drift 0.1 deg/h, accelerometer bias 6e-4 g, ... ; proof-mass offsets of 5 mm, lever
arms up to 30 cm measured on the housing to 5 mm), the paper's noise (0.1 deg/h and
3e-4 g, read as the 1-sigma of a 1 s mean), the 9-cycle plan plus six check positions
(each axis up and down), fitted with ``--grade navigation --noise``. Pooled within-sigma
rule per parameter group and on the check positions' z. Writes
docs/validation/turntable-nav-grade.md (quoted in docs/papers.md)."""

from __future__ import annotations

import os
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import numpy as np
import pytest

G0 = 9.80665
N_SEEDS = 20
FS = 100.0
NOISE_1S = {"accel": 3e-4 * G0, "gyro": float(np.radians(0.1 / 3600.0))}  # 1-sigma of a 1 s mean
CYCLE_S, TILTED_S, CHECK_S = 300.0, 150.0, 30.0
# attitudes putting +z, -z, +x, -x, +y, -y up (roll, pitch, yaw deg): [90, 0, 0] is +y up
CHECK_ATTITUDES = ([0, 0, 0], [180, 0, 0], [0, -90, 0], [0, 90, 0], [90, 0, 0], [-90, 0, 0])
OUT = Path(__file__).resolve().parents[1] / "docs" / "validation" / "turntable-nav-grade.md"
GROUPS = ("accel_bias", "accel_K", "gyro_bias", "gyro_K", "gyro_D", "lever_arm",
          "proof_mass_offsets")


def per_sample_noise(fs: float = FS) -> dict:
    """The paper's noise per sample at fs Hz (a 1 s mean of fs white samples)."""
    return {k: v * np.sqrt(fs) for k, v in NOISE_1S.items()}


def plan_text(seed: int) -> str:
    from calib_cli.sim.turntable_plans import turntable_plan_text

    txt = turntable_plan_text(seed, duration_s=CYCLE_S, tilted=True, tilted_duration_s=TILTED_S,
                              sample_rate_hz=FS)
    for k, att in enumerate(CHECK_ATTITUDES):
        txt += (f"[[segment]]\nlabel = 'check-{k + 1}'\nattitude_deg = {list(map(float, att))}\n"
                f"duration_s = {CHECK_S}\n")
    return txt


def nav_truth(plan, seed: int):
    """The plan's lever arms and 5 mm proof-mass offsets; every other parameter drawn
    from the navigation grade's prior (the fit's prior is then the truth's law)."""
    from calib_cli.methods.turntable import GRADES
    from calib_cli.model.truth import Truth
    from calib_cli.sim.turntable_plans import turntable_truth

    rng = np.random.default_rng(70_000 + seed)
    t = turntable_truth(plan, rng)
    w = GRADES["navigation"]
    p = dict(t.params)
    p["accel_bias"] = rng.standard_normal(3) * w["accel_bias"]
    p["accel_K"] = np.eye(3) + np.tril(rng.standard_normal((3, 3))) * w["accel_K"]
    p["gyro_bias"] = rng.standard_normal(3) * w["gyro_bias"]
    p["gyro_K"] = np.eye(3) + rng.standard_normal((3, 3)) * w["gyro_K"]
    p["gyro_D"] = rng.standard_normal((3, 3)) * w["gyro_D"]
    n = per_sample_noise()
    return Truth(t.model, p, {"accel_white": n["accel"], "gyro_white": n["gyro"]})


def run_seed(seed: int) -> dict:
    import time

    from calib_cli.io.plan import parse_plan
    from calib_cli.methods.turntable import TurntableOptions, fit_turntable
    from calib_cli.sim.simulate import simulate

    plan = parse_plan(plan_text(seed), "<nav-grade>")
    rec = simulate(plan, nav_truth(plan, seed), seed)
    n = per_sample_noise()
    t0 = time.perf_counter()
    res = fit_turntable(rec, TurntableOptions(grade="navigation",
                                              noise={"accel": n["accel"], "gyro": n["gyro"]}))
    dt = time.perf_counter() - t0
    truth = rec.truth["params"]
    z, sig = {}, {}
    for k in GROUPS:
        s = np.asarray(res.sigma[k], float)
        m = np.isfinite(s) & (s > 0)
        z[k] = ((np.asarray(res.params[k], float) - np.asarray(truth[k], float))[m] / s[m])
        sig[k] = s[m]
    cp = res.stats["check_positions"]
    z["check_g"] = np.array([p["g_error_z"] for p in cp["positions"]])
    z["check_earth_rate"] = np.array([p["earth_rate_up_error_z"] for p in cp["positions"]])
    sig["check_g"] = np.array([p["g_error_sigma"] for p in cp["positions"]])
    sig["check_earth_rate"] = np.array([p["earth_rate_up_error_sigma"] for p in cp["positions"]])
    return {"z": z, "sigma": sig, "time": dt, "verdict": cp["verdict"],
            "inflation": res.stats["accel_noise_inflation"]}


UNIT = {"accel_bias": (1e6 / G0, "ug"), "accel_K": (1e6, "ppm"),
        "gyro_bias": (3600 * 180 / np.pi, "deg/h"), "gyro_K": (1e6, "ppm"),
        "gyro_D": (3600 * 180 / np.pi * G0, "deg/h/g"), "lever_arm": (1e3, "mm"),
        "proof_mass_offsets": (1e3, "mm"), "check_g": (1e6 / G0, "ug"),
        "check_earth_rate": (3600 * 180 / np.pi, "deg/h")}


def pooled(z: np.ndarray) -> tuple[float, float]:
    a = np.abs(np.ravel(z))
    return float(np.sqrt(np.mean(a**2))), float(np.quantile(a, 0.99))


def table(rows: list[dict]) -> tuple[str, dict]:
    keys = list(rows[0]["z"])
    lines = ["| group | entries x seeds | RMS z | 99th pct abs z | max abs z | median sigma | "
             "rule |", "|---|---|---|---|---|---|---|"]
    verdict = {}
    for k in keys:
        z = np.concatenate([r["z"][k] for r in rows])
        s = np.concatenate([r["sigma"][k] for r in rows])
        rms, q99 = pooled(z)
        ok = 0.8 <= rms <= 1.25 and q99 < 3.3
        verdict[k] = (ok, rms, q99)
        f, u = UNIT[k]
        lines.append(f"| {k} | {len(z)} | {rms:.2f} | {q99:.2f} | {np.abs(z).max():.2f} | "
                     f"{np.median(s) * f:.3g} {u} | {'pass' if ok else '**fail**'} |")
    t = np.array([r["time"] for r in rows])
    lines.append("")
    lines.append(f"{len(rows)} seeds; fit time per seed {np.median(t):.1f} s median "
                 f"(machine under load); check-position verdicts: "
                 f"{sum(r['verdict'] == 'pass' for r in rows)} pass of {len(rows)}; "
                 f"accelerometer noise inflation > 1 in "
                 f"{sum(r['inflation'] > 1 for r in rows)} seeds.")
    return "\n".join(lines) + "\n", verdict


@pytest.mark.slow
def test_nav_grade_within_sigma():
    seeds = range(N_SEEDS)
    workers = int(os.environ.get("TT_WORKERS", "1"))
    if workers > 1:
        with ProcessPoolExecutor(workers) as ex:
            rows = list(ex.map(run_seed, seeds))
    else:
        rows = [run_seed(s) for s in seeds]
    text, verdict = table(rows)
    OUT.parent.mkdir(parents=True, exist_ok=True)
    OUT.write_text("<!-- written by tests/test_turntable_nav_slow.py (make validate "
                   "K=nav_grade) -->\n" + text)
    bad = {k: v for k, v in verdict.items() if not v[0]}
    assert not bad, bad
