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
    """The table's angle and rate are imprecise: the fit must not need or use them."""
    opt = TurntableOptions(passes=1)
    a = fit_turntable(short_rec, opt)
    b = fit_turntable(short_rec.with_(table_angle=None, table_rate=None), opt)
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


def test_block_prediction_is_the_catalogue_model():
    """The filter's accelerometer block mean (its closed form for the extended first pass)
    is the effect catalogue's forward model on the block's mean kinematics, and the
    catalogue's rigid-body term with a mean centripetal operator reduces to w x (w x r)
    + dw x r for a single sample."""
    from calib_cli.methods.turntable import _block_accel, turntable_model
    from calib_cli.model.frames import skew
    from calib_cli.model.kinematics import Kinematics, rigid_accel, rigid_body_accel

    rng = np.random.default_rng(7)
    for tangential in (True, False):
        model = turntable_model(3, True, True, tangential)
        p = model.random_params(rng, typical={"lever_arm": 0.3, "proof_mass_offsets": 0.01})
        nb = 5
        ws = rng.normal(0, 3, (nb, 4, 3))  # four samples per block
        cen = np.array([np.mean([skew(w) @ skew(w) for w in blk], axis=0) for blk in ws])
        dw = rng.normal(0, 10, (nb, 3))
        f = rng.normal(0, 9.8, (nb, 3))
        kin = Kinematics(np.arange(nb, dtype=float), f, ws.mean(axis=1), dw,
                         cycle=np.full(nb, 1), cen=cen)
        want = model.predict(p, kin, sensors=("accel",))["accel"]
        for j in range(nb):
            C = cen[j] + (skew(dw[j]) if tangential else 0.0)
            got = _block_accel(p["accel_K"], p["accel_bias"], f[j], C,
                               p["lever_arm"][1][None, :] + p["proof_mass_offsets"])
            assert np.allclose(got, want[j], rtol=0, atol=1e-12)
    w, dw, r = rng.normal(size=(6, 3)), rng.normal(size=(6, 3)), rng.normal(size=3)
    one = Kinematics(np.zeros(6), np.zeros((6, 3)), w, dw,
                     cen=np.array([skew(v) @ skew(v) for v in w]))
    assert np.allclose(rigid_accel(one, r), rigid_body_accel(w, dw, r), atol=1e-14)



