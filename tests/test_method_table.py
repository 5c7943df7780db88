"""The method table (issue 33): a method is one object registered once, and every way
in goes through it -- ``calib fit``, ``calib batch``, ``calib_cli.api``, ``calib plan
check``, ``calib diagnose``, ``calib report`` -- with the same checks in the same order.

The toy-method test adds a method as docs/architecture.md's recipe says -- one new
module and one registration line, in a copy of the package -- and runs it through the
command line, the batch, the Python API, plan check, the report and diagnose (its own
``Diagnose`` description)."""

from __future__ import annotations

import dataclasses
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np

import calib_cli
from calib_cli.methods import registry

PACKAGE = Path(calib_cli.__file__).parent
ROOT = PACKAGE.parent
PLAN = ROOT / "sample_data" / "twelve_position.toml"

TOY = '''"""A toy method: the accelerometer bias at known attitudes (the mean of the static
positions' specific force minus gravity's), scaled by a toy option."""

from calib_cli.methods.method import AtLeast, Diagnose, Method, Option, Requires


def fit_toy(rec, o, noise=None):
    import numpy as np

    from calib_cli.data import CalibrationResult
    from calib_cli.methods.segstats import static_stats
    from calib_cli.model.frames import attitude_to_rotation

    st = static_stats(rec, "accel")
    known = [k for k, s in enumerate(st.segments) if s.attitude is not None]
    g = np.array([0.0, 0.0, rec.site.gravity])
    up = np.array([attitude_to_rotation(st.segments[k].attitude).inv().apply(g)
                   for k in known])
    n = st.counts[known]
    r = st.means[known] - up
    b = o.scale * (n[:, None] * r).sum(axis=0) / n.sum()
    sig = np.asarray(noise["accel"] if noise is not None else st.sigma, float) * np.ones(3)
    sb = o.scale * sig / np.sqrt(n.sum())
    return CalibrationResult(
        "toy", {"accel_bias": b}, {"accel_bias": sb}, {"accel_bias": "m/s^2"},
        np.diag(sb**2), [("accel_bias", i) for i in range(3)],
        {"accel_residual_rms": float(np.sqrt(np.mean((r - b) ** 2))), "unobservable": []},
        layout=rec.layout, serial=rec.serial, model=[{"name": "bias", "sensor": "accel"}])


def toy_base(pb, base="full"):
    """The toy's own model in catalogue effects, for calib diagnose: the bias alone."""
    from calib_cli.model.effects import make_effect

    return [make_effect("bias", "accel")], ["accel_bias"], False


METHOD = Method(
    "toy", "a toy: the accelerometer bias at known attitudes", fit_toy,
    options=(Option("scale", 1.0, "A toy factor on the bias.", "float", lo=0.0, lo_open=True),),
    requires=Requires("triad", ("accel",), min_static=1), plan_kinds=("static",),
    diagnose=Diagnose(base="calib_cli.methods.toy:toy_base", sensors=("accel",),
                      needs=(AtLeast("static", 2, "{count} static positions: the toy needs 2"),)))
'''
REGISTRATION = '\nregister(resolve("calib_cli.methods.toy:METHOD"))\n'


DRIVER = r'''"""Runs in the copied package: the command line in-process (one interpreter for
all the commands), the API, and prints what the test checks as JSON."""
import contextlib, io, json, sys
from pathlib import Path

from calib_cli.cli.main import main


def calib(*args):
    out, err = io.StringIO(), io.StringIO()
    code = 0
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        try:
            main([str(a) for a in args])
        except SystemExit as exc:
            code = exc.code if isinstance(exc.code, int) else 0
    return {"code": code, "out": out.getvalue(), "err": err.getvalue()}


d, plan = Path(sys.argv[1]), sys.argv[2]
r = {"simulate": calib("simulate", plan, "--out", d / "raw.h5", "--seed", "3"),
     "help": calib("fit", "--help"), "help_toy": calib("fit", "toy", "--help"),
     "fit": calib("fit", "toy", d / "raw.h5", "--out", d / "toy.h5", "--scale", "1"),
     "bad": calib("fit", "toy", d / "raw.h5", "--out", d / "x.h5", "--scale", "-1")}
(d / "pipe.toml").write_text('[[step]]\nstep = "fit"\nmethod = "toy"\nscale = 1.0\n')
r["batch"] = calib("batch", d / "pipe.toml", d / "raw.h5", "--out", d / "out", "--json")
from calib_cli import api

r["api"] = api.fit("toy", api.read_raw(d / "raw.h5"), scale=1.0).params["accel_bias"].tolist()
r["show"] = calib("show", d / "toy.h5", "--json")
r["plan"] = calib("plan", "check", plan, "--method", "toy", "--json", "--like", d / "raw.h5")
r["report"] = calib("report", d / "toy.h5", "--out", d / "rep")
r["diagnose"] = calib("diagnose", d / "raw.h5", "--method", "toy", "--out", d / "diag.h5",
                      "--json")
print(json.dumps(r))
'''


