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

The modules each method of the method table names (its ``report``,
methods/registry.py) are imported when a report is built, so a new method adds its
sections in a new module named by its declaration, without editing this one.
A method with no registered section gets the generic report (parameters with
sigma, statistics, provenance) and a note saying so. docs/report.md.
"""

from __future__ import annotations

import base64
import importlib
import json
from pathlib import Path
from typing import Callable

import numpy as np

from calib_cli.data import CalibrationResult
from calib_cli.io.escape import html_text, md_text
from calib_cli.report.figures import png_bytes
from calib_cli.report.items import (  # noqa: F401  (re-exported for the section modules)
    AddedEffect,
    FigureItem,
    ReportContext,
    Section,
    Table,
    added_effects,
)

# method -> section builders, in order
SECTIONS: dict[str, list[Callable]] = {}
# effect name (model/effects.py) -> builder(ctx, AddedEffect) -> Section: the section of an
# effect a fit added (`calib fit METHOD --with`, a diagnosis's steps)
EFFECT_SECTIONS: dict[str, Callable] = {}
_loaded = False


def register(*methods: str):
    """Decorator: add a section builder for calibrations of these methods."""

    def deco(fn):
        for m in methods:
            SECTIONS.setdefault(m, []).append(fn)
        return fn

    return deco


def register_effect(*names: str):
    """Decorator: the section builder of the effects of these names."""

    def deco(fn):
        for n in names:
            EFFECT_SECTIONS[n] = fn
        return fn

    return deco


def _load_section_modules() -> None:
    """Import the section modules the method table names (each method's ``report``,
    methods/registry.py); their ``@register`` decorators fill SECTIONS."""
    global _loaded
    if _loaded:
        return
    from calib_cli.methods.registry import FITS

    for m in FITS.values():
        for mod in m.report:
            importlib.import_module(mod)
    # the sections of the effects a fit adds (--with, a diagnosis's steps), for every method
    importlib.import_module("calib_cli.report.sections_effects")
    _loaded = True


# ---------------------------------------------------------------------------
# generic sections


def _fmt(x) -> str:
    from calib_cli.report.format import num

    return num(x, 6)


def parameter_table(cal: CalibrationResult) -> Table:
    from calib_cli.model.display import entries

    rows = [[e.name, e.value, e.sigma, e.unit] for e in entries(cal.params, cal.sigma, cal.units)]
    return Table("Parameters with their 1-sigma uncertainty (display units; files hold SI, or "
                 "the recorded counts; 'fixed': set by the model, no uncertainty).",
                 ["parameter", "value", "1 sigma", "unit"], rows)


# a normalized residual (residual RMS / noise) above this fails the noise-floor verdict
NORMALIZED_LIMIT = 1.5
# |g| error RMS after correction above this multiple of its noise floor fails
G_FLOOR_LIMIT = 2.0


def verdict(ctx: ReportContext) -> tuple[str, str]:
    """("pass"|"fail"|"undecided", one line): against the tolerances when the
    report was given some, else against the noise floor -- the |g| error after
    correction versus its floor (fits of the accelerometers), the normalized
    residual (residual RMS in units of the noise) for the others."""
    from calib_cli.model.display import MG, g_error_label

    cal, st = ctx.cal, ctx.cal.stats
    if ctx.tolerances is not None:
        from calib_cli.io.history import entry_of
        from calib_cli.io.tolerance import evaluate

        res = evaluate(entry_of(ctx.cal_path, cal, ctx.prov, ctx.history), ctx.history,
                       ctx.tolerances)
        checked = [k for k in ctx.tolerances if k in cal.params]
        skipped = ""
        if res["not_evaluated"]:
            skipped = "; not evaluated: " + "; ".join(res["not_evaluated"])
        if res["not_reported"]:
            skipped += f"; not reported by this calibration: {', '.join(res['not_reported'])}"
        if res["failures"]:
            return "fail", (f"FAIL against the tolerances ({len(res['failures'])} failing): "
                            + "; ".join(res["failures"][:5])
                            + ("; ..." if len(res["failures"]) > 5 else "") + skipped + ".")
        if res["status"] == "incomplete":
            return "undecided", (f"INCOMPLETE against the tolerances: the rules evaluated pass "
                                 f"({len(checked)} parameters: {', '.join(checked)})"
                                 + skipped + ".")
        return "pass", (f"PASS against the tolerances ({len(checked)} parameters checked: "
                        f"{', '.join(checked) or 'none reported by this method'})"
                        + skipped + ".")
    crit = []  # (ok, text)
    ga, gf = st.get("g_error_rms_after"), st.get("g_error_floor")
    if ga is not None and gf is not None and np.isfinite(ga) and np.isfinite(gf) and gf > 0:
        crit.append((ga <= G_FLOOR_LIMIT * gf,
                     f"{g_error_label(st)} after correction {ga * MG:.4g} mg vs its noise floor "
                     f"{gf * MG:.4g} mg (limit {G_FLOOR_LIMIT:g}x)"))
    r = None
    if st.get("normalized_innovation_rms") is not None:
        r, what = float(st["normalized_innovation_rms"]), "normalized innovation RMS"
    elif st.get("chi2_dof") is not None:
        r, what = float(np.sqrt(max(float(st["chi2_dof"]), 0.0))), "normalized residual"
    else:
        chi = [np.asarray(st.get(f"{s}_chi2", []), float) for s in ("accel", "gyro")]
        dof = [np.asarray(st.get(f"{s}_dof", []), float) for s in ("accel", "gyro")]
        c, d = sum(float(np.nansum(x)) for x in chi), sum(float(np.nansum(x)) for x in dof)
        if d > 0:
            r, what = float(np.sqrt(c / d)), "normalized residual (all sensors)"
    if r is not None and np.isfinite(r):
        crit.append((r <= NORMALIZED_LIMIT,
                     f"{what} {r:.3g} (residual RMS / noise; limit {NORMALIZED_LIMIT:g})"))
    if not crit:
        return "undecided", ("not determined: no tolerances given and the calibration holds "
                             "no noise-floor statistic (pass --tolerances TOL.toml).")
    ok = all(c for c, _ in crit)
    return ("pass" if ok else "fail"), (
        ("PASS" if ok else "FAIL") + " against the noise floor: "
        + "; ".join(t for _, t in crit) + ".")


def header_section(ctx: ReportContext) -> Section:
    """Unit, method, dates, inputs with their SHA-256, and the verdict."""
    import datetime as _dt

    from calib_cli.report.format import value_text

    cal, prov = ctx.cal, ctx.prov
    _, line = verdict(ctx)
    rows = [["unit serial", cal.serial or "not recorded"],
            ["method", cal.method + (f" ({cal.stats['method']})" if isinstance(
                cal.stats.get("method"), str) and cal.stats["method"] != cal.method else "")],
            ["calibration file", Path(ctx.cal_path).name],
            ["calibrated (UTC)", str(prov.get("created_utc") or "not recorded")],
            ["report made (UTC)",
             _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%dT%H:%M:%SZ")]]
    hashes = prov.get("input_sha256")
    if isinstance(hashes, str):
        try:
            hashes = json.loads(hashes)
        except ValueError:
            hashes = {"input": hashes}
    for name, h in (hashes or {}).items():
        rows.append([f"input {name}", f"SHA-256 {value_text('sha256', h)}"])
    if ctx.raw_path:
        from calib_cli.io.h5 import sha256_file

        rows.append([f"report input {Path(ctx.raw_path).name}",
                     f"SHA-256 {sha256_file(ctx.raw_path)}"])
    if ctx.tolerances_path:
        rows.append(["tolerances", Path(ctx.tolerances_path).name])
    return Section("Verdict", text=[f"Verdict: {line}"],
                   tables=[Table("Unit, method, dates and inputs.", ["item", "value"], rows)])


def _maybe_json(v):
    if isinstance(v, str) and v[:1] in "[{":
        try:
            return json.loads(v)
        except ValueError:
            pass
    return v


def generic_sections(ctx: ReportContext) -> list[Section]:
    from calib_cli.model.display import (
        StatUnits,
        counts_note,
        g_error_line,
        g_figures_line,
        value_text,
    )

    cal, prov = ctx.cal, ctx.prov
    st = cal.stats
    summary = [f"Method: {cal.method}. Unit serial: {cal.serial or 'not recorded'}."]
    line = g_error_line(st)
    if line:
        summary.append(line + ".")
    note = counts_note(cal.params, cal.units)
    if note:
        summary.append(note)
    if st.get("g_norm_std_after") is not None:
        summary.append(g_figures_line(st) + " (Avrutov et al.'s figures of merit).")
    if st.get("unobservable"):
        summary.append("Unobservable from this data: " + ", ".join(st["unobservable"]) + ".")
    infl = st.get("sigma_inflation", 1.0)
    if infl not in (1.0, None) and np.isfinite(infl):
        summary.append(f"Sigma inflated by sqrt({infl:.3g}): the residuals "
                       "scatter more than the noise explains.")
    summary += ctx.notes
    su = StatUnits.of(cal)
    stats = Table("Fit statistics in display units (accelerometer mg, gyro deg/h, noise "
                  "densities ug/sqrt(Hz) and deg/sqrt(h), angles deg; data recorded in counts "
                  "stay counts; files hold SI).", ["statistic", "value"],
                  [[k, value_text(k, v, units=su)] for k, v in st.items()])
    keys = ("kind", "format_version", "tool_version", "created_utc", "unit_serial", "command",
            "input_sha256")
    provt = Table("Provenance of the calibration file.", ["attribute", "value"],
                  [[k, value_text(k, _maybe_json(prov.get(k)))] for k in keys if k in prov])
    return [Section("Summary", text=summary),
            Section("Parameters", tables=[parameter_table(cal)]),
            Section("Statistics", tables=[stats]),
            Section("Provenance", tables=[provt])]


def allan_section(ctx: ReportContext) -> Section | None:
    if ctx.allan is None:
        return None
    from calib_cli.methods.allan import CONFIDENCE, TERM_NAMES
    from calib_cli.report.figures import allan_figure
    from calib_cli.report.format import allan_display, num

    res = ctx.allan
    rows = []
    for i, c in enumerate(res.channels):
        _, _, tu = allan_display(res.units[i])
        row = [c]
        for k in TERM_NAMES:
            v, lo, hi = (res.terms[k][f][i] * tu[k][0] for f in ("value", "lo", "hi"))
            row.append("not visible" if not np.isfinite(v) else
                       f"{num(v, 3)} [{num(lo, 3)}, {num(hi, 3)}] {tu[k][1]}")
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
    """All sections for this calibration: the verdict, the summary, the method's
    sections (its registered ones, else the generic section built from its params,
    sigma and units), a diagnosis's steps, one section per effect the fit added,
    then the parameters, the Allan deviation, the statistics and the provenance."""
    from calib_cli.report import generic

    _load_section_modules()
    base = generic_sections(ctx)
    specific = []
    for fn in SECTIONS.get(ctx.cal.method, [generic.method_section]):
        out = fn(ctx)
        if out is None:
            continue
        specific += out if isinstance(out, list) else [out]
    if ctx.diagnosis is not None:
        from calib_cli.report.diagnosis_section import diagnosis_section

        specific.append(diagnosis_section(ctx))
    added = added_effects(ctx.cal)
    for sec in specific:
        if not sec.figures:
            # the base method's section of a --with fit or a diagnosis (its statistics
            # differ from the method's own fit's): the base model's parameters as a figure
            sec.figures.append(generic.base_parameter_figure(ctx, added))
    for eff in added:
        specific.append(EFFECT_SECTIONS.get(eff.name, generic.effect_section)(ctx, eff))
    allan = allan_section(ctx)
    return [header_section(ctx), base[0], *specific, base[1],
            *([allan] if allan else []), *base[2:]]


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
table{border-collapse:collapse;margin:.5em 0 1.5em;min-width:60%}td,th{border:1px solid #bbb;
padding:2px 8px;font-size:90%;text-align:left}th{background:#eee}img{max-width:100%}
figcaption{font-size:90%;color:#444;margin-bottom:1.5em}caption{text-align:left;
font-style:italic;margin-bottom:.3em}.verdict{font-weight:bold;padding:.4em .6em;
border-left:6px solid #999}.verdict.pass{border-color:#009E73;background:#e6f5ef}
.verdict.fail{border-color:#D55E00;background:#fbece3}td{word-break:break-word}"""


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
            cls = ""
            if p.startswith("Verdict: "):
                word = p.split()[1] if len(p.split()) > 1 else ""
                cls = ' class="verdict {}"'.format(
                    {"PASS": "pass", "FAIL": "fail"}.get(word, "undecided"))
            body.append(f"<p{cls}>{html_text(p)}</p>")
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
