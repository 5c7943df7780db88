"""Every kind of calibration file a report is made of: each fit method (the
accelerometer fit in both forms, data in counts, the three alignments), each
effect `calib fit --with` adds, each method's diagnosis; simulated from `calib
plan make` plans (and the shipped thermal plan with its truth) with fixed seeds,
fitted and reported through the command line as a user runs it.

Used by tests/test_report_every_kind.py (`make test`: the reports' text and
figures checked, rendered by headless Chromium where it is installed) and by
`make screenshots` (the PNGs in docs/figures/):

    python -m calib_cli.validation.report_cases OUT_DIR [--png DIR] [--only NAME,...]
"""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
SAMPLE_PLANS = ROOT / "sample_data" / "plans"

# record name -> `calib plan make` arguments (None: made otherwise, see records())
PLANS = {
    "static": ["static"],
    "scalar": ["static", "--fit", "scalar"],
    "ferraris": ["ferraris"],
    "align": ["align", "--duration", "30"],
    "turntable": ["turntable", "--duration", "60"],
    "rimu": ["rimu"],
}

# a unit whose outputs are raw counts (a 16-bit ADC, zero near 32768), for the Ferraris plan
COUNTS_TRUTH = """[params]
accel_bias = [32768.0, 32800.0, 32700.0]
accel_K = [[414.0, 0.0, 0.0], [1.5, 412.0, 0.0], [4.0, 8.8, 414.5]]
gyro_bias = [32768.0, 32450.0, 32500.0]
gyro_K = [[4780.0, -40.0, -55.0], [-25.0, 4766.0, 150.0], [-74.0, 108.0, 4769.0]]
[noise]
accel_white = 4.0
gyro_white = 4.0
[output]
units = "count"
"""


@dataclass(frozen=True)
class Case:
    """One calibration file: its name, the record it is made from, the command
    (two words, `fit accel` or `diagnose ""`, then the options; without RAW and --out)
    and what it shows."""

    name: str
    record: str
    command: tuple
    what: str


CASES = [
    # every fit method
    Case("accel", "static", ("fit", "accel"), "static accelerometer fit, known attitudes"),
    Case("accel-scalar", "scalar", ("fit", "accel"), "static accelerometer fit, |f| = g"),
    Case("gyro", "ferraris", ("fit", "gyro"), "Ferraris gyro fit"),
    Case("gyro-counts", "counts", ("fit", "gyro"), "Ferraris gyro fit of data in counts"),
    Case("align", "align", ("fit", "align"), "two-position alignment"),
    Case("align-static", "align", ("fit", "align", "--method", "static"),
         "static-only alignment"),
    Case("align-classic", "align", ("fit", "align", "--method", "classic"),
         "classic analytic alignment"),
    Case("rimu", "rimu", ("fit", "rimu"), "redundant unit"),
    Case("turntable", "turntable", ("fit", "turntable"), "rotating-table fit"),
    Case("thermal", "thermal", ("fit", "thermal"), "thermal fit (the shipped plan and truth)"),
    # every effect --with adds
    Case("with-accel_nonlinearity", "static", ("fit", "accel", "--with", "accel_nonlinearity"),
         "accelerometer nonlinearity"),
    Case("with-accel.scale_asymmetry", "static",
         ("fit", "accel", "--with", "accel.scale_asymmetry"), "accelerometer scale asymmetry"),
    Case("with-misalignment", "static",
         ("fit", "accel", "--with", "misalignment", "--base", "diagonal"), "misalignment"),
    Case("with-temperature_drift", "thermal",
         ("fit", "accel", "--with", "accel.temperature_drift"), "temperature drift"),
    Case("with-bias_random_walk", "static", ("fit", "accel", "--with", "accel.bias_random_walk"),
         "bias random walk (noise model)"),
    Case("with-gyro.scale_asymmetry", "ferraris",
         ("fit", "gyro", "--with", "gyro.scale_asymmetry"), "gyro scale asymmetry"),
    Case("with-g_sensitivity", "ferraris", ("fit", "gyro", "--with", "g_sensitivity"),
         "gyro g-sensitivity"),
    Case("with-bias_instability", "ferraris", ("fit", "gyro", "--with", "gyro.bias_instability"),
         "bias instability (noise model)"),
    Case("with-align-g_sensitivity", "align", ("fit", "align", "--with", "g_sensitivity"),
         "g-sensitivity in the alignment"),
    Case("with-rimu-accel_nonlinearity", "rimu", ("fit", "rimu", "--with", "accel_nonlinearity"),
         "nonlinearity of a redundant unit"),
    Case("with-lever_arm", "turntable", ("fit", "turntable", "--with", "lever_arm,g_sensitivity"),
         "lever arms and g-sensitivity on the table"),
    Case("with-proof_mass_offsets", "turntable",
         ("fit", "turntable", "--with",
          "lever_arm,g_sensitivity,proof_mass_offsets,time_offset"),
         "proof-mass offsets and time offset"),
    # every method's diagnosis
    *(Case(f"diagnose-{m}", rec, ("diagnose", "", "--method", m), f"diagnosis, method {m}")
      for m, rec in (("accel", "static"), ("gyro", "ferraris"), ("align", "align"),
                     ("rimu", "rimu"), ("turntable", "turntable"))),
]

