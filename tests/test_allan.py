"""Allan deviation: the streaming estimator against allantools, and the IEEE
952 noise terms on simulated white + true flicker + rate random walk noise."""

from __future__ import annotations

import allantools
import h5py
import numpy as np
import pytest

from calib_cli.methods import allan as A


def noise(n, tau0, N, B, K, seed):
    """Rate samples: white (random walk coefficient N, unit*sqrt(s)), true
    flicker of bias instability B (allantools' Kasdin generator, one-sided
    PSD B^2/(pi f), Allan floor sqrt(2 ln2/pi) B = 0.664 B) and rate random
    walk K (unit/sqrt(s))."""
    rng = np.random.default_rng(seed)
    np.random.seed(seed)  # the Kasdin generator draws from numpy's global state
    fl = allantools.Noise(n, B**2, -1)  # b = -1 sequence used as rate: S = (qd/pi)/f
    fl.generateNoise()
    white = rng.standard_normal(n) * N / np.sqrt(tau0)
    rrw = np.cumsum(rng.standard_normal(n)) * K * np.sqrt(tau0)
    return white + fl.time_series + rrw


def coefficients(floor, tau_w, tau_r):
    """N, B, K such that the white and rate-random-walk lines cross the
    flicker floor at tau_w and tau_r."""
    return floor * np.sqrt(tau_w), floor / A.BI_FACTOR, floor * np.sqrt(3.0 / tau_r)


def test_exact_mode_equals_allantools_and_chunking_does_not_matter():
    rng = np.random.default_rng(3)
    y = rng.standard_normal((50000, 2)) + np.cumsum(rng.standard_normal((50000, 2)), 0) * 0.01
    tau, ad, _ = A.overlapping_adev(y, 0.1, stride_div=0, chunk=7777)
    for c in range(2):
        _, ref, _, _ = allantools.oadev(y[:, c], rate=10.0, data_type="freq", taus=tau)
        np.testing.assert_allclose(ad[:, c], ref, rtol=1e-9)
    _, ad2, _ = A.overlapping_adev(y, 0.1, stride_div=0, chunk=50000)
    np.testing.assert_allclose(ad, ad2, rtol=1e-12)
    # the default strided estimator stays within a few per cent of full overlap
    _, ad3, cl = A.overlapping_adev(y, 0.1, chunk=4096)
    rel = np.abs(ad3 / ad - 1)
    assert np.all(rel <= 3 * A.rel_sigma(cl)[:, None] + 1e-12)
    assert np.all(rel[:5] <= 1e-12)  # m <= 16: the same estimator


def test_ci_factors_bracket_one_and_shrink():
    lo, hi = A.ci_factors([4, 100, 10000])
    assert np.all(lo < 1) and np.all(hi > 1)
    assert np.all(np.diff(hi) < 0) and np.all(np.diff(lo) > 0)


NBK = ("random_walk", "bias_instability", "rate_random_walk")  # simulated by noise()


def _check(n, tau0, floor, tau_w, tau_r, seeds, channels=3):
    N, B, K = coefficients(floor, tau_w, tau_r)
    out = {k: [] for k in A.TERM_NAMES}
    inside = {k: [] for k in A.TERM_NAMES}
    for seed in seeds:
        y = np.column_stack([noise(n, tau0, N, B, K, 1000 * seed + c) for c in range(channels)])
        tau, ad, _ = A.overlapping_adev(y, tau0)
        res = A.analyse(tau, ad, tau0, n, [f"g_{c}" for c in range(channels)],
                        ["rad/s"] * channels, 1e-3)
        # the record is >= 10 x the tau of the true minimum, sqrt(3) N / K
        assert n * tau0 >= 10 * np.sqrt(3) * N / K
        for k, true in zip(NBK, (N, B, K), strict=True):
            d = res.terms[k]
            out[k] += list(d["value"] / true)
            inside[k] += list((d["lo"] <= true) & (true <= d["hi"]))
        # no quantisation in this data: not visible
        out["quantization"] += list(res.terms["quantization"]["value"])
        inside["quantization"] += list(~np.isfinite(res.terms["quantization"]["value"]))
    return {k: np.array(v) for k, v in out.items()}, {k: np.array(v) for k, v in inside.items()}


def test_noise_terms_recovered_fast():
    # 100 Hz, 1.5 h: white below 0.3 s, flicker floor, rate random walk above 50 s
    ratio, inside = _check(2**19, 0.01, 1e-5, 0.3, 50.0, seeds=[0], channels=3)
    assert np.all(np.abs(ratio["random_walk"] - 1) <= 0.10), ratio["random_walk"]
    assert np.all(np.abs(ratio["bias_instability"] - 1) <= 0.25), ratio["bias_instability"]
    assert np.all(np.isfinite(ratio["rate_random_walk"]))
    for k in A.TERM_NAMES:
        assert inside[k].all(), (k, ratio[k])  # quantization: "inside" = not visible


