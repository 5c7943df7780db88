"""Size-effect compensation in apply (issue 22 item 1, the rough-stand paper's point):
each accelerometer brought to the triad's reference point with the gyros' rate and its
derivative, w x (w x p_i) + dw/dt x p_i."""

from __future__ import annotations

import re
import shutil

import numpy as np
import pytest
from click.testing import CliRunner

from calib_cli.cli.main import cli
from calib_cli.data import CalibrationResult
from calib_cli.io.h5 import read_raw, write_calibration, write_raw
from calib_cli.io.plan import parse_plan
from calib_cli.methods.apply import apply_triad
from calib_cli.model.effects import Layout
from calib_cli.sim.simulate import simulate
from calib_cli.sim.turntable_plans import turntable_truth
from tests.turntable_profiles import profile_plan_text

MODEL = [{"name": "bias", "sensor": "accel"},
         {"name": "scale_misalignment", "sensor": "accel", "structure": "lower"},
         {"name": "bias", "sensor": "gyro"},
         {"name": "scale_misalignment", "sensor": "gyro", "structure": "full"},
         {"name": "g_sensitivity", "sensor": "gyro"},
         {"name": "lever_arm", "sensor": "accel", "tangential": True},
         {"name": "proof_mass_offsets", "sensor": "accel", "tangential": True}]


def _fast_profile(text: str) -> str:
    """Every cycle's profile: trapezoid at 300 deg/s^2 through holds at 100, 200, -200,
    -100 deg/s (20 s each), so the record reaches the issue's 200 deg/s in 120 s."""
    from calib_cli.sim.rate_profiles import trapezoid_knots

    knots = [[round(a, 6), round(b, 6)] for a, b in
             trapezoid_knots(120.0, 300.0, (100, 200, -200, -100), 20.0)]
    return re.sub(r"(?m)^rate_profile = .*$", f"rate_profile = {knots}", text)


def _records():
    """Noise-free rotating records of one unit with and without proof-mass offsets."""
    plan = parse_plan(_fast_profile(profile_plan_text(2, "trapezoid-300", duration_s=120.0,
                                                      wobble_dps=0.5)))
    truth = turntable_truth(plan, np.random.default_rng(2), noise={"accel_white": 0.0,
                                                                   "gyro_white": 0.0})
    P = np.array([[0, 8e-3, -6e-3], [7e-3, 0, 9e-3], [-10e-3, 5e-3, 0]])
    with_p = type(truth)(truth.model, {**truth.params, "proof_mass_offsets": P}, truth.noise)
    no_p = type(truth)(truth.model, {**truth.params, "proof_mass_offsets": np.zeros((3, 3))},
                       truth.noise)
    return simulate(plan, with_p, 2), simulate(plan, no_p, 2), with_p.params


def _cal(params, p_error=0.0, seed=0):
    p = np.asarray(params["proof_mass_offsets"], float)
    p = p + (np.random.default_rng(seed).standard_normal((3, 3)) * p_error) * (1 - np.eye(3))
    pr = {k: np.asarray(v, float) for k, v in params.items() if k != "lever_arm"}
    pr["proof_mass_offsets"] = p
    sig = {k: np.full(np.shape(v), 1e-6) for k, v in pr.items()}
    sig["proof_mass_offsets"] = np.where(np.eye(3) > 0, 0.0, max(p_error, 1e-6))
    return CalibrationResult(method="turntable", params=pr, sigma=sig,
                             units={k: "-" for k in pr}, covariance=np.zeros((0, 0)),
                             cov_order=[], stats={}, model=[m for m in MODEL
                                                            if m["name"] != "lever_arm"],
                             layout=Layout(n_cycles=0))


