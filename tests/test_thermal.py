"""Thermal calibration (issue 21), fast checks: the catalogue's temperature
drift in the contract's form, `fit thermal` on a small soak and a ramp with
lag, apply's refusals, and the C header against `calib apply`.
The many-seed figures are in test_thermal_slow.py (`make validate`)."""

from __future__ import annotations

import json
import shutil
import subprocess

import h5py
import numpy as np
import pytest
from click.testing import CliRunner

from calib_cli.cli.main import cli
from calib_cli.io.h5 import write_raw
from calib_cli.methods.thermal import fit_thermal
from calib_cli.model.effects import Layout, lag_temperature, make_effect, temp_poly
from calib_cli.model.imu_model import ImuModel
from calib_cli.model.kinematics import Kinematics
from calib_cli.model.truth import effect_from_description
from calib_cli.sim.simulate import simulate
from calib_cli.validation import thermal_cases as TC

KEYS = ("accel_bias", "accel_K", "accel_temp_bias", "accel_temp_scale", "gyro_bias",
        "gyro_temp_bias")


def _kin(n=5, temp=None, seed=0):
    rng = np.random.default_rng(seed)
    f = rng.standard_normal((n, 3)) * 9.8
    return Kinematics(np.arange(n) * 0.1, f, rng.standard_normal((n, 3)) * 0.1, np.zeros((n, 3)),
                      temp=temp)


def test_temperature_drift_follows_contract_section_7():
    """A_i = b_i + sum_k bT_ik dT^(k+1) + (1 + sum_k sT_ik dT^(k+1)) (K f)_i"""
    eff = (make_effect("bias", "accel"), make_effect("scale_misalignment", "accel"),
           make_effect("temperature_drift", "accel", order=2, temp_ref=20.0))
    m = ImuModel(eff, Layout())
    K = np.array([[1.01, 0.02, -0.01], [0.003, 0.99, 0.02], [-0.02, 0.01, 1.02]])
    p = {"accel_bias": np.array([0.1, -0.2, 0.3]), "accel_K": K,
         "accel_temp_bias": np.array([[1e-3, 2e-5], [-1e-3, 1e-5], [5e-4, -3e-5]]),
         "accel_temp_scale": np.array([[1e-4, 3e-6], [-2e-4, 1e-6], [5e-5, -2e-6]])}
    temp = np.array([-40.0, 0.0, 20.0, 60.0, 85.0])
    kin = _kin(temp=temp)
    y = m.predict(p, kin, sensors=("accel",))["accel"]
    dT = temp - 20.0
    Kf = kin.f @ K.T
    want = p["accel_bias"] + temp_poly(p["accel_temp_bias"], dT) + \
        (1 + temp_poly(p["accel_temp_scale"], dT)) * Kf
    assert np.allclose(y, want, rtol=0, atol=1e-12)
    # by hand for one sample and axis
    i, n = 1, 0
    d = dT[n]
    hand = (p["accel_bias"][i] + p["accel_temp_bias"][i, 0] * d + p["accel_temp_bias"][i, 1] * d**2
            + (1 + p["accel_temp_scale"][i, 0] * d + p["accel_temp_scale"][i, 1] * d**2) * Kf[n, i])
    assert abs(y[n, i] - hand) < 1e-12
    # order 1 keeps the (3,) shape
    assert make_effect("temperature_drift", "gyro").specs(Layout())[0].shape == (3,)
    assert make_effect("temperature_drift", "gyro", order=3).specs(Layout())[0].shape == (3, 3)


def test_previous_form_still_read_as_fitted():
    """A description without ``order`` (files before section 7's form) keeps the
    scale term on the nominal input."""
    old = effect_from_description({"name": "temperature_drift", "sensor": "accel"})
    assert old.scale_on == "input" and old.order == 1
    m = ImuModel((make_effect("scale_misalignment", "accel"), old), Layout())
    K = np.eye(3) * 1.01
    p = {"accel_K": K, "accel_temp_bias": np.zeros(3), "accel_temp_scale": np.full(3, 1e-3)}
    kin = _kin(temp=np.full(5, 35.0))
    y = m.predict(p, kin, sensors=("accel",))["accel"]
    assert np.allclose(y, kin.f @ K.T + 10.0 * 1e-3 * kin.f, atol=1e-12)
    new = effect_from_description({"name": "temperature_drift", "sensor": "accel", "order": 1,
                                   "temp_ref": 25.0})
    assert new.scale_on == "transfer"