# the effects of methods/fit_with.py that CASES must cover
def covered_effects() -> set:
    out = set()
    for c in CASES:
        if "--with" in c.command:
            for w in c.command[c.command.index("--with") + 1].split(","):
                out.add(w.split(".")[-1])
    return out


def _run(args: list, where: Path) -> None:
    """`calib ARGS` in this process (exit code 0 or an AssertionError with its output)."""
    from click.testing import CliRunner

    from calib_cli.cli.main import cli

    r = CliRunner().invoke(cli, ["-q", *map(str, args)], catch_exceptions=False)
    if r.exit_code != 0:
        raise AssertionError(f"calib {' '.join(map(str, args))} -> exit {r.exit_code}: "
                             f"{r.output}")


def records(out: Path, needed=None) -> dict:
    """Record name -> raw.h5 in OUT (simulated; seed 7)."""
    out.mkdir(parents=True, exist_ok=True)
    needed = set(needed or [*PLANS, "counts", "thermal"])
    paths = {}
    for name, args in PLANS.items():
        if name not in needed and not (name == "ferraris" and "counts" in needed):
            continue
        _run(["plan", "make", *args, "--out", out / f"{name}.toml"], out)
        if name in needed:
            _run(["simulate", out / f"{name}.toml", "--out", out / f"{name}.h5", "--seed", "7"], out)
            paths[name] = out / f"{name}.h5"
    if "counts" in needed:
        (out / "counts_truth.toml").write_text(COUNTS_TRUTH, encoding="utf-8")
        _run(["simulate", out / "ferraris.toml", "--truth", out / "counts_truth.toml", "--out",
              out / "counts.h5", "--seed", "7"], out)
        paths["counts"] = out / "counts.h5"
    if "thermal" in needed:
        _run(["simulate", SAMPLE_PLANS / "thermal.toml", "--truth",
              SAMPLE_PLANS / "thermal_truth.toml", "--out", out / "thermal.h5", "--seed", "7"],
             out)
        paths["thermal"] = out / "thermal.h5"
    return paths


def build(out, only=None) -> dict:
    """Make every case's calibration and its report (with the raw record) in OUT:
    name -> report directory."""
    out = Path(out)
    cases = [c for c in CASES if not only or c.name in only]
    raws = records(out, {c.record for c in cases})
    reports = {}
    for c in cases:
        cal = out / f"cal-{c.name}.h5"
        # the command's two words ("fit accel"; "diagnose" and ""), RAW, its options
        _run([w for w in c.command[:2] if w] + [raws[c.record], *c.command[2:], "--out", cal],
             out)
        rep = out / f"report-{c.name}"
        _run(["report", cal, raws[c.record], "--out", rep], out)
        reports[c.name] = rep
    return reports


# --------------------------------------------------------------------------------------
# checks

BAD = re.compile(r"\?|\b(nan|NaN|None|null|inf|Infinity)\b|not registered")
ALWAYS_WITHOUT_FIGURE = ("Verdict", "Summary", "Parameters", "Statistics", "Provenance")


def problems(report_dir) -> list[str]:
    """What is wrong with one report: a placeholder ('?', nan, None, null, inf),
    'not registered', a section (other than the tables-only ones) without a figure,
    an image that does not resolve or decode."""
    import base64
    import io

    import matplotlib.image as mpimg

    d = Path(report_dir)
    md = (d / "report.md").read_text(encoding="utf-8")
    html = (d / "report.html").read_text(encoding="utf-8")
    out = []
    # a '?' inside inline code or a URL is not a placeholder
    text = re.sub(r"`[^`]*`", "", md)
    out += [f"{m.group(0)!r} in report.md: ...{text[max(0, m.start() - 60):m.end() + 30]!r}"
            for m in BAD.finditer(text)]
    body = re.sub(r'src="[^"]*"', "", html)
    body = re.sub(r"<code>.*?</code>", "", body)
    out += [f"{m.group(0)!r} in report.html" for m in BAD.finditer(re.sub(r"<[^>]+>", " ", body))]
    for sec in re.split(r"^## ", md, flags=re.M)[1:]:
        title = sec.splitlines()[0].strip()
        if title not in ALWAYS_WITHOUT_FIGURE and "![" not in sec:
            out.append(f"section {title!r} has no figure")
    for target in re.findall(r"!\[[^\]]*\]\(([^)]+)\)", md):
        try:
            img = mpimg.imread(d / target, format="png")
            assert img.ndim == 3 and min(img.shape[:2]) > 100
        except Exception as exc:  # noqa: BLE001
            out.append(f"image {target}: {exc}")
    for s in re.findall(r'src="data:image/png;base64,([^"]*)"', html):
        try:
            mpimg.imread(io.BytesIO(base64.b64decode(s)), format="png")
        except Exception as exc:  # noqa: BLE001
            out.append(f"embedded image: {exc}")
    return out


