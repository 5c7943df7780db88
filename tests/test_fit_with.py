"""calib fit METHOD --with EFFECT, --list-effects, and a diagnosis file as a
calibration (issue 18, docs/diagnose.md "From a diagnosis to a calibration")."""

from __future__ import annotations

import json
import shutil
import subprocess

import h5py
import numpy as np
import pytest

from calib_cli.cli.main import cli
from calib_cli.io.h5 import read_calibration
from calib_cli.methods.apply import model_of
from calib_cli.model.correction import correct
from calib_cli.sim.simulate import simulate
from calib_cli.validation import diagnose_cases as C

TRUTH = ('[params]\naccel_bias_mg = [1, 2, 3]\n'
         'accel_nonlinearity = [6e-5, -4e-5, 5e-5]\n')  # about 600 ug/g^2: 40-60 sigma


class _R:
    def __init__(self, out, err):
        self.stdout, self.stderr = out, err


def run(capsys, *args, code=0):
    """The calib command in-process (exit code and one-line errors as the CLI's)."""
    from calib_cli.cli.common import Ctx
    from calib_cli.cli.main import main

    capsys.readouterr()
    quiet = Ctx.quiet
    with pytest.raises(SystemExit) as e:
        main([str(a) for a in args])
    Ctx.quiet = quiet
    out, err = capsys.readouterr()
    assert e.value.code == code, (e.value.code, err)
    return _R(out, err)


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("withfx")
    (d / "plan.toml").write_text(C.ACCEL_PLAN)
    (d / "truth.toml").write_text(TRUTH)
    assert cli.main(["simulate", str(d / "plan.toml"), "--truth", str(d / "truth.toml"),
                     "--out", str(d / "raw.h5"), "--seed", "5"], standalone_mode=False) in (0, None)
    assert cli.main(["diagnose", str(d / "raw.h5"), "--method", "accel", "--out",
                     str(d / "diag.h5"), "--calibration", str(d / "dcal.h5"), "--json", "-q"],
                    standalone_mode=False) in (0, None)
    return d


def test_fit_with_agrees_with_the_diagnosis_within_a_tenth_of_sigma(files, capsys):
    d = files
    capsys.readouterr()
    cli.main(["show", str(d / "diag.h5"), "--json"], standalone_mode=False)
    j = json.loads(capsys.readouterr().out)
    assert [s["with"] for s in j["steps"]] == ["accel_nonlinearity"]
    assert j["fit_command"].startswith("calib fit accel ")
    assert "--with accel_nonlinearity" in j["fit_command"]
    for k in ("params", "sigma", "units", "stats", "base_model", "steps",
              "residual_rms_initial", "residual_rms_final", "noise_rms"):
        assert k in j
    cli.main(["fit", "accel", str(d / "raw.h5"), "--out", str(d / "with.h5"), "--with",
              "accel_nonlinearity", "-q"], standalone_mode=False)
    a, b, c = (read_calibration(d / n) for n in ("diag.h5", "dcal.h5", "with.h5"))
    assert set(a.params) == set(c.params) == {"accel_bias", "accel_K", "accel_nonlinearity"}
    for k in c.params:
        s = np.asarray(c.sigma[k], float)
        ok = s > 0
        for other in (a, b):
            z = np.abs(np.asarray(other.params[k]) - np.asarray(c.params[k]))[ok] / s[ok]
            assert np.all(z < 0.1), (k, z.max())
    # the whole model with covariance, and the truth within sigma
    assert a.covariance.shape == (len(a.cov_order),) * 2 and len(a.cov_order) == 15
    k2, s2 = c.params["accel_nonlinearity"], c.sigma["accel_nonlinearity"]
    assert np.all(np.abs(k2 - [6e-5, -4e-5, 5e-5]) < 4.5 * s2)
    st = c.stats
    assert st["with"] == ["accel_nonlinearity"] and st["g_error_rms_after"] < 0.1 * \
        st["g_error_rms_before"]


