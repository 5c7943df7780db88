"""Structural test of every method's report (accel, gyro, align, turntable,
rimu, the Allan section, diagnose): every image resolves and decodes, no
"nan"/"None"/"null" text, every number finite or "not determined", a header
with the unit, dates, method, input hashes and a verdict line."""

from __future__ import annotations

import base64
import io
import re
from pathlib import Path

import matplotlib.image as mpimg
import numpy as np
import pytest
from click.testing import CliRunner

from calib_cli.cli.main import cli
from calib_cli.data import Recording, Segment
from calib_cli.io.h5 import write_raw

BAD_WORDS = re.compile(r"\b(nan|NaN|None|null|inf|Infinity)\b")


def _run(*args):
    r = CliRunner().invoke(cli, ["-q", *map(str, args)])
    assert r.exit_code == 0, (args, r.output, r.exception)
    return r


@pytest.fixture(scope="module")
def reports(tmp_path_factory):
    """method -> report directory, each made by the CLI from a simulated record."""
    d = tmp_path_factory.mktemp("reports")
    plans = {"static": [], "ferraris": [], "align": ["--duration", "30"],
             "turntable": ["--duration", "60"], "rimu": []}
    for m, extra in plans.items():
        _run("plan", "make", m, *extra, "--out", d / f"{m}.toml")
        _run("simulate", d / f"{m}.toml", "--out", d / f"{m}.h5", "--seed", "3")
    fits = {"accel": ("accel", "static"), "gyro": ("gyro", "ferraris"),
            "align": ("align", "align"), "turntable": ("turntable", "turntable"),
            "rimu": ("rimu", "rimu")}
    rng = np.random.default_rng(0)
    n = 9000  # 90 s at 100 Hz: a free-running record, for the Allan section
    write_raw(d / "free.h5", Recording(
        time=np.arange(n) / 100.0, accel=rng.standard_normal((n, 3)) * 1e-2 + [0, 0, 9.81],
        gyro=rng.standard_normal((n, 3)) * 1e-3, segments=(Segment("rest", "static", 0, n),)))
    out = {}
    for name, (method, raw) in fits.items():
        _run("fit", method, d / f"{raw}.h5", "--out", d / f"{name}.cal.h5")
        second = d / ("free.h5" if name == "accel" else f"{raw}.h5")
        _run("report", d / f"{name}.cal.h5", second, "--out", d / f"rep-{name}")
        out[name] = d / f"rep-{name}"
    _run("diagnose", d / "static.h5", "--method", "accel", "--out", d / "diag.h5",
         "--report", d / "rep-diagnose")
    out["diagnose"] = d / "rep-diagnose"
    return out


def _decodes(data: bytes):
    img = mpimg.imread(io.BytesIO(data), format="png")
    assert img.ndim == 3 and min(img.shape[:2]) > 100


def check_markdown(md_path: Path) -> list[str]:
    """Problems of one Markdown report: images that do not resolve or decode,
    words that stand for a missing number."""
    text = md_path.read_text(encoding="utf-8")
    problems = []
    for target in re.findall(r"!\[[^\]]*\]\(([^)]+)\)", text):
        f = md_path.parent / target
        if not f.is_file():
            problems.append(f"image {target} missing")
            continue
        try:
            _decodes(f.read_bytes())
        except Exception as exc:  # noqa: BLE001
            problems.append(f"image {target} does not decode: {exc}")
    problems += [f"'{m.group(0)}' in: {text[max(0, m.start() - 60):m.end() + 20]!r}"
                 for m in BAD_WORDS.finditer(text)]
    return problems


def check_html(html_path: Path) -> list[str]:
    html = html_path.read_text(encoding="utf-8")
    problems = []
    srcs = re.findall(r'src="([^"]*)"', html)
    for s in srcs:
        if not s.startswith("data:image/png;base64,"):
            problems.append(f"external image {s[:40]}")
            continue
        try:
            _decodes(base64.b64decode(s.split(",", 1)[1]))
        except Exception as exc:  # noqa: BLE001
            problems.append(f"embedded image does not decode: {exc}")
    text = re.sub(r'src="[^"]*"', "", html)
    problems += [f"'{m.group(0)}' in HTML" for m in BAD_WORDS.finditer(text)]
    return problems


METHODS = ["accel", "gyro", "align", "turntable", "rimu"]


@pytest.mark.parametrize("method", METHODS)
def test_report_structure(reports, method):
    rep = reports[method]
    assert not check_markdown(rep / "report.md")
    assert not check_html(rep / "report.html")
    md = (rep / "report.md").read_text(encoding="utf-8")
    assert re.search(r"^Verdict: (PASS|FAIL|not determined)", md, re.M), "no verdict line"
    for item in ("unit serial", "calibrated (UTC)", "report made (UTC)", "SHA-256"):
        assert item in md, item
    assert "![" in md, "no figure"