@pytest.mark.slow
def test_noise_terms_recovered_many_seeds():
    from pathlib import Path

    ratio, inside = _check(2**20, 0.01, 1e-5, 0.3, 100.0, seeds=range(20), channels=3)
    lines = ["# Allan noise terms: validation (written by `make validate`)", "",
             "White + true flicker (allantools Kasdin) + rate random walk, 100 Hz, 2^20 "
             "samples (2.9 h), white line crossing the floor at 0.3 s, rate random walk at "
             "100 s (true minimum at 9.5 s); 20 seeds x 3 channels.", "",
             "| term | mean estimate / truth | min | max | 95 % interval covers truth |",
             "|---|---|---|---|---|"]
    for k in NBK:
        r = ratio[k]
        lines.append(f"| {k} | {np.nanmean(r):.3f} | {np.nanmin(r):.3f} | {np.nanmax(r):.3f} | "
                     f"{inside[k].mean():.0%} |")
    print("\n".join(lines))
    docs = Path(__file__).resolve().parents[1] / "docs"
    if docs.is_dir():
        (docs / "validation" / "allan.md").write_text("\n".join(lines) + "\n")
    assert np.all(np.abs(ratio["random_walk"] - 1) <= 0.10)
    assert np.all(np.abs(ratio["bias_instability"] - 1) <= 0.25)
    assert inside["quantization"].mean() >= 0.9  # no quantisation simulated: not visible
    for k in NBK:
        # 95 % intervals: at least 90 % of 60 channel readings cover the truth
        assert inside[k].mean() >= 0.90, (k, inside[k].mean(), ratio[k])


def test_averaging_time_interpolates():
    tau = np.array([1.0, 2.0, 4.0, 8.0])
    ad = 1.0 / np.sqrt(tau)
    t = A.averaging_time(tau, ad, 1 / np.sqrt(3.0))
    assert t == pytest.approx(3.0, rel=1e-9)
    assert np.isnan(A.averaging_time(tau, ad, 0.1))
    assert A.averaging_time(tau, ad, 2.0) == 1.0


def test_white_only_has_no_floor_or_rrw():
    rng = np.random.default_rng(0)
    tau, ad, cl = A.overlapping_adev(rng.standard_normal(2**16) * 0.1, 0.01)
    t = A.channel_terms(tau, ad, cl)
    assert t["random_walk"].value == pytest.approx(0.01, rel=0.02)
    assert np.isnan(t["rate_random_walk"].value)
    assert np.isnan(t["bias_instability"].value)


# ---------------------------------------------------------------------------
# the command


def _free_running_raw(path, n=2**16, fs=100.0, seed=0):
    from calib_cli.data import Recording, Segment
    from calib_cli.io.h5 import write_raw

    rng = np.random.default_rng(seed)
    t = np.arange(n) / fs
    acc = rng.standard_normal((n, 3)) * 1e-2 + [0, 0, 9.81]
    gyr = rng.standard_normal((n, 3)) * 1e-3
    rec = Recording(time=t, accel=acc, gyro=gyr, segments=(Segment("rest", "static", 0, n),),
                    serial="SN-1")
    write_raw(path, rec)


def test_allan_command_writes_file_plot_and_show(tmp_path):
    import json

    from click.testing import CliRunner

    from calib_cli.cli.main import cli
    from calib_cli.io.allan_h5 import read_allan

    raw, out, png = tmp_path / "raw.h5", tmp_path / "a.h5", tmp_path / "a.png"
    _free_running_raw(raw)
    r = CliRunner().invoke(cli, ["allan", str(raw), "--out", str(out), "--plot", str(png),
                                 "--json", "--target", "gyro=1e-4"])
    assert r.exit_code == 0, r.output
    obj = json.loads(r.stdout)
    gx = obj["channels"]["gyro_x"]
    assert gx["random_walk"]["value"] == pytest.approx(1e-3 * np.sqrt(0.01), rel=0.02)
    # white noise: averaging time where 1e-3 / sqrt(tau / 0.01) = 1e-4, i.e. 1 s
    assert gx["averaging_time"] == pytest.approx(1.0, rel=0.1)
    with h5py.File(out) as h5:
        assert h5.attrs["kind"].decode() == "allan" and "input_sha256" in h5.attrs
    res = read_allan(out)
    assert res.channels[:3] == ["accel_x", "accel_y", "accel_z"]
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    r = CliRunner().invoke(cli, ["show", str(out), "--json"])
    assert r.exit_code == 0 and json.loads(r.stdout)["kind"] == "allan"


