"""Experiment design (issue 20, docs/plan.md): plan check agrees with the fit,
predicts the unobservable entries exactly, and generated plans run out of the
box. The many-seed acceptance runs are in test_plan_slow.py."""

import json

import numpy as np
import pytest

from calib_cli import design
from calib_cli.io.plan import parse_plan
from calib_cli.sim import plan_make as pm
from calib_cli.sim.simulate import simulate
from tests import plan_cases as pc


def _write(tmp_path, name, d):
    p = tmp_path / f"{name}.toml"
    p.write_text(pm.to_toml(d))
    return p


# -- agreement with the fit on the same record -----------------------------------

@pytest.mark.parametrize("name", ["vector", "scalar", "ferraris", "align", "rimu"])
def test_predicted_sigma_matches_fit_sigma(name):
    """plan check --like RAW over the fit's sigma on RAW (without its chi^2
    inflation) lies in [0.87, 1.15] for every parameter; one seed's errors are
    within 4 predicted sigma."""
    plan = pc.plan_of(name)
    truth = pc.truth_of(name, plan)
    rec = simulate(plan, truth, 7)
    pred = design.check(plan, "auto", design.noise_like(rec), truth, suggestions=False)
    res = pc.fit(pred.method, rec)
    assert sorted(pred.result.sigma) == sorted(res.sigma)
    assert pred.unobservable == res.stats["unobservable"] == []
    for key, r in pc.sigma_ratios(pred, res).items():
        assert len(r), key
        assert r.min() >= 0.87 and r.max() <= 1.15, (key, r.min(), r.max())
    z = pc.normalised_errors(name, 7, design.check(plan, truth=truth, suggestions=False))
    assert max(np.abs(v).max() for v in z.values()) < 4.0


# plans written from the contract alone (issue 33): attitudes unknown (the simulator would
# draw them at random), no g; a navigation-grade alignment with its turn recorded
CONTRACT_PLANS = {
    "scalar-unknown-attitudes": (
        'name = "scalar18"\nkind = "static"\nsample_rate_hz = 100.0\ntransition_s = 3.0\n'
        "[site]\nlatitude_deg = 45.0\n"
        + "".join(f'[[segment]]\nlabel = "p{i}"\nduration_s = 10.0\n' for i in range(18))),
    "align-navigation-unknown-attitude": (
        'name = "align-contract"\nkind = "align"\nsample_rate_hz = 100.0\n'
        'transition_s = 4.0\n[site]\nlatitude_deg = 48.0\n'
        '[[segment]]\nlabel = "position-1"\nduration_s = 120.0\n'
        '[[segment]]\nlabel = "turn"\nrotation_axis_body = [0.0, 0.0, 1.0]\n'
        "rotation_angle_deg = 90.0\nduration_s = 10.0\n"
        '[[segment]]\nlabel = "position-2"\nduration_s = 120.0\n'),
}


@pytest.mark.parametrize("name", sorted(CONTRACT_PLANS))
def test_contract_plan_prediction_matches_fit(name):
    """As above on plans that leave the attitudes unknown: the prediction takes them from
    the --like recording (design.attitudes_like), where the information of the fit
    depends on them (at the simulator's random attitudes the median ratio was 0.42 for
    the alignment's accel_bias, 1.55-1.90 on the issue's hidden scalar records)."""
    plan = parse_plan(CONTRACT_PLANS[name], f"{name}.toml")
    rec = simulate(plan, None, 12)
    pred = design.check(plan, "auto", design.noise_like(rec), suggestions=False)
    res = pc.fit(pred.method, rec)
    assert pred.unobservable == res.stats["unobservable"] == []
    for key, r in pc.sigma_ratios(pred, res).items():
        assert len(r) and r.min() >= 0.87 and r.max() <= 1.15, (key, r.min(), r.max())