def test_list_effects_and_what_a_record_cannot_excite(files, capsys):
    d = files
    out = run(capsys, "fit", "accel", "--list-effects").stdout.splitlines()
    assert any(ln.startswith("accel_nonlinearity: ") for ln in out)
    assert not any(ln.startswith("lever_arm") for ln in out)  # static method: not accepted
    out = run(capsys, "fit", "turntable", "--list-effects").stdout
    assert "lever_arm:" in out and "gyro.temperature_drift:" in out
    out = run(capsys, "fit", "accel", d / "raw.h5", "--list-effects").stdout
    assert "accel_nonlinearity: excited by this record" in out
    assert "lever_arm: not excited" in out and "record rotating cycles" in out
    r = run(capsys, "fit", "accel", d / "raw.h5", "--out", d / "x.h5", "--with", "lever_arm", code=4)
    assert "raw.h5" in r.stderr and "record rotating cycles" in r.stderr
    assert len(r.stderr.strip().splitlines()) == 1
    r = run(capsys, "fit", "accel", d / "raw.h5", "--out", d / "x.h5", "--with", "misalignment", code=2)
    assert "--base diagonal" in r.stderr
    run(capsys, "fit", "accel", d / "raw.h5", "--out", d / "x.h5", "--with", "nonlinear", code=2)
    run(capsys, "fit", "accel", d / "raw.h5", "--out", d / "x.h5", "--with", "gyro.scale_asymmetry",
        code=2)
    assert not (d / "x.h5").exists()


def test_noise_term_widens_sigma_and_is_reported_not_applied(files):
    from calib_cli.io.h5 import read_raw
    from calib_cli.methods.fit_with import fit_with

    rec = read_raw(files / "raw.h5")
    res, _, _ = fit_with(rec, "accel", [("accel_nonlinearity", "accel"),
                                       ("bias_random_walk", "accel")])
    assert "accel bias_random_walk" in res.stats["noise_model"]
    assert not any(d["name"] == "bias_random_walk" for d in res.model)
    assert "accel_bias_rw" not in res.params


def test_diagnosis_file_is_a_calibration_for_apply_export_compare(files, capsys):
    d = files
    run(capsys, "apply", d / "diag.h5", d / "raw.h5", "--out", d / "corr.h5")
    r = run(capsys, "show", d / "diag.h5", d / "dcal.h5", "--json")
    assert "differences" in r.stdout or "z" in r.stdout
    j = json.loads(run(capsys, "export", d / "diag.h5", "--format", "json").stdout)
    assert "k2_i f_i^2" in j["formula"]["accel"]
    assert np.allclose(j["correction"]["accel"]["k2"],
                       read_calibration(d / "diag.h5").params["accel_nonlinearity"])


@pytest.mark.skipif(shutil.which("cc") is None, reason="no C compiler")
def test_c_header_with_nonlinearity_reproduces_apply(files, capsys):
    import h5py

    d = files
    run(capsys, "export", d / "diag.h5", "--format", "c-header", "--out", d / "nl.h")
    (d / "nl.c").write_text('#include <stdio.h>\n#include "nl.h"\nint main(void) {\n'
                            '  double A[3], f[3];\n'
                            '  while (scanf("%lf %lf %lf", &A[0], &A[1], &A[2]) == 3) {\n'
                            '    calib_correct_accel(A, f);\n'
                            '    printf("%.17g %.17g %.17g\\n", f[0], f[1], f[2]);\n  }\n'
                            '  return 0;\n}\n')
    subprocess.run(["cc", "-std=c99", "-O2", "-Wall", "-Werror", "-o", str(d / "nl"),
                    str(d / "nl.c"), "-lm"], check=True, cwd=d)
    run(capsys, "apply", d / "diag.h5", d / "raw.h5", "--out", d / "corr2.h5")
    with h5py.File(d / "raw.h5") as h:
        A = h["samples/accel"][()][::50]
    with h5py.File(d / "corr2.h5") as h:
        ref = h["samples/accel"][()][::50]
    inp = "\n".join(" ".join("%.17g" % x for x in row) for row in A) + "\n"
    out = subprocess.run([str(d / "nl")], input=inp, capture_output=True, text=True,
                         check=True).stdout
    got = np.array([[float(x) for x in ln.split()] for ln in out.splitlines()])
    assert np.abs(got - ref).max() < 1e-9 * 9.81  # the 3 iterations converge to apply's inverse
    # and the nonlinear terms matter at this size (the test can fail)
    cal = read_calibration(d / "diag.h5")
    lin = correct(model_of(cal), {k: v for k, v in cal.params.items()
                                  if k != "accel_nonlinearity"}, "accel", A)
    assert np.abs(lin - ref).max() > 1e-4