def test_size_effect_compensation_cuts_the_error_5x():
    rec_p, rec_0, params = _records()
    rot = np.zeros(len(rec_p), bool)
    for s in rec_p.segments:
        rot[s.slice] = s.kind == "rotating"
    ref, _ = apply_triad(_cal({**params, "proof_mass_offsets": np.zeros((3, 3))}),
                         rec_0.accel, rec_0.gyro)  # the force at the reference point
    plain, _ = apply_triad(_cal(params), rec_p.accel, rec_p.gyro)  # no time: no compensation
    # the fitted offsets of a 9-cycle plan carry ~0.25 mm: compensate with such an error
    comp, _ = apply_triad(_cal(params, p_error=2.5e-4), rec_p.accel, rec_p.gyro, time=rec_p.time)
    e_plain = np.sqrt(np.mean((plain - ref)[rot] ** 2))
    e_comp = np.sqrt(np.mean((comp - ref)[rot] ** 2))
    assert e_plain > 5 * e_comp, (e_plain, e_comp)
    # with the exact offsets what is left is the rate derivative at the trapezoid's corners
    # (central differences across a jump of the angular acceleration)
    exact, _ = apply_triad(_cal(params), rec_p.accel, rec_p.gyro, time=rec_p.time)
    assert np.sqrt(np.mean((exact - ref)[rot] ** 2)) < 0.15 * e_plain


def test_apply_cli_compensates_in_chunks(tmp_path, monkeypatch):
    """The chunked CLI gives what one call on the whole record gives (context at the seams)."""
    import calib_cli.cli.cmd_apply as cmd_apply

    rec_p, _rec_0, params = _records()
    cal = _cal(params)
    write_raw(tmp_path / "raw.h5", rec_p)
    write_calibration(tmp_path / "cal.h5", cal, [])
    monkeypatch.setattr(cmd_apply, "CHUNK", 5000)
    res = CliRunner().invoke(cli, ["apply", str(tmp_path / "cal.h5"), str(tmp_path / "raw.h5"),
                                   "--out", str(tmp_path / "out.h5")])
    assert res.exit_code == 0, res.output
    out = read_raw(tmp_path / "out.h5", kinds=("corrected",))
    whole, _ = apply_triad(cal, rec_p.accel, rec_p.gyro, time=rec_p.time)
    assert np.abs(out.accel - whole).max() == pytest.approx(0.0, abs=1e-12)


CPROG = r"""
#include <stdio.h>
#include "cal.h"
int main(void) {
    double A[3], W[3], dw[3], f[3], w[3];
    while (scanf("%lf %lf %lf %lf %lf %lf %lf %lf %lf", &A[0], &A[1], &A[2], &W[0], &W[1],
                 &W[2], &dw[0], &dw[1], &dw[2]) == 9) {
        calib_correct_accel(A, f);
        calib_correct_gyro(W, f, w);     /* w: what dw/dt is taken from */
        calib_size_effect(w, dw, f);     /* each accelerometer to the reference point */
        calib_correct_gyro(W, f, w);     /* D f with the force at the reference point */
        printf("%.17g %.17g %.17g %.17g %.17g %.17g\n", f[0], f[1], f[2], w[0], w[1], w[2]);
    }
    return 0;
}
"""


