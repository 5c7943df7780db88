"""Report sections of the thermal fit (docs/thermal.md): bias and scale versus
temperature per axis, the blocks' data and the fitted curve with its 1-sigma
band (heating and cooling branches marked), and |g| error versus temperature
before and after correction."""

from __future__ import annotations

import numpy as np
from matplotlib.figure import Figure

from calib_cli.model.effects import temp_poly
from calib_cli.report.builder import FigureItem, ReportContext, Section, Table, register
from calib_cli.report.figures import BLUE, ORANGE, VERMILION

MG = 1e3 / 9.80665
RAMP = 0.1 / 60.0  # degC/s: heating / cooling blocks (methods/thermal.py RAMP_RATE)


def _coef_cov(cal, key, axis, order):
    """Covariance (order x order) of row ``axis`` of a (3, N) / (3,) key."""
    idx = []
    for j, (k, flat) in enumerate(cal.cov_order):
        k = k.decode() if isinstance(k, bytes) else k
        if k == key and (int(flat) // order if order > 1 else int(flat)) == axis:
            idx.append(j)
    if len(idx) != order:
        return None
    C = np.asarray(cal.covariance, float)[np.ix_(idx, idx)]
    return C if np.all(np.isfinite(C)) else None


def curve_band(cal, key, axis, dT):
    """Fitted polynomial of row ``axis`` at dT and its 1-sigma (None where unknown)."""
    c = np.asarray(cal.params[key], float)
    c2 = c[:, None] if c.ndim == 1 else c
    order = c2.shape[1]
    y = temp_poly(c2[axis:axis + 1], dT)[:, 0]
    C = _coef_cov(cal, key, axis, order)
    if C is None:
        return y, None
    J = np.stack([dT ** (k + 1) for k in range(order)], axis=1)
    return y, np.sqrt(np.einsum("ni,ij,nj->n", J, C, J))


def _branches(rate):
    return {"heating": rate > RAMP, "cooling": rate < -RAMP,
            "steady": np.abs(rate) <= RAMP}


def sensor_figure(cal, sensor: str) -> Figure | None:
    t = cal.tables
    if f"block_{sensor}" not in t or f"{sensor}_temp_bias" not in cal.params:
        return None
    T = np.asarray(t["block_temp"], float)
    rate = np.asarray(t.get("block_rate", np.zeros_like(T)), float)
    y = np.asarray(t[f"block_{sensor}"], float)
    res = np.asarray(t[f"block_{sensor}_resid"], float)
    Tref = float(cal.stats.get("temp_ref_degC", 25.0))
    dT = T - Tref
    grid = np.linspace(T.min(), T.max(), 200) - Tref
    acc = sensor == "accel"
    fb, ub = (MG, "mg") if acc else (180 / np.pi * 3600, "deg/h")
    scale_ok = np.all(np.isfinite(np.asarray(cal.sigma.get(f"{sensor}_temp_scale", np.nan))))
    ncol = 2 if scale_ok else 1
    fig = Figure(figsize=(5.2 * ncol + 1.4, 7.5), layout="constrained")
    axes = np.atleast_2d(fig.subplots(3, ncol, sharex=True, squeeze=False))
    b0 = np.asarray(cal.params[f"{sensor}_bias"], float)
    for i in range(3):
        ax = axes[i, 0]
        model_b = temp_poly(np.atleast_2d(np.asarray(cal.params[f"{sensor}_temp_bias"],
                                                     float)).reshape(3, -1)[i:i + 1], dT)[:, 0]
        pts = b0[i] + model_b + res[:, i]
        for name, m in _branches(rate).items():
            if m.any():
                ax.plot(T[m], pts[m] * fb, ".", ms=3, label=name)
        yc, sc = curve_band(cal, f"{sensor}_temp_bias", i, grid)
        ax.plot(grid + Tref, (b0[i] + yc) * fb, "k-", lw=1, label="fit")
        if sc is not None:
            ax.fill_between(grid + Tref, (b0[i] + yc - sc) * fb, (b0[i] + yc + sc) * fb,
                            color="k", alpha=0.2, label="1 sigma")
        ax.set_ylabel(f"{'xyz'[i]} bias ({ub})")
        ax.grid(alpha=0.3)
        if scale_ok:
            ax2 = axes[i, 1]
            sT = np.asarray(cal.params[f"{sensor}_temp_scale"], float).reshape(3, -1)
            bT = np.asarray(cal.params[f"{sensor}_temp_bias"], float).reshape(3, -1)
            kf = (y[:, i] - b0[i] - temp_poly(bT[i:i + 1], dT)[:, 0]) / \
                (1 + temp_poly(sT[i:i + 1], dT)[:, 0])
            big = np.abs(kf) > 0.5 * np.abs(kf).max()
            sp = temp_poly(sT[i:i + 1], dT)[:, 0] + res[:, i] / np.where(big, kf, 1.0)
            for name, m in _branches(rate).items():
                if (m & big).any():
                    ax2.plot(T[m & big], sp[m & big] * 1e6, ".", ms=3, label=name)
            yc, sc = curve_band(cal, f"{sensor}_temp_scale", i, grid)
            ax2.plot(grid + Tref, yc * 1e6, "k-", lw=1)
            if sc is not None:
                ax2.fill_between(grid + Tref, (yc - sc) * 1e6, (yc + sc) * 1e6, color="k",
                                 alpha=0.2)
            ax2.set_ylabel(f"{'xyz'[i]} scale change (ppm)")
            ax2.grid(alpha=0.3)
    # beside the axes, never over the data
    fig.legend(*axes[0, 0].get_legend_handles_labels(), loc="outside right upper", fontsize=7)
    for ax in axes[-1]:
        ax.set_xlabel("temperature (degC)")
    fig.suptitle(f"{sensor}: bias{' and scale' if scale_ok else ''} versus temperature")
    return fig


def g_figure(cal) -> Figure | None:
    t = cal.tables
    if "block_accel" not in t:
        return None
    from calib_cli.methods.apply import apply_triad

    T = np.asarray(t["block_temp"], float)
    A = np.asarray(t["block_accel"], float)
    g = float(cal.stats.get("g_reference", 9.80665))
    f, _ = apply_triad(cal, A, None, temp=T)
    f0, _ = apply_triad(cal, A, None, temp=np.full(len(T), float(cal.stats.get("temp_ref_degC",
                                                                            25.0))))
    fig = Figure(figsize=(8.4, 4.0), layout="constrained")
    ax = fig.subplots()
    ax.plot(T, (np.linalg.norm(A, axis=1) - g) * MG, ".", ms=3, color=VERMILION, label="raw")
    ax.plot(T, (np.linalg.norm(f0, axis=1) - g) * MG, ".", ms=3, color=ORANGE,
            label="static correction only (T_ref)")
    ax.plot(T, (np.linalg.norm(f, axis=1) - g) * MG, ".", ms=3, color=BLUE,
            label="with the thermal terms")
    ax.axhline(0, color="k", lw=1)
    ax.set_xlabel("temperature (degC)")
    ax.set_ylabel("|f| - g (mg)")
    ax.set_title("|g| error versus temperature")
    ax.legend(fontsize=8, loc="upper left", bbox_to_anchor=(1.01, 1.0), borderaxespad=0)
    ax.grid(alpha=0.3)
    return fig


@register("thermal")
def thermal_sections(ctx: ReportContext):
    cal = ctx.cal
    st = cal.stats
    figs = []
    for s in ("accel", "gyro"):
        fig = sensor_figure(cal, s)
        if fig is not None:
            figs.append(FigureItem(
                f"thermal-{s}", fig,
                f"{s}: each point is a {st.get('block_s', 10):g} s block (its fit residual "
                "added to the fitted curve), marked heating, cooling or steady; the black "
                "line is the fitted polynomial with its 1-sigma band. What to look for: the "
                "points follow the curve within the noise; heating and cooling points on "
                "either side of it are hysteresis or a thermal lag (try --with thermal_lag)."))
    gf = g_figure(cal)
    if gf is not None:
        figs.append(FigureItem(
            "thermal-g-error", gf,
            "|f| - g per block: raw, corrected with the static part only (the model at T_ref), "
            "and corrected with the thermal terms. What to look for: the blue points flat at "
            "zero over the whole range."))
    rows = []
    for s in ("accel", "gyro"):
        h = (st.get("temp_hysteresis") or {}).get(s)
        hs = (st.get("temp_hysteresis_sigma") or {}).get(s)
        if h is not None and hs is not None:
            f, u = (MG, "mg") if s == "accel" else (180 / np.pi * 3600, "deg/h")
            rows.append([s] + [f"{a * f:+.4g} +- {b * f:.2g} {u}" for a, b in zip(h, hs)])
    tables = []
    if rows:
        hr = st.get("temp_hysteresis_range_degC") or [np.nan, np.nan]
        tables.append(Table("Hysteresis: mean residual heating minus cooling over "
                            f"{float(hr[0]):.1f} .. {float(hr[1]):.1f} degC.",
                            ["sensor", "x", "y", "z"], rows))
    rng = st.get("temp_range_degC") or [np.nan, np.nan]
    text = [f"Order {int(st.get('temp_order', 0))} in T - {float(st.get('temp_ref_degC', 25)):g} "
            f"degC, calibrated range {float(rng[0]):.1f} .. {float(rng[1]):.1f} degC, "
            f"{int(st.get('n_blocks', 0))} blocks, warm-up excluded "
            f"{float(st.get('warmup_excluded_s', 0)):.0f} s."]
    return Section("Thermal calibration", text=text, tables=tables, figures=figs)
