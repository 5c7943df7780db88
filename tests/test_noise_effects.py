"""Noise as part of the sensor model (issue 17): white noise, bias random walk and
flicker are catalogue effects with seeded, stateful realisations, so the emulator's
generator streams exactly what ``simulate`` writes for the same truth and seed."""

from __future__ import annotations

import numpy as np
import pytest

from calib_cli.io.plan import parse_plan
from calib_cli.model.truth import truth_from_dict

TRUTH = {"params": {"accel_bias_mg": [2.0, -1.5, 3.0], "gyro_bias_dps": [0.2, -0.1, 0.05],
                    "accel_K": [[1.002, 0.001, 0.0], [0.0, 0.998, 0.0], [0.0, 0.0, 1.001]],
                    "gyro_bias_rw": [2e-5, 3e-5, 1e-5], "gyro_bias_instability": [1e-4] * 3,
                    "accel_bias_rw": [1e-4] * 3},
         "noise": {"accel_white_density": 2e-3, "gyro_white": 1e-3}}


def _static_plan(duration_s: float, rate: float = 100.0):
    return parse_plan(f"name = 'still'\nkind = 'static'\nsample_rate_hz = {rate}\n"
                      "[site]\nlatitude_deg = 50.45\nheight_m = 180.0\n"
                      f"[[segment]]\nlabel = 'still'\nattitude_deg = [0, 0, 0]\n"
                      f"duration_s = {duration_s}\n", "<still>")


def _emulator(plan, truth, seed):
    from calib_cli.acquire.emulator import Emulator
    from calib_cli.acquire.profile import load_imu_profile

    return Emulator(load_imu_profile("generic-bin6"), truth=truth, site=plan.site,
                    rate=plan.sample_rate, seed=seed)


def _stream(emu, n, rng):
    parts, k = [], 0
    while k < n:
        m = int(min(rng.integers(1, 700), n - k))
        parts.append(emu.samples(k, m))
        k += m
    return {s: np.concatenate([p[s] for p in parts]) for s in ("accel", "gyro")}


def test_emulator_stream_is_simulate_bit_for_bit():
    from calib_cli.sim.simulate import simulate

    plan = _static_plan(60.0)
    truth = truth_from_dict(TRUTH, __import__("calib_cli.plan", fromlist=["x"]).plan_layout(plan))
    rec = simulate(plan, truth, seed=7)
    emu = _emulator(plan, truth, seed=7)
    try:
        got = _stream(emu, len(rec), np.random.default_rng(0))
    finally:
        emu.stop()
    assert np.array_equal(got["accel"], rec.accel) and np.array_equal(got["gyro"], rec.gyro)
    other = simulate(plan, truth, seed=8)
    assert not np.array_equal(other.gyro, rec.gyro)


def test_noise_terms_are_effects_and_never_calibration_params():
    from calib_cli.model.effects import CATALOGUE, STOCHASTIC, make_effect
    from calib_cli.model.truth import key_owner
    from calib_cli.plan import plan_layout

    for name in ("white_noise", "bias_random_walk", "bias_instability"):
        assert make_effect(name, "gyro").stage == STOCHASTIC and name in CATALOGUE
    truth = truth_from_dict(TRUTH, plan_layout(_static_plan(1.0)))
    model, params = truth.noise_model()
    assert {e.name for e in model.effects} >= {"white_noise", "bias_random_walk",
                                               "bias_instability"}
    assert "accel_white_density" in params and "accel_white" not in truth.params
    assert "accel_white" not in key_owner(model.layout, {})  # the truth's [noise] table


def test_random_params_is_the_truth_draw():
    from calib_cli.model.effects import Layout
    from calib_cli.model.truth import default_truth

    a = default_truth(Layout(), np.random.default_rng(3))
    b = a.model.random_params(np.random.default_rng(3))
    assert all(np.array_equal(a.params[k], b[k]) for k in b)


@pytest.mark.slow
def test_emulator_two_hours_allan_finds_random_walk_and_flicker(tmp_path, run_cli):
    """2 h at 100 Hz from the emulator's generator (not paced: faster than real
    time), with gyro bias random walk and flicker: `calib allan` finds both within
    its stated confidence bounds."""
    import json
    import time

    from calib_cli.data import Recording
    from calib_cli.io.h5 import write_raw

    hours, fs = 2.0, 100.0
    plan = _static_plan(hours * 3600, fs)
    K, B = 2e-6, 2e-5  # rad/s/sqrt(s), rad/s: the floor (1 - 130 s) and the +1/2 slope in 2 h
    truth = truth_from_dict(
        {"params": {"gyro_bias_rw": [K] * 3, "gyro_bias_instability": [B] * 3},
         "noise": {"accel_white": 3e-3, "gyro_white": 1e-4}}, __import__(
            "calib_cli.plan", fromlist=["x"]).plan_layout(plan))
    emu = _emulator(plan, truth, seed=11)
    n = int(hours * 3600 * fs)
    t0 = time.perf_counter()
    try:
        got = {"accel": [], "gyro": []}
        for k in range(0, n, 60000):
            chunk = emu.samples(k, min(60000, n - k))
            for s in got:
                got[s].append(chunk[s])
    finally:
        emu.stop()
    elapsed = time.perf_counter() - t0
    assert elapsed < hours * 3600 / 10  # at least 10 x faster than real time
    from calib_cli.data import Segment

    rec = Recording(time=np.arange(n) / fs, accel=np.concatenate(got["accel"]),
                    gyro=np.concatenate(got["gyro"]), site=plan.site, plan_kind="static",
                    segments=(Segment("still", "static", 0, n),), serial="EMU-ALLAN")
    raw = tmp_path / "raw.h5"
    write_raw(raw, rec, ["<emulator>"])
    out = tmp_path / "allan.h5"
    code, so, se = run_cli("allan", raw, "--out", out, "--json")
    assert code == 0, se
    chans = json.loads(so)["channels"]
    rows = []
    for c in [c for c in chans if c.startswith("g")]:
        for term, truth_v in (("rate_random_walk", K), ("bias_instability", B)):
            t = chans[c][term]
            if t["value"] is None:  # not visible in the curve
                rows.append((c, term, None, False))
                continue
            rows.append((c, term, round(t["value"] / truth_v, 3), t["lo"] <= truth_v <= t["hi"]))
    print(f"emulator 2 h at {fs:g} Hz generated in {elapsed:.1f} s; value/truth, in 95 % interval:",
          rows)
    assert len(rows) == 6 and all(ok for *_, ok in rows), rows
