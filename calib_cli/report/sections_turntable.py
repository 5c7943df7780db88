"""The turntable fit in reports: the sigma history (when each lever arm and
proof-mass offset became observable), the lever arms per cycle and the table
axis found in body axes (docs/turntable.md)."""

from __future__ import annotations

import numpy as np
from matplotlib.figure import Figure

from calib_cli.io.escape import mpl_text
from calib_cli.report.builder import FigureItem, ReportContext, Section, Table, register
from calib_cli.report.figures import LINESTYLES, OKABE_ITO, line_style
from calib_cli.report.format import CHECK_POSITION_HEADER, DPH, MG, check_position_rows, value_text

BLOCK_S = 0.5  # residuals are shown as means over blocks of this length


def sigma_history_figure(res, title: str | None = None) -> Figure:
    """The 1-sigma of each lever-arm component and proof-mass offset over time
    (the forward filter's covariance), log scale, mm."""
    t = np.asarray(res.tables.get("sigma_history_time", []), float)
    sig = np.asarray(res.tables.get("sigma_history", np.zeros((0, 0))), float)
    labels = list(res.tables.get("sigma_history_labels", []))
    fig = Figure(figsize=(9, 4.8), layout="constrained")
    ax = fig.subplots()
    # lever arms: one look per free component (each cycle's curve drops in its own
    # cycle, named at the top); proof-mass offsets: a colour each. A short legend.
    seen: dict = {}  # cycle -> free components drawn so far
    labelled: set = set()
    pm_colours = [c for i, c in enumerate(OKABE_ITO) if i not in (0, 4)]
    n_pm = 0
    for k, lab in enumerate(labels):
        if str(lab).startswith("lever_arm["):
            cyc = str(lab).split(".")[0]
            comp = seen.get(cyc, 0)
            seen[cyc] = comp + 1
            style = {"color": OKABE_ITO[0] if comp == 0 else OKABE_ITO[4],
                     "ls": "-" if comp == 0 else "--"}
            lab_show = None if comp in labelled else (
                f"lever arm of each cycle, {'first' if comp == 0 else 'second'} free component")
            labelled.add(comp)
        else:
            style = {"color": pm_colours[n_pm % len(pm_colours)],
                     "ls": LINESTYLES[(n_pm // len(pm_colours)) % len(LINESTYLES)]}
            n_pm += 1
            lab_show = f"proof-mass offset {lab}"
        ax.semilogy(t - (t[0] if len(t) else 0.0), sig[:, k] * 1e3, lw=1.0,
                    label=None if lab_show is None else mpl_text(lab_show), **style)
    # cycle boundaries: the history is sampled within the cycles only, so the transitions
    # between them are the gaps of its time axis; each cycle named at the top
    t0 = t[0] if len(t) else 0.0
    names = list(res.stats.get("cycles") or [])
    if len(t) > 2:
        dt = np.diff(t)
        cut = np.flatnonzero(dt > 2.2 * max(float(np.median(dt)), 1e-9)) + 1
        starts = np.concatenate([[0], cut])
        for k, i in enumerate(starts):
            if k:
                ax.axvline(t[i] - t0, color="0.55", lw=0.7, ls="-", zorder=0)
            if len(starts) == len(names):
                ax.annotate(mpl_text(names[k]), (t[i] - t0, 1.0),
                            xycoords=("data", "axes fraction"), xytext=(2, 2),
                            textcoords="offset points", fontsize=6, rotation=30,
                            ha="left", va="bottom")
    ax.set_xlabel("time from the first cycle's start (s); grey lines: cycle boundaries")
    ax.set_ylabel("1-sigma (mm)")
    ax.set_title(title or "turntable fit: sigma history of lever arms and proof-mass offsets",
                 pad=30 if names else 6)
    ax.grid(True, which="both", alpha=0.3)
    if labels:  # beside the axes, never over the data
        ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0)
    return fig


def estimate_history_figure(res) -> Figure:
    """The forward filter's running estimate of each lever-arm component and proof-mass
    offset over time with its +-1-sigma band (the rough-stand paper's fig. 4), mm; the
    final value (after all passes) as a short bar at the right. Lever arms and
    proof-mass offsets in two panels."""
    t = np.asarray(res.tables.get("sigma_history_time", []), float)
    sig = np.asarray(res.tables.get("sigma_history", np.zeros((0, 0))), float)
    est = np.asarray(res.tables.get("estimate_history", np.zeros((0, 0))), float)
    labels = list(res.tables.get("sigma_history_labels", []))
    t = t - (t[0] if len(t) else 0.0)
    groups = [("lever arms", [k for k, lab in enumerate(labels) if lab.startswith("lever")]),
              ("proof-mass offsets", [k for k, lab in enumerate(labels) if lab.startswith("p_")])]
    groups = [g for g in groups if g[1]]
    fig = Figure(figsize=(9, 2.6 + 2.4 * len(groups)), layout="constrained")
    axs = np.atleast_1d(fig.subplots(max(len(groups), 1), 1, sharex=True))
    final = {}
    pm = res.params.get("proof_mass_offsets")
    if pm is not None:  # p_ij, the labels' entries
        pm = np.asarray(pm, float)
        for lab in labels:
            if lab.startswith("p_"):
                final[lab] = pm["xyz".index(lab[2]), "xyz".index(lab[3])]
    dx = 0.03 * (float(t[-1]) + 1.0) if len(t) else 1.0
    for ax, (name, idx) in zip(axs, groups):
        for n, k in enumerate(idx):
            sty = line_style(n)
            y, e = est[:, k] * 1e3, sig[:, k] * 1e3
            # drawn from where the entry is determined (sigma below half its prior)
            on = e < 0.5 * e[0] if len(e) else e > 0
            y, e = np.where(on, y, np.nan), np.where(on, e, np.nan)
            ax.plot(t, y, lw=1.0, label=mpl_text(labels[k]), **sty)
            ax.fill_between(t, y - e, y + e, color=sty["color"], alpha=0.12, lw=0)
            v = final.get(labels[k])
            if v is not None and np.isfinite(v) and len(t):
                ax.plot([t[-1], t[-1] + dx], [v * 1e3] * 2, lw=2.0, color=sty["color"])
        # the bands start at the prior (tens of cm): scale to where the estimates settle
        y_end = np.abs(est[-1, idx]) * 1e3 if len(est) else np.ones(1)
        e_mid = float(np.nanmedian(sig[-1, idx])) * 1e3 if len(sig) else 0.0
        span = max(float(np.nanmax(y_end)), 1.0) * 1.3 + 3 * e_mid
        ax.set_ylim(-span, span)
        ax.set_ylabel(f"{name} (mm)")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=6, ncol=1 + len(idx) // 16, loc="upper left",
                  bbox_to_anchor=(1.01, 1.0), borderaxespad=0)
    axs[0].set_title("turntable fit: running estimates with +-1-sigma bands (first filter "
                     "pass); bars at the right: final values", fontsize=9)
    axs[-1].set_xlabel("time from the first cycle's start (s)")
    return fig


def check_positions_table(st: dict) -> Table | None:
    """stats.check_positions as a table (None without a check position)."""
    cp = st.get("check_positions") or {}
    rows = check_position_rows(cp)
    if not rows:
        return None
    return Table("Check positions (static segments the fit did not use): |f| - g, and the "
                 "corrected rate along the vertical minus the earth rate's vertical component, "
                 "with 1-sigma (noise of the mean and the calibration's covariance); verdict "
                 f"{cp.get('verdict')} (pass: every |z| < 3.3).", CHECK_POSITION_HEADER, rows)


def sigma_history_plot(res, path, title: str | None = None) -> None:
    """PNG of ``sigma_history_figure`` (calib fit turntable --plot)."""
    sigma_history_figure(res, title).savefig(path, dpi=110)


def cycle_residuals(ctx: ReportContext):
    """Per rotating segment (cycle): block means of the corrected data's
    residuals, from the raw record and the calibration through the ordinary
    correction (methods.apply.apply_triad) and the rigid-body terms of the
    model (model.kinematics.rigid_body_accel):

    - accel: |f - w x (w x r_i) - dw x r_i| - g, with r_i = s + p_i the proof
      mass of accelerometer i (lever arm of the cycle plus its offset): the
      gravity the corrected accelerometers leave after the table's motion;
    - gyro: w . a - (table rate + earth rate along the table axis), a the
      table axis in body axes found by the fit; only where the record carries
      the table rate (or angle).

    Returns a list of dicts {label, t, rate, accel, gyro} (time s from the
    record's start, table rate deg/s, accel mg, gyro deg/h or None)."""
    from calib_cli.methods.apply import apply_triad
    from calib_cli.model.kinematics import rigid_body_accel

    rec = ctx.recording()
    cal, st = ctx.cal, ctx.cal.stats
    if rec is None or rec.gyro is None or rec.layout.redundant:
        return []
    f, w = apply_triad(cal, rec.accel, rec.gyro)
    g = float(st.get("g_reference") or rec.site.gravity)
    s_all = np.asarray(cal.params.get("lever_arm", np.zeros((0, 3))), float).reshape(-1, 3)
    P = np.asarray(cal.params.get("proof_mass_offsets", np.zeros((3, 3))), float)
    P = np.nan_to_num(P)
    axes_body = np.asarray(st.get("table_axis_body") or [], float).reshape(-1, 3)
    we_enu = np.asarray(rec.site.earth_rate_enu, float)
    rate_rec = rec.table_rate
    if rate_rec is None and rec.table_angle is not None:
        rate_rec = np.gradient(np.unwrap(rec.table_angle), rec.time)
    out = []
    cycles = [s for s in rec.segments if s.kind == "rotating"]
    for k, seg in enumerate(cycles):
        sl = seg.slice
        t = rec.time[sl]
        if len(t) < 4:
            continue
        ws, fs = w[sl], f[sl]
        dw = np.gradient(ws, t, axis=0)
        s = s_all[k] if k < len(s_all) else np.zeros(3)
        fc = np.empty_like(fs)
        for i in range(3):
            fc[:, i] = fs[:, i] - rigid_body_accel(ws, dw, s + P[i])[:, i]
        ra = np.linalg.norm(fc, axis=1) - g
        a = axes_body[k] if k < len(axes_body) else None
        if a is None or not np.all(np.isfinite(a)):
            a = ws.mean(axis=0) / max(np.linalg.norm(ws.mean(axis=0)), 1e-12)
        a = a / np.linalg.norm(a)
        along = ws @ a
        rg = None
        if rate_rec is not None and seg.table_axis_enu is not None:
            ax_enu = np.asarray(seg.table_axis_enu, float)
            ax_enu = ax_enu / np.linalg.norm(ax_enu)
            want = rate_rec[sl] + float(we_enu @ ax_enu)
            # the axis found by the fit may point either way along the table axis
            sign = 1.0 if np.sum(along * want) >= 0 else -1.0
            rg = sign * along - want
        n = max(int(round(BLOCK_S / np.median(np.diff(t)))), 1)
        m = len(t) // n
        out.append({"label": seg.label, "t": _blk(t - rec.time[0], m, n),
                    "rate": np.degrees(np.abs(_blk(along, m, n))), "accel": _blk(ra, m, n) * MG,
                    "gyro": None if rg is None else _blk(rg, m, n) * DPH})
    return out


def _blk(x, m: int, n: int) -> np.ndarray:
    """Means of m consecutive blocks of n samples."""
    return x[: m * n].reshape(m, n).mean(axis=1)


def _residual_figure(res, x: str, title: str, xlabel: str, boundaries: bool) -> Figure:
    """Accel (and gyro) residuals against r[x] ("t" or "rate"), a colour per cycle;
    grey lines at the cycle starts with ``boundaries``."""
    has_g = any(r["gyro"] is not None for r in res)
    fig = Figure(figsize=(10, 6.0 if has_g else 3.6), layout="constrained")
    axs = np.atleast_1d(fig.subplots(2 if has_g else 1, 1, sharex=True))
    for k, r in enumerate(res):
        sty = line_style(k)
        axs[0].plot(r[x], r["accel"], ".", ms=2, color=sty["color"], label=mpl_text(r["label"]))
        if has_g and r["gyro"] is not None:
            axs[1].plot(r[x], r["gyro"], ".", ms=2, color=sty["color"])
        if boundaries:
            for ax in axs:
                ax.axvline(r[x][0], color="0.6", lw=0.6)
    axs[0].set_ylabel("|g| residual (mg)")
    axs[0].set_title(title)
    if has_g:
        axs[1].set_ylabel("rate residual along\nthe table axis (deg/h)")
    axs[-1].set_xlabel(xlabel)
    for ax in axs:
        ax.axhline(0, color="k", lw=0.8)
        ax.grid(alpha=0.3)
    axs[0].legend(fontsize=7, markerscale=4, loc="upper left", bbox_to_anchor=(1.01, 1.0),
                  borderaxespad=0, title="cycle", title_fontsize=7)
    return fig


def residual_time_figure(res) -> Figure:
    """Accel and gyro residuals against time, a colour per cycle, cycle boundaries."""
    return _residual_figure(res, "t", "Turntable fit: residuals of the corrected data against "
                            f"time ({BLOCK_S:g} s means)",
                            "time from the record's start (s); grey lines: cycle starts", True)


def residual_rate_figure(res) -> Figure:
    """The same residuals against the table rate, a colour per cycle."""
    return _residual_figure(res, "rate", "Turntable fit: residuals against the table rate, "
                            "per cycle", "table rate (deg/s)", False)


def _summary_line(ctx: ReportContext) -> str:
    """Cycles and the fit's options: the turntable fit's own statistics, else (fit
    --with, a diagnosis: the diagnose refit engine) the record's rotating segments and
    the calibration's model."""
    st = ctx.cal.stats
    if st.get("n_cycles") is not None:
        return (f"{st['n_cycles']} rotation cycles ({', '.join(st.get('cycles', []))}); lever "
                f"arms: {st.get('lever_arm_mode', 'not recorded')}, proof masses: "
                f"{st.get('proof_mass_mode', 'not recorded')}, tangential term: "
                f"{value_text('tangential', st.get('tangential'))}.")
    rec = ctx.recording()
    cycles = [s.label for s in rec.segments if s.kind == "rotating"] if rec is not None else []
    model = ", ".join(str(m) for m in st.get("base_model") or []) or "not recorded"
    line = f"Fitted by the diagnose refit engine; base model: {model}"
    if st.get("with"):
        line += f"; added: {', '.join(map(str, st['with']))}"
    if cycles:
        line += f"; {len(cycles)} rotation cycles in the record ({', '.join(cycles)})"
    return line + "."


@register("turntable")
def turntable_sections(ctx: ReportContext):
    cal, st = ctx.cal, ctx.cal.stats
    text = [_summary_line(ctx)]
    if st.get("accel_noise_inflation", 1.0) > 1.0:
        text.append(f"The model did not explain the accelerometer data: noise widened "
                    f"x{st['accel_noise_inflation']:.1f}: an effect the data show is missing from "
                    "the model (`calib diagnose --method turntable` names it).")
    tables = []
    if "lever_arm" in cal.params and "lever_arm" not in (st.get("with") or []):
        s = np.asarray(cal.params["lever_arm"], float)
        sd = cal.sigma.get("lever_arm")
        sd = np.full(s.shape, np.nan) if sd is None else np.asarray(sd, dtype=float)
        labels = st.get("cycles", [str(i + 1) for i in range(len(s))])
        tables.append(Table("Lever arm of each cycle (mm, body axes; the component along the "
                            "table axis is fixed at 0).", ["cycle", "x", "y", "z"],
                            [[lab] + [f"{v * 1e3:+.2f} +- {e * 1e3:.2f}" for v, e in zip(r, q)]
                             for lab, r, q in zip(labels, s, sd)]))
    cpt = check_positions_table(st)
    if cpt is not None:
        tables.append(cpt)
    elif (st.get("check_positions") or {}).get("note"):
        # the check positions are static segments of the plan the fit did not use; the
        # |g| error of the summary is over the table's rests between rotations
        text.append("Check positions (static segments of the plan, not used by the fit): "
                    + st["check_positions"]["note"] + ".")
    figs = []
    if cal.tables.get("sigma_history_labels") is not None and len(cal.tables["sigma_history_labels"]):
        figs.append(FigureItem(
            "sigma-history", sigma_history_figure(cal),
            "1-sigma of each lever-arm component (lever_arm[cycle].axis) and proof-mass offset "
            "(p_ij) over the record, mm, log scale: the lever arms in blue (solid: the first "
            "free component of each cycle, dashed: the second; each drops in its own cycle, "
            "named at the top), the proof-mass offsets a colour each. "
            "What to look for: each curve drops when its cycle "
            "excites it (rotation about the orthogonal axis); a curve that stays high was not "
            "excited by the experiment."))
        if cal.tables.get("estimate_history") is not None:
            figs.append(FigureItem(
                "estimate-history", estimate_history_figure(cal),
                "Running estimate of each lever-arm component and proof-mass offset over the "
                "record (the filter's first pass, mm) with its +-1-sigma band, as in the "
                "rough-stand paper's fig. 4; a short bar at the right marks the final value. "
                "Each curve starts where its entry is determined (sigma below half its prior). What "
                "to look for: each estimate settles when its cycle excites it and stays inside "
                "its band afterwards; a later jump beyond the band points to a model error in "
                "that cycle. The final values come from the later passes, linearised about "
                "the first pass's result, and may differ from the first pass's end by more "
                "than its band on a MEMS unit."))
    res = cycle_residuals(ctx) if ctx.raw_kind in ("raw", "corrected") else []
    if res:
        figs.append(FigureItem(
            "residuals-time", residual_time_figure(res),
            f"Residuals of the corrected record against time ({BLOCK_S:g} s means), one colour "
            "per cycle. Top: |f| - g after removing the centripetal and tangential terms of "
            "each proof mass (mg). Bottom (where the record carries the table rate): the "
            "corrected rate along the fitted table axis minus the table rate and the earth "
            "rate (deg/h). What to look for: flat bands around zero of the width of the "
            "noise; a step at a rate change points to a time offset, a slope within a cycle "
            "to drift, a cycle offset from the others to a wrong lever arm or axis."))
        figs.append(FigureItem(
            "residuals-rate", residual_rate_figure(res),
            "The same residuals against the table rate (deg/s), one colour per cycle. What "
            "to look for: no trend with rate; a parabola in the |g| residual is a lever arm "
            "or proof-mass offset the model got wrong (w^2 r), a straight line in the rate "
            "residual a gyro scale error."))
    elif ctx.raw_path is None:
        text.append("Give the raw record as second argument (calib report CAL RAW --out DIR) "
                    "for the residuals against time and rate.")
    return Section("Rotating-table calibration", text=text, tables=tables, figures=figs)
