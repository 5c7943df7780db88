"""The report: sections chosen by the calibration's method, rendered as
Markdown (PNG files beside it) and as one self-contained HTML file (PNG
embedded as base64 data URIs, inline CSS, no external references).

Method-specific sections register themselves per method:

    from calib_cli.report.builder import register

    @register("turntable")
    def turntable_sections(ctx):          # ctx: ReportContext
        fig = ...                         # matplotlib Figure (report.figures helpers)
        return Section("Lever arms", text=["..."],
                       figures=[FigureItem("lever-arm-history", fig, "What to look for: ...")])

Modules named ``calib_cli/report/sections_*.py`` are imported automatically,
so a new method adds its sections in a new module without editing this one.
A method with no registered section gets the generic report (parameters with
sigma, statistics, provenance) and a note saying so. docs/report.md.
"""

from __future__ import annotations

import base64
import importlib
import json
import pkgutil
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np
from matplotlib.figure import Figure

from calib_cli.data import CalibrationResult
from calib_cli.io.escape import html_text, md_text
from calib_cli.report.figures import png_bytes


@dataclass
class FigureItem:
    """A figure with its file stem and caption (what to look for)."""

    name: str
    fig: Figure
    caption: str


@dataclass
class Table:
    caption: str
    header: list
    rows: list  # list of lists of str


@dataclass
class Section:
    title: str
    text: list = field(default_factory=list)  # paragraphs (plain text)
    tables: list = field(default_factory=list)
    figures: list = field(default_factory=list)


@dataclass
class ReportContext:
    """What section builders see. raw_path/raw_kind: the optional second
    input; allan: its Allan analysis when it is a free-running record;
    notes: remarks for the summary."""

    cal: CalibrationResult
    cal_path: str
    prov: dict
    raw_path: str | None = None
    raw_kind: str | None = None
    allan: object | None = None
    notes: list = field(default_factory=list)
    _recording: object | None = None

    def recording(self):
        """The RAW recording, read into memory on first use (None without RAW)."""
        if self._recording is None and self.raw_path and self.raw_kind in ("raw", "corrected"):
            from calib_cli.io.h5 import read_raw

            self._recording = read_raw(self.raw_path)
        return self._recording


# method -> section builders, in order
SECTIONS: dict[str, list[Callable]] = {}
_loaded = False


def register(*methods: str):
    """Decorator: add a section builder for calibrations of these methods."""

    def deco(fn):
        for m in methods:
            SECTIONS.setdefault(m, []).append(fn)
        return fn

    return deco


def _load_section_modules() -> None:
    global _loaded
    if _loaded:
        return
    import calib_cli.report as pkg

    for mod in sorted(m.name for m in pkgutil.iter_modules(pkg.__path__)):
        if mod.startswith("sections_"):
            importlib.import_module(f"calib_cli.report.{mod}")
    _loaded = True


# ---------------------------------------------------------------------------
# generic sections


def _fmt(x) -> str:
    if x is None:
        return "null"
    if isinstance(x, float):
        return "NaN" if not np.isfinite(x) else f"{x:.6g}"
    return str(x)


def parameter_table(cal: CalibrationResult) -> Table:
    from calib_cli.cli.render import display_of  # display units only

    rows = []
    for key, val in cal.params.items():
        val = np.asarray(val, dtype=float)
        sig = np.asarray(cal.sigma.get(key, np.full(val.shape, np.nan)), dtype=float)
        factor, unit = display_of(key, cal.units.get(key, ""))
        for idx in np.ndindex(val.shape):
            name = f"{key}[{','.join(map(str, idx))}]" if val.ndim else key
            s = sig[idx]
            st = "unobservable" if not np.isfinite(s) else ("fixed" if s == 0 else
                                                             f"{s * factor:.3g}")
            rows.append([name, f"{val[idx] * factor:.9g}", st, unit or cal.units.get(key, "")])
    return Table("Parameters with their 1-sigma uncertainty (display units; files hold SI).",
                 ["parameter", "value", "1 sigma", "unit"], rows)


