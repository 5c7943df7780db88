"""Shared cases of the experiment-design tests (docs/plan.md): a plan per
method, its fit, and the errors of a simulated seed in units of the
predicted sigma."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from calib_cli import design
from calib_cli.io.plan import parse_plan
from calib_cli.io.truth import load_truth
from calib_cli.sim import plan_make as pm
from calib_cli.sim.simulate import plan_layout, simulate

ROOT = Path(__file__).resolve().parents[1]
RIMU_TRUTH = ROOT / "sample_data" / "rimu_truth_adis16405.toml"


def plan_of(name: str):
    d = {"vector": lambda: pm.static_plan(12, "vector"),
         "scalar": lambda: pm.static_plan(12, "scalar"),
         "ferraris": pm.ferraris_plan,
         "align": lambda: pm.align_plan()[0],
         "rimu": lambda: pm.rimu_plan(),
         "turntable3": lambda: pm.turntable_plan(),
         "turntable9": lambda: pm.turntable_plan(tilted=True)}[name]()
    return parse_plan(pm.to_toml(d), f"<{name}>")


def truth_of(name: str, plan):
    return load_truth(RIMU_TRUTH, plan_layout(plan)) if name == "rimu" else None


def fit(method: str, rec):
    if method in ("vector", "scalar"):
        from calib_cli.methods.accel_lsq import fit_accel

        return fit_accel(rec, method)
    if method == "gyro":
        from calib_cli.methods.gyro import fit_gyro

        return fit_gyro(rec)
    if method == "align":
        from calib_cli.methods.align import fit_align

        return fit_align(rec)
    if method == "turntable":
        from calib_cli.methods.turntable import fit_turntable

        return fit_turntable(rec)
    from calib_cli.methods.rimu import fit_rimu

    return fit_rimu(rec)


def sigma_ratios(pred, res) -> dict:
    """predicted sigma / (the fit's sigma without its chi^2 inflation), per key,
    over the entries both determine."""
    infl = float(res.stats.get("sigma_inflation") or 1.0)
    if res.method == "turntable":  # its accelerometer noise widened by this factor
        infl = float(res.stats.get("accel_noise_inflation") or 1.0) ** 2
    out = {}
    for k, s in pred.result.sigma.items():
        s = np.asarray(s, float)
        f = np.asarray(res.sigma[k], float) / np.sqrt(infl)
        ok = np.isfinite(s) & (s > 0) & np.isfinite(f) & (f > 0)
        out[k] = s[ok] / f[ok]
    return out


def _true_params(name, rec, res):
    tp = {k: np.asarray(v, float) for k, v in rec.truth["params"].items()}
    if name == "scalar":  # the scalar fit's frame is the accelerometers': K lower triangular
        K = tp["accel_K"]
        tp["accel_K"] = np.linalg.cholesky(K @ K.T)
    if name == "align":
        tp["attitude"] = np.asarray(rec.truth["attitudes"][0], float)
    for k in res.params:
        if k not in tp:  # not in the truth model: zero (e.g. gyro_D), identity for a K
            tp[k] = np.eye(3) if k.endswith("_K") else np.zeros_like(np.asarray(res.params[k]))
    return tp


def normalised_errors(name: str, seed: int, pred, own: bool = False) -> dict:
    """(estimate - truth) / predicted sigma per key, for one simulated seed; with
    ``own`` also / the fit's own sigma: {key: (z_predicted, z_fit)}."""
    plan = plan_of(name)
    rec = simulate(plan, truth_of(name, plan), seed)
    res = fit(pred.method, rec)
    tp = _true_params(name, rec, res)
    out = {}
    for k, s in pred.result.sigma.items():
        s = np.asarray(s, float)
        e = np.asarray(res.params[k], float) - tp[k]
        if k == "attitude" or k.endswith("_dAz"):
            e = (e + np.pi) % (2 * np.pi) - np.pi
        ok = np.isfinite(s) & (s > 0)
        out[k] = e[ok] / s[ok]
        if own:
            f = np.asarray(res.sigma[k], float)[ok]
            out[k] = (out[k], e[ok] / np.where(np.isfinite(f) & (f > 0), f, np.nan))
    return out


def predicted(name: str, noise=None):
    plan = plan_of(name)
    truth = truth_of(name, plan)
    return design.check(plan, "auto", noise or design.default_noise(plan, truth=truth), truth,
                        suggestions=False)