def test_lag_filter_exact_for_a_ramp():
    t = np.arange(0, 3000.0, 0.5)
    T = 20 + 0.02 * t  # ramp from a soak at 20
    tau = 100.0
    exact = 20 + 0.02 * (t - tau * (1 - np.exp(-t / tau)))
    assert np.max(np.abs(lag_temperature(t, T, tau) - exact)) < 1e-9


def _check_within(res, truth, limit=4.5):
    z = []
    for k in KEYS:
        e, s = np.asarray(res.params[k]), np.asarray(res.sigma[k])
        tv = np.asarray(truth.params[k], float)
        if tv.shape != e.shape:
            tv = tv.reshape(3, -1)
            pad = np.zeros(e.shape if e.ndim == 2 else (3, 1))
            pad[:, :tv.shape[1]] = tv[:, :pad.shape[1]]
            tv = pad if e.ndim == 2 else pad[:, 0]
        ok = s > 0
        z.append(((e - tv)[ok] / s[ok]).ravel())
    z = np.concatenate(z)
    assert np.max(np.abs(z)) < limit, np.round(z, 2)
    return z


@pytest.mark.parametrize("seed", [1, 2])
def test_soak_fit_recovers_truth(seed):
    tr = TC.thermal_truth(np.random.default_rng(seed))
    rec = simulate(TC.plan(TC.soak_plan_text(temps=(-40, -10, 25, 55, 85), soak_s=1800)), tr,
                   seed=seed)
    res = fit_thermal(rec)
    assert res.stats["temp_order"] == 2
    assert res.params["accel_temp_bias"].shape == (3, 2)
    assert np.all(np.isnan(res.sigma["gyro_temp_scale"]))
    assert "gyro_temp_scale[0,0]" in res.stats["unobservable"]
    assert res.stats["warmup_excluded_s"] > 0
    assert res.stats["temp_hysteresis"]["accel"] is None  # soaks only: no branches
    _check_within(res, tr)
    assert res.stats["g_error_rms_after"] < 0.05 * res.stats["g_error_rms_before"]


def test_ramp_lag_hysteresis_and_tau():
    tr = TC.thermal_truth(np.random.default_rng(5), lag_tau=200.0)
    rec = simulate(TC.plan(TC.ramp_plan_text()), tr, seed=5)
    plain = fit_thermal(rec)
    h = np.array(plain.stats["temp_hysteresis"]["accel"])
    hs = np.array(plain.stats["temp_hysteresis_sigma"]["accel"])
    assert np.max(np.abs(h / hs)) > 5
    lag = fit_thermal(rec, lag=True)
    h = np.array(lag.stats["temp_hysteresis"]["accel"])
    hs = np.array(lag.stats["temp_hysteresis_sigma"]["accel"])
    assert np.max(np.abs(h / hs)) < 3
    tau, st = float(lag.params["thermal_lag_tau"]), float(lag.sigma["thermal_lag_tau"])
    assert abs(tau - 200.0) < 4 * st, (tau, st)
    _check_within(lag, tr)


def _cli(*args):
    r = CliRunner().invoke(cli, [str(a) for a in args])
    assert r.exit_code == 0, (r.exit_code, r.output)
    return r


def _fails(code, *args, capsys=None):
    """Run through the entry point (exit-code mapping); the stderr line."""
    from calib_cli.cli.main import main

    with pytest.raises(SystemExit) as e:
        main([str(a) for a in args])
    assert e.value.code == code
    return capsys.readouterr().err if capsys else ""


