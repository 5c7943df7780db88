"""Quantisation noise in the Allan fit (issue 22 item 4, docs/allan.md):
quantised increments with the remainder carried give IEEE 952's Q (slope -1);
rounding each rate sample is white noise instead."""

from __future__ import annotations

import numpy as np
import pytest

from calib_cli.methods import allan as A
from calib_cli.model.quantisation import quantise_increments, quantise_samples

TAU0 = 0.01
QUANTUM = 1e-4  # rad per count (an angle increment)
Q_TRUE = QUANTUM / np.sqrt(12.0)


def _record(seed, n, frac=0.7, floor=None):
    """White rate noise moving the phase by frac quanta per sample (1 sigma),
    a constant rate, optionally a flicker floor; increments quantised."""
    rng = np.random.default_rng(seed)
    N = frac * QUANTUM / np.sqrt(TAU0)
    y = 2e-3 + rng.standard_normal((n, 3)) * N / np.sqrt(TAU0)
    if floor is not None:
        import allantools

        np.random.seed(seed)
        for c in range(3):
            fl = allantools.Noise(n, (floor / A.BI_FACTOR) ** 2, -1)
            fl.generateNoise()
            y[:, c] += fl.time_series
    return y, N


def _analyse(y):
    tau, ad, _ = A.overlapping_adev(y, TAU0)
    return A.analyse(tau, ad, TAU0, len(y), ["g_x", "g_y", "g_z"], ["rad/s"] * 3, np.nan)


def test_quantisation_recovered_within_the_allan_bounds():
    y, N = _record(1, 2**19)
    res = _analyse(quantise_increments(y, TAU0, QUANTUM))
    q = res.terms["quantization"]
    assert np.all((q["lo"] <= Q_TRUE) & (Q_TRUE <= q["hi"])), (q["value"] / Q_TRUE)
    assert np.all(np.abs(q["value"] / Q_TRUE - 1) < 0.03)
    # minimum averaging time: where the -1 line meets the white noise, 3 Q^2 / N^2
    np.testing.assert_allclose(res.min_avg(), 3 * Q_TRUE**2 / N**2, rtol=0.1)
    from calib_cli.cli.cmd_allan import allan_json

    js = allan_json(res)
    assert {"quantization", "min_averaging_time"} <= set(js["channels"]["g_x"])
    assert A.term_units("rad/s")["quantization"] == "rad/s*s"


def test_rounding_each_rate_sample_is_white_noise_not_quantisation():
    y, N = _record(2, 2**18)
    q = 30 * QUANTUM  # a rate quantum, rad/s
    res = _analyse(quantise_samples(y, q))
    assert not np.isfinite(res.terms["quantization"]["value"]).any()
    assert np.isnan(res.min_avg()).all()
    N_eff = np.sqrt(N**2 + q**2 * TAU0 / 12.0)
    np.testing.assert_allclose(res.terms["random_walk"]["value"], N_eff, rtol=0.05)


def test_increments_keep_the_integral():
    y, _ = _record(3, 1000)
    yq = quantise_increments(y, TAU0, QUANTUM)
    err = np.cumsum(yq * TAU0, axis=0) - np.cumsum(y * TAU0, axis=0)
    assert np.abs(err).max() <= QUANTUM / 2 + 1e-12


@pytest.mark.slow
def test_quantisation_recovered_many_seeds_with_a_flicker_floor():
    inside, ratio = [], []
    for seed in range(20):
        y, _ = _record(100 + seed, 2**19, floor=3e-6)
        q = _analyse(quantise_increments(y, TAU0, QUANTUM)).terms["quantization"]
        inside += list((q["lo"] <= Q_TRUE) & (Q_TRUE <= q["hi"]))
        ratio += list(q["value"] / Q_TRUE)
    ratio = np.array(ratio)
    print(f"Q recovered: mean ratio {ratio.mean():.4f}, min {ratio.min():.4f}, max "
          f"{ratio.max():.4f}, 95 % interval covers truth {np.mean(inside):.0%} of 60")
    assert np.all(np.abs(ratio - 1) < 0.05)
    assert np.mean(inside) >= 0.90
