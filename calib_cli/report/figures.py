"""Figures for reports and `calib allan --plot` (matplotlib, headless).

Every function returns a matplotlib Figure built without pyplot (no global
state, no display); ``png_bytes`` renders it. Each figure has units on its
axes; the caption that says what to look for lives with the report section.
"""

from __future__ import annotations

import io

import matplotlib
import numpy as np
from cycler import cycler
from matplotlib.figure import Figure

from calib_cli.io.escape import mpl_text
from calib_cli.methods.allan import ARW_TAU, BI_FACTOR, RRW_TAU, AllanResult

DPI = 100

# Okabe & Ito's colour-blind-safe palette (Color Universal Design): every report
# figure cycles through it; lines beyond 8 also change their dash pattern, so
# no two curves of one axis share a look.
BLUE, VERMILION, GREEN, ORANGE = "#0072B2", "#D55E00", "#009E73", "#E69F00"
SKY, PURPLE, YELLOW, BLACK = "#56B4E9", "#CC79A7", "#F0E442", "#000000"
OKABE_ITO = [BLUE, VERMILION, GREEN, ORANGE, SKY, PURPLE, BLACK, YELLOW]
LINESTYLES = ["-", "--", ":", "-."]


def use_palette() -> None:
    """Make the Okabe-Ito colours the default cycle (figures made after this)."""
    matplotlib.rcParams["axes.prop_cycle"] = cycler(color=OKABE_ITO)


def line_style(k: int) -> dict:
    """Colour and dash of the k-th curve of an axis with many curves."""
    return {"color": OKABE_ITO[k % len(OKABE_ITO)],
            "ls": LINESTYLES[(k // len(OKABE_ITO)) % len(LINESTYLES)]}


use_palette()


def png_bytes(fig: Figure) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=DPI)
    return buf.getvalue()


def _groups(channels):
    """Channel indices grouped by sensor (the prefix before '_')."""
    out: dict[str, list[int]] = {}
    for i, c in enumerate(channels):
        out.setdefault(c.split("_")[0], []).append(i)
    return out


def allan_figure(res: AllanResult, title: str = "Allan deviation") -> Figure:
    """One log-log axis per sensor: every channel's overlapping Allan
    deviation with its confidence band, and the IEEE 952 lines (-1/2 slope
    through N at 1 s, the 0.664 B floor, +1/2 slope through K at 3 s)."""
    from calib_cli.report.format import allan_display

    groups = _groups(res.channels)
    fig = Figure(figsize=(6.4 * len(groups), 4.8), layout="constrained")
    axes = fig.subplots(1, len(groups), squeeze=False)[0]
    t = res.tau
    for ax, (sensor, idx) in zip(axes, groups.items(), strict=True):
        c, unit, _ = allan_display(res.units[idx[0]])
        for k, i in enumerate(idx):
            col = OKABE_ITO[k % len(OKABE_ITO)]
            ax.loglog(t, res.adev[:, i] * c, marker="o", ms=3, color=col,
                      label=mpl_text(res.channels[i]))
            ax.fill_between(t, res.adev_lo[:, i] * c, res.adev_hi[:, i] * c, color=col,
                            alpha=0.15, lw=0)
            N = res.terms["random_walk"]["value"][i]
            B = res.terms["bias_instability"]["value"][i]
            K = res.terms["rate_random_walk"]["value"][i]
            if np.isfinite(N):
                ax.loglog(t, c * N * np.sqrt(ARW_TAU / t), ls="--", lw=0.8, color=col)
            if np.isfinite(B):
                ax.axhline(c * BI_FACTOR * B, ls=":", lw=0.8, color=col)
            if np.isfinite(K):
                ax.loglog(t, c * K * np.sqrt(t / RRW_TAU), ls="-.", lw=0.8, color=col)
        lo = np.nanmin(res.adev_lo[:, idx]) * c
        hi = np.nanmax(res.adev_hi[:, idx]) * c
        ax.set_ylim(lo / 2, hi * 2)
        ax.set_xlabel("averaging time tau (s)")
        ax.set_ylabel(f"Allan deviation ({unit})")
        ax.set_title(mpl_text(f"{title}: {sensor}"))
        ax.grid(True, which="both", alpha=0.3)
        # what the thin lines are, in words, beside the channels
        ax.plot([], [], "k--", lw=0.8, label="white noise (slope -1/2)")
        ax.plot([], [], "k:", lw=0.8, label="bias instability floor")
        ax.plot([], [], "k-.", lw=0.8, label="rate random walk (slope +1/2)")
        ax.legend(fontsize=7)
    return fig


def detection_figure(t, accel, gyro, rep, title: str = "Static detection",
                     units: dict | None = None) -> Figure:
    """The signal with the detected static intervals shaded and numbered, and
    the detector's own statistic: the moving standard deviation of each axis
    over the window, in multiples of its noise floor (worst axis), against the
    threshold. A dip that stays above the line, or one shorter than the
    minimum duration, is an interval not found."""
    from calib_cli.methods.static_detect import moving_std

    t = np.asarray(t, float)
    accel = np.asarray(accel, float)
    dt = float(np.median(np.diff(t))) if len(t) > 1 else 1.0
    w = max(3, int(round(rep.window_s / dt)))
    stat = np.max(moving_std(accel, w) / rep.floor_accel, axis=1)
    if gyro is not None and rep.floor_gyro is not None:
        stat = np.maximum(stat, np.max(moving_std(gyro, w) / rep.floor_gyro, axis=1))
    step = max(1, len(t) // 20000)  # plot at most ~20k points per curve
    ts = t[::step] - t[0]
    rows = 3 if gyro is not None else 2
    fig = Figure(figsize=(11, 2.6 * rows + 0.6), layout="constrained")
    axs = fig.subplots(rows, 1, sharex=True)
    units = units or {}  # the recording's units: counts stay counts
    series = [(f"accelerometer ({units.get('accel') or 'm/s^2'})", accel)] + (
        [(f"gyro ({units.get('gyro') or 'rad/s'})", np.asarray(gyro, float))]
        if gyro is not None else [])
    for ax, (lab, x) in zip(axs, series, strict=False):
        for j in range(x.shape[1]):
            ax.plot(ts, x[::step, j], lw=0.7, color=OKABE_ITO[j % len(OKABE_ITO)],
                    label="xyz"[j] if x.shape[1] == 3 else str(j))
        ax.set_ylabel(lab)
        ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.005, 1.0), borderaxespad=0)
    axs[-1].semilogy(ts, stat[::step], lw=0.7, color=BLACK, label="moving std / floor")
    axs[-1].axhline(rep.multiplier, color=VERMILION, ls="--", lw=1,
                    label=f"threshold {rep.multiplier:g}x")
    axs[-1].set_ylabel(f"moving std over {rep.window_s:g} s\n(multiples of the floor)")
    axs[-1].legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.005, 1.0), borderaxespad=0)
    for k, (a, b) in enumerate(rep.intervals):
        for ax in axs:
            ax.axvspan(t[a] - t[0], t[b - 1] - t[0], color=GREEN, alpha=0.18, lw=0)
        axs[0].annotate(str(k + 1), ((t[a] + t[b - 1]) / 2 - t[0], 1.0),
                        xycoords=("data", "axes fraction"), ha="center", va="bottom",
                        fontsize=7)
    axs[-1].set_xlabel("time from the start (s); green: detected static intervals, numbered")
    axs[0].set_title(mpl_text(f"{title}: {len(rep.intervals)} intervals (window "
                              f"{rep.window_s:g} s, threshold {rep.multiplier:g}x, min "
                              f"{rep.min_duration_s:g} s)"), pad=14)
    return fig


