"""Rotating-table calibration (calib fit turntable): fast checks on simulated data.

The many-seed validation is tests/test_turntable_slow.py (make validate).
"""

from __future__ import annotations

import json
import re

import numpy as np
import pytest

from calib_cli.io.plan import parse_plan
from calib_cli.methods.turntable import TurntableOptions, fit_turntable
from calib_cli.sim.simulate import _table_errors, simulate
from calib_cli.sim.turntable_plans import TABLE_AXIS, cycle_attitudes, turntable_plan_text


def _z(res, truth):
    """Normalized errors of every estimated entry (sigma > 0)."""
    out = []
    for k, v in res.params.items():
        s = res.sigma[k]
        m = s > 0
        out.append(((v - truth[k])[m] / s[m]).ravel())
    return np.concatenate(out)


@pytest.fixture(scope="module")
def short_rec():
    plan = parse_plan(turntable_plan_text(3, duration_s=240.0))
    return simulate(plan, None, 3)


def test_plan_geometry():
    cyc = cycle_attitudes(tilted=True, tilt_deg=5.0)
    assert len(cyc) == 9
    from calib_cli.model.frames import attitude_to_rotation

    for _label, att, a_b in cyc:
        rot = attitude_to_rotation(np.radians(att))
        np.testing.assert_allclose(rot.apply(a_b), TABLE_AXIS, atol=1e-9)
    for _label, _att, a_b in cyc[3:]:
        # tilted 5 deg from its instrument axis, one axis orthogonal to the table axis
        assert np.degrees(np.arccos(np.max(np.abs(a_b)))) == pytest.approx(5.0)
        assert np.sum(np.abs(a_b) < 1e-12) == 1


def test_table_errors_only_on_request():
    plan = parse_plan(turntable_plan_text(0, duration_s=60.0))
    tau = np.arange(0, 60, 0.01)
    theta, rate, acc = tau * 1.0, np.ones_like(tau), np.zeros_like(tau)
    th, rt, ac = _table_errors(plan, tau, theta, rate, acc, np.random.default_rng(1))
    assert np.abs(rt - rate).max() > 1e-3  # the true motion is not the recorded one
    # the angle is the integral of the true rate
    np.testing.assert_allclose(np.gradient(th, tau)[5:-5], rt[5:-5], atol=1e-4)
    bare = parse_plan(turntable_plan_text(0, duration_s=60.0, rate_error=0.0, wobble_dps=0.0))
    rng = np.random.default_rng(1)
    th2, rt2, _ = _table_errors(bare, tau, theta, rate, acc, rng)
    assert th2 is theta and rt2 is rate
    assert rng.standard_normal() == np.random.default_rng(1).standard_normal()


def test_standard_cycles_within_sigma(short_rec):
    res = fit_turntable(short_rec, TurntableOptions(proof_mass="estimate"))
    truth = short_rec.truth["params"]
    z = _z(res, truth)
    assert len(z) == 3 + 6 + 3 + 9 + 9 + 6 + 6
    assert np.abs(z).max() < 4.5, np.round(z, 2)
    assert 0.5 < np.sqrt(np.mean(z**2)) < 1.6
    # lever arms within 5 mm (sub-mm in fact), axial entries fixed at 0 with sigma 0
    assert np.abs(res.params["lever_arm"] - truth["lever_arm"]).max() < 5e-3
    for c in range(3):
        assert res.params["lever_arm"][c, c] == 0 and res.sigma["lever_arm"][c, c] == 0
    assert res.params["lever_arm"].shape == (3, 3)
    assert res.stats["accel_noise_inflation"] == 1.0
    # sigma history: non-increasing on the whole, ends at the reported sigma
    h = res.tables["sigma_history"]
    assert h.shape[1] == len(res.tables["sigma_history_labels"]) == 12
    assert np.all(h[-1] <= h[0])


