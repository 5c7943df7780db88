"""calib allan --kalibr and calib export --format kalibr|px4|ardupilot (issue 19)."""

from __future__ import annotations

import csv

import numpy as np
import pytest
import yaml

from calib_cli.data import Recording, Segment
from calib_cli.io.allan_h5 import read_allan
from calib_cli.io.export_autopilot import KALIBR_KEYS
from calib_cli.io.h5 import read_calibration, write_raw

RATE = 50.0
TRUTH = {"accel": (2e-3, 2e-4), "gyro": (1e-3, 1e-4)}  # (N white, K rate random walk), SI


@pytest.fixture(scope="module")
def rest(tmp_path_factory):
    """A record at rest: white noise N / sqrt(dt) per sample plus a bias
    random walk with increments K sqrt(dt)."""
    d = tmp_path_factory.mktemp("kalibr")
    rng = np.random.default_rng(11)
    n = int(3000 * RATE)
    dt = 1 / RATE
    t = np.arange(n) * dt
    out = {}
    for s, (N, K) in TRUTH.items():
        white = rng.standard_normal((n, 3)) * N / np.sqrt(dt)
        walk = np.cumsum(rng.standard_normal((n, 3)) * K * np.sqrt(dt), axis=0)
        out[s] = white + walk + (np.array([0, 0, 9.81]) if s == "accel" else 0.0)
    rec = Recording(time=t, accel=out["accel"], gyro=out["gyro"],
                    segments=(Segment("rest", "static", 0, n, 0),))
    write_raw(d / "rest.h5", rec)
    return d


def test_allan_kalibr_densities_within_confidence(rest, run_cli):
    code, _, err = run_cli("-q", "allan", rest / "rest.h5", "--out", rest / "allan.h5",
                           "--kalibr", rest / "imu.yaml", "--rostopic", "/imu_raw")
    assert code == 0, err
    d = yaml.safe_load((rest / "imu.yaml").read_text())
    assert tuple(d) == KALIBR_KEYS and set(d) == set(KALIBR_KEYS)
    assert d["rostopic"] == "/imu_raw" and d["update_rate"] == pytest.approx(RATE)
    res = read_allan(rest / "allan.h5")
    for s, (N, K) in TRUTH.items():
        idx = [i for i, c in enumerate(res.channels) if c.startswith(s)]
        name = "accelerometer" if s == "accel" else "gyroscope"
        for term, truth, key in (("random_walk", N, f"{name}_noise_density"),
                                 ("rate_random_walk", K, f"{name}_random_walk")):
            tv = res.terms[term]
            for i in idx:  # the truth inside every axis' 95 % interval
                assert tv["lo"][i] <= truth <= tv["hi"][i], (s, term, i, tv["lo"][i], tv["hi"][i])
            # Kalibr's figure: the largest axis, itself an Allan reading of that axis
            j = idx[int(np.nanargmax([tv["value"][i] for i in idx]))]
            assert d[key] == pytest.approx(tv["value"][j])
            assert tv["lo"][j] <= truth <= tv["hi"][j]


def test_export_kalibr_from_calibration(rest, run_cli, tmp_path):
    """Kalibr needs all four noise figures: without --allan, exit 3 naming it and
    nothing written (a calibration holds none; --raw alone gives no random walk)."""
    sim = tmp_path / "s.h5"
    code, _, err = run_cli("-q", "simulate", "sample_data/twelve_position.toml", "--out", sim)
    assert code == 0, err
    cal = tmp_path / "c.h5"
    assert run_cli("-q", "fit", "gyro", sim, "--out", cal)[0] == 0
    for extra in ((), ("--raw", sim)):
        code, out, err = run_cli("export", cal, "--format", "kalibr", "--out", tmp_path / "k.yaml",
                                 *extra)
        assert code == 3 and "--allan ALLAN.h5" in err and len(err.strip().splitlines()) == 1
        assert not (tmp_path / "k.yaml").exists() and out == ""
    if not (rest / "allan.h5").exists():
        run_cli("-q", "allan", rest / "rest.h5", "--out", rest / "allan.h5")
    code, out, err = run_cli("export", cal, "--format", "kalibr", "--allan", rest / "allan.h5")
    d = yaml.safe_load(out)
    assert all(d[k] is not None for k in KALIBR_KEYS)


@pytest.mark.parametrize("target", ["px4", "ardupilot"])
def test_export_autopilot_params(tmp_path, run_cli, target):
    sim = tmp_path / "s.h5"
    assert run_cli("-q", "simulate", "sample_data/twelve_position.toml", "--out", sim)[0] == 0
    cal = tmp_path / "c.h5"
    assert run_cli("-q", "fit", "gyro", sim, "--out", cal)[0] == 0
    out = tmp_path / f"cal.{target}"
    code, _, err = run_cli("export", cal, "--format", target, "--out", out)
    assert code == 0, err
    text = out.read_text()
    rows = [r for r in csv.reader([ln for ln in text.splitlines() if not ln.startswith("#")],
                                  delimiter="\t" if target == "px4" else ",")]
    params = {r[2]: float(r[3]) for r in rows} if target == "px4" else \
        {r[0]: float(r[1]) for r in rows}
    c = read_calibration(cal)
    kinv = np.linalg.inv(c.params["accel_K"])
    names = ({"aoff": "CAL_ACC0_{}OFF", "ascale": "CAL_ACC0_{}SCALE", "goff": "CAL_GYRO0_{}OFF"}
             if target == "px4" else
             {"aoff": "INS_ACCOFFS_{}", "ascale": "INS_ACCSCAL_{}", "goff": "INS_GYROFFS_{}"})
    for i, ax in enumerate("XYZ"):
        assert params[names["aoff"].format(ax)] == pytest.approx(c.params["accel_bias"][i], abs=0)
        assert params[names["ascale"].format(ax)] == pytest.approx(kinv[i, i], abs=0)
        assert params[names["goff"].format(ax)] == pytest.approx(c.params["gyro_bias"][i], abs=0)
    assert "cross-axis" in text and "g-sensitivity" in text
    if target == "ardupilot":
        assert "INS_GYR_CAL = 0" in text
    else:
        assert "CAL_ACC0_ID" in text
