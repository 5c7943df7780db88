"""Experiment design acceptance over 20 simulated seeds (make validate):
error / predicted sigma meets the pooled within-sigma rule per group (RMS in
[0.8, 1.25], 99 % below 3.3), and plan optimize's static plan delivers its
target in every seed."""

import numpy as np
import pytest

from tests import plan_cases as pc

SEEDS = range(100, 120)


def pooled_rule(z: np.ndarray) -> tuple[float, float]:
    z = np.abs(np.ravel(z))
    return float(np.sqrt(np.mean(z**2))), float(np.quantile(z, 0.99))


@pytest.mark.slow
@pytest.mark.parametrize("name", ["vector", "scalar", "ferraris", "align", "rimu"])
def test_within_sigma_over_seeds(name):
    pred = pc.predicted(name)
    errs = [pc.normalised_errors(name, s, pred) for s in SEEDS]
    bad = []
    for key in pred.result.sigma:
        z = np.concatenate([e[key].ravel() for e in errs])
        if name == "align" and key == "attitude":
            z = np.concatenate([e[key][:2] for e in errs])  # heading: see the test below
        if not len(z):
            continue
        rms, q99 = pooled_rule(z)
        print(f"{name} {key}: RMS z {rms:.3f}, 99th pct {q99:.2f} ({len(z)} values)")
        if not (0.8 <= rms <= 1.25 and q99 < 3.3):
            bad.append((key, rms, q99))
    assert not bad, (name, bad)


# Turntable groups whose errors miss the rule (or sit at its edge) against the fit's OWN
# sigma as well: the estimator's calibration on these generated plans, not the
# prediction's (docs/plan.md, seeds 100-119): turntable3 accel_K 99th pct 3.38 (the fit's
# own 3.37). For it only the agreement of the predicted z with the fit's own z is
# asserted here. (turntable9 gyro_D, RMS z 1.27 while the rate channel was rate rows that
# counted the gyro noise twice, is 1.09 since it is an angle: docs/turntable.md.)
TURNTABLE_ESTIMATOR_LIMITS = {"turntable3": ("accel_K",)}
# turntable3 accel_K is pooled over 60 seeds instead (test below): over seeds 120-159 the
# fit's own z has RMS 0.99, 99th pct 2.46, largest 3.16 (per entry 0.87-1.07), so the 3.37
# of seeds 100-119 is those seeds' draw, as with the heading below
ACCEL_K_SEEDS = range(100, 160)


@pytest.mark.slow
@pytest.mark.parametrize("name", ["turntable3", "turntable9"])
def test_turntable_within_sigma_over_seeds(name):
    """The turntable plan check over 20 seeds of the simulator's random MEMS unit: error /
    predicted sigma meets the pooled rule per group, except where the fit's own sigma
    misses it too; everywhere the RMS of the predicted z is within 10 % of the RMS of
    the fit's own z (the prediction is as good as the fit's own covariance)."""
    pred = pc.predicted(name)
    errs = [pc.normalised_errors(name, s, pred, own=True) for s in SEEDS]
    bad = []
    for key in pred.result.sigma:
        z = np.concatenate([e[key][0].ravel() for e in errs])
        zf = np.concatenate([e[key][1].ravel() for e in errs])
        if not len(z):
            continue
        rms, q99 = pooled_rule(z)
        rms_f, q99_f = pooled_rule(zf[np.isfinite(zf)])
        print(f"{name} {key}: RMS z {rms:.3f}, 99th pct {q99:.2f}; against the fit's own "
              f"sigma {rms_f:.3f}, {q99_f:.2f} ({len(z)} values)")
        ok = 0.8 <= rms <= 1.25 and q99 < 3.3
        ok_f = 0.8 <= rms_f <= 1.25 and q99_f < 3.3
        known = key in TURNTABLE_ESTIMATOR_LIMITS.get(name, ())
        if (not ok and not known) or abs(rms / rms_f - 1) > 0.1:
            bad.append((key, rms, q99, rms_f, q99_f, ok_f))
    assert not bad, (name, bad)


@pytest.mark.slow
def test_turntable3_accel_K_within_sigma_over_60_seeds():
    pred = pc.predicted("turntable3")
    z = np.concatenate([pc.normalised_errors("turntable3", s, pred)["accel_K"].ravel()
                        for s in ACCEL_K_SEEDS])
    rms, q99 = pooled_rule(z)
    print(f"turntable3 accel_K over {len(ACCEL_K_SEEDS)} seeds: RMS z {rms:.3f}, 99th pct "
          f"{q99:.2f}, largest {np.abs(z).max():.2f} ({len(z)} values)")
    assert 0.8 <= rms <= 1.25 and q99 < 3.3, (rms, q99)


# The heading is one number per seed: 20 values pool too few for the rule (its RMS then
# has a standard error of 0.16, and [0.8, 1.25] fails a correct sigma one time in six).
# Seeds 100-119 alone give RMS 1.64 (p = 7e-5 for a correct sigma): the white-noise draws
# of those seeds have gyro x means of RMS 1.45 sigma (p = 6e-5; seeds 0-999: 1.04), not a
# missing term of the fit (docs/plan.md). 100 seeds, those 20 included.
HEADING_SEEDS = range(100, 200)


