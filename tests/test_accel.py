"""Static multi-position accelerometer fit against simulated truth (fast seeds)."""

import numpy as np
import pytest

from calib_cli.errors import EstimationError
from calib_cli.io.plan import parse_plan
from calib_cli.methods.accel_lsq import fit_accel, fit_scalar, fit_vector
from calib_cli.model.effects import Layout
from calib_cli.model.truth import truth_from_dict
from calib_cli.sim.simulate import simulate
from tests.conftest import TRUTH_SI, TWELVE, random_unit_attitudes, static_plan_text

HARD = 4.5


def z_vector(res, truth):
    return np.concatenate([((res.params[k] - truth.params[k]) / res.sigma[k]).ravel()
                           for k in ("accel_bias", "accel_K")])


def kkt_sigma(res):
    """K K^T of a lower-triangular fit and its sigma by linear propagation."""
    L = res.params["accel_K"]
    idx = [i for i, (k, _) in enumerate(res.cov_order) if k == "accel_K"]
    flat = [j for k, j in res.cov_order if k == "accel_K"]
    C = res.covariance[np.ix_(idx, idx)]
    J = np.zeros((9, len(flat)))
    for c, j in enumerate(flat):
        dL = np.zeros(9)
        dL[j] = 1
        dL = dL.reshape(3, 3)
        J[:, c] = (dL @ L.T + L @ dL.T).ravel()
    return L @ L.T, np.sqrt(np.diag(J @ C @ J.T)).reshape(3, 3)


def z_scalar(res, truth):
    S, sS = kkt_sigma(res)
    Kt = truth.params["accel_K"]
    St = Kt @ Kt.T
    iu = np.triu_indices(3)
    zb = (res.params["accel_bias"] - truth.params["accel_bias"]) / res.sigma["accel_bias"]
    return np.concatenate([zb, ((S - St) / sS)[iu]])


@pytest.fixture(scope="module")
def truth():
    return truth_from_dict(TRUTH_SI, Layout())


def test_vector_recovers_truth_within_sigma(truth):
    plan = parse_plan(static_plan_text())
    ratios = []
    for seed in range(3):
        res = fit_vector(simulate(plan, truth, seed))
        z = z_vector(res, truth)
        assert np.all(np.abs(z) < HARD), z
        ratios.append(res.stats["g_error_rms_after"] / res.stats["g_error_floor"])
        assert res.stats["g_error_rms_before"] > 20 * res.stats["g_error_rms_after"]
        assert res.stats["unobservable"] == []
        assert res.stats["n_positions"] == 12
    assert np.mean(ratios) <= 1.3


def test_vector_with_fixture_attitude_error(truth):
    rng = np.random.default_rng(5)
    plan_lines = static_plan_text(sigma_deg=0.1)
    # true attitudes differ from the nominal ones by the fixture error
    for seed in range(3):
        text = plan_lines
        for a in TWELVE:
            err = [float(x) for x in np.array(a, float) + rng.normal(0, 0.1, 3)]
            text = text.replace(f"attitude_deg = {list(map(float, a))}\n",
                                f"attitude_deg = {list(map(float, a))}\nsim_attitude_deg = {err}\n", 1)
        res = fit_vector(simulate(parse_plan(text), truth, seed))
        assert res.stats["attitude_sigma_used"]
        assert np.all(np.abs(z_vector(res, truth)) < HARD)


def test_scalar_from_identity_recovers_bias_and_KKT(truth):
    rng = np.random.default_rng(1)
    for seed in range(3):
        plan = parse_plan(static_plan_text(random_unit_attitudes(18, rng), known=False))
        rec = simulate(plan, truth, seed)
        res = fit_scalar(rec, start="identity")
        assert np.all(np.abs(z_scalar(res, truth)) < HARD)
        K = res.params["accel_K"]
        assert np.all(np.triu(K, 1) == 0) and np.all(np.diag(K) > 0)
        assert res.sigma["accel_K"][0, 1] == 0  # fixed by convention


COUNTS = {"params": {"accel_bias": [33123.0, 33276.0, 32360.0],
                     "accel_K": [[415.0, 0.0, -4.15], [4.13, 413.0, 4.13], [8.3, 4.15, 415.0]]},
          "noise": {"accel_white": 4.0, "gyro_white": 2.0},
          "output": {"units": "count"}}


def test_scalar_on_raw_counts_through_robust_start():
    truth = truth_from_dict(COUNTS, Layout())
    rng = np.random.default_rng(2)
    for seed in range(2):
        plan = parse_plan(static_plan_text(random_unit_attitudes(18, rng), known=False))
        rec = simulate(plan, truth, seed)
        assert rec.units["accel"] == "count"
        res = fit_accel(rec)  # auto -> scalar, ellipsoid start
        assert res.method == "scalar"
        assert np.all(np.abs(z_scalar(res, truth)) < HARD)
        assert res.units["accel_K"] == "count/(m/s^2)" and res.units["accel_bias"] == "count"
        assert res.stats["g_error_rms_before"] is None
        # the identity start fails on counts: the robust start is what makes it work
        with pytest.raises(EstimationError):
            r2 = fit_scalar(rec, start="identity")
            assert np.all(np.abs(z_scalar(r2, truth)) < HARD)


def test_too_few_and_degenerate_positions(truth):
    few = parse_plan(static_plan_text(TWELVE[:3]))
    with pytest.raises(EstimationError, match=">= 4 static positions"):
        fit_vector(simulate(few, truth, 0))
    same = parse_plan(static_plan_text([[10, 20, 30]] * 6))
    with pytest.raises(EstimationError, match="span 3-D"):
        fit_vector(simulate(same, truth, 0))
    same_unknown = parse_plan(static_plan_text([[10, 20, 30]] * 12, known=False))
    with pytest.raises(EstimationError):
        fit_scalar(simulate(same_unknown, truth, 0))
    with pytest.raises(EstimationError, match=">= 9"):
        fit_scalar(simulate(parse_plan(static_plan_text(TWELVE[:6], known=False)), truth, 0))