def test_accel_jacobian_is_the_catalogue_models_derivative(short_rec):
    """The filter's hand-written accelerometer rows of H (``_accel_rows``, which
    ``_filter_pass`` updates with) are the derivatives of the one forward model: central
    differences of ``ImuModel.predict`` on a block's mean kinematics, gravity in body axes
    from the block's mean attitude, at a linearisation point far from a neutral unit (the
    record's truth: K and G not identity, lever arms of 0.26-0.29 m, proof masses up to
    14 mm). Columns: accelerometer bias, K's free entries, the cycle's two lever-arm
    components (in its basis), the proof-mass offsets and the attitude error phi: to 1e-6
    of each column's norm (plus the differences' own rounding, eps |h| / step, which
    dominates for columns of 1e-3 m/s^2 per unit). The 21 gyro parameters, through the
    block's corrected gyros (its mean attitude from the block start, which the filter's
    phi carries, and its centripetal and tangential terms), to 1e-4 of the block's gyro
    rows (norm): the filter holds the specific force's proof-mass correction, which moves
    with the rates, fixed in the gyros' D f (measured 8e-5). (With each step's left
    Jacobian truncated at I + [step x]/2, as it was, the gyro columns were 1.4e-4 of the
    gravity part off at 200 deg/s and 100 Hz; strapdown.left_jacobian is now exact.)"""
    from dataclasses import replace

    from calib_cli.methods import turntable as tt
    from calib_cli.model.frames import skew
    from calib_cli.model.kinematics import Kinematics
    from calib_cli.model.strapdown import exp_matrix

    rec = short_rec
    truth = rec.truth["params"]
    cycles = tt._select(rec)
    L = tt._Layout(len(cycles), True, True, 1)
    theta = np.zeros(L.size)  # the contract parameters mapped as _pass_at does
    for key in tt.IMU_KEYS + ("proof_mass_offsets",):
        v = np.asarray(truth[key], float).ravel()
        for flat in tt._FREE.get(key, range(len(v))):
            theta[tt._column(L, key, flat)] = v[flat]
    for c, cy in enumerate(cycles):
        theta[L.idx["s"][2 * c:2 * c + 2]] = cy.basis.T @ truth["lever_arm"][c]
    par = tt._unpack(theta, L, cycles)
    for key in tt.IMU_KEYS + ("proof_mass_offsets", "lever_arm"):  # the mapping round trip
        assert np.abs(tt._contract_params(par)[key] - truth[key]).max() < 1e-15, key
    assert np.abs(par["K"] - np.eye(3)).max() > 5e-3 and np.abs(par["P"]).max() > 0.01
    model = tt.turntable_model(len(cycles), True, True, True)
    g_n = rec.site.specific_force_enu
    block_n = int(round(0.2 * rec.sample_rate))
    ns = 3 + L.size
    # the steps: 1e-6 of each group's scale (the "mems" prior widths), 1e-6 rad for phi
    width = tt.GRADES["mems"]
    step = np.full(ns, 1e-6)
    for key, short in tt._SHORT.items():
        step[3 + L.idx[short]] = 1e-6 * width[key]
    step[3 + L.idx["s"]] = 1e-6 * width["lever_arm"]
    groups = {"phi": np.arange(3), "ab": 3 + L.idx["ab"], "K": 3 + L.idx["K"],
              "p": 3 + L.idx["p"], "gyro": 3 + L.gyro}
    worst = dict.fromkeys(list(groups) + ["s"], 0.0)  # largest |H - fd| / |H| per group
    ratio = dict.fromkeys(worst, 0.0)  # largest |H - fd| / tolerance per group
    for c in (0, 1):
        # a window of 16 blocks about the cycle's fastest table acceleration (the ramp
        # from +200 to -200 deg/s): blocks at the steady rates and on the ramp
        w_ax = rec.gyro[cycles[c].sl] @ cycles[c].a_nom
        nbk = len(w_ax) // block_n
        wm = w_ax[:nbk * block_n].reshape(nbk, block_n).mean(axis=1)
        k = int(np.argmax(np.abs(np.diff(wm))))
        start = cycles[c].sl.start + (k - 8) * block_n
        cy = replace(cycles[c], sl=slice(start, start + 16 * block_n))
        # the attitude at the block start: the mounting turned about the table axis
        Rh = exp_matrix(cy.a_enu * 1.1) @ cy.rot_nom.as_matrix()
        b = tt._blocks(rec, cy, par, block_n, True, None)
        cols = {**groups, "s": 3 + L.idx["s"][2 * c:2 * c + 2]}

        def h(x, j, c=c, cy=cy, b=b, Rh=Rh, gyro=False):
            """The catalogue's block mean at state x = (phi, theta): predict on the
            block's mean kinematics (recomputed from the gyros if ``gyro``), gravity
            from the mean attitude exp(phi) Rh r_mean."""
            p = tt._unpack(theta + x[3:], L, cycles)
            bb = tt._blocks(rec, cy, p, block_n, True, None) if gyro else b
            gb = (exp_matrix(x[:3]) @ Rh @ bb.r_mean[j]).T @ g_n
            kin = Kinematics(bb.t[j:j + 1], gb[None], bb.wbar[j:j + 1], bb.dw[j:j + 1],
                             cycle=np.array([c]), cen=bb.cen[j:j + 1])
            return model.predict(tt._contract_params(p), kin, sensors=("accel",))["accel"][0]

        for j in (4, 8, 9, 12):  # 200 deg/s, on the ramp (3, -110 deg/s), -200 deg/s
            r = par["s"][c][None, :] + par["P"]
            Cw = b.cen[j] + skew(b.dw[j])
            H, Rbar, gb, KW = tt._accel_rows(
                L, c, cy.basis, ns, par["K"], r, Cw, Rh, b.r_mean[j], b.wg[:, j],
                tt._rigid_gyro_rows(par["K"], r, b.cg[j]), g_n, skew(g_n))
            # the linearised passes take the rigid-body gyro rows of all blocks at once
            assert np.array_equal(tt._rigid_gyro_rows(par["K"], r, b.cg)[j],
                                  tt._rigid_gyro_rows(par["K"], r, b.cg[j]))
            h0 = h(np.zeros(ns), j)
            # the linearised passes' prediction: the model without gravity, plus K gravity
            kin0 = Kinematics(b.t[j:j + 1], np.zeros((1, 3)), b.wbar[j:j + 1],
                              b.dw[j:j + 1], cycle=np.array([c]), cen=b.cen[j:j + 1])
            h_rig = model.predict(tt._contract_params(par, par["s"]), kin0,
                                  sensors=("accel",))["accel"][0]
            assert np.allclose(h_rig + par["K"] @ gb, h0, rtol=0, atol=1e-12)
            # nothing else in the accelerometer rows
            rest = np.ones(ns, bool)
            for cc in cols.values():
                rest[cc] = False
            assert not np.any(H[:, rest])
            kw_norm = float(np.linalg.norm(H[:, groups["gyro"]]))
            for name, cc in cols.items():
                for col in cc:
                    d = np.zeros(ns)
                    d[col] = step[col]
                    fd = (h(d, j, gyro=name == "gyro")
                          - h(-d, j, gyro=name == "gyro")) / (2 * step[col])
                    err = float(np.linalg.norm(H[:, col] - fd))
                    norm = float(np.linalg.norm(H[:, col]))
                    rnd = 4 * np.finfo(float).eps * np.abs(h0).max() / step[col]
                    tol = (1e-4 * kw_norm if name == "gyro" else 1e-6 * norm) + rnd
                    ratio[name] = max(ratio[name], err / tol)
                    if rnd < 1e-7 * norm:  # the differences' rounding below 1e-7 of it
                        worst[name] = max(worst[name], err / norm)
    print("\nlargest |analytic - fd| / |column| (columns > 1e7 rounding):",
          {k: f"{v:.1e}" for k, v in worst.items()},
          "\nlargest |analytic - fd| / tolerance:", {k: f"{v:.3f}" for k, v in ratio.items()})
    assert max(ratio.values()) < 1.0, ratio