def test_toy_method_is_one_module_and_one_line(tmp_path):
    root = tmp_path / "src"
    shutil.copytree(PACKAGE, root / "calib_cli", ignore=shutil.ignore_patterns("__pycache__"))
    (root / "calib_cli" / "methods" / "toy.py").write_text(TOY)
    reg = root / "calib_cli" / "methods" / "registry.py"
    reg.write_text(reg.read_text() + REGISTRATION)
    d = tmp_path / "work"
    d.mkdir()
    (tmp_path / "driver.py").write_text(DRIVER)
    env = {**os.environ, "PYTHONPATH": str(root), "MPLBACKEND": "Agg"}
    p = subprocess.run([sys.executable, str(tmp_path / "driver.py"), str(d), str(PLAN)],
                       cwd=root, env=env, capture_output=True, text=True, timeout=600)
    assert p.returncode == 0, p.stderr
    r = json.loads(p.stdout)
    for k in ("simulate", "help", "help_toy", "fit", "batch", "show", "plan", "report",
              "diagnose"):
        assert r[k]["code"] == 0, (k, r[k]["err"])
    # the command line: listed, its option generated and checked (exit 3 naming it)
    assert "toy" in r["help"]["out"] and "--scale" in r["help_toy"]["out"]
    assert r["bad"]["code"] == 3 and "--scale" in r["bad"]["err"]
    # the batch: a step with the option as a key
    assert json.loads(r["batch"]["out"])["summary"]["ok"] == 1
    # the Python API, the option as a keyword: the command line's result
    shown = json.loads(r["show"]["out"])
    assert np.allclose(r["api"], shown["params"]["accel_bias"], rtol=1e-12)
    # plan check predicts it (the fit's own information at the recording's noise)
    pred = json.loads(r["plan"]["out"])
    assert pred["method"] == "toy" and pred["unobservable"] == []
    ratio = np.asarray(pred["sigma"]["accel_bias"]) / np.asarray(shown["sigma"]["accel_bias"])
    assert np.all((ratio > 0.87) & (ratio < 1.15)), ratio
    # the report
    md = (d / "rep" / "report.md").read_text()
    assert "toy" in md and "accel_bias" in md
    # calib diagnose: through the toy's own Diagnose description (its base model, the
    # bias alone), no diagnose code touched
    diag = json.loads(r["diagnose"]["out"])
    assert diag["method"] == "toy" and diag["base_model"] == ["accel_bias"]
    assert diag["residual_rms_final"] < diag["residual_rms_initial"]


def test_every_way_in_offers_the_table():
    """calib fit's subcommands, the batch's fit steps, the API, plan check's and
    diagnose's --method: the table's names and no list of their own."""
    from calib_cli import api, design
    from calib_cli.batch.registry import FITS as batch_fits
    from calib_cli.cli import cmd_diagnose, cmd_fit, cmd_plan

    names = set(registry.FITS)
    assert {"accel", "gyro", "align", "rimu", "turntable", "thermal"} <= names
    assert set(cmd_fit.fit_group.commands) == names
    assert set(batch_fits) == names | {"auto"}
    assert api.FITS is registry.FITS
    choices = next(p for p in cmd_plan.plan_check_cmd.params if p.name == "method").type.choices
    assert set(choices) == set(registry.plan_method_names()) >= names | {"auto"}
    dchoices = next(p for p in cmd_diagnose.diagnose_cmd.params if p.name == "method").type.choices
    assert set(dchoices) == {m for m in names if registry.FITS[m].diagnose}
    for m in registry.FITS.values():  # batch keys and API keywords are the options' names
        assert set(batch_fits[m.name].options) >= set(m.option_names())
        assert [f.name for f in dataclasses.fields(m.options_type)] == [o.name for o in m.options]
    assert design.resolve_method(api.load_plan(PLAN)) == "vector"