def holdout_g_errors(seed: int, scale=(10.0, 15.0)):
    """|g| error per position of an independent record (same plan and unit, hidden
    nonlinearity) corrected by: the truth (the noise floor), the diagnosis's
    calibration, and the base fit (calib fit accel)."""
    from calib_cli.methods.accel_lsq import fit_accel
    from calib_cli.methods.diagnose import diagnose

    rng = np.random.default_rng(seed)
    truth = C.hidden_effect_truth("accel_nonlinearity", rng, scale=scale)
    plan = C.plan_of("accel")
    rec, hold = simulate(plan, truth, seed=seed), simulate(plan, truth, seed=seed + 100000)
    cal = diagnose(rec, "accel").calibration(rec)
    base = fit_accel(rec)

    def g_err(model, params):
        out = []
        for s in hold.static_segments():
            x = correct(model, params, "accel", np.asarray(hold.accel[s.slice], float),
                        temp=np.asarray(hold.temp[s.slice], float))
            out.append(np.linalg.norm(x.mean(axis=0)) - hold.site.gravity)
        return np.array(out)

    return (g_err(truth.model, truth.params), g_err(model_of(cal), cal.params),
            g_err(model_of(base), base.params))


def _pooled(seeds):
    parts = [holdout_g_errors(s) for s in seeds]
    rms = [float(np.sqrt(np.mean(np.concatenate([p[i] for p in parts]) ** 2)))
           for i in range(3)]
    return rms[1] / rms[0], rms[2] / rms[0]


def test_holdout_g_error_of_the_diagnosis_calibration_fast():
    diag, base = _pooled([1, 2])
    assert diag <= 1.3 and base >= 3.0, (diag, base)


@pytest.mark.slow
def test_holdout_g_error_of_the_diagnose_calibration_20_seeds():
    diag, base = _pooled(range(1, 21))
    print(f"hold-out |g| error RMS: diagnosis calibration {diag:.3f}x, base {base:.2f}x the "
          "noise floor (20 seeds)")
    assert diag <= 1.2 and base >= 3.0, (diag, base)


SIX = ('name = "six"\nkind = "static"\nsample_rate_hz = 50.0\n[site]\n'
       'latitude_deg = 45.0\n' + "".join(
           f'[[segment]]\nlabel = "p{i}"\nattitude_deg = [{a}, {b}, 0]\nduration_s = 5.0\n'
           for i, (a, b) in enumerate([(0, -90), (0, 90), (90, 0), (-90, 0), (0, 0),
                                       (180, 0)])))


def test_axis_aligned_plan_reports_nonlinearity_and_asymmetry_not_separable():
    from calib_cli.io.plan import parse_plan
    from calib_cli.methods.diagnose import diagnose
    from calib_cli.model.truth import truth_from_dict
    from calib_cli.sim.simulate import plan_layout

    plan = parse_plan(SIX)
    truth = truth_from_dict({"params": {"accel_scale_asymmetry": [3e-3, -3e-3, 2e-3]}},
                            plan_layout(plan))
    d = diagnose(simulate(plan, truth, seed=4), "accel")
    assert [s.with_arg for s in d.steps] == ["accel_nonlinearity"]
    assert any("not separable" in n and "35-55 deg" in n for n in d.notes)


