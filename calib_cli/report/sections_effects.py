"""One report section per effect a fit added to its method's base model (`calib
fit METHOD --with EFFECT`, the steps of a diagnosis), each with its figure:

- input-output curves (accel_nonlinearity, scale_asymmetry, misalignment,
  g_sensitivity, temperature_drift): what the effect adds to each channel's
  reading over a sweep of its input, computed by the calibration's own forward
  model (``ImuModel.predict`` with and without the effect), with the 1-sigma
  band of the fitted entries propagated through the same model (their
  covariance, by finite differences);
- the geometry of lever arms and proof-mass offsets (mm, three projections);
- the noise-model terms (bias random walk, bias instability) with their sigma.

An effect not listed here gets ``report.generic.effect_section``.
"""

from __future__ import annotations

import numpy as np
from matplotlib.figure import Figure

from calib_cli.io.escape import mpl_text
from calib_cli.model.display import DPH, MG, data_units
from calib_cli.report.builder import register_effect
from calib_cli.report.figures import OKABE_ITO, parameter_figure
from calib_cli.report.generic import CAPTION, describe_effect, entry_table
from calib_cli.report.items import AddedEffect, FigureItem, ReportContext, Section

AX = "xyz"
N_SWEEP = 61


def _models(cal, eff: AddedEffect):
    """(the calibration's model, the same without this effect)."""
    from calib_cli.model.imu_model import ImuModel
    from calib_cli.model.truth import effect_from_description

    effs = [effect_from_description(d) for d in cal.model]
    without = [e for e in effs if not (e.name == eff.name and
                                       (not eff.sensor or e.sensor == eff.sensor))]
    return ImuModel(tuple(effs), cal.layout), ImuModel(tuple(without), cal.layout)


def _kin(f=None, w=None, temp=None, n=N_SWEEP):
    from calib_cli.model.kinematics import Kinematics

    z = np.zeros((n, 3))
    return Kinematics(np.arange(n) * 0.01, z if f is None else f, z if w is None else w, z,
                      temp=temp)


def _free_entries(cal, keys):
    """[(column of the covariance, key, flat index)] of the keys' free entries."""
    out = []
    for j, (k, flat) in enumerate(cal.cov_order):
        k = k.decode() if isinstance(k, bytes) else str(k)
        if k in keys:
            out.append((j, k, int(flat)))
    return out


def response(cal, eff: AddedEffect, kin, sensor: str):
    """(y, sd): what the effect adds to ``sensor``'s readings (N, n) in data units over
    the kinematics, and its 1-sigma from the covariance of the effect's entries (None
    where the file holds no finite covariance for them)."""
    full, without = _models(cal, eff)
    p = {k: np.asarray(v, float) for k, v in cal.params.items()}

    def contrib(q):
        return (full.predict(q, kin, sensors=(sensor,))[sensor]
                - without.predict(q, kin, sensors=(sensor,))[sensor])

    y = contrib(p)
    free = _free_entries(cal, eff.keys)
    C = np.asarray(cal.covariance, float)
    if not free or C.size == 0:
        return y, None
    cols = [j for j, _, _ in free]
    Cs = C[np.ix_(cols, cols)]
    ok = np.all(np.isfinite(Cs), axis=0) & np.all(np.isfinite(Cs), axis=1)
    if not ok.any():
        return y, None
    J = []
    for (j, k, flat), good in zip(free, ok):
        if not good:
            continue
        h = max(float(np.sqrt(max(C[j, j], 0.0))), 1e-12)
        q = dict(p)
        v = np.array(q[k], float)
        v.flat[flat] += h
        q[k] = v
        J.append((contrib(q) - y) / h)
    J = np.stack(J, axis=-1)  # (N, n, m)
    Cg = Cs[np.ix_(ok, ok)]
    var = np.einsum("xni,ij,xnj->xn", J, Cg, J)
    return y, np.sqrt(np.clip(var, 0.0, None))


def _display(cal, sensor: str, y) -> tuple[float, str]:
    """Display factor and unit of a sensor's reading: counts stay counts; SI
    accelerometers in mg (ug when the effect stays below 0.05 mg), gyros in deg/h."""
    u = data_units(cal.units)[sensor]
    if "count" in u:
        return 1.0, u
    if sensor == "accel":
        small = np.nanmax(np.abs(y)) * MG < 0.05 if np.size(y) else False
        return (MG * 1e3, "ug") if small else (MG, "mg")
    return DPH, "deg/h"