def generic_sections(ctx: ReportContext) -> list[Section]:
    cal, prov = ctx.cal, ctx.prov
    st = cal.stats
    summary = [f"Method: {cal.method}. Unit serial: {cal.serial or 'unknown'}."]
    if st.get("g_error_rms_after") is not None:
        b = st.get("g_error_rms_before")
        summary.append("|g| error RMS over the static positions: before "
                       f"{'n/a (counts)' if b is None else f'{b * 1e3 / 9.80665:.4f} mg'}, "
                       f"after {st['g_error_rms_after'] * 1e3 / 9.80665:.4f} mg "
                       f"(noise floor {st.get('g_error_floor', float('nan')) * 1e3 / 9.80665:.4f}"
                       " mg).")
    if st.get("g_norm_std_after") is not None:
        from calib_cli.units import g_figures_line

        summary.append(g_figures_line(st) + " (Avrutov et al.'s figures of merit).")
    if st.get("unobservable"):
        summary.append("Unobservable from this data: " + ", ".join(st["unobservable"]) + ".")
    if st.get("sigma_inflation", 1.0) not in (1.0, None):
        summary.append(f"Sigma inflated by sqrt({st['sigma_inflation']:.3g}): the residuals "
                       "scatter more than the noise explains.")
    summary += ctx.notes
    stats = Table("Fit statistics (SI units).", ["statistic", "value"],
                  [[k, _fmt(v) if not isinstance(v, (list, dict)) else json.dumps(v)[:120]]
                   for k, v in st.items()])
    keys = ("kind", "format_version", "tool_version", "created_utc", "unit_serial", "command",
            "input_sha256")
    provt = Table("Provenance of the calibration file.", ["attribute", "value"],
                  [[k, str(prov.get(k, ""))] for k in keys if k in prov])
    return [Section("Summary", text=summary),
            Section("Parameters", tables=[parameter_table(cal)]),
            Section("Statistics", tables=[stats]),
            Section("Provenance", tables=[provt])]


def allan_section(ctx: ReportContext) -> Section | None:
    if ctx.allan is None:
        return None
    from calib_cli.methods.allan import CONFIDENCE, TERM_NAMES, term_units
    from calib_cli.report.figures import allan_figure

    res = ctx.allan
    rows = []
    for i, c in enumerate(res.channels):
        tu = term_units(res.units[i])
        row = [c]
        for k in TERM_NAMES:
            v, lo, hi = (res.terms[k][f][i] for f in ("value", "lo", "hi"))
            row.append("not visible" if not np.isfinite(v) else
                       f"{v:.3g} [{lo:.3g}, {hi:.3g}] {tu[k]}")
        at = res.averaging_time[i]
        row.append(f"{at:.3g} s" if np.isfinite(at) else
                   ("not reached" if np.isfinite(res.target[i]) else "no target"))
        tq = res.min_avg()[i]
        row.append(f"{tq:.3g} s" if np.isfinite(tq) else "-")
        rows.append(row)
    tab = Table(f"IEEE Std 952 noise terms with {CONFIDENCE:.0%} intervals, the shortest "
                "averaging time that brings the noise below the target, and the minimum "
                "averaging time per position from the quantisation term (where the "
                "quantisation stops dominating the noise of a mean).",
                ["channel", "quantization Q", "random walk N", "bias instability B",
                 "rate random walk K", "averaging time", "min. averaging (Q)"], rows)
    fig = FigureItem("allan", allan_figure(res),
                     "Overlapping Allan deviation of each channel (shaded: "
                     f"{CONFIDENCE:.0%} interval from the number of independent clusters) "
                     "with the IEEE 952 lines: dashed slope -1/2 (random walk N, read at "
                     "1 s), dotted the flicker floor 0.664 B, dash-dot slope +1/2 (rate "
                     "random walk K, read at 3 s). What to look for: the curves of one sensor "
                     "should lie together; a bump or a slope steeper than +1/2 at long tau "
                     "means temperature drift or a disturbance, not sensor noise; the tau of "
                     "the minimum is the longest useful averaging time for a static position.")
    return Section(f"Allan deviation ({res.meta.get('segment', '')}, "
                   f"{res.duration:.6g} s)", tables=[tab], figures=[fig])