@pytest.mark.slow
def test_align_heading_within_sigma():
    pred = pc.predicted("align")
    z = np.array([pc.normalised_errors("align", s, pred)["attitude"][2] for s in HEADING_SEEDS])
    rms, q99 = pooled_rule(z)
    print(f"align heading over {len(z)} seeds: RMS z {rms:.3f}, 99th pct {q99:.2f}")
    assert 0.8 <= rms <= 1.25 and q99 < 3.3, (rms, q99)


def optimized_static(seeds, tmp_path, run_cli):
    """plan optimize on the 12-position static plan with --target
    accel_K.diag=50e-6 at 2 mg-class noise (0.02 m/s^2 per sample at 100 Hz):
    the optimized plan, simulated and fitted, reports sigma <= 1.1 x the target
    in every seed and its errors meet the within-sigma rule."""
    import json

    from calib_cli.io.plan import load_plan
    from calib_cli.methods.accel_lsq import fit_accel
    from calib_cli.model.truth import Truth, default_truth
    from calib_cli.sim.simulate import simulate

    src, opt = tmp_path / "s12.toml", tmp_path / "opt.toml"
    assert run_cli("plan", "make", "static", "--positions", "12", "--out", src)[0] == 0
    code, out, err = run_cli("plan", "optimize", src, "--target", "accel_K.diag=50e-6",
                             "--accel-noise", "0.02", "--out", opt, "--json")
    assert code == 0, err
    d = json.loads(out)
    assert d["duration_s"] < d["duration_before_s"]
    plan = load_plan(opt)
    z, worst = [], 0.0
    for s in seeds:
        t = default_truth(plan_layout_of(plan), np.random.default_rng(s))
        t = Truth(t.model, t.params, {"accel_white": 0.02, "gyro_white": 1e-3})
        rec = simulate(plan, t, s)
        res = fit_accel(rec)
        sig = np.diag(res.sigma["accel_K"]) / np.sqrt(res.stats["sigma_inflation"])
        worst = max(worst, float(np.max(np.diag(res.sigma["accel_K"]))) / 50e-6)
        z.append((np.diag(res.params["accel_K"]) - np.diag(t.params["accel_K"])) / sig)
    return d, worst, np.concatenate(z)


def plan_layout_of(plan):
    from calib_cli.sim.simulate import plan_layout

    return plan_layout(plan)


@pytest.mark.slow
def test_optimize_static_target_over_seeds(tmp_path, run_cli):
    d, worst, z = optimized_static(SEEDS, tmp_path, run_cli)
    assert worst <= 1.1
    rms, q99 = pooled_rule(z)
    assert 0.8 <= rms <= 1.25 and q99 < 3.3, (rms, q99)


def optimized_turntable(seeds, tmp_path, run_cli):
    """plan optimize on the 9-cycle turntable plan with --target
    proof_mass_offsets=1e-3 (the simulator's MEMS unit): the optimized plan,
    simulated and fitted, reports sigma <= 1.1 x the target in every seed and its
    proof-mass errors meet the within-sigma rule."""
    import json

    from calib_cli.io.plan import load_plan
    from calib_cli.methods.turntable import fit_turntable
    from calib_cli.sim.simulate import simulate

    src, opt = tmp_path / "tt9.toml", tmp_path / "opt.toml"
    assert run_cli("plan", "make", "turntable", "--tilted", "--out", src)[0] == 0
    code, out, err = run_cli("plan", "optimize", src, "--target", "proof_mass_offsets=1e-3",
                             "--out", opt, "--json")
    assert code == 0, err
    d = json.loads(out)
    assert d["duration_s"] < d["duration_before_s"]
    plan = load_plan(opt)
    off = ~np.eye(3, dtype=bool)
    z, worst = [], 0.0
    for s in seeds:
        rec = simulate(plan, None, s)
        res = fit_turntable(rec)
        sig = np.asarray(res.sigma["proof_mass_offsets"], float)[off]
        worst = max(worst, float(np.max(sig)) / 1e-3)
        e = (np.asarray(res.params["proof_mass_offsets"], float)
             - np.asarray(rec.truth["params"]["proof_mass_offsets"], float))[off]
        z.append(e / sig)
    return d, worst, np.concatenate(z)


@pytest.mark.slow
def test_optimize_turntable_target_over_seeds(tmp_path, run_cli):
    d, worst, z = optimized_turntable(SEEDS, tmp_path, run_cli)
    rms, q99 = pooled_rule(z)
    print(f"turntable optimize: {d['member']}, {d['duration_s']:.0f} s (was "
          f"{d['duration_before_s']:.0f} s); worst fit sigma / target {worst:.3f}; "
          f"RMS z {rms:.3f}, 99th pct {q99:.2f}")
    assert worst <= 1.1
    assert 0.8 <= rms <= 1.25 and q99 < 3.3, (rms, q99)
