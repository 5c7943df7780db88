"""Report sections of the static accelerometer fit (methods vector and scalar):
|g| per position before and after correction, residuals per axis and position."""

from __future__ import annotations

from pathlib import Path

import numpy as np
from matplotlib.figure import Figure

from calib_cli.io.escape import mpl_text
from calib_cli.model.display import MG, data_units
from calib_cli.report.builder import FigureItem, ReportContext, Section, Table, register
from calib_cli.report.figures import BLUE, VERMILION


def g_figure(labels, before, after, sigma_after, g_ref) -> Figure:
    """Two axes: |mean f| per position before/after with the reference g and
    the means; below, after - g in mg with the 1-sigma noise floor of each position."""
    fig = Figure(figsize=(max(6.4, 0.45 * len(labels) + 3), 6.4), layout="constrained")
    ax1, ax2 = fig.subplots(2, 1, sharex=True)
    x = np.arange(len(labels))
    if before is not None and np.any(np.isfinite(before)):
        ax1.plot(x, before, "o", color=VERMILION, label="before (raw)")
        ax1.axhline(np.nanmean(before), color=VERMILION, ls=":", lw=1,
                    label=f"mean before {np.nanmean(before):.5f}")
    ax1.plot(x, after, "s", color=BLUE, label="after correction")
    ax1.axhline(np.mean(after), color=BLUE, ls=":", lw=1,
                label=f"mean after {np.mean(after):.5f}")
    ax1.axhline(g_ref, color="k", lw=1, label=f"reference g {g_ref:.5f}")
    ax1.set_ylabel("|mean specific force| (m/s^2)")
    ax1.set_title("|g| per static position")
    ax1.legend(fontsize=8, ncol=2)
    ax1.grid(alpha=0.3)
    ax1.ticklabel_format(axis="y", useOffset=False)
    ax2.errorbar(x, (after - g_ref) * MG, yerr=sigma_after * MG, fmt="s", color=BLUE,
                 capsize=3, label="after - g (bars: 1 sigma noise floor)")
    ax2.axhline(0, color="k", lw=1)
    ax2.set_ylabel("|f| - g after correction (mg)")
    ax2.set_xlabel("static position")
    ax2.set_xticks(x, [mpl_text(s) for s in labels], rotation=45, ha="right", fontsize=8)
    ax2.legend(fontsize=8)
    ax2.grid(alpha=0.3)
    return fig


def residual_figure(labels, resid, scale: float = MG, unit: str = "mg", what: str = "") -> Figure:
    """Residuals per position: per axis (vector fit, (m, 3)), per sensor ((m, n)) or of |f|
    (scalar, (m,)), in ``unit`` (resid in SI times ``scale``); ``what`` names the sensor."""
    fig = Figure(figsize=(max(6.4, 0.45 * len(labels) + 3), 4.0), layout="constrained")
    ax = fig.subplots()
    x = np.arange(len(labels))
    r = np.asarray(resid, dtype=float) * scale
    if r.ndim == 2:
        w = 0.8 / r.shape[1]
        for j in range(r.shape[1]):
            ax.bar(x + (j - (r.shape[1] - 1) / 2) * w, r[:, j], w, label=f"{'xyz'[j]} axis"
                   if r.shape[1] == 3 else f"sensor {j}",
                   hatch="//" if j >= 8 else None)  # beyond the palette's 8 colours
        per = "axis" if r.shape[1] == 3 else "sensor"
        ax.set_title(f"{what}residuals per {per} and position (measured - model)", fontsize=10)
    else:
        ax.bar(x, r, 0.6, label="|f| - g")
        ax.set_title("Residuals of the fit per position (|K^-1 (A - b)| - g)", fontsize=10)
    ax.axhline(0, color="k", lw=1)
    ax.set_ylabel(f"residual ({unit})")
    ax.set_xlabel("static position")
    ax.set_xticks(x, [mpl_text(s) for s in labels], rotation=45, ha="right", fontsize=8)
    if r.ndim == 2 and r.shape[1] > 3:  # many sensors: the legend beside the axes
        ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0)
    else:
        ax.legend(fontsize=8)
    ax.grid(alpha=0.3, axis="y")
    return fig


