"""The model layer: frames, gravity, earth rate, kinematics, effects, packing."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from scipy.spatial.transform import Rotation

from calib_cli.model import kinematics as kn
from calib_cli.model.earth import EARTH_RATE, Site, normal_gravity
from calib_cli.model.effects import Bias, Layout, ScaleMisalignment
from calib_cli.model.frames import attitude_to_rotation, rotation_to_attitude
from calib_cli.model.imu_model import ImuModel, Packing, base_model

D2R = np.pi / 180


def test_contract_attitude_convention():
    # [0, -90, 0] deg puts body +x up: an ideal accelerometer reads +g on x
    site = Site(latitude=0.0, g=9.8)
    for rpy, axis in (([0, -90, 0], 0), ([90, 0, 0], 1), ([0, 0, 0], 2)):
        rot = attitude_to_rotation(np.array(rpy) * D2R)
        f = rot.inv().apply(site.specific_force_enu)
        assert np.allclose(f, np.eye(3)[axis] * 9.8, atol=1e-12)
    # yaw turns counter-clockwise from East: yaw 90 puts body x North
    rot = attitude_to_rotation(np.array([0, 0, 90]) * D2R)
    assert np.allclose(rot.apply([1, 0, 0]), [0, 1, 0], atol=1e-12)
    # scipy form of the contract
    rpy = np.array([0.1, -0.2, 0.3])
    assert np.allclose(attitude_to_rotation(rpy).as_matrix(),
                       Rotation.from_euler("ZYX", rpy[::-1]).as_matrix())
    assert np.allclose(rotation_to_attitude(attitude_to_rotation(rpy)), rpy)


def test_normal_gravity_wgs84_reference_values():
    assert abs(normal_gravity(0.0) - 9.7803253359) < 1e-9
    assert abs(normal_gravity(np.pi / 2) - 9.8321849378) < 1e-8
    # free-air gradient about -3.086e-6 /s^2 per m
    assert abs((normal_gravity(0.8, 1000.0) - normal_gravity(0.8)) / 1000 + 3.086e-6) < 2e-8


def test_earth_rate_enu():
    s = Site(latitude=0.5)
    assert np.allclose(s.earth_rate_enu, EARTH_RATE * np.array([0, np.cos(0.5), np.sin(0.5)]))
    assert Site(g=9.81).gravity == 9.81


def _table_motion():
    """A table angle with its rate and angular acceleration over 4 s at 1 kHz, a site and
    a start attitude (the kinematics tests' common motion)."""
    t = np.arange(0, 4, 1e-3)
    theta = 2.0 * t**2 + 0.5 * np.sin(3 * t)
    rate = 4.0 * t + 1.5 * np.cos(3 * t)
    acc = 4.0 - 4.5 * np.sin(3 * t)
    return Site(latitude=0.7), t, theta, rate, acc, attitude_to_rotation(np.array([10, 20, 30]) * D2R)


def test_table_kinematics_match_numerical_derivatives():
    site, t, theta, rate, acc, rot0 = _table_motion()
    axis = np.array([1.0, 0.0, 0.2])
    kin = kn.table_kinematics(t, axis, theta, rate, acc, rot0, site)
    rot = kn.table_attitude(axis, theta, rot0)
    # body rate relative to ENU from finite differences of the attitude
    drot = (rot[:-1].inv() * rot[1:]).as_rotvec() / 1e-3
    w_rel = kin.w - rot.inv().apply(np.tile(site.earth_rate_enu, (len(t), 1)))
    assert np.allclose(drot, 0.5 * (w_rel[:-1] + w_rel[1:]), atol=1e-5)
    dw_num = np.gradient(kin.w, t, axis=0)
    assert np.allclose(dw_num[5:-5], kin.dw[5:-5], atol=1e-4)
    assert np.allclose(np.linalg.norm(kin.f, axis=1), site.gravity)


def test_wobbling_table_axis_matches_numerical_derivatives():
    """A bearing's runout (the table axis rocking) (sim_table_axis_wobble_urad):
    the gyros' rate integrates to the attitude; dw/dt matches to first order in the cone."""
    from scipy.spatial.transform import Rotation

    site, t, theta, rate, acc, rot0 = _table_motion()
    axis = np.array([0.0, 1.0, 0.0])
    amp, phase = 2e-3, 0.4
    kin = kn.table_kinematics(t, axis, theta, rate, acc, rot0, site, axis_wobble=(amp, phase))
    e1 = np.cross(axis, [1.0, 0.0, 0.0])
    e2 = np.cross(axis, e1)
    eps = amp * (np.outer(np.cos(theta + phase), e1) + np.outer(np.sin(2 * theta + phase), e2))
    W = Rotation.from_rotvec(eps)
    rot = W * kn.table_attitude(axis, theta, Rotation.identity()) * W[0].inv() * rot0
    assert np.allclose(rot[0].as_matrix(), rot0.as_matrix())
    drot = (rot[:-1].inv() * rot[1:]).as_rotvec() / 1e-3
    w_rel = kin.w - rot.inv().apply(np.tile(site.earth_rate_enu, (len(t), 1)))
    assert np.allclose(drot, 0.5 * (w_rel[:-1] + w_rel[1:]), atol=1e-5)
    # the axis really moves: the rate has a component off the nominal axis
    off = np.linalg.norm(np.cross(rot.apply(w_rel), axis), axis=1)
    assert off.max() > 0.5 * amp * np.abs(rate).max()
    dw_num = np.gradient(kin.w, t, axis=0)
    assert np.allclose(dw_num[5:-5], kin.dw[5:-5], atol=amp**2 * 300 + 1e-4)
    assert np.allclose(np.linalg.norm(kin.f, axis=1), site.gravity)


def test_slew_reaches_target_with_zero_end_rates():
    site = Site()
    a = attitude_to_rotation([0.1, 0.2, 0.3])
    b = attitude_to_rotation([-0.5, 0.4, 2.0])
    t = np.linspace(0, 3, 301)
    kin = kn.slew_kinematics(t, a, b, site)
    w_rel_end = kin.w[-1] - b.inv().apply(site.earth_rate_enu)
    assert np.allclose(w_rel_end, 0, atol=1e-12)
    assert np.allclose(kin.f[-1], b.inv().apply(site.specific_force_enu), atol=1e-9)


def test_lever_arm_centripetal_by_hand():
    kin = kn.Kinematics(np.zeros(1), np.zeros((1, 3)), np.array([[0, 0, 2.0]]), np.zeros((1, 3)))
    # w = 2 rad/s about z, r = 0.3 m along x: centripetal -w^2 r = -1.2 m/s^2 along x
    assert np.allclose(kn.force_at(kin, [0.3, 0, 0]), [[-1.2, 0, 0]])


def test_bias_and_K_forward():
    model = ImuModel((Bias("accel"), ScaleMisalignment("accel")), Layout())
    K = np.array([[1.01, 0.002, 0], [0, 0.99, 0], [0.003, 0, 1.0]])
    b = np.array([0.1, 0.2, 0.3])
    f = np.array([[1.0, 2.0, 9.8]])
    kin = kn.Kinematics(np.zeros(1), f, np.zeros((1, 3)), np.zeros((1, 3)))
    y = model.predict({"accel_bias": b, "accel_K": K}, kin, sensors=("accel",))["accel"]
    assert np.allclose(y, b + f @ K.T)


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**31 - 1), st.sampled_from(["full", "lower", "diagonal"]))
def test_packing_round_trip(seed, structure):
    rng = np.random.default_rng(seed)
    model = base_model(accel_structure=structure)
    pk = Packing.for_model(model)
    theta = rng.standard_normal(pk.size)
    params = pk.unpack(theta, model.neutral_params())
    assert np.allclose(pk.pack(params), theta)
    K = params["accel_K"]
    if structure == "lower":
        assert np.all(np.triu(K, 1) == 0)
    if structure == "diagonal":
        assert np.all(K[~np.eye(3, dtype=bool)] == 0)
    assert len(pk.labels()) == pk.size