def _curve_panels(cal, eff, panels, sensor, xlabel, title) -> Figure:
    """panels: [(panel title, x values, kinematics, its main channel or -1)]; one line
    per output channel that the effect moves, with its 1-sigma band."""
    res = [(name, x, *response(cal, eff, kin, sensor), main) for name, x, kin, main in panels]
    allys = np.concatenate([r[2].ravel() for r in res]) if res else np.zeros(1)
    f, unit = _display(cal, sensor, allys)
    top = float(np.nanmax(np.abs(allys))) if allys.size else 0.0
    fig = Figure(figsize=(4.0 * len(res) + 1.6, 3.6), layout="constrained")
    axes = np.atleast_1d(fig.subplots(1, len(res), sharey=True))
    n = res[0][2].shape[1] if res else 0
    for ax, (name, x, y, sd, main) in zip(axes, res):
        for ch in range(n):
            if top > 0 and np.max(np.abs(y[:, ch])) < 1e-3 * top and ch != main:
                continue  # a channel this input does not move
            col = OKABE_ITO[ch % len(OKABE_ITO)]
            lab = f"{sensor} {AX[ch] if n == 3 else ch}"
            ax.plot(x, y[:, ch] * f, color=col, lw=1.3, label=mpl_text(lab))
            if sd is not None:
                ax.fill_between(x, (y[:, ch] - sd[:, ch]) * f, (y[:, ch] + sd[:, ch]) * f,
                                color=col, alpha=0.18, lw=0)
        ax.axhline(0.0, color="0.5", lw=0.7)
        ax.set_title(mpl_text(name), fontsize=9)
        ax.set_xlabel(mpl_text(xlabel))
        ax.grid(alpha=0.3)
    axes[0].set_ylabel(mpl_text(f"added to the reading ({unit})"))
    handles = {}
    for ax in axes:  # every channel drawn in any panel, once
        for h, lab in zip(*ax.get_legend_handles_labels()):
            handles.setdefault(lab, h)
    fig.legend(list(handles.values()), list(handles), loc="outside right upper", fontsize=7)
    fig.suptitle(mpl_text(title), fontsize=10)
    return fig


def _single_panel(cal, sensor, x, y, sd, xlabel, title) -> Figure:
    """One axis: a line per channel with its 1-sigma band."""
    f, unit = _display(cal, sensor, y)
    fig = Figure(figsize=(8.0, 4.0), layout="constrained")
    ax = fig.subplots()
    n = y.shape[1]
    for ch in range(n):
        col = OKABE_ITO[ch % len(OKABE_ITO)]
        ax.plot(x, y[:, ch] * f, color=col, lw=1.3,
                label=mpl_text(f"{sensor} {AX[ch] if n == 3 else ch}"))
        if sd is not None:
            ax.fill_between(x, (y[:, ch] - sd[:, ch]) * f, (y[:, ch] + sd[:, ch]) * f,
                            color=col, alpha=0.18, lw=0)
    ax.axhline(0.0, color="0.5", lw=0.7)
    ax.set_xlabel(mpl_text(xlabel))
    ax.set_ylabel(mpl_text(f"added to the reading ({unit})"))
    ax.grid(alpha=0.3)
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.02, 1.0), borderaxespad=0)
    ax.set_title(mpl_text(title), fontsize=10)
    return fig


def _g(cal) -> float:
    return float(cal.stats.get("g_reference") or 9.80665)


def _max_rate(ctx) -> float:
    """The largest rate of the record (rad/s), else 200 deg/s."""
    rec = ctx.recording()
    if rec is not None and rec.gyro is not None and rec.units.get("gyro") == "rad/s":
        return max(float(np.nanmax(np.abs(rec.gyro))), np.radians(10.0))
    return np.radians(200.0)


def _input_sweep(ctx, eff, in_sensor: str, out_sensor: str) -> Figure:
    cal = ctx.cal
    if in_sensor == "accel":
        g = _g(cal)
        u = np.linspace(-1.2 * g, 1.2 * g, N_SWEEP)
        x, xl = u / g, "specific force along the axis (g)"
    else:
        r = _max_rate(ctx)
        u = np.linspace(-r, r, N_SWEEP)
        x, xl = np.degrees(u), "rate about the axis (deg/s)"
    panels = []
    for i in range(3):
        v = np.zeros((N_SWEEP, 3))
        v[:, i] = u
        kin = _kin(f=v) if in_sensor == "accel" else _kin(w=v)
        panels.append((f"input along {AX[i]}", x, kin, i if cal.layout.n == 3 else -1))
    return _curve_panels(cal, eff, panels, out_sensor, xl,
                         f"{eff.with_arg}: what it adds to the {out_sensor} readings")