def test_gyro_and_turntable_reports_have_residual_figures(reports):
    gyro = (reports["gyro"] / "report.md").read_text()
    assert "gyro-residuals" in gyro
    tt = (reports["turntable"] / "report.md").read_text()
    assert "residuals-time" in tt and "residuals-rate" in tt


def test_allan_section_in_deg_per_hour(reports):
    md = (reports["accel"] / "report.md").read_text()
    assert "## Allan deviation" in md
    assert "deg/h" in md and "deg/sqrt(h)" in md


def test_diagnose_report_structure(reports):
    rep = reports["diagnose"]
    assert not check_markdown(rep / "summary.md")


def test_checker_catches_a_planted_problem(tmp_path):
    (tmp_path / "r.md").write_text("# r\n\nnoise floor nan mg\n\n![x](missing.png)\n")
    problems = check_markdown(tmp_path / "r.md")
    assert any("missing" in p for p in problems) and any("'nan'" in p for p in problems)


def test_detect_plot(tmp_path):
    csv = Path(__file__).resolve().parents[1] / "sample_data" / "twelve_position.csv"
    _run("detect", csv, "--plot", tmp_path / "det.png")
    _decodes((tmp_path / "det.png").read_bytes())


def test_verdict_against_tolerances(reports, tmp_path):
    cal = reports["accel"].parent / "accel.cal.h5"
    tol = tmp_path / "tol.toml"
    tol.write_text("[param.accel_bias]\nmin_mg = -0.001\nmax_mg = 0.001\n")
    _run("report", cal, "--out", tmp_path / "fail", "--tolerances", tol)
    md = (tmp_path / "fail" / "report.md").read_text()
    assert re.search(r"^Verdict: FAIL against the tolerances", md, re.M)
    assert 'class="verdict fail"' in (tmp_path / "fail" / "report.html").read_text()
    tol.write_text("[param.accel_bias]\nmin_mg = -100\nmax_mg = 100\n")
    _run("report", cal, "--out", tmp_path / "pass", "--tolerances", tol)
    md = (tmp_path / "pass" / "report.md").read_text()
    assert re.search(r"^Verdict: PASS against the tolerances", md, re.M)
    r = CliRunner().invoke(cli, ["report", str(cal), "--out", str(tmp_path / "x"),
                                 "--tolerances", str(tmp_path / "missing.toml")])
    from calib_cli.errors import InputError

    # main() maps InputError to exit 3 with one line; nothing is left behind
    assert isinstance(r.exception, InputError) and r.exception.exit_code == 3
    assert not (tmp_path / "x").exists()


def test_pdf_is_the_same_report(reports, tmp_path):
    cal = reports["turntable"].parent / "turntable.cal.h5"
    raw = reports["turntable"].parent / "turntable.h5"
    _run("report", cal, raw, "--out", tmp_path / "rep", "--pdf")
    pdf = (tmp_path / "rep" / "report.pdf").read_bytes()
    assert pdf.startswith(b"%PDF-") and pdf.rstrip().endswith(b"%%EOF")
    n_fig = len(re.findall(r"^!\[", (tmp_path / "rep" / "report.md").read_text(), re.M))
    pages = len(re.findall(rb"/Type /Page\b", pdf))
    assert n_fig >= 3 and pages >= 1 + n_fig  # text, then one page per figure
    assert (tmp_path / "rep" / "report.html").is_file()  # the HTML report as without --pdf


def test_every_figure_uses_the_colour_blind_safe_palette():
    """Each module that makes a matplotlib figure takes the Okabe-Ito cycle from
    report/figures.py (use_palette), so no figure falls back to matplotlib's."""
    root = Path(__file__).resolve().parents[1] / "calib_cli"
    makers = [p for p in root.rglob("*.py")
              if re.search(r"\bFigure\(|plt\.subplots\(|plt\.figure\(", p.read_text())]
    assert makers
    for p in makers:
        if p.name in ("figures.py", "pdf.py"):  # pdf.py: pages of text and PNG images only
            continue
        text = p.read_text()  # report.builder imports report.figures (use_palette at import)
        assert "use_palette" in text or "calib_cli.report.builder import" in text, p
    import matplotlib

    from calib_cli.report.figures import OKABE_ITO

    assert matplotlib.rcParams["axes.prop_cycle"].by_key()["color"] == OKABE_ITO


def test_static_report_has_the_detection_figure(reports, tmp_path):
    d = reports["accel"].parent
    _run("report", d / "accel.cal.h5", d / "static.h5", "--out", tmp_path / "rep")
    md = (tmp_path / "rep" / "report.md").read_text()
    assert "![static-detection]" in md and not check_markdown(tmp_path / "rep" / "report.md")
    from calib_cli.report.sections_static import _detection_options

    assert _detection_options("calib import csv a.csv --window 2 --threshold=4 --out r.h5") == {
        "window_s": 2.0, "multiplier": 4.0, "min_static_s": 1.0}
