"""calib export: formats, and the C header against `calib apply`."""

from __future__ import annotations

import json
import shutil
import subprocess

import h5py
import numpy as np
import pytest
from click.testing import CliRunner

from calib_cli.cli.main import cli
from calib_cli.io.h5 import write_calibration, write_raw
from calib_cli.io.plan import parse_plan
from calib_cli.model.truth import describe_effect
from calib_cli.sim.simulate import simulate

try:  # tests/ as rootdir-inserted path (no __init__.py) or as a package
    from samples_9 import PLAN, triad_calibration
except ImportError:  # pragma: no cover
    from tests.samples_9 import PLAN, triad_calibration


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("export")
    cal, raw = d / "cal.h5", d / "raw.h5"
    write_calibration(cal, triad_calibration())
    write_raw(raw, simulate(parse_plan(PLAN), None, seed=3))
    return d, cal, raw


def run(*args):
    r = CliRunner().invoke(cli, [str(a) for a in args])
    assert r.exit_code == 0, r.output
    return r.stdout


def test_json_yaml_csv_agree(files):
    d, cal, _ = files
    obj = json.loads(run("export", cal, "--format", "json"))
    c = triad_calibration()
    K = np.array(obj["correction"]["accel"]["K"])
    np.testing.assert_allclose(K, c.params["accel_K"], rtol=0, atol=1e-15)
    np.testing.assert_allclose(np.array(obj["correction"]["gyro"]["D"]), c.params["gyro_D"],
                               atol=1e-15)
    np.testing.assert_allclose(np.array(obj["correction"]["accel"]["K_inv"]) @ K, np.eye(3),
                               atol=1e-14)
    np.testing.assert_allclose(np.array(obj["correction"]["gyro"]["G_inv"]),
                               np.linalg.inv(c.params["gyro_K"]), rtol=1e-13)
    np.testing.assert_allclose(obj["correction"]["gyro"]["d"], c.params["gyro_bias"], atol=1e-17)
    assert obj["formula"]["gyro"] == "w = G^-1 (W - d - D f)"
    # YAML: one line per key, flow lists that are also JSON
    y = run("export", cal, "--format", "yaml")
    line = next(ln for ln in y.splitlines() if ln.strip().startswith("K_inv:"))
    np.testing.assert_array_equal(json.loads(line.split(":", 1)[1]),
                                  obj["correction"]["accel"]["K_inv"])
    assert not y.startswith("{")
    # CSV: every entry of every parameter, full precision
    rows = run("export", cal, "--format", "csv").splitlines()
    assert rows[0] == "parameter,index,value,sigma,unit"
    got = {(r.split(",")[0], r.split(",")[1]): float(r.split(",")[2]) for r in rows[1:]}
    assert got[("accel_K", "1 2")] == c.params["accel_K"][1, 2]
    assert got[("gyro_bias", "0")] == c.params["gyro_bias"][0]


def test_nonlinear_model_exported_with_its_formula_refused_with_thermal(tmp_path):
    """Issue 18: a non-affine term is exported as coefficients with the formula (the
    C program check is in tests/test_fit_with.py); with temperature drift too, refused."""
    from dataclasses import replace

    from calib_cli.cli.main import main
    from calib_cli.model.effects import Nonlinearity, TemperatureDrift

    c = triad_calibration()
    c = replace(c, model=c.model + [describe_effect(Nonlinearity("accel"))],
                params={**c.params, "accel_nonlinearity": np.full(3, 1e-5)})
    write_calibration(tmp_path / "nl.h5", c)
    with pytest.raises(SystemExit) as e:
        main(["export", str(tmp_path / "nl.h5"), "--format", "c-header", "--out",
              str(tmp_path / "x.h")])
    assert e.value.code == 0
    text = (tmp_path / "x.h").read_text()
    assert "CALIB_ACCEL_K2" in text and "fabs" in text
    c2 = replace(c, model=c.model + [describe_effect(TemperatureDrift("accel"))],
                 params={**c.params, "accel_temp_bias": np.zeros(3),
                         "accel_temp_scale": np.zeros(3)})
    write_calibration(tmp_path / "nlt.h5", c2)
    with pytest.raises(SystemExit) as e:
        main(["export", str(tmp_path / "nlt.h5"), "--format", "c-header", "--out",
              str(tmp_path / "y.h")])
    assert e.value.code == 3
    assert not (tmp_path / "y.h").exists()


CPROG = r"""
#include <stdio.h>
#include "cal.h"
int main(void) {
    double A[3], W[3], f[3], w[3];
    while (scanf("%lf %lf %lf %lf %lf %lf", &A[0], &A[1], &A[2], &W[0], &W[1], &W[2]) == 6) {
        calib_correct_accel(A, f);
        calib_correct_gyro(W, f, w);
        printf("%.17g %.17g %.17g %.17g %.17g %.17g\n", f[0], f[1], f[2], w[0], w[1], w[2]);
    }
    return 0;
}
"""


@pytest.mark.skipif(shutil.which("cc") is None, reason="no C compiler")
@pytest.mark.parametrize("single", [False, True])
def test_c_header_compiles(files, single):
    d, cal, _ = files
    h = d / ("calf.h" if single else "cal.h")
    opts = ["--float", "--prefix", "imu1"] if single else []  # float with a renamed prefix
    run("export", cal, "--format", "c-header", "--out", h, *opts)
    P = "IMU1" if single else "CALIB"
    src = d / "use.c"
    src.write_text(f'#include "{h.name}"\n'
                   f"int calib_dummy(void) {{ return (int){P}_ACCEL_KINV[0][0]; }}\n")
    subprocess.run(["cc", "-std=c99", "-Wall", "-Werror", "-c", str(src), "-o", str(d / "use.o")],
                   check=True, cwd=d)
    text = h.read_text()
    assert ("typedef float imu1_real_t;" in text) if single else ("typedef double" in text)
    assert "f = K^-1 (A - b)" in text and "w = G^-1 (W - d - D f)" in text
    assert "sha256" in text and "SN-42" in text


@pytest.mark.skipif(shutil.which("cc") is None, reason="no C compiler")
def test_c_program_reproduces_apply(files):
    d, cal, raw = files
    run("export", cal, "--format", "c-header", "--out", d / "cal.h")
    (d / "prog.c").write_text(CPROG)
    subprocess.run(["cc", "-std=c99", "-O2", "-Wall", "-o", str(d / "prog"), str(d / "prog.c")],
                   check=True, cwd=d)
    run("apply", cal, raw, "--out", d / "corr.h5")
    with h5py.File(raw) as h:
        A, W = h["samples/accel"][()], h["samples/gyro"][()]
    with h5py.File(d / "corr.h5") as h:
        f_ref, w_ref = h["samples/accel"][()], h["samples/gyro"][()]
    inp = "\n".join(" ".join("%.17g" % x for x in row) for row in np.hstack([A, W])) + "\n"
    out = subprocess.run([str(d / "prog")], input=inp, capture_output=True, text=True,
                         check=True).stdout
    got = np.array([[float(x) for x in ln.split()] for ln in out.splitlines()])
    assert got.shape == (len(A), 6)
    ref = np.hstack([f_ref, w_ref])
    scale = np.abs(ref).max(axis=0)  # relative to each channel's range (w is ~0 at rest)
    rel = np.abs(got - ref) / scale
    print(f"C vs apply: max relative difference {rel.max():.3g}")
    assert rel.max() <= 1e-12, rel.max()
    # and the correction did something (the test can fail)
    assert np.abs(f_ref - A).max() > 1e-3