def test_like_through_the_command_line(run_cli, tmp_path):
    """The same through `calib plan check --like --json` and `calib fit`."""
    plan = tmp_path / "plan.toml"
    plan.write_text(CONTRACT_PLANS["scalar-unknown-attitudes"])
    assert run_cli("simulate", plan, "--out", tmp_path / "raw.h5", "--seed", 4)[0] == 0
    code, so, err = run_cli("plan", "check", plan, "--like", tmp_path / "raw.h5", "--json",
                            "--no-suggest")
    assert code == 0, err
    pred = json.loads(so)
    assert run_cli("fit", "accel", tmp_path / "raw.h5", "--out", tmp_path / "cal.h5")[0] == 0
    fit = json.loads(run_cli("show", tmp_path / "cal.h5", "--json")[1])
    assert pred["method"] == "scalar"
    for k in ("accel_bias", "accel_K"):
        a, b = np.asarray(pred["sigma"][k], float), np.asarray(fit["sigma"][k], float)
        ok = np.isfinite(b) & (b > 0)
        assert 0.87 <= np.median(a[ok] / b[ok]) <= 1.15, (k, a, b)
    assert pred["unobservable"] == fit["stats"]["unobservable"]


def test_like_a_recording_of_another_plan_lends_its_noise_only():
    """--like a recording of another plan (a new plan checked against last week's record):
    its segment i is some other position, so its attitudes (and a turntable's lever arms
    and channels) are not the plan's; only its noise levels carry over, and the output
    says so."""
    text = CONTRACT_PLANS["scalar-unknown-attitudes"]
    plan = parse_plan(text, "a.toml")
    rec = simulate(plan, None, 4)  # the simulator's unit, with noise
    other = parse_plan(text.replace('label = "p3"', 'label = "q3"'), "b.toml")
    assert design.recorded_from(plan, rec) and not design.recorded_from(other, rec)
    assert design.recorded_from(other, rec.with_(plan_text=""))  # imported: taken as is
    nz = design.noise_like(rec)
    own = design.check(plan, "auto", nz, suggestions=False)
    pred = design.check(other, "auto", nz, suggestions=False)
    assert "another plan" in pred.noise.source and "another plan" not in own.noise.source
    np.testing.assert_allclose(pred.noise.accel, own.noise.accel)
    # the plans differ in one label only: the prediction differs because the other plan's
    # positions are not simulated at the recorded attitudes
    a, b = (np.asarray(x.result.sigma["accel_K"], float) for x in (own, pred))
    assert not np.allclose(a, b, rtol=1e-3), (a, b)


# -- unobservable entries predicted exactly ---------------------------------------

def test_two_position_east_axis_unobservable_exact():
    d, warning = pm.align_plan(axis=(1, 0, 0), start=(0, 0, 0))
    assert "East-West" in warning
    plan = parse_plan(pm.to_toml(d), "<ew>")
    rec = simulate(plan, None, 3)
    pred = design.check(plan, noise=design.noise_like(rec), suggestions=False)
    res = pc.fit("align", rec)
    want = ["accel_bias[0]", "gyro_bias[0]", "attitude[1]", "attitude[2]"]
    assert pred.unobservable == res.stats["unobservable"] == want


def test_static_plan_in_one_plane_unobservable_exact():
    """Gravity always in the body x-y plane: K's z column is lost (f_z = 0 in
    every position), the biases stay (the positions are not all at one f)."""
    ups = [np.array(u, float) for u in ([1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0],
                                        [1, 1, 0], [1, -1, 0], [-1, 1, 0])]
    atts = [pm.attitude_up(u) for u in ups]
    d = pm._base("planar", "static", 100.0, {"method": "custom"})
    d["segment"] = [{"label": f"p{i}", "attitude_deg": a, "duration_s": 10.0}
                    for i, a in enumerate(atts)]
    plan = parse_plan(pm.to_toml(d), "<planar>")
    rec = simulate(plan, None, 1)
    pred = design.check(plan, noise=design.noise_like(rec))
    from calib_cli.methods.accel_lsq import fit_vector

    res = fit_vector(rec, strict=False)
    assert pred.unobservable == res.stats["unobservable"]
    assert pred.unobservable == ["accel_K[0,2]", "accel_K[1,2]", "accel_K[2,2]"]
    # the top suggestion makes everything observable: a position with body z vertical
    top = pred.suggestions[0]
    assert set(top["fixes"]) == set(pred.unobservable)
    assert "z" in top["add"]