@pytest.mark.slow
@pytest.mark.parametrize("key,mag", [("accel_scale_asymmetry", 3e-3),
                                     ("accel_nonlinearity", 3e-4)])
def test_not_separable_on_axis_aligned_plans_20_seeds(key, mag):
    """On the six axis-aligned positions a hidden scale asymmetry or nonlinearity
    (60-100 % of the given size per axis, random signs) is reported as not separable
    from the other in >= 19 of 20 seeds (measured: 20/20 each)."""
    from calib_cli.io.plan import parse_plan
    from calib_cli.methods.diagnose import diagnose
    from calib_cli.model.truth import truth_from_dict
    from calib_cli.sim.simulate import plan_layout

    plan = parse_plan(SIX)
    ok = 0
    for seed in range(20):
        rng = np.random.default_rng(seed)
        v = (rng.uniform(0.6, 1.0, 3) * rng.choice([-1, 1], 3) * mag).tolist()
        truth = truth_from_dict({"params": {key: v}}, plan_layout(plan))
        d = diagnose(simulate(plan, truth, seed=seed + 50), "accel")
        ok += len(d.steps) >= 1 and any("not separable" in n for n in d.notes)
    assert ok >= 19, ok


def test_diagnose_gyro_names_scale_asymmetry_and_closes_the_turn_angles(tmp_path, capsys):
    import gyro_sim as G

    plan = tmp_path / "gyro.toml"
    plan.write_text(G.plan_text().replace(
        'name = "gyro-sim"', 'name = "gyro-sim"\ntemperature_profile = '
        '[[0, 20.0], [80, 35.0], [160, 24.0], [260, 32.0]]'))
    (tmp_path / "t.toml").write_text('[params]\ngyro_bias_dps = [0.1, -0.2, 0.05]\n'
                                     'gyro_scale_asymmetry = [2e-3, -1.5e-3, 1e-3]\n')
    raw, diag, cal = tmp_path / "raw.h5", tmp_path / "diag.h5", tmp_path / "cal.h5"
    run(capsys, "simulate", plan, "--truth", tmp_path / "t.toml", "--out", raw, "--seed", "3")
    j = json.loads(run(capsys, "diagnose", raw, "--method", "gyro", "--out", diag,
                       "--calibration", cal, "--json", "--report", tmp_path / "rep").stdout)
    assert [s["with"] for s in j["steps"]] == ["gyro.scale_asymmetry"]
    assert j["fit_command"].endswith("--with gyro.scale_asymmetry")
    assert j["residual_rms_final"] <= 1.2 * j["noise_rms"] < j["residual_rms_initial"]
    worst = max(abs(r["error_initial_deg"]) for r in j["turn_angle_error_deg"])
    assert max(abs(r["error_final_deg"]) for r in j["turn_angle_error_deg"]) < worst / 5
    assert "Turn-angle error" in (tmp_path / "rep" / "summary.md").read_text()
    run(capsys, "fit", "gyro", raw, "--out", tmp_path / "with.h5", "--with", "scale_asymmetry")
    a, c = read_calibration(diag), read_calibration(tmp_path / "with.h5")
    for k in c.params:
        s = np.asarray(c.sigma[k], float)
        ok = np.isfinite(s) & (s > 0)
        assert np.all(np.abs(np.asarray(a.params[k]) - c.params[k])[ok] < 0.1 * s[ok]), k
    est, sig = c.params["gyro_scale_asymmetry"], c.sigma["gyro_scale_asymmetry"]
    assert np.all(np.abs(est - [2e-3, -1.5e-3, 1e-3]) < 4.5 * sig)
    ex = json.loads(run(capsys, "export", diag, "--format", "json").stdout)
    assert np.allclose(ex["correction"]["gyro"]["a"], a.params["gyro_scale_asymmetry"])
    r = run(capsys, "fit", "gyro", raw, "--out", tmp_path / "x.h5", "--with", "lever_arm",
            code=2)
    assert "the gyro method takes" in r.stderr


