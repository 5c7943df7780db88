"""The section a diagnosis file adds to `calib report DIAG.h5`: the base model,
the steps (which effect, its score against its threshold, the residual before
and after), what was not tested, and where the base and the final model
disagree with the data (the residuals the file holds, noise units). The
effects the steps added get their own sections (report/sections_effects.py)."""

from __future__ import annotations

import numpy as np
from matplotlib.figure import Figure
from matplotlib.ticker import MaxNLocator

from calib_cli.io.escape import mpl_text
from calib_cli.model.display import num
from calib_cli.report.figures import BLUE, VERMILION, use_palette
from calib_cli.report.items import FigureItem, ReportContext, Section, Table

use_palette()  # the Okabe-Ito colour-blind-safe cycle of every calib figure


def _stages(arrays: dict) -> list:
    """[(name, {array name: (M, n)})] of the base model and the final model."""
    res = arrays.get("residuals") or {}
    steps = sorted((k for k in res if k.startswith("step")), key=lambda k: int(k[4:] or 0))
    out = [("base model", res["initial"])] if "initial" in res else []
    if steps:
        out.append(("final model", res[steps[-1]]))
    return out


def disagreement_figure(summary: dict, arrays: dict) -> Figure:
    """Bin residual RMS over the channels (noise units) against time, base and final
    model, and the RMS per segment; equation groups by index where the diagnosis
    has no time bins (the gyro method's static, transition and turn equations)."""
    stages = _stages(arrays)
    t = np.asarray((arrays.get("bins") or {}).get("time", []), float)
    seg_rows = summary.get("residual_by_segment") or []
    timed = len(t) > 0 and all(len(a) == len(t) for _, per in stages for a in per.values())
    if timed:
        fig = Figure(figsize=(10, 6.4 if seg_rows else 3.4), layout="constrained")
        axes = np.atleast_1d(fig.subplots(2 if seg_rows else 1, 1))
        for (name, per), col in zip(stages, (VERMILION, BLUE)):
            z = np.sqrt(np.mean(np.concatenate(list(per.values()), axis=1) ** 2, axis=1))
            axes[0].plot(t - t[0], z, ".", ms=3, color=col, label=name, alpha=0.8)
        axes[0].set_xlabel("time from the record's start (s)")
        axes[0].set_ylabel("bin RMS residual / noise")
    else:
        return _equation_figure(stages)
    axes[0].axhline(1.0, color="k", lw=0.8, ls="--")
    axes[0].legend(fontsize=8, loc="upper right")
    axes[0].grid(alpha=0.3)
    axes[0].set_title("Where the model and the data disagree (1 = noise)", pad=12)
    if timed and seg_rows:
        x = np.arange(len(seg_rows))
        a = [float(r.get("rms_initial") or 0.0) for r in seg_rows]
        b = [float(r.get("rms_final") or 0.0) for r in seg_rows]
        axes[1].bar(x - 0.2, a, 0.4, color=VERMILION, label="base model")
        axes[1].bar(x + 0.2, b, 0.4, color=BLUE, label="final model")
        axes[1].axhline(1.0, color="k", lw=0.8, ls="--")
        axes[1].set_xticks(x, [mpl_text(str(r.get("segment", ""))) for r in seg_rows],
                           rotation=45, ha="right", fontsize=7)
        axes[1].set_ylabel("segment RMS / noise")
        axes[1].legend(fontsize=8)
        axes[1].grid(alpha=0.3, axis="y")
    return fig