def test_rimu_sensor_never_excited_unobservable_exact():
    """Only z-up and z-down, table at rest: the horizontal sensors see nothing."""
    d = pm.rimu_plan(table_rate=0.0)
    d["segment"] = [s for s in d["segment"] if s["label"] in ("z-up", "z-down")]
    plan = parse_plan(pm.to_toml(d), "<rimu-z>")
    truth = pc.truth_of("rimu", plan)
    rec = simulate(plan, truth, 2)
    pred = design.check(plan, noise=design.noise_like(rec), truth=truth, suggestions=False)
    from calib_cli.methods.rimu import fit_rimu

    res = fit_rimu(rec)
    assert pred.unobservable == res.stats["unobservable"]
    assert "accel_scale_error[0]" in pred.unobservable


# -- generated plans out of the box ----------------------------------------------

@pytest.mark.parametrize("args,fit", [
    (["static", "--positions", "6"], ["fit", "accel"]),
    (["static", "--positions", "12", "--fit", "scalar"], ["fit", "accel"]),
    (["ferraris"], ["fit", "gyro"]),
    (["align", "--axis", "0,1,1", "--angle", "90", "--duration", "60"], ["fit", "align"]),
    (["rimu"], ["fit", "rimu"]),
])
def test_plan_make_check_simulate_fit(tmp_path, run_cli, args, fit):
    plan = tmp_path / "p.toml"
    code, _, err = run_cli("plan", "make", *args, "--out", plan)
    assert code == 0, err
    assert "[generator]" in plan.read_text()
    code, out, err = run_cli("plan", "check", plan, "--json", "--no-suggest")
    assert code == 0, err
    d = json.loads(out)
    assert {"method", "params", "sigma", "unobservable", "suggestions"} <= set(d)
    assert d["unobservable"] == []
    raw, cal = tmp_path / "raw.h5", tmp_path / "cal.h5"
    assert run_cli("simulate", plan, "--out", raw, "--seed", "1")[0] == 0
    code, _, err = run_cli(*fit, raw, "--out", cal)
    assert code == 0, err
    code, out, _ = run_cli("show", cal, "--json")
    shown = json.loads(out)
    for k, s in d["sigma"].items():
        assert np.shape(shown["sigma"][k]) == np.shape(s), k
    # plan check --like RAW against the fit's sigma on RAW (its inflation removed)
    code, out, err = run_cli("plan", "check", plan, "--like", raw, "--json", "--no-suggest")
    assert code == 0, err
    like = json.loads(out)
    infl = float(shown["stats"].get("sigma_inflation") or 1.0)
    for k, s in like["sigma"].items():
        a = np.array(s, dtype=float)
        b = np.array(shown["sigma"][k], dtype=float) / np.sqrt(infl)
        ok = np.isfinite(a) & (a > 0) & np.isfinite(b) & (b > 0)
        if args[0] == "rimu" and k.endswith(("_dAz", "_dEl")):
            # a sensor along body z: its sigma depends on its unknown tilt (docs/plan.md)
            el0 = parse_plan(plan.read_text(), str(plan)).rimu_el0
            ok &= np.abs(np.abs(el0) - np.pi / 2) > 1e-6
        r = a[ok] / b[ok]
        assert r.min() >= 0.87 and r.max() <= 1.15, (k, r.min(), r.max())


def test_plan_make_bad_options_exit_2(tmp_path, run_cli):
    code, _, err = run_cli("plan", "make", "static", "--positions", "6", "--fit", "scalar",
                           "--out", tmp_path / "x.toml")
    assert code == 2 and "9 positions" in err
    assert not (tmp_path / "x.toml").exists()