def test_fit_rimu_with_g_sensitivity_within_sigma_and_apply(tmp_path, capsys):
    from calib_cli.io.h5 import write_raw
    from calib_cli.io.plan import parse_plan
    from calib_cli.methods.fit_with import fit_with
    from calib_cli.model.truth import truth_from_dict
    from calib_cli.sim.simulate import plan_layout

    rimu = ('name = "rimu-six"\nkind = "rimu"\nsample_rate_hz = 50.0\ntransition_s = 2.0\n'
            '[site]\nlatitude_deg = 50.45\n[rimu]\nprofile = "tetrahedron"\n' + "".join(
                f'[[segment]]\nlabel = "p{i}"\nattitude_deg = [{a}, {b}, 0]\n'
                'table_axis_enu = [0, 0, 1]\n'
                'rate_profile = [[0, 20], [4, 20], [6, -60], [10, -60]]\n'
                for i, (a, b) in enumerate([(0, -90), (0, 90), (90, 0), (-90, 0), (0, 0),
                                            (180, 0)])))
    plan = parse_plan(rimu)
    D = np.zeros((9, 3))
    D[[0, 4, 8], [0, 1, 2]] = [2e-4, -1.5e-4, 1e-4]
    truth = truth_from_dict({"params": {"gyro_D": D.tolist()}}, plan_layout(plan))
    rec = simulate(plan, truth, seed=9)
    res, _, _ = fit_with(rec, "rimu", [("g_sensitivity", "gyro")])
    est, sig = res.params["gyro_D"], res.sigma["gyro_D"]
    ok = np.isfinite(sig) & (sig > 0)
    assert np.all(np.abs(est - D)[ok] < 4.5 * sig[ok])
    assert res.layout.redundant and "gyro_D" in res.params
    raw = tmp_path / "raw.h5"
    write_raw(raw, rec)
    run(capsys, "fit", "rimu", raw, "--out", tmp_path / "cal.h5", "--with", "g_sensitivity")
    # apply inverts the redundant unit's model with gyro_D through the forward model
    run(capsys, "apply", tmp_path / "cal.h5", raw, "--out", tmp_path / "c.h5")

    import dataclasses

    from calib_cli.methods.rimu import apply_rimu, segment_kinematics

    cal = read_calibration(tmp_path / "cal.h5")
    base = dataclasses.replace(cal, model=[d for d in cal.model
                                           if d.get("name") != "g_sensitivity"])
    wo = apply_rimu(base, rec.accel, rec.gyro)["gyro_body"]
    e_with, e_base = [], []
    with h5py.File(tmp_path / "c.h5") as h:
        wb = h["samples/gyro_body"][...]
        n_gyro = h["samples/gyro"].shape[1]
    for s in rec.segments:
        w = segment_kinematics(rec, s).w.mean(axis=0)
        e_with.append(wb[s.slice].mean(axis=0) - w)
        e_base.append(wo[s.slice].mean(axis=0) - w)
    # the rate from the corrected outputs: the g-sensitivity D f removed
    rms = lambda e: float(np.sqrt(np.mean(np.square(e))))  # noqa: E731
    assert rms(e_with) < rms(e_base) / 5, (rms(e_with), rms(e_base))
    assert n_gyro == 9 and "gyro_D" in cal.params
    run(capsys, "fit", "rimu", raw, "--out", tmp_path / "x.h5", "--with", "misalignment",
        code=2)


