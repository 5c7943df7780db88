"""Two-position analytic alignment (issue 3): fast tests (docs/align.md)."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from calib_cli.errors import EstimationError
from calib_cli.methods.align import fit_align
from calib_cli.methods.align_classic import fit_classic
from calib_cli.model import kinematics as kn
from calib_cli.model.earth import Site
from calib_cli.model.frames import attitude_to_rotation
from calib_cli.model.strapdown import integrate_relative
from calib_cli.sim.simulate import simulate
from calib_cli.validation import align_cases as ac

D2R = np.pi / 180


def _z(case):
    return case["err"] / case["sigma"]


# ---------------------------------------------------------------------------
# the earth rate during the turn


def test_strapdown_removes_earth_rate():
    """Integrating the true rates of a 130 deg turn gives the true rotation to
    1e-9 rad with the earth rate removed, and an error of ~1e-3 rad without."""
    site = Site(latitude=32 * D2R)
    t = np.arange(0, 18.0, 0.02)
    C0 = attitude_to_rotation(np.array([0.8, -0.5, 30.0]) * D2R)
    phi = np.array([1.0, 1.0, 1.0]) / np.sqrt(3) * 130 * D2R
    kin = kn.slew_kinematics(t, C0, C0 * Rotation.from_rotvec(phi), site, phi=phi)
    rel = integrate_relative(t, kin.w, C0, site)
    err = (rel.dR * Rotation.from_rotvec(phi).inv()).magnitude()
    assert err < 1e-9
    # without removal (rates integrated as if the earth did not turn): ~W T
    q = Rotation.identity()
    for w0, w1, dt in zip(kin.w[:-1], kin.w[1:], np.diff(t), strict=True):
        q = q * Rotation.from_rotvec(0.5 * (w0 + w1) * dt)
    assert (q * Rotation.from_rotvec(phi).inv()).magnitude() > 5e-4


def test_strapdown_sensitivities_match_reintegration():
    site = Site(latitude=32 * D2R)
    t = np.arange(0, 18.0, 0.02)
    C0 = attitude_to_rotation(np.array([0.8, -0.5, 30.0]) * D2R)
    phi = np.array([0.3, -1.0, 0.4]) * 2.0
    kin = kn.slew_kinematics(t, C0, C0 * Rotation.from_rotvec(phi), site, phi=phi)
    rel = integrate_relative(t, kin.w, C0, site)
    d = np.array([1e-6, -2e-6, 3e-6])
    rel2 = integrate_relative(t, kin.w - d, C0, site)
    psi = (rel2.dR * rel.dR.inv()).as_rotvec()
    assert np.allclose(psi, -rel.S_bias @ d, rtol=1e-3, atol=1e-7)  # earth-term coupling ~ W T psi
    dG = np.random.default_rng(0).standard_normal((3, 3)) * 1e-4
    rel3 = integrate_relative(t, kin.w - kin.w @ dG.T, C0, site)
    psi = (rel3.dR * rel.dR.inv()).as_rotvec()
    assert np.allclose(psi, -rel.S_K @ dG.ravel(), rtol=1e-3, atol=1e-8)
    alpha = np.array([2e-4, -1e-4, 3e-4])
    rel4 = integrate_relative(t, kin.w, Rotation.from_rotvec(alpha) * C0, site)
    psi = (rel4.dR * rel.dR.inv()).as_rotvec()
    assert np.allclose(psi, rel.earth_sensitivity(C0, site) @ alpha, rtol=1e-2, atol=1e-10)


# ---------------------------------------------------------------------------
# within sigma on a few seeds (the 200-seed runs are in test_align_slow.py)


@pytest.mark.parametrize("label", ["vertical-120", "diag-130"])
def test_within_sigma_few_seeds(label):
    _, axis, ang = next(r for r in ac.ROTATIONS if r[0] == label)
    case = ac.run_case([(axis, ang)], range(3), fit_align)
    z = _z(case)
    assert np.all(np.isfinite(z))
    assert np.all(np.abs(z) < 4.5), z
    # navigation grade: biases to a few micro-g / thousandths of deg/h, heading
    assert np.all(case["sigma"][:, 2] < 5 * ac.UG)
    assert np.all(case["sigma"][:, 3:6] < 0.02 * ac.DPH)
    assert np.all(case["sigma"][:, 8] < 0.1 * D2R)


def test_classic_baselines_within_sigma():
    for turns in ([((0, 0, 1), 180.0)], [((0, 0, 1), 90.0)] * 3):
        case = ac.run_case(turns, range(2), fit_classic, duration=120.0)
        assert np.all(np.abs(_z(case)) < 4.5), _z(case)


def test_the_general_method_reads_classic_schedules_too():
    case = ac.run_case([((0, 0, 1), 90.0)] * 3, range(2), fit_align, duration=120.0)
    assert np.all(np.abs(_z(case)) < 4.5)


# ---------------------------------------------------------------------------
# observability


def _east_case(angle=120.0, yaw=0.0):
    """Body x exactly East (roll only), turn about body x."""
    p = ac.plan([((1, 0, 0), angle)], duration=120.0, start=(0.5, 0.0, yaw))
    truth = ac.nav_truth(np.random.default_rng(3))
    return simulate(p, truth, seed=3), truth


def test_east_axis_loses_the_axis_biases_and_heading():
    rec, truth = _east_case()
    res = fit_align(rec)
    un = set(res.stats["unobservable"])
    assert {"accel_bias[0]", "gyro_bias[0]", "attitude[2]"} <= un
    # the biases across the axis stay observable and right
    for k, i in (("accel_bias", 1), ("accel_bias", 2), ("gyro_bias", 1), ("gyro_bias", 2)):
        assert np.isfinite(res.sigma[k][i])
        assert abs(res.params[k][i] - truth.params[k][i]) < 4.5 * res.sigma[k][i]
    assert np.isnan(res.sigma["accel_bias"][0]) and np.isnan(res.sigma["attitude"][2])
    assert "horizontal" in res.stats["observability"]


def test_north_axis_keeps_everything_and_azimuth_sets_the_weakness():
    """Horizontal axis at azimuth beta: sigma of the axis accel bias ~ 1/cos(beta)."""
    sig = {}
    for beta_from_north in (0.0, 60.0):
        # body x at azimuth beta from North: yaw (from East, ccw) = 90 - beta
        rec, truth = _east_case(yaw=90.0 - beta_from_north)
        res = fit_align(rec)
        assert not res.stats["unobservable"]
        z = (res.params["accel_bias"] - truth.params["accel_bias"]) / res.sigma["accel_bias"]
        assert np.all(np.abs(z) < 4.5)
        sig[beta_from_north] = res.sigma["accel_bias"][0]
    # g sigma_w / (W cos(lat) cos(beta)): some hundreds of micro-g over 120 s
    assert 100 * ac.UG < sig[0.0] < 2000 * ac.UG
    assert 1.6 < sig[60.0] / sig[0.0] < 2.5


def test_turn_near_zero_or_full_is_exit_4():
    for ang in (2.0, 358.0):
        p = ac.plan([((0, 1, 0.3), ang)], duration=30.0)
        rec = simulate(p, ac.nav_truth(np.random.default_rng(0)), seed=0)
        with pytest.raises(EstimationError, match="turn the unit"):
            fit_align(rec)


def test_mems_grade_falls_back_to_accelerometers():
    from calib_cli.model.effects import Layout
    from calib_cli.model.truth import default_truth

    p = ac.plan([((1, 1, 1), 130.0)], duration=60.0)
    truth = default_truth(Layout(), np.random.default_rng(2))  # MEMS: 5e-3 rad/s biases
    rec = simulate(p, truth, seed=2)
    res = fit_align(rec)
    assert res.stats["earth_rate_used"] is False
    assert "MEMS" in res.stats["grade_check"]
    assert "attitude[2]" in res.stats["unobservable"]
    # tilt and accel biases: within sigma (K of the accelerometers is a MEMS
    # error the method does not model, so only a loose bound here)
    att = rec.truth["attitudes"][0]
    assert np.all(np.isfinite(res.sigma["accel_bias"]))
    assert np.all(np.abs(res.params["attitude"][:2] - att[:2]) < 0.05)
    with pytest.raises(EstimationError, match="MEMS"):
        fit_align(rec, gyro="use")


def test_plan_stated_turn():
    p = ac.plan([((1, 1, 1), 130.0)], duration=120.0)
    truth = ac.nav_truth(np.random.default_rng(4), k_prior=0.0)
    rec = simulate(p, truth, seed=4)
    res = fit_align(rec, rotation="plan")
    assert res.stats["rotations"][0]["source"] == "plan"
    z = (res.params["accel_bias"] - truth.params["accel_bias"]) / res.sigma["accel_bias"]
    assert np.all(np.abs(z) < 4.5)


# ---------------------------------------------------------------------------
# CLI


def _run(args):
    from calib_cli.cli.main import main

    try:
        main(args)
    except SystemExit as e:
        return e.code
    return 0


def test_cli_end_to_end(tmp_path, capsys):
    raw, cal = tmp_path / "raw.h5", tmp_path / "cal.h5"
    assert _run(["-q", "simulate", "docs/examples/align_plan.toml", "--truth",
                 "docs/examples/align_truth.toml", "--out", str(raw), "--seed", "7"]) == 0
    assert _run(["-q", "fit", "align", str(raw), "--out", str(cal)]) == 0
    capsys.readouterr()
    assert _run(["show", str(cal), "--json"]) == 0
    js = json.loads(capsys.readouterr().out)
    assert js["method"] == "align"
    assert set(js["params"]) == {"accel_bias", "gyro_bias", "attitude"}
    assert js["units"]["attitude"] == "rad"
    assert abs(np.degrees(js["stats"]["rotation_angle"]) - 130.0) < 0.01
    assert np.allclose(js["stats"]["rotation_axis_body"], np.ones(3) / np.sqrt(3), atol=1e-4)
    assert js["stats"]["unobservable"] == []
    assert abs(np.degrees(js["params"]["attitude"][2]) - 30.0) < 0.2
    assert np.allclose(js["params"]["accel_bias"], np.array([120, -80, 150]) * ac.UG,
                       atol=150 * ac.UG)
    # special attitude: body z within 2 deg of the vertical at position 1 reads
    # its bias as f_z - g, off by the second-order tilt term g (1 - cos(tau))
    d = [r for r in js["stats"]["direct_readings"] if r["sensor"] == "accel"]
    assert [(r["position"], r["axis"]) for r in d] == [("position-1", 2)]
    tau = np.radians(d[0]["tilt_deg"])
    g = js["stats"]["g_reference"]
    assert abs(d[0]["bias"] - (150 * ac.UG - g * (1 - np.cos(tau)))) < 5 * ac.UG


def test_cli_bad_inputs(tmp_path, capsys):
    assert _run(["fit", "align", str(tmp_path / "none.h5"), "--out", str(tmp_path / "c.h5")]) == 3
    assert "none.h5" in capsys.readouterr().err
    # one static position only: exit 4, says what to add, no output file
    plan = tmp_path / "one.toml"
    plan.write_text('kind = "align"\nsample_rate_hz = 20\n[site]\nlatitude_deg = 32\n'
                    '[[segment]]\nlabel = "p1"\nduration_s = 20\n')
    raw = tmp_path / "one.h5"
    assert _run(["-q", "simulate", str(plan), "--out", str(raw)]) == 0
    out = tmp_path / "c.h5"
    assert _run(["fit", "align", str(raw), "--out", str(out)]) == 4
    assert "second position" in capsys.readouterr().err
    assert not out.exists()
    assert _run(["fit", "align", str(raw), "--out", str(out), "--gyro-k-ppm", "-1"]) == 3


def test_cli_classic_rejects_a_tilted_axis(tmp_path, capsys):
    raw = tmp_path / "r.h5"
    assert _run(["-q", "simulate", "docs/examples/align_plan.toml", "--truth",
                 "docs/examples/align_truth.toml", "--out", str(raw)]) == 0
    assert _run(["fit", "align", str(raw), "--out", str(tmp_path / "c.h5"),
                 "--method", "classic"]) == 4
    assert "two-position" in capsys.readouterr().err


def test_accelerometer_only_on_request():
    p = ac.plan([((0, 1, 0.3), 120.0)], duration=120.0)
    truth = ac.nav_truth(np.random.default_rng(6))
    rec = simulate(p, truth, seed=6)
    res = fit_align(rec, gyro="ignore")
    assert res.stats["earth_rate_used"] is False
    assert res.stats["unobservable"] == ["attitude[2]"]
    att = rec.truth["attitudes"][0]
    z = (res.params["attitude"][:2] - att[:2]) / res.sigma["attitude"][:2]
    za = (res.params["accel_bias"] - truth.params["accel_bias"]) / res.sigma["accel_bias"]
    assert np.all(np.abs(np.concatenate([z, za])) < 4.5)


def test_plan_turn_with_stated_uncertainty_widens_sigma():
    p = ac.plan([((1, 1, 1), 130.0)], duration=120.0)
    truth = ac.nav_truth(np.random.default_rng(8), k_prior=0.0)
    rec = simulate(p, truth, seed=8)
    exact = fit_align(rec, rotation="plan")
    loose = fit_align(rec, rotation="plan", turn_sigma=0.01 * D2R)
    assert np.all(loose.sigma["accel_bias"] >= exact.sigma["accel_bias"] * 0.999)
    assert loose.sigma["accel_bias"].max() > 3 * exact.sigma["accel_bias"].max()
