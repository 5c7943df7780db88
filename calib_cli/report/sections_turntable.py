"""The turntable fit in reports: the sigma history (when each lever arm and
proof-mass offset became observable), the lever arms per cycle and the table
axis found in body axes (docs/turntable.md)."""

from __future__ import annotations

import numpy as np
from matplotlib.figure import Figure

from calib_cli.io.escape import mpl_text
from calib_cli.report.builder import FigureItem, ReportContext, Section, Table, register


def sigma_history_figure(res, title: str | None = None) -> Figure:
    """The 1-sigma of each lever-arm component and proof-mass offset over time
    (the forward filter's covariance), log scale, mm."""
    t = np.asarray(res.tables.get("sigma_history_time", []), float)
    sig = np.asarray(res.tables.get("sigma_history", np.zeros((0, 0))), float)
    labels = list(res.tables.get("sigma_history_labels", []))
    fig = Figure(figsize=(9, 4.8), layout="constrained")
    ax = fig.subplots()
    for k, lab in enumerate(labels):
        style = "-" if lab.startswith("lever") else "--"
        ax.semilogy(t - (t[0] if len(t) else 0.0), sig[:, k] * 1e3, style, lw=1.0, label=mpl_text(lab))
    ax.set_xlabel("time from the first cycle's start (s)")
    ax.set_ylabel("1-sigma (mm)")
    ax.set_title(title or "turntable fit: sigma history of lever arms and proof-mass offsets")
    ax.grid(True, which="both", alpha=0.3)
    if labels:
        ax.legend(fontsize=6, ncol=3, loc="upper right")
    return fig


def sigma_history_plot(res, path, title: str | None = None) -> None:
    """PNG of ``sigma_history_figure`` (calib fit turntable --plot)."""
    sigma_history_figure(res, title).savefig(path, dpi=110)


@register("turntable")
def turntable_sections(ctx: ReportContext):
    cal, st = ctx.cal, ctx.cal.stats
    text = [f"{st.get('n_cycles', '?')} rotation cycles ({', '.join(st.get('cycles', []))}); "
            f"lever arms: {st.get('lever_arm_mode', '?')}, proof masses: "
            f"{st.get('proof_mass_mode', '?')}, tangential term: {st.get('tangential', '?')}."]
    if st.get("accel_noise_inflation", 1.0) > 1.0:
        text.append(f"The model did not explain the accelerometer data: noise widened "
                    f"x{st['accel_noise_inflation']:.1f} (lever arms or proof masses missing?).")
    tables = []
    if "lever_arm" in cal.params:
        s = np.asarray(cal.params["lever_arm"], float)
        sd = cal.sigma.get("lever_arm")
        sd = np.full(s.shape, np.nan) if sd is None else np.asarray(sd, dtype=float)
        labels = st.get("cycles", [str(i + 1) for i in range(len(s))])
        tables.append(Table("Lever arm of each cycle (mm, body axes; the component along the "
                            "table axis is fixed at 0).", ["cycle", "x", "y", "z"],
                            [[lab] + [f"{v * 1e3:+.2f} +- {e * 1e3:.2f}" for v, e in zip(r, q)]
                             for lab, r, q in zip(labels, s, sd)]))
    figs = []
    if cal.tables.get("sigma_history_labels") is not None and len(cal.tables["sigma_history_labels"]):
        figs.append(FigureItem(
            "sigma-history", sigma_history_figure(cal),
            "1-sigma of each lever-arm component (solid) and proof-mass offset (dashed) over "
            "the record, mm, log scale. What to look for: each curve drops when its cycle "
            "excites it (rotation about the orthogonal axis); a curve that stays high was not "
            "excited by the experiment."))
    return Section("Rotating-table calibration", text=text, tables=tables, figures=figs)