@pytest.fixture(scope="module")
def thermal_files(tmp_path_factory):
    d = tmp_path_factory.mktemp("thermal")
    tr = TC.thermal_truth(np.random.default_rng(11))
    rec = simulate(TC.plan(TC.soak_plan_text(temps=(-20, 25, 70), soak_s=900)), tr, seed=11)
    write_raw(d / "raw.h5", rec)
    hold = simulate(TC.plan(TC.soak_plan_text(temps=(0, 50), soak_s=900, hold_s=10)), tr, seed=12)
    write_raw(d / "hold.h5", hold)
    cold = simulate(TC.plan(TC.soak_plan_text(temps=(-40,), soak_s=60, hold_s=5)), tr, seed=13)
    write_raw(d / "cold.h5", cold)
    write_raw(d / "notemp.h5", hold.with_(temp=None))
    _cli("fit", "thermal", d / "raw.h5", "--out", d / "cal.h5", "--order", "2")
    return d


def test_thermal_in_the_batch_and_the_api(thermal_files):
    """fit thermal is a method of the table like the others (issue 33): the batch step and
    the API give the command line's calibration."""
    import json

    from calib_cli import api
    from calib_cli.io.h5 import read_calibration, read_raw

    d = thermal_files
    (d / "pipe.toml").write_text('[[step]]\nstep = "fit"\nmethod = "thermal"\norder = 2\n')
    r = _cli("batch", d / "pipe.toml", d / "raw.h5", "--out", d / "out", "--json")
    out = d / "out" / json.loads(r.output)["inputs"][0]["outputs"]["calibration"]
    cli, bat = read_calibration(d / "cal.h5"), read_calibration(out)
    res = api.fit("thermal", read_raw(d / "raw.h5"), order=2)
    assert sorted(cli.params) == sorted(bat.params) == sorted(res.params)
    for k in cli.params:
        assert np.allclose(cli.params[k], bat.params[k], rtol=1e-12, atol=0)
        assert np.allclose(cli.params[k], res.params[k], rtol=1e-12, atol=0)


def test_cli_fit_show_apply(thermal_files):
    d = thermal_files
    obj = json.loads(_cli("show", d / "cal.h5", "--json").stdout)
    assert obj["stats"]["temp_order"] == 2 and obj["stats"]["temp_ref_degC"] == 25.0
    assert len(obj["stats"]["temp_range_degC"]) == 2
    assert obj["sigma"]["gyro_temp_scale"][0][0] is None
    _cli("apply", d / "cal.h5", d / "hold.h5", "--out", d / "corr.h5")
    from calib_cli.cli.cmd_apply import corrected_norms
    from calib_cli.io.h5 import read_raw

    g = read_raw(d / "hold.h5").site.gravity
    err = np.array([v - g for k, v in corrected_norms(d / "corr.h5").items()
                    if not k.startswith("soak")])
    # the raw error is several mg; each 10 s hold at 10 Hz averages 100 samples of
    # 1e-3 m/s^2 white noise, so its |f| carries ~1e-4 m/s^2 of noise by itself: the RMS
    # over the 12 holds is within 2.5 x that (the old bound, 1e-4, sat at the noise level
    # and passed or failed with the noise realisation)
    assert np.sqrt(np.mean(err ** 2)) < 2.5e-4


def test_apply_refusals(thermal_files, capsys):
    d = thermal_files
    err = _fails(3, "apply", d / "cal.h5", d / "cold.h5", "--out", d / "c1.h5", capsys=capsys)
    assert "cold.h5" in err and "calibrated range" in err and len(err.strip().splitlines()) == 1
    assert not (d / "c1.h5").exists()
    _cli("apply", d / "cal.h5", d / "cold.h5", "--out", d / "c1.h5", "--extrapolate")
    err = _fails(3, "apply", d / "cal.h5", d / "notemp.h5", "--out", d / "c2.h5", capsys=capsys)
    assert "notemp.h5" in err and "--temp" in err
    _cli("apply", d / "cal.h5", d / "notemp.h5", "--out", d / "c2.h5", "--temp", "25")