def test_flicker_sum_allan_floor_is_0664_B():
    """The Gauss-Markov sum behind bias_instability has Allan minimum 0.664 B
    (closed-form Allan variance of each process)."""
    from calib_cli.model.effects import FLICKER_SCALE, FLICKER_TAUS

    taus = np.logspace(0, np.log10(3000), 200)
    x = taus[:, None] / FLICKER_TAUS[None, :]
    q2 = FLICKER_SCALE**2
    avar = (q2 * FLICKER_TAUS**2 / taus[:, None] ** 2
            * (2 * x - 3 + 4 * np.exp(-x) - np.exp(-2 * x))).sum(axis=1)
    adev = np.sqrt(avar)
    assert abs(adev.min() - 0.664) < 0.002
    assert adev.max() / adev.min() < 1.04  # flat: a flicker floor over 3.5 decades


def test_flicker_realisation_variance():
    """A realisation has the variance the process sum states."""
    from calib_cli.model.effects import FLICKER_SCALE, FLICKER_TAUS, BiasInstability
    from calib_cli.model.kinematics import Kinematics

    n = 20000
    kin = Kinematics(np.arange(n) * 0.01, np.zeros((n, 3)), np.zeros((n, 3)), np.zeros((n, 3)))
    e = BiasInstability("gyro")
    x = np.concatenate([e.realise({"gyro_bias_instability": np.ones(3)}, kin, Layout(),
                                  np.random.default_rng(s)) for s in range(10)])
    # the short-time-constant processes dominate the within-record variance
    fast = FLICKER_TAUS[FLICKER_TAUS < 20]
    assert np.var(np.diff(x, axis=0)) == pytest.approx(
        sum(2 * (1 - np.exp(-0.01 / T)) * FLICKER_SCALE**2 for T in FLICKER_TAUS), rel=0.1)
    assert len(fast) > 0