def test_allan_bad_segment_is_input_error(tmp_path):
    from calib_cli.cli.main import main

    raw = tmp_path / "raw.h5"
    _free_running_raw(raw, n=4096)
    with pytest.raises(SystemExit) as e:
        main(["allan", str(raw), "--segment", "nope", "--out", str(tmp_path / "x.h5")])
    assert e.value.code == 3
    assert not (tmp_path / "x.h5").exists()


def test_streaming_state_does_not_grow_with_the_record():
    """Between chunks each octave keeps at most 2 * STRIDE_DIV phase values,
    so memory is bounded by the chunk size whatever the record length."""
    rng = np.random.default_rng(1)
    n, chunk = 2**18, 1000
    acc = A.OctaveAllan(n, 2, 0.01)
    for a in range(0, n, chunk):
        acc.feed(rng.standard_normal((min(chunk, n - a), 2)))
        assert max(len(t) for t in acc.tails) <= 2 * A.STRIDE_DIV
    assert len(acc.m) == 17  # octaves up to n / 3 samples
    tau, ad, cnt = acc.result()
    # white noise of unit variance: adev = 1 / sqrt(m)
    np.testing.assert_allclose(ad[:8] * np.sqrt(tau[:8, None] / 0.01), 1.0, rtol=0.1)


def test_gap_in_time_is_input_error_and_no_static_is_estimation_error(tmp_path):
    from calib_cli.cli.main import main
    from calib_cli.data import Recording, Segment
    from calib_cli.io.h5 import write_raw

    n = 4096
    t = np.arange(n) / 100.0
    t[2000:] += 1.0  # a 1 s gap
    z = np.zeros((n, 3))
    write_raw(tmp_path / "gap.h5", Recording(time=t, accel=z, gyro=z,
                                             segments=(Segment("rest", "static", 0, n),)))
    with pytest.raises(SystemExit) as e:
        main(["allan", str(tmp_path / "gap.h5"), "--out", str(tmp_path / "a.h5")])
    assert e.value.code == 3 and not (tmp_path / "a.h5").exists()
    write_raw(tmp_path / "rot.h5", Recording(time=np.arange(n) / 100.0, accel=z, gyro=z,
                                             segments=(Segment("spin", "rotating", 0, n),)))
    with pytest.raises(SystemExit) as e:
        main(["allan", str(tmp_path / "rot.h5")])
    assert e.value.code == 4


@pytest.mark.slow
def test_simulator_bias_instability_has_the_0664_floor():
    """The catalogue's BiasInstability effect, simulated, seen by calib allan."""
    from calib_cli.io.plan import parse_plan
    from calib_cli.model.truth import truth_from_dict
    from calib_cli.sim.simulate import plan_layout, simulate

    plan = parse_plan('name = "bi"\nkind = "static"\nsample_rate_hz = 10.0\n[site]\n'
                      'latitude_deg = 0.0\n[[segment]]\nlabel = "rest"\n'
                      'attitude_deg = [0, 0, 0]\nduration_s = 20000.0\n')
    B = 1e-4
    truth = truth_from_dict({"params": {"gyro_bias_instability": [B] * 3},
                             "noise": {"accel_white_density": 1e-5,
                                       "gyro_white_density": 1e-7}}, plan_layout(plan))
    rec = simulate(plan, truth, seed=4)
    tau, ad, _ = A.overlapping_adev(rec.gyro, 0.1)
    band = (tau >= 1) & (tau <= 1000)
    floor = np.exp(np.mean(np.log(ad[band])))
    assert floor / (A.BI_FACTOR * B) == pytest.approx(1.0, abs=0.1)


def test_command_reads_in_chunks_like_in_memory(tmp_path, monkeypatch):
    """The CLI's chunked HDF5 reader (small chunks here) gives the in-memory curve."""
    import calib_cli.cli.cmd_allan as cmd
    from calib_cli.io.h5 import read_raw

    raw = tmp_path / "raw.h5"
    _free_running_raw(raw, n=20000, seed=4)
    monkeypatch.setattr(cmd, "CHUNK", 777)
    res = cmd.compute_allan(str(raw))
    rec = read_raw(raw)
    tau, ad, _ = A.overlapping_adev(np.hstack([rec.accel, rec.gyro]), 0.01, chunk=1 << 20)
    np.testing.assert_allclose(res.tau, tau, rtol=1e-9)
    np.testing.assert_allclose(res.adev, ad, rtol=1e-9)