@pytest.mark.skipif(shutil.which("cc") is None, reason="no C compiler")
def test_c_header_size_effect_matches_apply(tmp_path):
    """The exported header's size-effect function, fed the raw samples and exactly the
    rate derivative apply used, gives apply's corrected force and rate to 1e-9."""
    import json
    import subprocess

    from calib_cli.methods.apply import rate_derivative

    rec, _rec_0, params = _records()
    cal = _cal(params, p_error=2.5e-4)  # some entries off truth: any p, not just the truth's
    write_calibration(tmp_path / "cal.h5", cal, [])
    run = CliRunner().invoke(cli, ["export", str(tmp_path / "cal.h5"), "--format", "c-header",
                                   "--out", str(tmp_path / "cal.h")])
    assert run.exit_code == 0, run.output
    text = (tmp_path / "cal.h").read_text()
    assert "CALIB_PROOF_MASS" in text and "calib_size_effect" in text
    obj = json.loads(CliRunner().invoke(cli, ["export", str(tmp_path / "cal.h5"),
                                              "--format", "json"]).stdout)
    assert "proof_mass_offsets" not in obj.get("not_applied", [])
    np.testing.assert_array_equal(obj["correction"]["size_effect"]["proof_mass_offsets"],
                                  np.asarray(cal.params["proof_mass_offsets"]))
    (tmp_path / "prog.c").write_text(CPROG)
    subprocess.run(["cc", "-std=c99", "-O2", "-Wall", "-Wextra", "-Werror", "-o",
                    str(tmp_path / "prog"), str(tmp_path / "prog.c")], check=True, cwd=tmp_path)
    sl = slice(0, len(rec.time), 7)  # every 7th sample: the whole record, fewer lines
    _f0, w0 = apply_triad(cal, rec.accel, rec.gyro)  # the rates apply differentiates
    dw = rate_derivative(w0, rec.time)
    f_ref, w_ref = apply_triad(cal, rec.accel, rec.gyro, time=rec.time)
    inp = "\n".join(" ".join("%.17g" % x for x in row)
                    for row in np.hstack([rec.accel, rec.gyro, dw])[sl]) + "\n"
    out = subprocess.run([str(tmp_path / "prog")], input=inp, capture_output=True, text=True,
                         check=True).stdout
    got = np.array([[float(x) for x in ln.split()] for ln in out.splitlines()])
    ref = np.hstack([f_ref, w_ref])[sl]
    assert got.shape == ref.shape
    diff = np.abs(got - ref).max()
    print(f"C size effect vs apply: max abs difference {diff:.3g}")
    assert diff <= 1e-9, diff
    # and the compensation is not nothing at this size
    plain, _ = apply_triad(cal, rec.accel, rec.gyro)
    assert np.abs(plain - f_ref).max() > 1e-3


@pytest.mark.slow
def test_fitted_offsets_cut_the_error_5x():
    """The same with the offsets a 9-cycle fit gives (MEMS noise, 3 x 600 s + 6 x 300 s):
    the fitted p carries its real error (sigma ~0.25 mm), not a drawn one."""
    from calib_cli.methods.turntable import fit_turntable
    from calib_cli.model.truth import Truth
    from calib_cli.sim.turntable_plans import turntable_plan_text

    rec_p, rec_0, params = _records()
    plan9 = parse_plan(turntable_plan_text(5, tilted=True))
    t9 = turntable_truth(plan9, np.random.default_rng(5))
    unit = {k: v for k, v in params.items() if k != "lever_arm"}  # the same unit on the table
    res = fit_turntable(simulate(plan9, Truth(t9.model, {**t9.params, **unit}, t9.noise), 5))
    p_fit = np.asarray(res.params["proof_mass_offsets"], float)
    sig = np.asarray(res.sigma["proof_mass_offsets"], float)
    off = ~np.eye(3, dtype=bool)
    rot = np.zeros(len(rec_p), bool)
    for s in rec_p.segments:
        rot[s.slice] = s.kind == "rotating"
    ref, _ = apply_triad(_cal({**params, "proof_mass_offsets": np.zeros((3, 3))}),
                         rec_0.accel, rec_0.gyro)
    plain, _ = apply_triad(_cal(params), rec_p.accel, rec_p.gyro)
    comp, _ = apply_triad(_cal({**params, "proof_mass_offsets": p_fit}), rec_p.accel,
                          rec_p.gyro, time=rec_p.time)
    e_plain = np.sqrt(np.mean((plain - ref)[rot] ** 2))
    e_comp = np.sqrt(np.mean((comp - ref)[rot] ** 2))
    print(f"fitted p: sigma {np.median(sig[off]) * 1e3:.3f} mm (median), error RMS "
          f"{np.sqrt(np.mean((p_fit - params['proof_mass_offsets'])[off] ** 2)) * 1e3:.3f} mm; "
          f"specific-force error {e_plain:.3g} -> {e_comp:.3g} m/s^2 ({e_plain / e_comp:.1f}x)")
    assert np.all(np.isfinite(sig[off]))
    assert e_plain > 5 * e_comp, (e_plain, e_comp)