def test_covariance_flags_null_directions_with_fewer_equations_than_unknowns():
    from calib_cli.methods.lsq import covariance

    J = np.array([[1.0, 1.0, 0.0]])  # one equation, three unknowns
    cov, unobs = covariance(J, np.ones(3))
    assert unobs.all() or unobs.sum() >= 2


def test_simulate_accepts_truth_with_other_cycle_count():
    from calib_cli.io.plan import parse_plan
    from calib_cli.model.truth import default_truth
    from calib_cli.sim.simulate import plan_layout, simulate

    plan = parse_plan("kind='rimu'\n[rimu]\nel0_deg=[0,0,90,45]\naz0_deg=[0,90,0,45]\n"
                      "[[segment]]\nlabel='a'\nduration_s=1\ntable_axis_enu=[0,0,1]\n"
                      "table_rate_dps=10\n")
    lay = plan_layout(plan)
    truth = default_truth(Layout(n=4, el0=lay.el0, az0=lay.az0, n_cycles=0),
                          np.random.default_rng(0))
    rec = simulate(plan, truth, 0)
    assert rec.accel.shape[1] == 4


def test_left_jacobian_against_scipy_rotations():
    """strapdown.left_jacobian: Exp(phi + d) Exp(phi)^T = Exp(J_l(phi) d) to first order,
    with SciPy's rotations (central differences), for angles from 1e-5 rad (the series
    branch) to 3 rad."""
    from calib_cli.model.strapdown import left_jacobian

    rng = np.random.default_rng(3)
    for ang in (1e-5, 5e-4, 0.035, 0.5, 3.0):
        phi = rng.standard_normal(3)
        phi *= ang / np.linalg.norm(phi)
        J = left_jacobian(phi[None])[0]
        h = 1e-6
        fd = np.zeros((3, 3))
        for k in range(3):
            d = np.zeros(3)
            d[k] = h
            up = (Rotation.from_rotvec(phi + d) * Rotation.from_rotvec(phi).inv()).as_rotvec()
            dn = (Rotation.from_rotvec(phi - d) * Rotation.from_rotvec(phi).inv()).as_rotvec()
            fd[:, k] = (up - dn) / (2 * h)
        assert np.abs(J - fd).max() < 1e-8, (ang, np.abs(J - fd).max())


@pytest.mark.parametrize("kind", ["instant", "interval-mean"])
def test_block_integration_sensitivity_is_the_attitudes_derivative(kind):
    """strapdown.block_integration's sensitivities for the gyro biases (a constant column
    per axis) against central differences of its own attitudes: q_end (the block end's left
    perturbation), qbar (the samples' mean) and wg[c] (the derivative of the mean of
    dR^T e_c, how the samples' gravity moves), on a rate that turns and accelerates.
    Measured: 5e-5 of the largest entry (instant samples), 7e-4 (interval means, whose mean
    attitude over a period the sensitivity takes at the period's middle)."""
    from calib_cli.model.strapdown import block_integration

    nb, m, grp = 6, 10, 2
    t = np.arange(nb * m + 2) / 100.0
    w = np.stack([2.0 * np.sin(3 * t), 1.0 + 0.5 * t, 0.3 * np.cos(5 * t)], axis=1)
    s = np.broadcast_to(np.eye(3), (nb * m // grp, 3, 3)).copy()
    b0 = block_integration(w, s, t, m, nb, kind, grp)
    h = 1e-6
    for p in range(3):
        bp, bm = (block_integration(w + sgn * h * np.eye(3)[p], s, t, m, nb, kind, grp)
                  for sgn in (1, -1))
        q_end = Rotation.from_matrix(np.einsum("bij,bkj->bik", bp.r_end, bm.r_end)).as_rotvec()
        assert np.allclose(q_end / (2 * h), b0.q_end[:, :, p], atol=2e-3 * np.abs(b0.q_end).max())
        rel = np.einsum("bnij,bnkj->bnik", bp.dR, bm.dR).reshape(-1, 3, 3)
        q_i = Rotation.from_matrix(rel).as_rotvec().reshape(nb, m, 3) / (2 * h)
        assert np.allclose(q_i.mean(axis=1), b0.qbar[:, :, p], atol=2e-3 * np.abs(b0.qbar).max())
        for c in range(3):
            g = (bp.dR[..., c, :] - bm.dR[..., c, :]).mean(axis=1) / (2 * h)
            assert np.allclose(g, b0.wg[c][:, :, p], atol=2e-3 * np.abs(b0.wg).max())