def test_plan_make_turntable_limits(tmp_path, run_cli):
    plan = tmp_path / "tt.toml"
    code, _, err = run_cli("plan", "make", "turntable", "--tilted", "--max-rate", "100",
                           "--max-accel", "50", "--max-duration", "2000", "--out", plan)
    assert code == 0, err
    p = parse_plan(plan.read_text(), str(plan))
    assert sum(s.kind == "rotating" for s in p.segments) == 9
    for s in p.segments:
        knots = np.array(s.extra["rate_profile"])
        assert np.abs(knots[:, 1]).max() <= 100.0 + 1e-9
        slope = np.abs(np.diff(knots[:, 1]) / np.diff(knots[:, 0]))
        assert slope.max() <= 50.0 + 1e-6
    total = sum(s.duration for s in p.segments) + 4.0 * 8
    assert total <= 2000.0 + 1e-6


def test_plan_make_turntable_simulate_fit(tmp_path, run_cli):
    plan, raw, cal = tmp_path / "tt.toml", tmp_path / "tt.h5", tmp_path / "ttc.h5"
    assert run_cli("plan", "make", "turntable", "--duration", "120", "--out", plan)[0] == 0
    assert "lever_arm_m" not in plan.read_text()
    assert run_cli("simulate", plan, "--out", raw, "--seed", "1")[0] == 0
    code, _, err = run_cli("fit", "turntable", raw, "--out", cal)
    assert code == 0, err


@pytest.fixture(scope="module")
def short_turntable():
    """A generated 3-cycle plan of 120 s cycles and one simulated record of it."""
    plan = parse_plan(pm.to_toml(pm.turntable_plan(duration=120.0)), "<tt3>")
    return plan, simulate(plan, None, 7)


def test_turntable_predicted_sigma_matches_fit_sigma(short_turntable):
    """The turntable plan check (the fit's own set-up and its final linearised filter pass
    at the unit, started like the fit's from the prior plus a coarser pass's information)
    over the fit's sigma on the same record: [0.87, 1.15] for every entry (issue 20: started
    from the prior alone, one accel_K and one gyro_K cross-axis entry came out 0.49 and
    0.69)."""
    plan, rec = short_turntable
    pred = design.check(plan, "auto", design.noise_like(rec), suggestions=False)
    res = pc.fit("turntable", rec)
    assert pred.method == "turntable" and sorted(pred.result.sigma) == sorted(res.sigma)
    assert pred.unobservable == res.stats["unobservable"] == []
    for key, r in pc.sigma_ratios(pred, res).items():
        assert len(r), key
        assert r.min() >= 0.87 and r.max() <= 1.15, (key, r.min(), r.max())


def test_turntable_prediction_takes_the_levels_of_like(short_turntable):
    """plan check --like RAW predicts at the levels the fit of RAW estimated (the table
    axis's noise, the sensors' white noise), on the fit's own rows: the same levels in
    stats.prediction_levels, and without --like the table at its best (the axis at the
    fit's floor) gives sigma no larger."""
    import warnings

    from calib_cli.methods.turntable import TurntableOptions
    from calib_cli.methods.turntable.design import covariance_at, levels_of

    plan, rec = short_turntable
    nom = design.nominal_truth(plan)
    clean = simulate(plan, nom, 0)
    opt = TurntableOptions()
    lv = levels_of(rec, opt)
    with warnings.catch_warnings():
        warnings.simplefilter("error", RuntimeWarning)
        like = covariance_at(clean, opt, {"accel": lv.accel, "gyro": lv.gyro}, like=rec)
        best = covariance_at(clean, opt, {"accel": lv.accel, "gyro": lv.gyro})
    got = like.stats["prediction_levels"]
    assert got["source"] == "like" and best.stats["prediction_levels"]["source"] == "stated"
    assert abs(got["table_axis_noise_mrad"] - lv.axis * 1e3) < 1e-9
    for key, s in like.sigma.items():
        s, t = np.asarray(s, float), np.asarray(best.sigma[key], float)
        ok = np.isfinite(s) & (s > 0)
        assert np.all(t[ok] <= s[ok] * 1.001), key


