"""Report sections of the two-position alignment (method align) and of the
redundant-unit fit (method rimu): residuals per position and, for a RIMU, each
sensor's fitted errors with their 1-sigma bars."""

from __future__ import annotations

import numpy as np
from matplotlib.figure import Figure

from calib_cli.model.display import data_units, num
from calib_cli.report.builder import FigureItem, ReportContext, Section, Table, register
from calib_cli.report.sections_static import MG, residual_figure
from calib_cli.units import SUFFIXES

UG = MG * 1e3  # m/s^2 -> micro-g
DPH = 1.0 / SUFFIXES["_dph"]  # rad/s -> deg/h
DPS = 1.0 / SUFFIXES["_dps"]  # rad/s -> deg/s


def _labels(ctx: ReportContext, n: int) -> list:
    labels = list(ctx.cal.tables.get("segment_labels", []))
    return labels if len(labels) == n else [str(i + 1) for i in range(n)]


def _residual_items(ctx: ReportContext, units: dict, hint: str) -> list:
    """One residual figure per sensor kind found in the calibration (in the recorded
    units where those are counts)."""
    items = []
    du = data_units(ctx.cal.units)
    for sensor, (scale, unit) in units.items():
        if "count" in du[sensor]:
            scale, unit = 1.0, du[sensor]
        r = ctx.cal.residuals.get(f"{sensor}_segment")
        if r is None or np.ndim(r) != 2:
            continue
        items.append(FigureItem(
            f"{sensor}-residuals",
            residual_figure(_labels(ctx, len(r)), r, scale, unit, f"{sensor}: "),
            f"Residuals of the {sensor} segment means (measured minus model), in {unit}. "
            f"What to look for: {hint}"))
    return items


def _static_align_section(ctx: ReportContext):
    """--method static: no turn; conditioning and every position's attitude."""
    st = ctx.cal.stats
    deg = st.get("degeneracy")
    text = [f"{_positions(ctx)} static positions, no turn used (static-only "
            "alignment: both attitudes and the six biases from the static equations).",
            f"Condition number of the equations (normalised units) "
            f"{num(st.get('condition_number'), 3)}, limit {num(st.get('condition_max'), 3)}"
            + (f": degenerate, {deg}." if deg else ": well conditioned, no degeneracy."),
            _earth_rate_line(st) + "."]
    labels = _labels(ctx, len(st.get("attitudes_all", [])))
    rows = []
    for lab, att, sig in zip(labels, st.get("attitudes_all", []),
                             st.get("attitudes_all_sigma", []), strict=False):
        rows.append([lab] + [f"{np.degrees(a):.4f} +- "
                             + ("unobservable" if s is None else f"{np.degrees(s):.4f}")
                             for a, s in zip(att, sig, strict=False)])
    tables = [Table("Attitude of every position, deg, with 1 sigma.",
                    ["position", "roll", "pitch", "yaw"], rows)] if rows else []
    return Section("Static-only alignment", text=text, tables=tables, figures=[])


def _positions(ctx: ReportContext) -> str:
    """The number of static positions: the fit's statistic, else the record's."""
    n = ctx.cal.stats.get("n_positions")
    if n is None:
        rec = ctx.recording()
        n = sum(1 for s in rec.segments if s.kind == "static") if rec is not None else None
    return "The" if n is None else str(n)


def _earth_rate_line(st: dict) -> str:
    used = st.get("earth_rate_used")
    why = f" ({st['grade_check']})" if st.get("grade_check") else ""
    if used is None:
        return "Fitted by the diagnose refit engine (the earth rate in the gyro equations)"
    return ("The gyros resolve the earth rate: it gives the heading" if used else
            "The gyros cannot resolve the earth rate (15 deg/h): it is treated as noise and "
            "the heading is not determined") + why