def test_fit_thermal_without_temperature_is_exit_3(thermal_files, capsys):
    d = thermal_files
    err = _fails(3, "fit", "thermal", d / "notemp.h5", "--out", d / "x.h5", capsys=capsys)
    assert "notemp.h5" in err


CPROG = r"""
#include <stdio.h>
#include "cal.h"
int main(void) {
    double A[3], W[3], T, f[3], w[3];
    while (scanf("%lf %lf %lf %lf %lf %lf %lf", &A[0], &A[1], &A[2], &W[0], &W[1], &W[2], &T) == 7) {
        calib_correct_accel(A, T, f);
        calib_correct_gyro(W, f, T, w);
        printf("%.17g %.17g %.17g %.17g %.17g %.17g\n", f[0], f[1], f[2], w[0], w[1], w[2]);
    }
    return 0;
}
"""


@pytest.mark.skipif(shutil.which("cc") is None, reason="no C compiler")
@pytest.mark.parametrize("single", [False, True])
def test_c_header_matches_apply(thermal_files, single):
    d = thermal_files
    args = ["export", d / "cal.h5", "--format", "c-header", "--out", d / "cal.h"]
    _cli(*(args + (["--float"] if single else [])))
    prog = CPROG.replace("double", "float").replace("%lf", "%f") if single else CPROG
    (d / "prog.c").write_text(prog)
    subprocess.run(["cc", "-std=c99", "-O2", "-Wall", "-Werror", "-o", str(d / "prog"),
                    str(d / "prog.c"), "-lm"], check=True, cwd=d)
    _cli("apply", d / "cal.h5", d / "hold.h5", "--out", d / "corr_c.h5")
    with h5py.File(d / "hold.h5") as h:
        A, W, T = h["samples/accel"][()], h["samples/gyro"][()], h["samples/temp"][()]
    with h5py.File(d / "corr_c.h5") as h:
        ref = np.hstack([h["samples/accel"][()], h["samples/gyro"][()]])
    idx = np.linspace(0, len(A) - 1, 200).astype(int)
    inp = "\n".join(" ".join("%.17g" % x for x in row)
                    for row in np.column_stack([A, W, T])[idx]) + "\n"
    out = subprocess.run([str(d / "prog")], input=inp, capture_output=True, text=True,
                         check=True).stdout
    got = np.array([[float(x) for x in ln.split()] for ln in out.splitlines()])
    ref = ref[idx]
    print("C header vs apply:", "float rel" if single else "double abs",
          np.max(np.abs(got - ref) / (np.abs(ref).max(axis=0) if single else 1.0)))
    if single:
        scale = np.abs(ref).max(axis=0)
        assert np.max(np.abs(got - ref) / scale) < 1e-5
    else:
        assert np.max(np.abs(got - ref)) < 1e-9, np.max(np.abs(got - ref))
    # the temperature terms matter at these temperatures
    assert np.abs(ref[:, :3] - A[idx]).max() > 1e-3


def test_export_json_holds_thermal_terms(thermal_files):
    d = thermal_files
    obj = json.loads(_cli("export", d / "cal.h5", "--format", "json").stdout)
    assert obj["thermal"]["order"] == 2 and obj["thermal"]["temp_ref_degC"] == 25.0
    assert np.array(obj["correction"]["accel"]["temp_bias"]).shape == (3, 2)
    assert "T_ref" in obj["formula"]["accel"]


def test_report_has_thermal_figures(thermal_files):
    d = thermal_files
    _cli("report", d / "cal.h5", "--out", d / "rep")
    md = (d / "rep" / "report.md").read_text()
    assert "Thermal calibration" in md
    for stem in ("thermal-accel", "thermal-gyro", "thermal-g-error"):
        assert any(stem in p.name for p in (d / "rep").glob("*.png")), stem


@pytest.mark.skipif(shutil.which("gcc") is None or shutil.which("nm") is None,
                    reason="no gcc/nm")