_CURVE_CAPTION = {
    "accel_nonlinearity": "The second-order term k2 u^2 of each accelerometer over its input "
    "(+-1.2 g), from the calibration's model, with its 1-sigma band. What to look for: a "
    "parabola well outside its band is a real nonlinearity; a band that covers zero means "
    "the data do not determine it (add positions at 0 g and at 35-55 deg tilt).",
    "scale_asymmetry": "The scale asymmetry: a different scale factor for positive and "
    "negative inputs (a kink at zero), with its 1-sigma band. What to look for: the two "
    "branches should differ by more than the band; otherwise the effect is not needed.",
    "misalignment": "What the fitted misalignment adds to each channel for an input along "
    "each axis (cross-axis readings), with their 1-sigma bands. What to look for: straight "
    "lines whose slope is the misalignment; a slope within its band is not determined.",
    "g_sensitivity": "The gyro reading caused by the specific force along each axis "
    "(g-sensitivity D f), with its 1-sigma band. What to look for: a slope outside the band "
    "on some gyro is a real g-sensitivity (deg/h per g); apply it where the unit sees "
    "changing gravity.",
}


@register_effect("accel_nonlinearity", "scale_asymmetry", "misalignment", "g_sensitivity")
def curve_section(ctx: ReportContext, eff: AddedEffect) -> Section:
    cal = ctx.cal
    if eff.name == "g_sensitivity":
        fig = _input_sweep(ctx, eff, "accel", "gyro")
    else:
        s = eff.sensor or "accel"
        fig = _input_sweep(ctx, eff, s, s)
    return Section(f"Added effect: {eff.with_arg}", text=[describe_effect(cal, eff)],
                   tables=[entry_table(cal, eff.keys, f"Parameters of {eff.with_arg}.")],
                   figures=[FigureItem(f"effect-{eff.name}", fig, _CURVE_CAPTION[eff.name])])


@register_effect("temperature_drift")
def thermal_section(ctx: ReportContext, eff: AddedEffect) -> Section:
    """The thermal curve: what the drift adds to each channel over the recorded
    temperatures (accelerometers with +1 g along their axis, so the scale part
    shows; gyros at rest)."""
    cal = ctx.cal
    s = eff.sensor or "accel"
    lo, hi = _temp_range(ctx, eff)
    T = np.linspace(lo, hi, N_SWEEP)
    # each accelerometer of a triad with +1 g along its own axis (the scale part shows),
    # a redundant unit level (z up); gyros at rest
    n = cal.layout.n
    ys, sds = [], []
    for i in range(3 if n == 3 else 1):
        v = np.zeros((N_SWEEP, 3))
        if s == "accel":
            v[:, i if n == 3 else 2] = _g(cal)
        y, sd = response(cal, eff, _kin(f=v, temp=T), s)
        chans = [i] if n == 3 else list(range(n))
        ys.append(y[:, chans])
        sds.append(None if sd is None else sd[:, chans])
    y = np.concatenate(ys, axis=1)
    sd = None if any(x is None for x in sds) else np.concatenate(sds, axis=1)
    fig = _single_panel(cal, s, T, y, sd, "temperature (degC)",
                        f"{eff.with_arg}: thermal curve over {lo:.1f} .. {hi:.1f} degC"
                        + (", each axis at +1 g" if s == "accel" and n == 3 else ""))
    cap = ("What the temperature drift adds to each channel over the recorded temperatures "
           "(bias and, for accelerometers at +1 g, scale), zero at the reference temperature "
           f"{float(eff.desc.get('temp_ref', 25.0)) if eff.desc else 25.0:g} degC, with its "
           "1-sigma band. What to look for: a curve outside its band over the range is a real "
           "drift; beyond the recorded range the polynomial is an extrapolation.")
    return Section(f"Added effect: {eff.with_arg}", text=[describe_effect(cal, eff)],
                   tables=[entry_table(cal, eff.keys, f"Parameters of {eff.with_arg}.")],
                   figures=[FigureItem("effect-temperature-drift", fig, cap)])


def _temp_range(ctx, eff) -> tuple[float, float]:
    rng = ctx.cal.stats.get("temp_range_degC")
    if isinstance(rng, (list, tuple)) and len(rng) == 2 and np.all(np.isfinite(rng)) \
            and rng[1] > rng[0]:
        return float(rng[0]), float(rng[1])
    rec = ctx.recording()
    if rec is not None and rec.temp is not None and np.ptp(rec.temp) > 0.1:
        return float(np.nanmin(rec.temp)), float(np.nanmax(rec.temp))
    ref = float(eff.desc.get("temp_ref", 25.0)) if eff.desc else 25.0
    return ref - 20.0, ref + 20.0