def test_apply_rimu_with_nonlinearity_removes_it_on_a_holdout(tmp_path, capsys):
    """issue 18: a RIMU calibration fitted with --with accel_nonlinearity is applied
    (the model inverted through the forward model): on an independent record of the
    same unit the static single-axis outputs match the true inputs at the noise
    floor, where the same calibration without the term leaves ~5x."""
    import dataclasses

    from calib_cli.io.h5 import read_raw, write_raw
    from calib_cli.methods.apply import apply_redundant
    from calib_cli.methods.rimu import apply_rimu, segment_kinematics

    plan = C.plan_of("rimu")
    truth = C.hidden_effect_truth("rimu: accel_nonlinearity", np.random.default_rng(1),
                                  scale=(10.0, 15.0))
    raw, hold = tmp_path / "raw.h5", tmp_path / "hold.h5"
    write_raw(raw, simulate(plan, truth, seed=1))
    rec = simulate(plan, truth, seed=1001)
    write_raw(hold, rec)
    run(capsys, "fit", "rimu", raw, "--out", tmp_path / "cal.h5", "--with", "accel_nonlinearity")
    run(capsys, "apply", tmp_path / "cal.h5", hold, "--out", tmp_path / "c.h5")
    cal = read_calibration(tmp_path / "cal.h5")
    out = read_raw(tmp_path / "c.h5")
    lay = rec.layout
    S = lay.axes(np.asarray(truth.params["accel_dEl"]), np.asarray(truth.params["accel_dAz"]))
    base = dataclasses.replace(cal, model=[d for d in cal.model
                                           if d.get("name") != "accel_nonlinearity"])
    wo = apply_rimu(base, rec.accel, rec.gyro)["accel"]
    err_with, err_base = [], []
    for s in rec.static_segments():
        u = segment_kinematics(rec, s).f @ S.T
        a = rec.accel[s.slice]
        floor = a.std(axis=0) / np.sqrt(len(a))
        err_with.append((out.accel[s.slice].mean(axis=0) - u.mean(axis=0)) / floor)
        err_base.append((wo[s.slice].mean(axis=0) - u.mean(axis=0)) / floor)
    rms = lambda e: float(np.sqrt(np.mean(np.square(e))))  # noqa: E731
    assert rms(err_with) <= 1.5 and rms(err_base) >= 3.0, (rms(err_with), rms(err_base))
    # the base model through the same inversion is apply_rimu's closed form
    got = apply_redundant(base, rec.accel[:500], rec.gyro[:500])
    ref = apply_rimu(base, rec.accel[:500], rec.gyro[:500])
    for k in ("accel", "accel_body", "gyro", "gyro_body"):
        assert np.allclose(got[k], ref[k], rtol=0, atol=1e-12), k


@pytest.mark.parametrize("case", ["lever_arm", "align: gyro temperature_drift"])
def test_fit_with_is_the_diagnosis_final_model_turntable_align(case):
    """issue 18: `fit --with` the steps a diagnosis named and the diagnosis's final
    model agree within 0.1 sigma on every parameter (they are one computation, the
    noise level settled for the final model in both), here on a turntable and an
    alignment record (the accel and gyro methods: the tests above)."""
    from calib_cli.methods.diagnose import diagnose
    from calib_cli.methods.fit_with import fit_with

    method, name, sensor, base = C.CASES[case]
    truth = C.hidden_effect_truth(case, np.random.default_rng(7))
    rec = simulate(C.plan_of(method), truth, seed=8)
    d = diagnose(rec, method, base=base)
    assert C.first_key(d) == C.expected(case)
    cal = d.calibration(rec)
    if method == "turntable":  # the filter's own --with (methods/turntable/diagnose.py)
        from calib_cli.methods.turntable import TurntableOptions
        from calib_cli.methods.turntable.diagnose import fit_with as filter_with

        res = filter_with(rec, TurntableOptions(), [(s.effect, s.sensor) for s in d.steps],
                          base)
    else:
        res, _, _ = fit_with(rec, method, [(s.effect, s.sensor) for s in d.steps], base=base)
    assert set(cal.params) == set(res.params)
    for k in res.params:
        s = np.asarray(res.sigma[k], float)
        ok = np.isfinite(s) & (s > 0)
        z = np.abs(np.asarray(cal.params[k]) - np.asarray(res.params[k]))[ok] / s[ok]
        assert np.all(z < 0.1), (k, z.max())
        assert np.allclose(np.asarray(cal.sigma[k])[ok], s[ok], rtol=0.01), k