def test_thermal_header_defines_only_documented_names(thermal_files):
    from calib_cli.io.export import c_header_symbols

    d = thermal_files
    _cli("export", d / "cal.h5", "--format", "c-header", "--out", d / "cal.h")
    (d / "use.c").write_text('#include "cal.h"\n')
    subprocess.run(["gcc", "-std=c99", "-Wall", "-Wextra", "-Werror", "-O0",
                    "-fkeep-static-functions", "-fkeep-inline-functions", "-c", "use.c", "-o",
                    "use.o"], cwd=d, check=True, capture_output=True)
    out = subprocess.run(["nm", "use.o"], cwd=d, check=True, capture_output=True,
                         text=True).stdout
    names = {ln.split()[-1] for ln in out.splitlines() if len(ln.split()) == 3}
    syms = c_header_symbols("calib", thermal=True)
    assert names == set(syms["objects"]) | set(syms["functions"])

    def macros(src):
        out = subprocess.run(["gcc", "-std=c99", "-dM", "-E", "-x", "c", src], cwd=d, check=True,
                             capture_output=True, text=True).stdout
        return {ln.split()[1].split("(")[0] for ln in out.splitlines()}
    (d / "empty.h").write_text("")
    assert macros("cal.h") - macros("empty.h") == set(syms["macros"])


@pytest.mark.skipif(shutil.which("cc") is None, reason="no C compiler")
def test_lag_header_filter_matches_catalogue(thermal_files):
    """The header's lag filter is the catalogue's lag_temperature."""
    from dataclasses import replace

    from calib_cli.io.export import to_c_header
    from calib_cli.io.h5 import read_calibration

    d = thermal_files
    c = read_calibration(d / "cal.h5")
    c = replace(c, model=c.model + [{"name": "thermal_lag", "sensor": ""}],
                params={**c.params, "thermal_lag_tau": np.array(150.0)})
    (d / "lag.h").write_text(to_c_header(c, {}, "cal.h5"))
    (d / "lag.c").write_text(
        '#include <stdio.h>\n#include "lag.h"\nint main(void) {\n'
        "    double s[2], T; int first = 1;\n"
        '    while (scanf("%lf", &T) == 1) {\n'
        "        if (first) { s[0] = s[1] = T; first = 0; printf(\"%.17g\\n\", T); continue; }\n"
        '        printf("%.17g\\n", calib_lag_temp(s, T, 0.1));\n    }\n    return 0;\n}\n')
    subprocess.run(["cc", "-std=c99", "-Wall", "-Werror", "-o", "lag", "lag.c", "-lm"], cwd=d,
                   check=True)
    t = np.arange(0, 600, 0.1)
    T = 20 + 10 * np.sin(t / 60.0)
    out = subprocess.run([str(d / "lag")], input="\n".join("%.17g" % x for x in T),
                         capture_output=True, text=True, check=True).stdout
    got = np.array([float(x) for x in out.split()])
    assert np.max(np.abs(got - lag_temperature(t, T, 150.0))) < 1e-9


def test_one_temperature_is_exit_4(tmp_path, capsys):
    tr = TC.thermal_truth(np.random.default_rng(3))
    rec = simulate(TC.plan(TC.soak_plan_text(temps=(25,), soak_s=30, hold_s=10)), tr, seed=3)
    write_raw(tmp_path / "one.h5", rec)
    err = _fails(4, "fit", "thermal", tmp_path / "one.h5", "--out", tmp_path / "c.h5",
                 capsys=capsys)
    assert "degC" in err and not (tmp_path / "c.h5").exists()


@pytest.mark.parametrize("design,opts", [
    ("soak", ["--temps", "5", "--soak", "600", "--unit-tau", "120", "--duration", "30"]),
    ("ramp", ["--ramp-dpm", "4", "--unit-tau", "60", "--duration", "40"])])