@register_effect("lever_arm", "proof_mass_offsets")
def geometry_section(ctx: ReportContext, eff: AddedEffect) -> Section:
    """Where the accelerometers sit: the lever arm of each rotating cycle (from the
    table axis to the triad) and the proof-mass offsets of the three accelerometers,
    in three projections, mm, with 1-sigma bars."""
    cal = ctx.cal
    key = eff.keys[0] if eff.keys else eff.name
    pts = np.asarray(cal.params.get(key, np.zeros((0, 3))), float).reshape(-1, 3)
    sd = np.asarray(cal.sigma.get(key, np.full(pts.shape, np.nan)), float).reshape(-1, 3)
    if key == "lever_arm":
        labels = _cycle_labels(ctx, len(pts))
        what = "lever arm of each rotating cycle"
    else:
        labels = [f"accel {AX[i]}" for i in range(len(pts))]
        what = "proof-mass offset of each accelerometer"
    fig = Figure(figsize=(12, 4.0), layout="constrained")
    axes = fig.subplots(1, 3)
    for ax, (a, b) in zip(axes, ((0, 1), (0, 2), (1, 2))):
        for k, (p, s) in enumerate(zip(pts, sd)):
            col = OKABE_ITO[k % len(OKABE_ITO)]
            ax.errorbar(p[a] * 1e3, p[b] * 1e3, xerr=np.nan_to_num(s[a]) * 1e3,
                        yerr=np.nan_to_num(s[b]) * 1e3, fmt="o", ms=5, color=col, capsize=2,
                        label=mpl_text(labels[k]))
        ax.plot(0, 0, "+", color="k", ms=10)
        ax.set_xlabel(f"body {AX[a]} (mm)")
        ax.set_ylabel(f"body {AX[b]} (mm)")
        ax.set_aspect("equal", adjustable="datalim")
        ax.grid(alpha=0.3)
    axes[-1].legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.02, 1.0), borderaxespad=0)
    fig.suptitle(mpl_text(f"{eff.with_arg}: {what}, body axes"), fontsize=10)
    cap = (f"The {what} in three projections of the body axes (mm; +: the origin, the "
           "table axis for lever arms, the triad's reference point for proof masses), with "
           "1-sigma bars. What to look for: bars much smaller than the distances; a lever "
           "arm that differs between cycles by more than its bars is expected only when the "
           "unit was re-mounted; a component along a cycle's table axis is fixed at 0 (it "
           "cannot be seen).")
    return Section(f"Added effect: {eff.with_arg}", text=[describe_effect(cal, eff)],
                   tables=[entry_table(cal, eff.keys, f"Parameters of {eff.with_arg}.")],
                   figures=[FigureItem(f"effect-{eff.name.replace('_', '-')}", fig, cap)])


def _cycle_labels(ctx, n: int) -> list:
    names = list(ctx.cal.stats.get("cycles") or [])
    if len(names) != n:
        rec = ctx.recording()
        if rec is not None:
            names = [s.label for s in rec.segments if s.kind == "rotating"]
    return names if len(names) == n else [f"cycle {k + 1}" for k in range(n)]


@register_effect("bias_random_walk", "bias_instability")
def noise_model_section(ctx: ReportContext, eff: AddedEffect) -> Section:
    """A wandering bias is a noise-model term: never applied or exported; its figure
    (stats.noise_model) with its sigma."""
    from calib_cli.model.display import catalogue_specs

    cal = ctx.cal
    nm = cal.stats.get("noise_model") or {}
    items = []
    for entry in nm.values():
        if not isinstance(entry, dict):
            continue
        for k, v in (entry.get("params") or {}).items():
            if eff.name == "bias_random_walk" and not k.endswith("_rw"):
                continue
            if eff.name == "bias_instability" and k.endswith("_rw"):
                continue
            if eff.sensor and not k.startswith(eff.sensor):
                continue
            spec = catalogue_specs().get(k)
            sg = (entry.get("sigma") or {}).get(k)
            sg = np.full(np.shape(v), np.nan) if sg is None else \
                np.array([np.nan if x is None else x for x in sg], float)
            items.append((k, np.asarray(v, float), sg, spec.unit if spec else ""))
    text = [f"{eff.with_arg} is a noise-model term: the deterministic parameters were "
            "refitted under its whitening (their sigma widens); it is never applied or "
            "exported."]
    if not items:
        text.append("The fitted figure is not in this file.")
        from calib_cli.report.generic import base_parameter_figure

        return Section(f"Added effect: {eff.with_arg}", text=text,
                       figures=[base_parameter_figure(ctx, [])])
    return Section(f"Added effect: {eff.with_arg}", text=text, figures=[FigureItem(
        f"effect-{eff.name.replace('_', '-')}", parameter_figure(
            items, f"{eff.with_arg}: the fitted wander per channel"), CAPTION)])