def test_diagnose_reads_the_description_and_refuses_a_method_without_one():
    """calib diagnose has no list of methods: a method's requirements and their messages
    come from its Diagnose description (exit 4 naming the shortfall), and a method
    without one is refused (InputError, exit 3) naming the methods that have one."""
    import pytest

    from calib_cli.errors import EstimationError, InputError
    from calib_cli.io.h5 import read_raw
    from calib_cli.methods.diagnose_problem import build_problem
    from calib_cli.methods.method import AtLeast, Diagnose, Method

    rec = read_raw(Path(__file__).parent / "fixtures" / "v0.1.0" / "raw_static.h5")
    fit = registry.FITS["accel"].fit
    picky = Method("picky", "needs many positions", fit, diagnose=Diagnose(
        base="calib_cli.methods.diagnose_models:accel_base", sensors=("accel",),
        needs=(AtLeast("static", 99, "{count} positions; picky needs 99"),)))
    mute = Method("mute", "no diagnosis", fit)
    for m in (picky, mute):
        registry.register(m)
    try:
        with pytest.raises(EstimationError) as e:
            registry.diagnose("picky", rec)
        n = len([s for s in rec.segments if s.kind == "static" and s.n >= 3])
        assert e.value.exit_code == 4 and e.value.message == f"{n} positions; picky needs 99"
        for name in ("mute", "thermal"):
            with pytest.raises(InputError) as e:
                registry.diagnose(name, rec)
            assert e.value.exit_code == 3 and "has no diagnosis" in e.value.message
            assert "accel" in e.value.message and "picky" in e.value.message
            with pytest.raises(InputError):
                build_problem(rec, name)
        assert "picky" in registry.diagnosable() and "mute" not in registry.diagnosable()
    finally:
        for m in (picky, mute):
            registry.FITS.pop(m.name)


def test_start_up_imports_no_numpy_for_the_table():
    """The command line builds its options from the table at start-up: the table
    imports nothing heavy (cli/cmd_fit.py's help stays fast)."""
    code = ("import sys; import calib_cli.methods.registry, calib_cli.cli.method_options; "
            "print(sorted(m for m in ('numpy', 'scipy', 'h5py') if m in sys.modules))")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                         check=True).stdout
    assert out.strip() == "[]"


def test_with_goes_through_the_same_checks(run_cli, tmp_path):
    """fit --with refuses a record the plain fit's check_recording refuses (with its
    message and exit code), and screens gross errors as the plain fit does."""
    from calib_cli.io.h5 import read_raw, write_raw

    fix = Path(__file__).parent / "fixtures" / "v0.1.0"
    for raw, method in ((fix / "raw_rimu.h5", "accel"), (fix / "raw_static.h5", "rimu")):
        plain = run_cli("fit", method, raw, "--out", tmp_path / "p.h5")
        withe = run_cli("fit", method, raw, "--out", tmp_path / "w.h5", "--with",
                        "scale_asymmetry" if method == "rimu" else "accel_nonlinearity")
        assert plain[0] == withe[0] == 3 and plain[2] == withe[2], (plain, withe)
    # a position whose stated attitude is 20 deg off: exit 4 naming it, plain and --with
    rec = read_raw(fix / "raw_static.h5")
    segs = list(rec.segments)
    k = next(i for i, s in enumerate(segs) if s.kind == "static" and abs(s.attitude[1]) < 1.0)
    segs[k] = dataclasses.replace(segs[k], attitude=segs[k].attitude + np.radians([20, 0, 0]))
    bad = tmp_path / "gross.h5"
    write_raw(bad, rec.with_(segments=tuple(segs)))
    plain = run_cli("fit", "accel", bad, "--out", tmp_path / "p.h5")
    withe = run_cli("fit", "accel", bad, "--out", tmp_path / "w.h5", "--with",
                    "accel_nonlinearity")
    assert plain[0] == withe[0] == 4 and plain[2] == withe[2], (plain, withe)
    assert repr(segs[k].label) in plain[2]
    assert not (tmp_path / "w.h5").exists()


def test_gyro_accel_provenance_in_the_batch(run_cli, tmp_path):
    """The gyro fit's "is the accel calibration independent?" check is the method's: the
    batch takes an accel calibration file as the command line does, with the same
    result (its uncertainty propagated when fitted on other data)."""
    from calib_cli.io.h5 import read_calibration

    plan = ROOT / "sample_data" / "plans" / "ferraris.toml"
    for seed in (1, 2):
        assert run_cli("simulate", plan, "--out", tmp_path / f"r{seed}.h5", "--seed", seed)[0] == 0
    assert run_cli("fit", "accel", tmp_path / "r1.h5", "--out", tmp_path / "acc.h5")[0] == 0
    code, _, err = run_cli("fit", "gyro", tmp_path / "r2.h5", "--accel", tmp_path / "acc.h5",
                           "--out", tmp_path / "g.h5")
    assert code == 0 and "from other data" in err, err
    (tmp_path / "pipe.toml").write_text(f'[[step]]\nstep = "fit"\nmethod = "gyro"\n'
                                        f'accel = "{tmp_path / "acc.h5"}"\n')
    code, so, err = run_cli("batch", tmp_path / "pipe.toml", tmp_path / "r2.h5", "--out",
                            tmp_path / "out", "--json")
    assert code == 0, err
    b = read_calibration(tmp_path / "out" / json.loads(so)["inputs"][0]["outputs"]["calibration"])
    c = read_calibration(tmp_path / "g.h5")
    for k in c.params:
        assert np.allclose(b.sigma[k], c.sigma[k], rtol=1e-12, equal_nan=True)