def parameter_figure(items: list, title: str = "") -> Figure:
    """Any parameters with their 1-sigma, one panel per key: ``items`` is a list of
    (key, values, sigmas, file unit). Each entry is a point with its error bar in
    display units (calib_cli.model.display); a dimensionless matrix (K) is drawn as
    its deviation from the identity in ppm; 'fixed' entries (sigma 0) are hollow,
    unobservable ones (sigma not finite) are crosses without a bar."""
    from calib_cli.model.display import display_of, is_matrix

    n = max(len(items), 1)
    cols = min(n, 3)
    rows = -(-n // cols)
    fig = Figure(figsize=(min(4.2 * cols, 12.5), 2.9 * rows + 0.5), layout="constrained")
    axes = np.atleast_1d(fig.subplots(rows, cols, squeeze=False)).ravel()
    for ax, (key, val, sig, unit) in zip(axes, items):
        val = np.atleast_1d(np.asarray(val, float))
        sig = np.atleast_1d(np.asarray(sig, float))
        if sig.shape != val.shape:
            sig = np.full(val.shape, np.nan)
        mat = is_matrix(key, unit) and val.ndim == 2 and val.shape[0] == val.shape[1]
        names, ys, es, shown = [], [], [], ""
        for idx in np.ndindex(val.shape):
            f, u = display_of(key, unit, idx)
            v = val[idx] - (1.0 if mat and idx[0] == idx[1] else 0.0)
            f, u = (1e6, "ppm") if mat else (f, u)
            names.append(",".join(map(str, idx)) if val.ndim > 1 or len(val) > 1 else "")
            ys.append(v * f)
            es.append(sig[idx] * f)
            shown = shown if shown == u or not shown else "display units"
            shown = shown or u
        x = np.arange(len(ys))
        ys, es = np.asarray(ys), np.asarray(es)
        free = np.isfinite(es) & (es > 0)
        fixed = es == 0
        unobs = ~np.isfinite(es)
        ax.errorbar(x[free], ys[free], yerr=es[free], fmt="o", ms=4, color=BLUE, capsize=2,
                    label="value +- 1 sigma")
        if fixed.any():
            ax.plot(x[fixed], ys[fixed], "o", ms=4, mfc="none", color=BLACK, label="fixed")
        if unobs.any():
            ax.plot(x[unobs], np.nan_to_num(ys[unobs]), "x", ms=6, color=VERMILION,
                    label="unobservable")
        ax.axhline(0.0, color="0.5", lw=0.7)
        ax.set_xticks(x, [mpl_text(s) for s in names], fontsize=7,
                      rotation=45 if len(x) > 9 else 0)
        what = f"{key} - I" if mat else key
        ax.set_title(mpl_text(what), fontsize=9)
        ax.set_ylabel(mpl_text(shown or "-"))
        ax.grid(alpha=0.3)
        if fixed.any() or unobs.any():
            ax.legend(fontsize=6)
    for ax in axes[len(items):]:
        ax.set_visible(False)
    if title:
        fig.suptitle(mpl_text(title), fontsize=10)
    return fig