def test_tilted_table_axis_estimated():
    """A table whose axis is 0.3 deg out of level (not in the plan): the tilt is
    estimated (the vertical component; the azimuth only the earth rate sees), and the
    calibration stays within sigma; taking the plan's axis as exact does not."""
    text = turntable_plan_text(2, duration_s=240.0, axis_tilt_deg=0.3)
    true_axis = np.array(json.loads(re.search(r"sim_table_axis_enu = (\[.*\])", text).group(1)))
    rec = simulate(parse_plan(text), None, 2)
    truth = rec.truth["params"]
    res = fit_turntable(rec, TurntableOptions(proof_mass="estimate"))
    z = _z(res, truth)
    assert np.abs(z).max() < 4.5, np.round(z, 2)
    (tilt,) = res.stats["table_axis_tilt_mrad"]
    assert tilt["perpendicular_enu"] == [[0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
    assert tilt["sigma_mrad"][0] is None  # azimuth (north component): not determined
    assert abs(tilt["tilt_mrad"][1] - 1e3 * true_axis[2]) < 4.5 * tilt["sigma_mrad"][1]
    exact = fit_turntable(rec, TurntableOptions(proof_mass="estimate", table_tilt_sigma=0.0))
    assert np.abs(_z(exact, truth)).max() > 6.0


def test_table_records_are_not_used(short_rec):
    """The table's angle and rate are imprecise (a wobbling table): the fit's checks refuse
    them, and it does not need them."""
    opt = TurntableOptions()
    a = fit_turntable(short_rec, opt)
    b = fit_turntable(short_rec.with_(table_angle=None, table_rate=None), opt)
    assert a.stats["table_encoder"]["mode"] == "off"
    assert len(a.stats["table_encoder"]["notes"]) == 6
    for k in a.params:
        np.testing.assert_array_equal(a.params[k], b.params[k])


def test_variants_ordering(short_rec):
    """Lever arms estimated beat lever arms measured on the housing (+-5 mm), which beat
    lever arms ignored, on accelerometer scale factors and biases."""
    truth = short_rec.truth["params"]
    err = {}
    for mode in ("off", "known", "estimate"):
        r = fit_turntable(short_rec, TurntableOptions(lever_arm=mode,
                                                      proof_mass="estimate" if mode == "estimate"
                                                      else "off"))
        err[mode] = (np.sqrt(np.mean((r.params["accel_bias"] - truth["accel_bias"]) ** 2)),
                     np.sqrt(np.mean(np.diag(r.params["accel_K"] - truth["accel_K"]) ** 2)))
        if mode == "off":
            assert r.stats["accel_noise_inflation"] > 3  # the data says the model is wrong
    for i in range(2):
        assert err["estimate"][i] * 2 < err["known"][i] < err["off"][i], err


def test_tilted_cycles_proof_mass():
    plan = parse_plan(turntable_plan_text(5, duration_s=150.0, tilted=True, tilted_duration_s=80.0))
    rec = simulate(plan, None, 5)
    res = fit_turntable(rec, TurntableOptions(proof_mass="estimate"))
    truth = rec.truth["params"]
    assert res.params["lever_arm"].shape == (9, 3)
    # s . a = 0 for every cycle's nominal axis
    for c, (_l, _att, a) in enumerate(cycle_attitudes(tilted=True)):
        assert abs(res.params["lever_arm"][c] @ a) < 1e-12
    z = _z(res, truth)
    assert np.abs(z).max() < 4.5
    sp = res.sigma["proof_mass_offsets"][~np.eye(3, dtype=bool)]
    assert np.all(sp < 1e-3)


def test_tangential_off_skips_accelerations(short_rec):
    res = fit_turntable(short_rec, TurntableOptions(tangential=False, proof_mass="off"))
    truth = short_rec.truth["params"]
    z = _z(res, truth)
    # proof masses (5 mm) are not modelled here; all else within the fast bound
    assert np.abs(z).max() < 4.5, np.round(z, 2)
    assert res.stats["tangential"] is False


def test_cli_simulate_fit_show(tmp_path, run_cli):
    plan = tmp_path / "plan.toml"
    plan.write_text(turntable_plan_text(2, duration_s=120.0))
    raw, cal = tmp_path / "raw.h5", tmp_path / "cal.h5"
    code, _, err = run_cli("simulate", str(plan), "--out", str(raw), "--seed", "2")
    assert code == 0, err
    png = tmp_path / "hist.png"
    code, out, err = run_cli("fit", "turntable", str(raw), "--out", str(cal), "--json",
                             "--proof-mass", "estimate", "--plot", str(png))
    assert code == 0, err
    obj = json.loads(out)
    assert obj["method"] == "turntable"
    assert np.shape(obj["params"]["lever_arm"]) == (3, 3)
    assert np.shape(obj["sigma"]["proof_mass_offsets"]) == (3, 3)
    for key in ("accel_residual_rms", "unobservable", "g_error_rms_before", "g_error_rms_after"):
        assert key in obj["stats"]
    assert png.stat().st_size > 1000
    code, out, _ = run_cli("show", str(cal), "--json")
    assert code == 0 and json.loads(out)["params"]["accel_K"][0][1] == 0.0
    code, _, err = run_cli("report", str(cal), "--out", str(tmp_path / "rep"))
    assert code == 0, err
    md = (tmp_path / "rep" / "report.md").read_text()
    assert "## Rotating-table calibration" in md and "Lever arm of each cycle" in md
    figs = json.loads((tmp_path / "rep" / "figures.json").read_text())["figures"]
    # the sigma history, and the estimate history (lever arms and proof masses: two panels)
    assert [f["axes"] for f in figs] == [1, 2]


def test_cli_errors(tmp_path, run_cli):
    text = turntable_plan_text(2, duration_s=60.0)
    plan = tmp_path / "plan.toml"
    plan.write_text("\n".join(ln for ln in text.splitlines() if not ln.startswith("lever_arm_m")))
    raw = tmp_path / "raw.h5"
    assert run_cli("simulate", str(plan), "--out", str(raw))[0] == 0
    code, _, err = run_cli("fit", "turntable", str(raw), "--out", str(tmp_path / "c.h5"),
                           "--lever-arm", "known")
    assert code == 3 and "lever_arm_m" in err and str(raw) in err
    assert not (tmp_path / "c.h5").exists()
    static = tmp_path / "static.toml"
    static.write_text("kind = 'turntable'\n[[segment]]\nlabel = 'a'\nattitude_deg = [0, 0, 0]\n"
                      "duration_s = 5\n")
    raw2 = tmp_path / "raw2.h5"
    assert run_cli("simulate", str(static), "--out", str(raw2))[0] == 0
    code, _, err = run_cli("fit", "turntable", str(raw2), "--out", str(tmp_path / "d.h5"))
    assert code == 4 and "rotating" in err


def test_rigid_body_term_is_the_catalogue_model():
    """The catalogue's rigid-body term with a mean centripetal operator reduces to
    w x (w x r) + dw x r for a single sample."""
    from calib_cli.model.frames import skew
    from calib_cli.model.kinematics import Kinematics, rigid_accel, rigid_body_accel

    rng = np.random.default_rng(7)
    w, dw, r = rng.normal(size=(6, 3)), rng.normal(size=(6, 3)), rng.normal(size=3)
    one = Kinematics(np.zeros(6), np.zeros((6, 3)), w, dw,
                     cen=np.array([skew(v) @ skew(v) for v in w]))
    assert np.allclose(rigid_accel(one, r), rigid_body_accel(w, dw, r), atol=1e-14)


@pytest.mark.parametrize("kind", ["instant", "interval-mean"])
def test_rows_are_the_forward_models_derivative(kind):
    """The filter's rows (accelerometer block means, table axis, channels) are the
    derivatives of their own prediction: central differences of a pass's residuals over
    every parameter, the trajectory held, against the rows' parameter columns A_glob, at a
    point away from the neutral unit. Tolerance per column, in units of the column's
    largest whitened entry: 0.15 for the gyro parameters, whose within-block sensitivity is
    taken per group of samples (strapdown.block_integration: exact for the biases, the
    group's mean and slope for the g-sensitivity, which moves with the specific force within
    the group); 3e-2 for the others, whose path through the gyros' g-sensitivity (the
    corrected specific force D sees, with its proof-mass terms) the rows leave out. Measured
    (60 s cycles, 200 deg/s): 5e-2 (gyro_D about the spin axis; 0.12 for interval means,
    a cross-axis gyro_K column of 1e-4 at the start of a ramp) and 2e-2 (a proof-mass
    offset on the accelerometer axis along the spin). A Jacobian error of this size moves
    the converged estimate by that fraction of its sigma; the prediction is exact."""
    from calib_cli.methods.turntable import estimator as es
    from calib_cli.methods.turntable.fit import prepared
    from calib_cli.methods.turntable.result import theta_labels

    text = turntable_plan_text(3, duration_s=60.0)
    if kind != "instant":
        text = f'sample_kind = "{kind}"\n' + text
    rec = simulate(parse_plan(text), None, 3)
    pb, st = prepared(rec, TurntableOptions())
    rng = np.random.default_rng(1)
    st.theta = st.theta + rng.normal(0, 0.1, st.theta.size) * np.minimum(pb.pm.sd, 1e-2)
    nbs = [20] * len(pb.nb)
    pr = es.run_pass(pb, st, nbs)
    labels = theta_labels(pb)
    worst = {"gyro": 0.0, "other": 0.0}
    for i in range(st.theta.size):
        h = 1e-6 * max(min(pb.pm.sd[i], 1.0), 1e-4)
        rs = []
        for sgn in (1, -1):
            s2 = es.State(st.theta + sgn * h * np.eye(st.theta.size)[i], st.C, st.rho,
                          st.C_start, st.axis_var, st.inflation, st.lever2)
            rs.append(es.run_pass(pb, s2, nbs).systems)
        for c, cs in enumerate(pr.systems):
            fd = -(rs[0][c].r - rs[1][c].r) / (2 * h)
            an = cs.A_glob[:, :, i]
            scale = np.abs(an * cs.weight).max()
            if scale == 0:
                continue
            g = "gyro" if labels[i].startswith("gyro") else "other"
            worst[g] = max(worst[g], float(np.abs((fd - an) * cs.weight).max() / scale))
    print(f"\n{kind}: largest column error", {k: f"{v:.1e}" for k, v in worst.items()})
    assert worst["other"] < 3e-2 and worst["gyro"] < 0.15, worst


def test_no_gravity_reference_warns():
    """Issue 32: on a vertical table without a gravity reference the accelerometers'
    terms are not determined and some fits do not converge (docs/turntable.md): fit
    turntable says so."""
    from types import SimpleNamespace

    from calib_cli.methods.registry import _notes_turntable
    from calib_cli.methods.turntable.result import gravity_reference_words

    class _Pb:
        cycles = []

    words = gravity_reference_words(_Pb())
    assert words.startswith("none")
    lines = _notes_turntable(SimpleNamespace(stats={"gravity_reference": words}), None)
    assert any("not determined" in ln and "exit 4" in ln for ln in lines), lines
    assert not _notes_turntable(SimpleNamespace(stats={"gravity_reference": "the rotating"}), None)


def test_table_angle_linearised_exactly_at_the_pass():
    """The channels' rows take d angle_j / d phi_j = a^T C_j and no dependence on the other
    blocks' phi. Measured from a fixed reference (the cycle's start) that is turned and
    tilted from the first block, the first block's phi moved every later angle by 1 % of
    its own move (a vertical axis's valley: 4000 in chi^2 at a full step); rebased onto the
    first block at each pass (estimator.angle_reference) the angle's value stays and the
    dependence is gone."""
    from types import SimpleNamespace

    from scipy.spatial.transform import Rotation

    from calib_cli.methods.turntable.estimator import angle_reference
    from calib_cli.methods.turntable.rows import table_angle

    rng = np.random.default_rng(3)
    a = np.array([0.0, 0.0, 1.0])
    turns = Rotation.from_rotvec(np.outer(np.linspace(0.0, 30.0, 60), a))
    body = Rotation.from_rotvec([0.012, -0.008, 0.3])  # the unit's tilt on the table
    C = (turns * body).as_matrix()
    C_start = (Rotation.from_rotvec([0.01, 0.005, 0.8]) * Rotation.from_matrix(C[0])).as_matrix()
    pb = SimpleNamespace(cycles=[SimpleNamespace(a_enu=a)])
    st = SimpleNamespace(C=[C], C_start=[C_start], angle_ref=None)
    before = table_angle(C, a, C_start)
    angle_reference(pb, st)
    ref, off = st.angle_ref[0]
    np.testing.assert_allclose(off + table_angle(C, a, ref), before, atol=1e-12)
    phi = 1e-6 * rng.standard_normal(3)
    C1 = C.copy()
    C1[0] = C[0] @ Rotation.from_rotvec(phi).as_matrix()
    lin = np.zeros(len(C))
    lin[0] = float(C[0].T @ a @ phi)  # the rows' linearisation: block 0's angle alone
    rebased = off + table_angle(C1, a, ref) - before
    fixed = table_angle(C1, a, C_start) - before
    assert np.abs(rebased - lin).max() < 1e-4 * np.abs(phi).max()
    assert np.abs(fixed - lin).max() > 1e-2 * abs(lin[0])  # the fixed reference: 3.6 %


def test_follow_valley_keeps_the_gyro_response_linear():
    """estimator.follow_valley: after a step of the mountings and gyro_K, each rotating
    cycle's gyro response about its axis (K a_b) is where the step's linearisation puts
    it (the second-order part goes into K, along a_b), and nothing but gyro_K changes."""
    from calib_cli.methods.turntable import estimator as es
    from calib_cli.methods.turntable.fit import prepared
    from calib_cli.methods.turntable.setup import axis_in_body
    from tests.turntable_profiles import profile_record

    rec, _truth = profile_record(1, "trapezoid-100", duration_s=120.0, geometry="vertical",
                                 encoder=True)
    pb, _st = prepared(rec, TurntableOptions())
    assert pb.follow_valley
    rng = np.random.default_rng(0)
    pm = pb.pm
    th0 = pm.mean.copy()
    th1 = th0.copy()
    th1[pm.idx["mount"].ravel()] += rng.normal(0, 0.01, pm.idx["mount"].size)
    K_step = rng.normal(0, 0.01, (3, 3))
    pm.set_params(th1, {"gyro_K": np.asarray(pm.params(th0)["gyro_K"]) + K_step})
    out = es.follow_valley(pb, th0, th1)
    K0 = np.asarray(pm.params(th0)["gyro_K"])
    K = np.asarray(pm.params(out)["gyro_K"])
    for c, cy in enumerate(pb.cycles):
        if cy.static:
            continue
        a0, J0 = axis_in_body(cy, th0[pm.idx["mount"][c]])
        a1, _ = axis_in_body(cy, out[pm.idx["mount"][c]])
        du = out[pm.idx["mount"][c]] - th0[pm.idx["mount"][c]]
        want = K0 @ a0 + K_step @ a0 + K0 @ (J0 @ du)
        np.testing.assert_allclose(K @ a1, want, atol=1e-12)
    other = np.ones(pm.size, bool)
    other[[int(pm.idx["packing"][q]) for q, (key, _f) in enumerate(pm.keys) if key == "gyro_K"]] = False
    np.testing.assert_array_equal(out[other], th1[other])


def test_propagation_rows_exact_along_a_re_propagated_heading():
    """rows.cycle_system: the propagation rows' Jacobian in the blocks' attitude errors is
    exact to first order (F = Exp(-e_j) r_end^T), also along a step that re-propagates
    the trajectory (phi_j+1 = r_end^T phi_j: a vertical axis's heading carried by the
    gyros' bias and scale), where r_end^T alone misses e_j x phi_j, the whole of the
    mismatch's change."""
    from scipy.spatial.transform import Rotation

    from calib_cli.methods.turntable import estimator as es
    from calib_cli.methods.turntable.fit import prepared
    from tests.turntable_profiles import profile_record

    rec, _truth = profile_record(1, "trapezoid-100", duration_s=60.0, geometry="vertical")
    pb, st = prepared(rec, TurntableOptions(table_encoder="off"))
    es.run_pass(pb, st, pb.nb)  # (the trajectory propagated over the whole cycle)
    # a trajectory off its propagation by the gyros' noise over a block (4e-5 rad)
    noise = np.random.default_rng(2).normal(0.0, 4e-5, (len(st.C[0]), 3))
    st.C[0] = np.einsum("bij,bjk->bik", st.C[0], Rotation.from_rotvec(noise).as_matrix())
    pr = es.run_pass(pb, st, pb.nb)
    cs, gp = pr.systems[0], pr.gps[0]
    F_plain = np.swapaxes(gp.r_end[:-1], 1, 2)
    phi = np.zeros((cs.nb, 3))
    phi[0] = 1e-3 * (st.C[0][0].T @ pb.cycles[0].a_enu)  # a heading of 1 mrad, carried on
    for j in range(cs.nb - 1):
        phi[j + 1] = F_plain[j] @ phi[j]
    C = [np.einsum("bij,bjk->bik", st.C[0][:cs.nb], Rotation.from_rotvec(phi).as_matrix())]
    moved = es.State(st.theta, C + st.C[1:], st.rho, st.C_start, st.axis_var, st.inflation,
                     st.lever2, st.angle_ref)
    de = es.run_pass(pb, moved, pb.nb).systems[0].e - cs.e
    lin = phi[1:] - np.einsum("bij,bj->bi", cs.F, phi[:-1])
    lin_plain = phi[1:] - np.einsum("bij,bj->bi", F_plain, phi[:-1])  # = 0
    assert np.abs(de).max() > 1e-8  # the mismatch does change: e_j x phi_j
    assert np.abs(de - lin).max() < 1e-2 * np.abs(de).max()
    assert np.abs(de - lin_plain).max() > 0.5 * np.abs(de).max()


def test_rate_sensitivity_carries_the_accelerometer_path():
    """blocks.rate_sensitivity with accelerometer columns: the corrected rates' change
    with the accelerometer parameters through the gyros' g-sensitivity D f, against
    finite differences of the corrections."""
    from calib_cli.methods.turntable.blocks import rate_sensitivity
    from calib_cli.methods.turntable.estimator import columns_of
    from calib_cli.methods.turntable.fit import prepared
    from calib_cli.model.correction import correct
    from calib_cli.model.kinematics import Kinematics
    from tests.turntable_profiles import profile_record

    rec, _truth = profile_record(1, "trapezoid-100", duration_s=60.0, geometry="vertical",
                                 encoder=True)
    pb, _st = prepared(rec, TurntableOptions())
    assert pb.accel_path
    pm = pb.pm
    th = pm.mean.copy()
    rng = np.random.default_rng(3)
    pm.set_params(th, {"gyro_D": rng.normal(0, 1e-3, (3, 3)),
                       "accel_bias": rng.normal(0, 0.05, 3)})
    A, W = rec.accel[:200], rec.gyro[:200]

    def rates(theta):
        p = pm.params(theta, pb.lever_known)
        f = correct(pb.model, p, "accel", A)
        return correct(pb.model, p, "gyro", W, other=f), f

    w, f = rates(th)
    kin = Kinematics(rec.time[:200], f, w, np.zeros_like(w))
    acc_cols, acc_idx = columns_of(pb.model, pm, "accel")
    s = rate_sensitivity(pb.model, pm.params(th, pb.lever_known), kin, pb.gyro_cols, acc_cols)
    ng = len(pb.gyro_cols)
    for k, i in enumerate(acc_idx):
        if acc_cols[k][0] not in ("accel_bias", "accel_K"):  # (the rigid-body terms: rows)
            continue
        h = 1e-4 * max(pm.sd[i], 1e-3)
        t1 = th.copy()
        t1[i] += h
        fd = (rates(t1)[0] - w) / h
        np.testing.assert_allclose(s[:, :, ng + k], fd, rtol=1e-3, atol=1e-9)