def _equation_figure(stages) -> Figure:
    """The gyro method's diagnosis: its equation groups' residuals (static gyro means in
    deg/h, transition and turn angles in arcsec), base and final model, a panel each."""
    from calib_cli.model.display import DEG, DPH

    groups = list(stages[0][1]) if stages else []
    fig = Figure(figsize=(10, 3.0 * max(len(groups), 1)), layout="constrained")
    axes = np.atleast_1d(fig.subplots(max(len(groups), 1), 1, squeeze=False)[:, 0])
    for ax, gname in zip(axes, groups):
        f, unit = (DEG * 3600.0, "arcsec") if "angle" in gname else (DPH, "deg/h")
        offs = (-0.12, 0.12) if len(stages) > 1 else (0.0,)
        for (name, per), col, off in zip(stages, (VERMILION, BLUE), offs):
            v = np.asarray(per.get(gname, []), float).ravel() * f
            ax.plot(np.arange(len(v)) + off, v, "o", ms=4, color=col, label=name, alpha=0.85)
        ax.xaxis.set_major_locator(MaxNLocator(integer=True))
        ax.axhline(0.0, color="k", lw=0.8)
        ax.set_ylabel(f"residual ({unit})")
        ax.set_title(mpl_text(gname.replace("_", " ")), fontsize=9)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0)
    axes[-1].set_xlabel("equation")
    fig.suptitle("Residuals of the gyro equations, base and final model")
    return fig


def diagnosis_section(ctx: ReportContext) -> Section:
    d = ctx.diagnosis or {}
    s = d.get("summary") or {}
    steps = s.get("steps") or []
    text = [f"Base model: {', '.join(map(str, s.get('base_model') or [])) or 'not recorded'}."]
    r0, r1, fl = s.get("residual_rms_initial"), s.get("residual_rms_final"), s.get("noise_rms")
    text.append(f"Residual RMS {num(r0, 3)} noise units with the base model, {num(r1, 3)} with "
                f"the final model; white noise alone would leave {num(fl, 3)}.")
    if steps:
        text.append("Effects added, in order: " + ", ".join(str(st.get("with")) for st in steps)
                    + " (each has its section below).")
    else:
        text.append("No candidate effect passed its threshold: the base model explains the "
                    "data down to the noise.")
    if s.get("fit_command"):
        text.append(f"The same calibration from the raw record: {s['fit_command']}")
    text += [str(n) for n in s.get("notes") or []]
    tables = []
    if steps:
        tables.append(Table("The steps: each effect's score (likelihood-ratio statistic) "
                            "against its threshold, and the residual RMS (noise units) "
                            "before and after adding it.",
                            ["step", "effect", "score", "threshold", "p", "residual RMS"],
                            [[str(k + 1), str(st.get("with")), num(st.get("score"), 4),
                              num(st.get("threshold"), 4), num(st.get("p_value"), 2),
                              f"{num(st.get('residual_rms_before'), 3)} -> "
                              f"{num(st.get('residual_rms_after'), 3)}"]
                             for k, st in enumerate(steps)]))
    if s.get("untested"):
        tables.append(Table("Effects not tested, and why.", ["effect", "why"],
                            [[str(k), str(v)] for k, v in s["untested"].items()]))
    te = s.get("turn_angle_error_deg") or []
    if te:
        tables.append(Table("Turn-angle error (integrated angle minus the plan's), base model "
                            "-> final model.", ["turn", "base (deg)", "final (deg)"],
                            [[str(r.get("turn")), num(r.get("error_initial_deg"), 4),
                              num(r.get("error_final_deg"), 4)] for r in te]))
    arrays = d.get("arrays") or {}
    timed = len((arrays.get("bins") or {}).get("time", [])) > 0
    cap = ("Residuals of the base model (vermilion) and of the final model (blue) in noise "
           "units (the dashed line: the noise). Top: each 0.5 s bin's RMS over the channels "
           "against time; bottom: the RMS of each segment. What to look for: the final model "
           "near 1 everywhere; a segment or a time span still above it is an effect the "
           "model lacks there.") if timed else (
           "Residuals of the gyro method's equations, base model (vermilion) and final model "
           "(blue): the static positions' gyro means (deg/h) and the angles of the "
           "transitions and turns (arcsec). What to look for: the final model's residuals "
           "within the noise of each equation; one equation far off is a disturbed position "
           "or turn.")
    fig = FigureItem("disagreement", disagreement_figure(s, arrays), cap)
    return Section("Diagnosis", text=text, tables=tables, figures=[fig])
