"""Report sections of the gyro fit (method gyro, docs/gyro.md): the angle
residual of every transition between static positions and of every turn of
known angle, and the gyro residual of every static position (earth rate)."""

from __future__ import annotations

import numpy as np
from matplotlib.figure import Figure
from matplotlib.patches import Patch

from calib_cli.io.escape import mpl_text
from calib_cli.model.display import data_units
from calib_cli.report.builder import FigureItem, ReportContext, Section, Table, register
from calib_cli.report.figures import BLUE, VERMILION
from calib_cli.report.format import DEG, DPH, num
from calib_cli.report.sections_static import residual_figure

ARCSEC = DEG * 3600.0  # rad -> arcsec


def angle_residual_figure(tr_labels, tr, turn_labels, turn, noise=None) -> Figure:
    """Bars of the angle residual (arcsec) per transition and per turn."""
    labels = list(tr_labels) + list(turn_labels)
    vals = np.concatenate([np.asarray(tr, float), np.asarray(turn, float)]) * ARCSEC
    colors = [BLUE] * len(tr) + [VERMILION] * len(turn)
    fig = Figure(figsize=(max(6.4, 0.5 * len(labels) + 3), 4.2), layout="constrained")
    ax = fig.subplots()
    x = np.arange(len(labels))
    ax.bar(x, vals, 0.6, color=colors)
    handles = [Patch(color=BLUE, label="transition between static positions"),
               Patch(color=VERMILION, label="turn of known angle")]
    if noise is not None and np.isfinite(noise):
        handles.append(ax.axhline(noise * ARCSEC, color="k", ls="--", lw=1,
                                  label=f"RMS of all ({noise * ARCSEC:.3g} arcsec)"))
    ax.set_ylabel("angle residual (arcsec)")
    ax.set_xlabel("segment")
    ax.set_xticks(x, [mpl_text(s) for s in labels], rotation=45, ha="right", fontsize=8)
    ax.set_title("Gyro fit: angle the calibrated gyros miss, per transition and turn")
    ax.grid(alpha=0.3, axis="y")
    ax.legend(handles=handles, fontsize=8)
    return fig


@register("gyro")
def gyro_sections(ctx: ReportContext):
    cal, st = ctx.cal, ctx.cal.stats
    tr = np.atleast_1d(np.asarray(cal.residuals.get("transition_angle", []), float))
    turn = np.atleast_1d(np.asarray(cal.residuals.get("turn_angle", []), float))
    tr_labels = list(st.get("transitions_used") or [])
    if len(tr_labels) != len(tr):
        tr_labels = [f"transition {i}" for i in range(len(tr))]
    turn_labels = list((st.get("turn_angles_deg") or {}).keys())
    if len(turn_labels) != len(turn):
        turn_labels = [f"turn {i}" for i in range(len(turn))]
    figs, tables = [], []
    if len(tr) + len(turn):
        allr = np.concatenate([tr, turn])
        figs.append(FigureItem(
            "gyro-residuals",
            angle_residual_figure(tr_labels, tr, turn_labels, turn,
                                  float(np.sqrt(np.mean(allr ** 2)))),
            "Angle residual of each transition (blue: the rotation the corrected gyros "
            "integrate between two static positions against the one the accelerometers "
            "see) and of each turn of known angle (vermilion), arcsec. What to look for: "
            "all bars of similar height; one transition far above the others was disturbed "
            "(the unit moved while settling, a bump); all turns high against the "
            "transitions points to a wrong turn angle in the plan."))
        rows = [[lab, kind, f"{v * ARCSEC:.3g}"]
                for lab, kind, v in [*((a, "transition", v) for a, v in zip(tr_labels, tr,
                                                                             strict=True)),
                                     *((a, "turn", v) for a, v in zip(turn_labels, turn,
                                                                      strict=True))]]
        tables.append(Table("Angle residual per transition and turn (arcsec).",
                            ["segment", "kind", "residual (arcsec)"], rows))
    rs = cal.residuals.get("static_gyro")
    labels = list(cal.tables.get("segment_labels", []))
    # the static residuals are in the recorded units: counts stay counts
    du = data_units(cal.units)["gyro"]
    scale, unit = (1.0, du) if "count" in du else (DPH, "deg/h")
    if rs is not None and np.ndim(rs) == 2 and len(labels) == len(rs):
        figs.append(FigureItem(
            "gyro-static-residuals", residual_figure(labels, rs, scale, unit, "gyro: "),
            "Gyro residual of every static position (mean reading minus the model's earth "
            f"rate, bias and g-sensitivity), {unit}, per axis. What to look for: scatter like "
            "the noise of the means; a pattern with the sign of gravity on one axis is a "
            "g-sensitivity the model lacks (fit with --g-sensitivity on)."))
    rms = [f"{what} residual RMS {num(_arcsec(st.get(key)))} arcsec"
           for what, key, n in (("transition", "transition_residual_rms_rad", len(tr)),
                                ("turn", "turn_residual_rms_rad", len(turn))) if n]
    text = [f"{num(st.get('n_positions'))} static positions, {len(tr)} transitions and "
            f"{len(turn)} turns used" + (f"; {', '.join(rms)}." if rms else ".")]
    for s in st.get("transitions_skipped") or []:
        text.append(f"Transition not used: {s}.")
    return Section("Gyro fit", text=text, tables=tables, figures=figs)


def _arcsec(x):
    return None if x is None else float(x) * ARCSEC