@register("vector", "scalar")
def static_sections(ctx: ReportContext):
    cal = ctx.cal
    if "g_table" not in cal.tables:
        return Section("Static positions", text=["The calibration file holds no |g| table."])
    tab = np.asarray(cal.tables["g_table"], dtype=float)
    cols = list(cal.tables.get("g_table_columns", ["samples", "g_before", "g_after",
                                                   "g_error_after", "g_sigma_after"]))
    labels = list(cal.tables.get("segment_labels", [str(i) for i in range(len(tab))]))
    col = {c: tab[:, i] for i, c in enumerate(cols)}
    g_ref = float(cal.stats.get("g_reference", np.nan))
    if not np.isfinite(g_ref):
        g_ref = float(np.mean(col["g_after"] - col["g_error_after"]))
    counts = cal.raw_units.get("accel") == "count"
    before = None if counts else col.get("g_before")
    figs = [FigureItem(
        "g-per-position",
        g_figure(labels, before, col["g_after"], col.get("g_sigma_after", 0 * tab[:, 0]), g_ref),
        "Top: the magnitude of the mean specific force of each static position, raw (red; "
        "absent for data in counts) and corrected (blue), with the reference gravity (black) "
        "and the means (dotted). Bottom: corrected |f| - g in mg with each position's 1-sigma "
        "noise floor. What to look for: after correction every position should sit on the "
        "reference within about its error bar; a position far off points to a disturbed "
        "position or a wrong plan attitude, a pattern by axis to an effect the model lacks.")]
    resid = cal.residuals.get("accel_segment")
    # the vector fit's residuals are in the recorded units (counts stay counts); the
    # scalar fit's are of |f| after correction (SI)
    du = data_units(cal.units)["accel"]
    scale, unit = (1.0, du) if cal.method == "vector" and "count" in du else (MG, "mg")
    if resid is not None and len(np.atleast_1d(resid)) == len(labels):
        figs.append(FigureItem(
            "residuals", residual_figure(labels, resid, scale, unit),
            f"Residuals of the fit (measured minus model) for each position, in {unit}, per "
            "axis for the vector fit, of |f| for the scalar fit. What to look for: scatter like "
            "the noise and no pattern; a residual that repeats with the sign of one axis "
            "suggests nonlinearity or scale asymmetry (try `calib diagnose`)."))
    det = _detection_item(ctx)
    if det is not None:
        figs.append(det)
    rows = [[lab, f"{int(c)}", "-" if before is None or not np.isfinite(b) else f"{b:.6f}",
             f"{a:.6f}", f"{e * MG:+.4f}", f"{s * MG:.4f}"]
            for lab, c, b, a, e, s in zip(labels, col["samples"],
                                          before if before is not None else col["samples"] * np.nan,
                                          col["g_after"], col["g_error_after"],
                                          col.get("g_sigma_after", col["samples"] * np.nan),
                                          strict=True)]
    table = Table("|g| per static position (m/s^2; differences in mg).",
                  ["position", "samples", "|f| before", "|f| after", "after - g (mg)",
                   "1 sigma (mg)"], rows)
    text = [f"{len(labels)} static positions, reference g = {g_ref:.6f} m/s^2."]
    return Section(f"Static accelerometer fit ({cal.method})", text=text, tables=[table],
                   figures=figs)


DETECT_OPTIONS = {"--window": "window_s", "--threshold": "multiplier",
                  "--min-static": "min_static_s"}


def _detection_options(command: str) -> dict:
    """The import's static-detection options, read back from the raw file's command line
    (`calib import csv ... --window 2`); the defaults where it gave none."""
    import shlex

    opts = {"window_s": 1.0, "multiplier": 3.0, "min_static_s": 1.0}
    try:
        words = shlex.split(command or "")
    except ValueError:
        return opts
    for i, w in enumerate(words[:-1]):
        key, _, val = w.partition("=")
        if key in DETECT_OPTIONS:
            try:
                v = float(val if val else words[i + 1])
            except ValueError:
                continue
            if np.isfinite(v) and v > 0:
                opts[DETECT_OPTIONS[key]] = v
    return opts