def build_report(ctx: ReportContext) -> list[Section]:
    """All sections for this calibration: summary and method sections first."""
    _load_section_modules()
    generic = generic_sections(ctx)
    specific = []
    builders = SECTIONS.get(ctx.cal.method, [])
    if not builders:
        generic[0].text.append(f"No method-specific section is registered for method "
                               f"{ctx.cal.method!r}; this report shows the generic parts.")
    for fn in builders:
        out = fn(ctx)
        if out is None:
            continue
        specific += out if isinstance(out, list) else [out]
    allan = allan_section(ctx)
    return [generic[0], *specific, generic[1], *([allan] if allan else []), *generic[2:]]


# ---------------------------------------------------------------------------
# rendering


def _md_table(t: Table) -> list[str]:
    esc = [[md_text(c, block=False) for c in r] for r in t.rows]
    head = [md_text(h, block=False) for h in t.header]
    out = [f"*{md_text(t.caption)}*", "", "| " + " | ".join(head) + " |",
           "|" + "|".join("---" for _ in t.header) + "|"]
    out += ["| " + " | ".join(r) + " |" for r in esc]
    return out + [""]


CSS = """body{font-family:sans-serif;max-width:1100px;margin:2em auto;color:#222}
table{border-collapse:collapse;margin:.5em 0 1.5em}td,th{border:1px solid #bbb;
padding:2px 8px;font-size:90%;text-align:left}th{background:#eee}img{max-width:100%}
figcaption{font-size:90%;color:#444;margin-bottom:1.5em}caption{text-align:left;
font-style:italic;margin-bottom:.3em}"""


def write_report(sections: list[Section], title: str, out_dir) -> dict:
    """Write report.md (+ PNG files) and report.html (self-contained) into
    out_dir (which must exist). Returns a manifest {figures: [{file, axes,
    caption}], markdown, html}. Figures are rendered once."""
    out_dir = Path(out_dir)
    # every text goes through the escaper of its language (calib_cli.io.escape): the
    # serial, method, labels, units and command line come from files
    md = [f"# {md_text(title)}", ""]
    body = [f"<h1>{html_text(title)}</h1>"]
    manifest = {"figures": [], "markdown": "report.md", "html": "report.html"}
    k = 0
    for sec in sections:
        md += [f"## {md_text(sec.title)}", ""]
        body.append(f"<h2>{html_text(sec.title)}</h2>")
        for p in sec.text:
            md += [md_text(p), ""]
            body.append(f"<p>{html_text(p)}</p>")
        for fi in sec.figures:
            k += 1
            fname = f"fig-{k:02d}-{fi.name}.png"
            data = png_bytes(fi.fig)
            (out_dir / fname).write_bytes(data)
            manifest["figures"].append({"file": fname, "axes": len(fi.fig.axes),
                                        "caption": fi.caption})
            md += [f"![{md_text(fi.name)}]({fname})", "", f"*Figure {k}. {md_text(fi.caption)}*",
                   ""]
            b64 = base64.b64encode(data).decode("ascii")
            body.append(f'<figure><img alt="{html_text(fi.name)}" '
                        f'src="data:image/png;base64,{b64}"><figcaption>Figure {k}. '
                        f"{html_text(fi.caption)}</figcaption></figure>")
        for t in sec.tables:
            md += _md_table(t)
            rows = "".join("<tr>" + "".join(f"<td>{html_text(c)}</td>" for c in r)
                           + "</tr>" for r in t.rows)
            head = "".join(f"<th>{html_text(h)}</th>" for h in t.header)
            body.append(f"<table><caption>{html_text(t.caption)}</caption><tr>{head}</tr>"
                        f"{rows}</table>")
    (out_dir / "report.md").write_text("\n".join(md), encoding="utf-8")
    page = ("<!DOCTYPE html>\n<html><head><meta charset=\"utf-8\">"
            f"<title>{html_text(title)}</title><style>{CSS}</style></head><body>\n"
            + "\n".join(body) + "\n</body></html>\n")
    (out_dir / "report.html").write_text(page, encoding="utf-8")
    (out_dir / "figures.json").write_text(json.dumps(manifest, indent=2), encoding="utf-8")
    return manifest