def test_plan_make_thermal_checks_simulates_and_fits(tmp_path, design, opts):
    """`calib plan make thermal` writes a plan that `plan check` predicts,
    `simulate` runs and `fit thermal` fits within sigma of the truth; the
    predicted sigma is the fit's at the same noise (order 2)."""
    from calib_cli.io.h5 import read_calibration
    from calib_cli.io.plan import load_plan

    plan = tmp_path / "plan.toml"
    _cli("plan", "make", "thermal", "--design", design, *opts, "--out", plan)
    p = load_plan(plan)
    temps = [s.extra["chamber_temp_degC"] for s in p.segments if "chamber_temp_degC" in s.extra]
    if design == "soak":
        assert temps == [-40.0, -8.8, 22.5, 53.8, 85.0] and len(p.segments) == 35
    else:
        assert temps == [-40.0, 85.0, -40.0]
        assert [s.extra.get("chamber_soak", True) for s in p.segments
                if "chamber_temp_degC" in s.extra] == [True, False, False]
    r = _cli("plan", "check", plan, "--json", "--no-suggest")
    pred = json.loads(r.output)
    assert pred["method"] == "thermal"
    assert "gyro_temp_scale[0,0]" in pred["unobservable"]
    tr = TC.thermal_truth(np.random.default_rng(3))
    rec = simulate(p, tr, seed=3)
    write_raw(tmp_path / "raw.h5", rec)
    _cli("fit", "thermal", tmp_path / "raw.h5", "--order", "2", "--out", tmp_path / "cal.h5")
    res = read_calibration(tmp_path / "cal.h5")
    _check_within(res, tr)
    # the prediction at the simulator's noise is the fit's sigma (same design, same order)
    nz = tr.noise
    r = _cli("plan", "check", plan, "--json", "--no-suggest", "--accel-noise",
             nz["accel_white"], "--gyro-noise", nz["gyro_white"])
    pred = json.loads(r.output)
    for k in ("accel_bias", "accel_temp_bias", "gyro_temp_bias"):
        ratio = np.asarray(res.sigma[k]) / np.asarray(pred["sigma"][k])
        print(design, k, "fit/predicted sigma", np.round(ratio.ravel(), 3))
        assert np.all((ratio > 0.9) & (ratio < 1.1)), (k, ratio)


def test_plan_make_thermal_refusals(capsys):
    err = _fails(2, "plan", "make", "thermal", "--design", "ramp", "--temp-range", "20,25",
                 "--out", "x.toml", capsys=capsys)
    assert "--temp-range must span at least 10 degC" in err


def _ap_params(text):
    import csv

    rows = csv.reader([ln for ln in text.splitlines() if ln and not ln.startswith("#")])
    return {r[0]: float(r[1]) for r in rows}


def _ap_correct(prm, sensor, v, temp, caltemp, m=1):
    """ArduPilot's TCal::correct_sensor, written out from
    AP_InertialSensor_tempcal.cpp (TEMP_REFERENCE 35, SCALE_FACTOR 1e6)."""
    short = {"accel": "ACC", "gyro": "GYR"}[sensor]
    tmin, tmax = prm[f"INS_TCAL{m}_TMIN"], prm[f"INS_TCAL{m}_TMAX"]
    c = [np.array([prm[f"INS_TCAL{m}_{short}{k}_{a}"] for a in "XYZ"]) for k in (1, 2, 3)]

    def poly(tdiff):
        return (c[0] + (c[1] + c[2] * tdiff) * tdiff) * tdiff * 1.0e-6

    t = min(max(temp, tmin), tmax)
    ct = min(max(caltemp, tmin), tmax)
    return v - poly(t - 35.0) + poly(ct - 35.0)


