"""calib report: renders for a sample calibration; PNGs decode with the
expected axes; the HTML is self-contained."""

from __future__ import annotations

import base64
import io
import json
import re
from dataclasses import replace

import matplotlib.image as mpimg
import numpy as np
import pytest
from click.testing import CliRunner

from calib_cli.cli.main import cli
from calib_cli.data import Recording, Segment
from calib_cli.io.h5 import write_calibration, write_raw
from calib_cli.io.plan import parse_plan
from calib_cli.methods.accel_lsq import fit_accel
from calib_cli.sim.simulate import simulate

try:  # tests/ as rootdir-inserted path (no __init__.py) or as a package
    from samples_9 import PLAN, triad_calibration
except ImportError:  # pragma: no cover
    from tests.samples_9 import PLAN, triad_calibration

EXPECTED_AXES = {"g-per-position": 2, "residuals": 1, "allan": 2,
                 "static-detection": 3}  # accelerometer, gyro, the detector's statistic


@pytest.fixture(scope="module")
def sample(tmp_path_factory):
    d = tmp_path_factory.mktemp("report")
    rec = simulate(parse_plan(PLAN), None, seed=5)
    write_calibration(d / "cal.h5", fit_accel(rec, "vector"), [])
    write_raw(d / "static.h5", rec)
    rng = np.random.default_rng(0)
    n = 12000  # 120 s at 100 Hz: a (short) free-running record
    free = Recording(time=np.arange(n) / 100.0,
                     accel=rng.standard_normal((n, 3)) * 1e-2 + [0, 0, 9.81],
                     gyro=rng.standard_normal((n, 3)) * 1e-3,
                     segments=(Segment("rest", "static", 0, n),))
    write_raw(d / "free.h5", free)
    return d


def _report(*args):
    r = CliRunner().invoke(cli, ["report", *map(str, args)])
    assert r.exit_code == 0, r.output
    return r


def _check_self_contained(html_text):
    assert not re.search(r"https?://", html_text)
    assert "<link" not in html_text and "<script" not in html_text and "url(" not in html_text
    assert "href=" not in html_text
    srcs = re.findall(r'src="([^"]*)"', html_text)
    assert srcs and all(s.startswith("data:image/png;base64,") for s in srcs)
    for s in srcs:
        png = base64.b64decode(s.split(",", 1)[1])
        img = mpimg.imread(io.BytesIO(png), format="png")
        assert img.ndim == 3 and img.shape[0] > 100 and img.shape[1] > 100
    return len(srcs)


def test_report_of_sample_calibration_with_allan(sample):
    out = sample / "rep"
    _report(sample / "cal.h5", sample / "free.h5", "--out", out)
    manifest = json.loads((out / "figures.json").read_text())
    names = [re.sub(r"^fig-\d+-|\.png$", "", f["file"]) for f in manifest["figures"]]
    assert names == ["g-per-position", "residuals", "static-detection", "allan"]
    for f, name in zip(manifest["figures"], names, strict=True):
        assert f["axes"] == EXPECTED_AXES[name]
        img = mpimg.imread(out / f["file"])
        assert img.ndim == 3 and min(img.shape[:2]) > 100
        assert "What to look for" in f["caption"]
    md = (out / "report.md").read_text()
    for f in manifest["figures"]:
        assert f"({f['file']})" in md
    assert "| accel_bias[0] |" in md and "1 sigma" in md
    assert _check_self_contained((out / "report.html").read_text()) == 4


def test_report_static_raw_is_not_free_running(sample):
    out = sample / "rep2"
    _report(sample / "cal.h5", sample / "static.h5", "--out", out)
    md = (out / "report.md").read_text()
    assert "not a free-running record" in md
    assert len(json.loads((out / "figures.json").read_text())["figures"]) == 3  # + detection


def test_unknown_method_gets_generic_report_and_registry_dispatch(sample, tmp_path):
    from calib_cli.report.builder import SECTIONS, Section, register

    c = replace(triad_calibration(), method="mystery")
    write_calibration(tmp_path / "m.h5", c)
    _report(tmp_path / "m.h5", "--out", tmp_path / "r")
    md = (tmp_path / "r" / "report.md").read_text()
    # the generic section: built from params, sigma and units, with its figure
    assert "## mystery fit" in md and "not registered" not in md
    assert "![parameters]" in md
    assert "gyro_D[2,2]" in md
    # a method section registered by another module is used
    register("mystery")(lambda ctx: Section("Mystery section", text=["hello"]))
    try:
        _report(tmp_path / "m.h5", "--out", tmp_path / "r2")
        md = (tmp_path / "r2" / "report.md").read_text()
        assert "## Mystery section" in md and "## mystery fit" not in md
    finally:
        SECTIONS.pop("mystery", None)


def test_report_bad_input_leaves_nothing(sample, tmp_path):
    from calib_cli.cli.main import main

    with pytest.raises(SystemExit) as e:
        main(["report", str(sample / "static.h5"), "--out", str(tmp_path / "r")])
    assert e.value.code == 3
    assert not (tmp_path / "r").exists()


def test_report_of_scalar_fit(tmp_path):
    plan = parse_plan('name = "hand"\nkind = "static"\nsample_rate_hz = 50.0\n'
                      'transition_s = 1.0\n[site]\nlatitude_deg = 45.0\n[[segment]]\n'
                      'label = "pos"\nrepeat = "auto"\nsim_repeat = 12\nduration_s = 3\n')
    rec = simulate(plan, None, seed=2)
    cal = fit_accel(rec, "scalar")
    assert cal.method == "scalar" and np.ndim(cal.residuals["accel_segment"]) == 1
    write_calibration(tmp_path / "s.h5", cal)
    _report(tmp_path / "s.h5", "--out", tmp_path / "r")
    manifest = json.loads((tmp_path / "r" / "figures.json").read_text())
    assert [f["axes"] for f in manifest["figures"]] == [2, 1]
    assert "Static accelerometer fit (scalar)" in (tmp_path / "r" / "report.md").read_text()


@pytest.mark.parametrize("kind", ["align", "rimu"])
def test_report_of_align_and_rimu(kind, tmp_path):
    """The method's own section renders: figures decode with their axes, HTML self-contained."""
    from pathlib import Path

    from calib_cli.io.plan import load_plan

    repo = Path(__file__).resolve().parents[1]
    plan, fit, title, axes = {
        "align": ("docs/examples/align_plan.toml", "calib_cli.methods.align:fit_align",
                  "Two-position alignment", [1, 1]),
        "rimu": ("sample_data/rimu_six_position.toml", "calib_cli.methods.rimu:fit_rimu",
                 "Redundant unit", [2, 2, 1, 1])}[kind]
    import importlib

    mod, _, fn = fit.partition(":")
    rec = simulate(load_plan(str(repo / plan)), None, seed=4)
    write_calibration(tmp_path / "c.h5", getattr(importlib.import_module(mod), fn)(rec))
    _report(tmp_path / "c.h5", "--out", tmp_path / "r")
    manifest = json.loads((tmp_path / "r" / "figures.json").read_text())
    assert [f["axes"] for f in manifest["figures"]] == axes
    assert f"## {title}" in (tmp_path / "r" / "report.md").read_text()
    assert _check_self_contained((tmp_path / "r" / "report.html").read_text()) == len(axes)