@register("align", "align-classic")
def align_sections(ctx: ReportContext):
    st = ctx.cal.stats
    if st.get("method") == "static":
        return _static_align_section(ctx)
    text = [f"{_positions(ctx)} static positions"
            + (f"; {st['observability']}." if st.get("observability") else "."),
            _earth_rate_line(st) + f"; chi-square per degree of freedom "
            f"{num(st.get('chi2_dof'), 3)}."]
    rows = [[r.get("from", ""), r.get("to", ""), r.get("source", ""),
             f"{np.degrees(float(r.get('angle', np.nan))):.3f}",
             " ".join(f"{v:+.4f}" for v in r.get("axis_body", []))] for r in st.get("rotations", [])]
    tables = [Table("Rotations between the positions (body axes of the first position).",
                    ["from", "to", "source", "angle (deg)", "axis (body)"], rows)] if rows else []
    direct = st.get("direct_readings") or []
    if direct:
        tables.append(Table(
            "Special attitudes: an axis within a few degrees of the vertical reads its bias "
            "directly (mean minus the gravity or earth-rate component).",
            ["position", "sensor", "axis", "bias", "tilt (deg)"],
            [[d["position"], d["sensor"], "xyz"[int(d["axis"])],
              f"{d['bias'] * (UG if d['sensor'] == 'accel' else DPH):+.2f} "
              f"{'ug' if d['sensor'] == 'accel' else 'deg/h'}", f"{d['tilt_deg']:.2f}"]
             for d in direct]))
    figs = _residual_items(ctx, {"accel": (UG, "micro-g"), "gyro": (DPH, "deg/h")},
                           "with two positions and 9 unknowns the residuals are small by "
                           "construction (3 degrees of freedom); compare them with the noise of "
                           "the segment means, not with zero.")
    return Section("Two-position alignment", text=text, tables=tables, figures=figs)


def _sensor_figure(cal, sensor: str) -> Figure:
    """Per sensor: scale error (ppm) and installation-angle errors dEl, dAz (mrad) with 1 sigma."""
    fig = Figure(figsize=(7.0, 5.0), layout="constrained")
    ax1, ax2 = fig.subplots(2, 1, sharex=True)
    ks = np.asarray(cal.params[f"{sensor}_scale_error"], float)
    x = np.arange(len(ks))  # 0-based, as the tables, the residual legend and rimu-check
    s_ks = np.asarray(cal.sigma.get(f"{sensor}_scale_error", ks * np.nan), float)
    ax1.errorbar(x, ks * 1e6, yerr=np.nan_to_num(s_ks) * 1e6, fmt="o", capsize=3)
    ax1.set_ylabel("scale error (ppm)")
    ax1.set_title(f"{sensor}: fitted errors of each sensor (bars: 1 sigma)")
    for name, off, mark in (("dEl", -0.1, "s"), ("dAz", 0.1, "^")):
        v = np.asarray(cal.params[f"{sensor}_{name}"], float) * 1e3
        s = np.asarray(cal.sigma.get(f"{sensor}_{name}", v * np.nan), float) * 1e3
        ax2.errorbar(x + off, v, yerr=np.nan_to_num(s), fmt=mark, capsize=3, label=name)
    ax2.set_ylabel("installation error (mrad)")
    ax2.set_xlabel("sensor (0-based, as in rimu-check)")
    ax2.set_xticks(x)
    ax2.legend(fontsize=8)
    for ax in (ax1, ax2):
        ax.axhline(0, color="k", lw=1)
        ax.grid(alpha=0.3)
    return fig


@register("rimu")
def rimu_sections(ctx: ReportContext):
    cal, st = ctx.cal, ctx.cal.stats
    n_pos = _positions(ctx)
    text = [f"{cal.layout.n} sensors of each kind, {n_pos.lower()} positions"
            + (f" ({', '.join(st['positions'])})." if st.get("positions") else ".")]
    rows = []
    for sensor, scale, unit in (("accel", MG, "mg"), ("gyro", DPS, "deg/s")):
        pred = st.get(f"{sensor}_body_error_predicted")
        if pred is not None:
            rows.append([sensor, f"{float(st.get(f'{sensor}_body_error_input', np.nan)) * scale:.4g} {unit}",
                         " / ".join(f"{v * scale:.3g}" for v in pred) + f" {unit}"])
    tables = [Table("Error the calibration itself leaves in the body-frame estimate (1 sigma, "
                    "RMS over the sphere of input directions, per body axis).",
                    ["sensor", "input magnitude", "x / y / z"], rows)] if rows else []
    figs = [FigureItem(f"{s}-sensors", _sensor_figure(cal, s),
                       f"The {s} sensors' scale errors and installation-angle errors with 1-sigma "
                       "bars. What to look for: a sensor whose bars are far wider than the others' "
                       "is poorly excited by the positions (or unobservable: no bar).")
            for s in ("accel", "gyro") if f"{s}_scale_error" in cal.params]
    figs += _residual_items(ctx, {"accel": (MG, "mg"), "gyro": (DPS, "deg/s")},
                            "scatter like the noise of the segment means; one sensor standing out "
                            "in every position suggests a fault (see `calib rimu-check`).")
    return Section("Redundant unit", text=text, tables=tables, figures=figs)