@pytest.mark.parametrize("float32", [False, True])
def test_export_ardupilot_tcal_matches_the_bias_drift(thermal_files, float32):
    """INS_TCAL1_*: ArduPilot's correction (its own formula, clamped to
    TMIN..TMAX, relative to INS_ACC1_CALTEMP) followed by the offsets removes
    exactly calib's bias at every temperature of the calibrated range."""
    from calib_cli.io.h5 import read_calibration
    from calib_cli.model.effects import temp_poly

    d = thermal_files
    _cli("export", d / "cal.h5", "--format", "ardupilot", "--out", d / "cal.parm")
    text = (d / "cal.parm").read_text()
    prm = _ap_params(text)
    if float32:  # the autopilot keeps its parameters as float
        prm = {k: float(np.float32(v)) for k, v in prm.items()}
    cal = read_calibration(d / "cal.h5")
    t_ref, (lo, hi) = cal.stats["temp_ref_degC"], cal.stats["temp_range_degC"]
    assert prm["INS_TCAL1_ENABLE"] == 1 and prm["INS_TCAL1_TMIN"] == pytest.approx(lo, abs=1e-5)
    assert prm["INS_TCAL1_TMAX"] == pytest.approx(hi, abs=1e-5)
    assert prm["INS_ACC1_CALTEMP"] == prm["INS_GYR1_CALTEMP"] == t_ref
    assert all(prm[f"INS_TCAL1_{s}3_{a}"] == 0 for s in ("ACC", "GYR") for a in "XYZ")  # order 2
    assert "scale terms are not held" in text and "accel_temp_scale" in text
    assert "accel_temp_bias: temperature terms" not in text  # held, not dropped
    for sensor, off in (("accel", "INS_ACCOFFS_"), ("gyro", "INS_GYROFFS_")):
        offs = np.array([prm[off + a] for a in "XYZ"])
        coef = np.asarray(cal.params[f"{sensor}_temp_bias"])
        for T in np.linspace(lo, hi, 9):
            want = cal.params[f"{sensor}_bias"] + temp_poly(coef, np.array([T - t_ref]))[0]
            got = -(_ap_correct(prm, sensor, np.zeros(3), T, t_ref) - offs)
            drift = np.abs(temp_poly(coef, np.array([lo - t_ref, hi - t_ref]))).max()
            tol = 1e-5 * drift + 1e-6 * np.abs(want).max() if float32 else 1e-12 + 1e-9 * drift
            assert np.all(np.abs(got - want) <= tol), (sensor, T, got - want)


def test_ardupilot_reexpansion_about_35():
    from calib_cli.io.export_autopilot import reexpand

    b = np.array([[1e-3, 2e-5, -3e-7], [0.0, 1e-5, 0.0], [-2e-3, 0.0, 4e-7]])
    c = reexpand(b, 20.0)
    T = np.linspace(-40, 85, 11)
    want = temp_poly(b, T - 20.0)
    got = np.stack([sum(c[:, j] * (t - 35.0) ** j for j in range(4)) for t in T])
    assert np.allclose(got, want, rtol=0, atol=1e-12)


def test_export_ardupilot_tref_outside_the_range(thermal_files):
    """T_ref above TMAX: ArduPilot would clamp CALTEMP, so CALTEMP is TMAX and the
    offsets are calib's biases at TMAX; the correction is still exact."""
    from calib_cli.io.h5 import read_calibration
    from calib_cli.model.effects import temp_poly

    d = thermal_files
    _cli("fit", "thermal", d / "raw.h5", "--order", "2", "--temp-ref", "80",
         "--out", d / "cal80.h5")
    r = _cli("export", d / "cal80.h5", "--format", "ardupilot")
    prm = _ap_params(r.output)
    cal = read_calibration(d / "cal80.h5")
    lo, hi = cal.stats["temp_range_degC"]
    assert prm["INS_ACC1_CALTEMP"] == pytest.approx(hi) and hi < 80
    offs = np.array([prm["INS_ACCOFFS_" + a] for a in "XYZ"])
    for T in np.linspace(lo, hi, 5):
        want = cal.params["accel_bias"] + temp_poly(cal.params["accel_temp_bias"],
                                                    np.array([T - 80.0]))[0]
        got = -(_ap_correct(prm, "accel", np.zeros(3), T, prm["INS_ACC1_CALTEMP"]) - offs)
        assert np.allclose(got, want, rtol=0, atol=1e-10)