def chromium() -> str | None:
    """The headless browser `make screenshots` uses, if installed."""
    return shutil.which("chromium") or shutil.which("chromium-browser")


def screenshot(html, png, width: int = 1280, height: int = 2400, timeout: float = 120.0,
               extra: tuple = ()) -> None:
    """Render HTML with headless Chromium into PNG (a fresh profile, no network)."""
    exe = chromium()
    if exe is None:
        raise FileNotFoundError("no chromium on PATH (apt-get install chromium)")
    with tempfile.TemporaryDirectory() as profile:
        subprocess.run([exe, "--headless", "--no-sandbox", "--disable-gpu", "--no-first-run",
                        "--disable-background-networking", "--disable-component-update",
                        "--disable-sync", "--hide-scrollbars", f"--user-data-dir={profile}",
                        f"--window-size={width},{height}", f"--screenshot={Path(png).resolve()}",
                        *extra, Path(html).resolve().as_uri()], stdout=subprocess.DEVNULL,
                       stderr=subprocess.DEVNULL, timeout=timeout, check=False)
    if not Path(png).is_file() or Path(png).stat().st_size < 5_000:
        raise RuntimeError(f"chromium rendered no page of {html}")


CELL_W, CELL_H, COLS, SCALE = 1280, 1600, 4, 0.25


def screenshot_all(htmls: list, png, timeout: float = 300.0) -> list:
    """Render every report in one headless Chromium (one launch, not one per
    report): a page of iframes, each report at 1280 x 1600 px scaled to a quarter,
    COLS to a row. Returns each report's cell (x0, y0, x1, y1) in PNG pixels."""
    rows = -(-len(htmls) // COLS)
    w, h = int(CELL_W * SCALE), int(CELL_H * SCALE)
    cells, frames = [], []
    for k, html in enumerate(htmls):
        x, y = (k % COLS) * w, (k // COLS) * h
        cells.append((x, y, x + w, y + h))
        frames.append(f'<iframe src="{Path(html).resolve().as_uri()}" style="position:absolute;'
                      f"left:{x}px;top:{y}px;width:{CELL_W}px;height:{CELL_H}px;border:0;"
                      f'transform:scale({SCALE});transform-origin:0 0"></iframe>')
    index = Path(png).with_suffix(".html")
    index.write_text("<!DOCTYPE html><html><body style=\"margin:0\">" + "".join(frames)
                     + "</body></html>", encoding="utf-8")
    screenshot(index, png, width=COLS * w, height=rows * h, timeout=timeout,
               extra=("--allow-file-access-from-files", "--virtual-time-budget=20000"))
    return cells


def _shrink(png: Path) -> None:
    """An adaptive 256-colour palette: a third of the bytes, the same look (the
    PNGs are kept in the repository)."""
    from PIL import Image

    with Image.open(png) as im:
        small = im.convert("RGB").quantize(colors=256, method=Image.Quantize.MEDIANCUT)
    small.save(png, optimize=True)


def main(argv=None) -> int:
    import argparse

    ap = argparse.ArgumentParser(prog="python -m calib_cli.validation.report_cases")
    ap.add_argument("out")
    ap.add_argument("--png", help="write docs/figures-style PNGs here (report-NAME.png)")
    ap.add_argument("--only", help="comma-separated case names")
    a = ap.parse_args(argv)
    reports = build(a.out, a.only.split(",") if a.only else None)
    bad = {n: problems(d) for n, d in reports.items()}
    for n, p in bad.items():
        for line in p:
            print(f"{n}: {line}", file=sys.stderr)
    if a.png:
        Path(a.png).mkdir(parents=True, exist_ok=True)
        for n, d in reports.items():
            png = Path(a.png) / f"report-{n}.png"
            screenshot(d / "report.html", png)
            _shrink(png)
            print(f"report-{n}.png")
    return 1 if any(bad.values()) else 0


if __name__ == "__main__":
    sys.exit(main())