def test_turntable_proof_masses_unobservable_without_tangential(short_turntable):
    """Three axial cycles and the tangential term off: the proof-mass offsets are
    unobservable, exactly as the fit's stats.unobservable on a record of the plan."""
    from calib_cli.methods.turntable import TurntableOptions, fit_turntable

    plan, rec = short_turntable
    pred = design.check(plan, "turntable", design.noise_like(rec), None,
                        {"tangential": "off"}, suggestions=False)
    res = fit_turntable(rec, TurntableOptions(tangential=False))
    want = [f"proof_mass_offsets[{i},{j}]" for i in range(3) for j in range(3) if i != j]
    assert pred.unobservable == res.stats["unobservable"] == want


def test_turntable_check_cli_options(tmp_path, run_cli):
    plan = tmp_path / "tt.toml"
    assert run_cli("plan", "make", "turntable", "--duration", "60", "--tilted-duration", "60",
                   "--out", plan)[0] == 0
    code, out, err = run_cli("plan", "check", plan, "--tangential", "off", "--json")
    assert code == 0, err
    d = json.loads(out)
    assert d["method"] == "turntable" and len(d["unobservable"]) == 6
    assert d["sigma"]["proof_mass_offsets"][0][1] is None
    # without the tangential term a tilted cycle fixes none of them: its centripetal term
    # w^2 (a_i a.p_i - (s_i - a_i a.s)) ties p_xy, p_yx and the cycle's lever arm across
    # its tilt in two equations of the same w^2 signature (three unknowns)
    assert not any(s["fixes"] for s in d["suggestions"])
    # with it, the three axial cycles determine them all
    code, out, err = run_cli("plan", "check", plan, "--json")
    assert code == 0, err
    assert json.loads(out)["unobservable"] == []
    static = _write(tmp_path, "s", pm.static_plan(6))
    code, _, err = run_cli("plan", "check", static, "--tangential", "off")
    assert code == 2 and "turntable" in err


def test_align_degenerate_axis_warns(tmp_path, run_cli):
    code, _, err = run_cli("plan", "make", "align", "--axis", "1,0,0", "--start", "0,0,0",
                           "--out", tmp_path / "a.toml")
    assert code == 0 and "East-West" in err


# -- inputs ----------------------------------------------------------------------

def test_noise_units_and_usage(tmp_path, run_cli):
    from calib_cli.cli.cmd_plan import parse_noise

    assert parse_noise("8mg", "accel") == pytest.approx(8e-3 * 9.80665)
    assert parse_noise("0.05dps", "gyro") == pytest.approx(np.radians(0.05))
    assert parse_noise("0.003", "accel") == 0.003
    plan = _write(tmp_path, "s", pm.static_plan(6))
    code, out, _ = run_cli("plan", "check", plan, "--accel-noise", "8mg", "--json",
                           "--no-suggest")
    assert code == 0
    a = json.loads(out)["sigma"]["accel_bias"][0]
    code, out, _ = run_cli("plan", "check", plan, "--accel-noise", "4mg", "--json",
                           "--no-suggest")
    assert json.loads(out)["sigma"]["accel_bias"][0] == pytest.approx(a / 2, rel=1e-3)
    assert run_cli("plan", "check", plan, "--accel-noise", "8parsec")[0] == 2
    assert run_cli("plan", "check", plan, "--like", plan, "--rate", "50")[0] == 2
    bad = tmp_path / "bad.toml"
    bad.write_text("kind = 'static'\n")
    code, _, err = run_cli("plan", "check", bad)
    assert code == 3 and "bad.toml" in err and len(err.strip().splitlines()) == 1
    three = tmp_path / "three.toml"
    three.write_text("kind = 'static'\n" + "".join(
        f"[[segment]]\nattitude_deg = {a}\n" for a in ([0, 0, 0], [180, 0, 0], [90, 0, 0])))
    code, _, err = run_cli("plan", "check", three)
    assert code == 4 and "three.toml" in err and ">= 4 static positions" in err
    assert "static detection" not in err and len(err.strip().splitlines()) == 1
    auto = tmp_path / "auto.toml"
    auto.write_text("kind = 'static'\n[[segment]]\nrepeat = 'auto'\n")
    code, _, err = run_cli("plan", "check", auto)
    assert code == 4 and "repeat" in err


