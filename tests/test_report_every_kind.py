"""The report of every kind of calibration file (issue 35): each fit method, data
in counts, each effect `fit --with` adds, each method's diagnosis -- made through
the command line from simulated records (calib_cli/validation/report_cases.py) --
has no placeholder ('?', nan, None, null), no 'not registered', no section
without its figure, figures that decode, units from the file; and renders in
headless Chromium where it is installed (`make screenshots` writes the PNGs of
docs/figures/ the same way)."""

from __future__ import annotations

import re

import pytest

from calib_cli.validation import report_cases as rc


@pytest.fixture(scope="module")
def reports(tmp_path_factory):
    return rc.build(tmp_path_factory.mktemp("every-kind"))


def test_the_cases_cover_every_method_effect_and_diagnosis():
    from calib_cli.cli.tree import tree
    from calib_cli.methods.fit_with import EFFECTS

    fits = {c.command[1] for c in rc.CASES if c.command[0] == "fit"}
    assert fits == set(tree()["commands"]["fit"]["commands"])
    assert rc.covered_effects() == set(EFFECTS)
    diag = {c.command[-1] for c in rc.CASES if c.command[0] == "diagnose"}
    choices = next(p["choices"] for p in tree()["commands"]["diagnose"]["params"]
                   if p["name"] == "method")
    assert diag == set(choices)


@pytest.mark.parametrize("name", [c.name for c in rc.CASES])
def test_report_has_no_placeholder_and_a_figure_in_every_section(reports, name):
    assert rc.problems(reports[name]) == []


def test_checker_catches_placeholders_and_figureless_sections(tmp_path):
    (tmp_path / "report.md").write_text("# r\n\n## Summary\n\nbefore ? mg\n\n## Effect\n\ntext\n")
    (tmp_path / "report.html").write_text("<p>nan</p>")
    p = rc.problems(tmp_path)
    assert any("'?'" in x for x in p) and any("'nan'" in x for x in p)
    assert any("'Effect' has no figure" in x for x in p)


def _md(reports, name):
    return (reports[name] / "report.md").read_text(encoding="utf-8")


def test_added_effects_have_their_own_sections(reports):
    md = _md(reports, "with-lever_arm")
    assert "## Added effect: lever_arm" in md and "## Added effect: g_sensitivity" in md
    assert "effect-lever-arm" in md and "effect-g_sensitivity" in md
    md = _md(reports, "with-accel_nonlinearity")
    assert "## Added effect: accel_nonlinearity" in md and "ug/g^2" in md
    assert "## Static accelerometer fit" in md  # the base method's section
    md = _md(reports, "diagnose-turntable")
    assert "## Diagnosis" in md and "disagreement" in md


def test_counts_stay_counts(reports):
    md = _md(reports, "gyro-counts")
    assert "Recorded in counts" in md and "count/(rad/s)" in md
    assert re.search(r"\| gyro_noise_sigma \| [\d., ]+ count \|", md)
    assert re.search(r"\| gyro_bias\[0\] \| 327\d\d\.\d+ \| [\d.]+ \| count \|", md)
    assert "deg/h, per axis" not in md  # the static gyro residuals are in counts


def test_thermal_units_carry_the_polynomial_power(reports):
    from calib_cli.io.h5 import read_calibration

    cal = read_calibration(reports["thermal"].parent / "cal-thermal.h5")
    assert cal.stats["temp_order"] == 2
    md = _md(reports, "thermal")
    assert "| accel_temp_bias[0,0] |" in md and "mg/degC |" in md
    assert re.search(r"\| accel_temp_bias\[0,1\] \| [^|]+ \| [^|]+ \| mg/degC\^2 \|", md)
    assert re.search(r"\| gyro_temp_bias\[2,1\] \| [^|]+ \| [^|]+ \| deg/h/degC\^2 \|", md)


def test_turntable_report_names_what_its_g_error_is_over(reports):
    """The plan has no static segment: the |g| error is over the table's rests, and
    the check positions say they are absent, without contradicting each other."""
    md = _md(reports, "turntable")
    assert "over the static positions" not in md
    assert "|mean f\\| - g over blocks of" in md or "|mean f| - g over blocks of" in md
    assert "Check positions (static segments of the plan, not used by the fit)" in md


@pytest.mark.skipif(rc.chromium() is None, reason="no chromium (apt-get install chromium)")
def test_every_report_renders_in_headless_chromium(reports, tmp_path):
    """One Chromium renders every report (a page of iframes, a quarter scale each):
    every report's cell shows a page with text and figures, not a blank."""
    import matplotlib.image as mpimg

    names = list(reports)
    cells = rc.screenshot_all([reports[n] / "report.html" for n in names], tmp_path / "all.png")
    img = mpimg.imread(tmp_path / "all.png")[..., :3]
    for name, (x0, y0, x1, y1) in zip(names, cells):
        cell = img[y0:y1, x0:x1]
        assert float(cell.std()) > 0.05 and float((cell < 0.5).mean()) > 0.005, name