def _detection_item(ctx: ReportContext):
    """The static-detection figure of `calib detect --plot` for the RAW record of the
    report (as the import ran it), or None without RAW."""
    rec = ctx.recording()
    if rec is None or len(rec.time) < 10:
        return None
    from calib_cli.io.h5 import provenance
    from calib_cli.methods.static_detect import detect_static
    from calib_cli.report.figures import detection_figure

    o = _detection_options(str(provenance(ctx.raw_path).get("command", "")))
    try:
        rep = detect_static(rec.time, rec.accel, rec.gyro, o["window_s"], o["multiplier"],
                            o["min_static_s"])
    except Exception:  # noqa: BLE001 - a record detection cannot read: no figure, a note
        ctx.notes.append("No static-detection figure: the detector could not run on the "
                         "record.")
        return None
    n_static = sum(1 for sg in rec.segments if sg.kind == "static")
    return FigureItem(
        "static-detection",
        detection_figure(rec.time, rec.accel, rec.gyro, rep, "Static detection of the record",
                         units=rec.units),
        f"The record's signals with the static intervals the detector finds (green, numbered: "
        f"{len(rep.intervals)}; the record has {n_static} static segments) at window "
        f"{o['window_s']:g} s, threshold {o['multiplier']:g}x the noise floor, minimum "
        f"{o['min_static_s']:g} s (the import's options), and the detector's statistic "
        "against the threshold, as `calib detect --plot` draws it. What to look for: one "
        "interval per plan position; a dip that stays above the threshold line, or is "
        "shorter than the minimum, is a position detection missed.")


@register("accel")
def accel_model_section(ctx: ReportContext):
    """The accelerometer base section of `fit accel --with` and of an accel diagnosis
    (the diagnose refit engine, which keeps no |g| table): |g| per static position of
    the RAW record before and after correction through the calibration's whole model."""
    cal = ctx.cal
    title = "Static accelerometer fit (" + (", ".join(
        map(str, cal.stats.get("base_model") or [])) or "base model") + ")"
    rec = ctx.recording()
    segs = [sg for sg in rec.segments if sg.kind == "static"] if rec is not None else []
    if not segs or rec.units.get("accel") not in ("m/s^2", "count"):
        text = ["Give the raw record as second argument (calib report CAL RAW --out DIR) for "
                "|g| per static position before and after correction."]
        return Section(title, text=text)
    from calib_cli.methods.apply import model_of
    from calib_cli.model.correction import correct

    means = np.array([rec.accel[sg.slice].mean(axis=0) for sg in segs])
    var = np.array([rec.accel[sg.slice].var(axis=0) / max(sg.n, 1) for sg in segs])
    temp = None if rec.temp is None else np.array([np.mean(rec.temp[sg.slice]) for sg in segs])
    f = correct(model_of(cal), cal.params, "accel", means, temp=temp)
    after = np.linalg.norm(f, axis=1)
    counts = "count" in rec.units.get("accel", "")
    before = None if counts else np.linalg.norm(means, axis=1)
    u = f / after[:, None]
    if counts:  # the noise of the counts through the scale factors
        kd = np.abs(np.diag(np.asarray(cal.params.get("accel_K", np.eye(3)), float)))
        var = var / kd ** 2
    sig = np.sqrt(np.sum(u ** 2 * var, axis=1))
    g_ref = float(cal.stats.get("g_reference") or rec.site.gravity)
    labels = [sg.label for sg in segs]
    fig = FigureItem(
        "g-per-position", g_figure(labels, before, after, sig, g_ref),
        "Top: |mean specific force| of each static position of the record, raw (red; absent "
        "for data in counts) and corrected through the calibration's whole model (blue), "
        "with the reference gravity. Bottom: corrected |f| - g in mg with each position's "
        "1-sigma noise of the mean. What to look for: every position on the reference within "
        "about its bar; a pattern by axis is an effect the model still lacks.")
    rows = [[lab, str(sg.n), "-" if before is None else f"{b:.6f}", f"{a:.6f}",
             f"{(a - g_ref) * MG:+.4f}", f"{s_ * MG:.4f}"]
            for lab, sg, b, a, s_ in zip(labels, segs, before if before is not None
                                         else after, after, sig, strict=True)]
    table = Table("|g| per static position of the record (m/s^2; differences in mg).",
                  ["position", "samples", "|f| before", "|f| after", "after - g (mg)",
                   "1 sigma (mg)"], rows)
    rms = float(np.sqrt(np.mean((after - g_ref) ** 2)))
    return Section(title, text=[f"{len(segs)} static positions of {Path(ctx.raw_path).name}; "
                                f"|g| error RMS after correction {rms * MG:.4g} mg."],
                   tables=[table], figures=[fig])
