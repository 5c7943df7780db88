"""methods/noise.py: each white-noise estimator recovers the sigma it is documented
for, on the data shape it is documented for; the tree product of rotations of the
gyro fit equals the sequential one; the scalar-first quaternion conversion."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from calib_cli.methods.noise import difference_sigma, pooled_within


def test_pooled_within_is_the_unbiased_scatter_about_each_mean():
    rng = np.random.default_rng(1)
    sig = np.array([0.01, 0.02, 0.05])
    pieces = [m + sig * rng.standard_normal((n, 3))
              for m, n in ((np.array([0, 0, 9.8]), 4000), (np.array([9.8, 0, 0]), 3000))]
    out = pooled_within(pieces)
    assert out.dof == 6998
    np.testing.assert_allclose(out.counts, [4000, 3000])
    np.testing.assert_allclose(out.means[1], [9.8, 0, 0], atol=3e-3)
    np.testing.assert_allclose(out.sigma, sig, rtol=0.05)
    empty = pooled_within([], 3)
    assert empty.means.shape == (0, 3) and np.isnan(empty.sigma).all()


@pytest.mark.parametrize("order", [1, 2, 3])
def test_difference_sigma_removes_a_polynomial_of_degree_order_minus_one(order):
    rng = np.random.default_rng(order)
    t = np.linspace(0, 10, 20000)
    trend = 3.0 * t ** (order - 1)  # constant, ramp or parabola: removed exactly
    x = (trend + 0.01 * rng.standard_normal(len(t)))[:, None]
    for robust in ("std", "mad", "auto"):
        np.testing.assert_allclose(difference_sigma(x, order, robust=robust), [0.01], rtol=0.05)


def test_difference_sigma_parts_skip_boundaries_and_mad_skips_spikes():
    rng = np.random.default_rng(3)
    x = 0.01 * rng.standard_normal((6000, 2))
    x[3000:] += 5.0  # a step between two parts
    x[100] += 1.0  # a spike
    parts = [(0, 3000), (3000, 6000)]
    np.testing.assert_allclose(difference_sigma(x, 2, parts, robust="mad"), [0.01, 0.01], rtol=0.06)
    assert difference_sigma(x, 2, robust="std")[0] > 0.02  # the step and spike inflate the std


def test_difference_sigma_quantised_falls_back_to_the_std():
    rng = np.random.default_rng(4)
    x = np.round(0.3 * rng.standard_normal((5000, 1)))  # mostly zeros: the MAD collapses
    assert difference_sigma(x, 1, robust="mad")[0] == 0.0
    assert difference_sigma(x, 1, robust="auto")[0] > 0.1


def test_gyro_tree_product_equals_the_sequential_product():
    from calib_cli.methods.gyro import integrate

    rng = np.random.default_rng(5)
    lists = [0.05 * rng.standard_normal((n, 3)) for n in (1, 7, 33)] + [np.zeros((0, 3))]
    got = integrate(lists)
    for p, G in zip(lists, got):
        R = Rotation.identity()
        for v in p:
            R = R * Rotation.from_rotvec(v)
        np.testing.assert_allclose(G, R.as_matrix(), atol=1e-12)


def test_scalar_first_quaternions_round_trip():
    from calib_cli.model.frames import rotation_from_wxyz, rotation_to_wxyz

    r = Rotation.from_rotvec([[0.3, -0.2, 0.1], [0.0, 0.0, 1.0]])
    q = rotation_to_wxyz(r)
    assert np.allclose(q[1], [np.cos(0.5), 0, 0, np.sin(0.5)])  # w first
    assert np.allclose(rotation_from_wxyz(q).as_matrix(), r.as_matrix())