def test_optimize_static_target_few_seeds(tmp_path, run_cli):
    from tests.test_plan_slow import optimized_static

    d, worst, z = optimized_static(range(3), tmp_path, run_cli)
    assert d["achieved"]["accel_K.diag=5e-05"] <= 50e-6
    assert worst <= 1.1 and np.abs(z).max() < 4.0
    assert d["member"] == "6 positions" and d["duration_s"] < 0.5 * d["duration_before_s"]


def test_record_warning_one_line(run_cli):
    """calib record's pre-check: one line for a plan that cannot deliver, nothing
    for a good plan or a repeat = "auto" plan."""
    d = pm.static_plan(6)
    good = parse_plan(pm.to_toml(d), "good.toml")
    assert design.record_warning(good, 100.0) is None
    d["segment"] = [s for s in d["segment"] if not s["label"].startswith("z")]
    flat = parse_plan(pm.to_toml(d), "flat.toml")
    w = design.record_warning(flat, 100.0)
    assert w and "unobservable" in w and "flat.toml" in w and "\n" not in w
    # a thermal plan without a rate table: gyro_temp_scale is the method's, not the plan's
    th, _ = pm.thermal_plan(design="soak", temps=5, soak=300.0, duration=20.0)
    assert design.record_warning(parse_plan(pm.to_toml(th), "th.toml"), 10.0) is None
    assert design.compact_labels([f"p[{i}]" for i in range(6)] + ["b[0]"]) == "p (6 entries), b[0]"
    auto = parse_plan("kind = 'static'\n[[segment]]\nrepeat = 'auto'\n", "auto.toml")
    assert design.record_warning(auto, 100.0) is None
    code, out, _ = run_cli("record", "--help")
    assert code == 0 and "--no-check" in out


def test_optimize_turntable_family(tmp_path, run_cli):
    """The turntable family: with and without the tilted cycles, the cycle durations
    scaled through the generator (never below 60 s); a plan without [generator]: exit 4.
    The 20-seed acceptance of the optimized plan is in test_plan_slow.py."""
    gen = pm.turntable_plan(tilted=True)["generator"]
    fam = dict(design._turntable_family(gen))
    assert set(fam) == {"3 axial and 6 tilted cycles", "3 axial cycles"}
    kw = fam["3 axial and 6 tilted cycles"]
    assert 2 ** design._turntable_lowest(kw) * 300.0 == pytest.approx(60.0)
    half = design._turntable_scaled(kw, 0.5)
    assert half["generator"]["duration_s"] == 300 and half["generator"]["tilted_duration_s"] == 150
    assert len(half["segment"]) == 9
    assert len(design._turntable_scaled(fam["3 axial cycles"], 0.5)["segment"]) == 3
    d = pm.turntable_plan()
    del d["generator"]
    plan = _write(tmp_path, "nogen", d)
    code, _, err = run_cli("plan", "optimize", plan, "--target", "proof_mass_offsets=1e-3")
    assert code == 4 and "plan make turntable" in err and len(err.strip().splitlines()) == 1


def test_turntable_like_a_recording_of_another_plan():
    """The same for a turntable plan: --like a record of another plan lends the levels the
    fit of that record estimates (and which channels it used), not its lever arms or its
    channels cycle by cycle."""
    from tests.turntable_profiles import profile_plan_text, profile_record

    rec, _ = profile_record(0, "trapezoid-100", duration_s=150.0)
    text = profile_plan_text(0, "trapezoid-100", duration_s=150.0)
    other = parse_plan(text.replace("label = 'x-axis'", "label = 'renamed'", 1), "b.toml")
    assert not design.recorded_from(other, rec)
    pred = design.check(other, "turntable", design.noise_like(rec), suggestions=False)
    assert "another plan" in pred.noise.source
    assert pred.result.stats["prediction_levels"]["source"] == "like"
    assert np.all(np.isfinite(np.asarray(pred.result.sigma["gyro_bias"], float)))
