"""Rich rendering of results: parameters with sigma in engineering units."""

from __future__ import annotations

import numpy as np
from rich.table import Table

from calib_cli.cli.common import Ctx, err_console
from calib_cli.model.display import DISPLAY, display_of  # noqa: F401  (re-exported)
from calib_cli.units import g_figures_line


def fmt_value(v: float, s: float | None, factor: float, matrix_key: bool) -> str:
    if s is None or not np.isfinite(s):
        sig = "unobservable"
    elif s == 0:
        sig = "fixed"
    elif matrix_key:
        sig = f"+- {s * 1e6:.3g} ppm"
    else:
        sig = f"+- {s * factor:.3g}"
    return f"{v * factor:.7g}  {sig}"


def params_table(params: dict, sigma: dict, units: dict, title: str = "parameters") -> Table:
    """Names, units and title come from files: shown through escape.term_text."""
    from calib_cli.io.escape import term_text

    tab = Table(title=term_text(title), show_lines=False)
    tab.add_column("parameter")
    tab.add_column("value +- 1 sigma")
    tab.add_column("unit")
    for key, val in params.items():
        val = np.asarray(val, dtype=float)
        sig = np.asarray(sigma.get(key, np.full(val.shape, np.nan)), dtype=float)
        factor, unit = display_of(key, units.get(key, ""))
        matrix_key = key.endswith("_K") and "count" not in units.get(key, "")
        if val.ndim == 0:
            tab.add_row(term_text(key), fmt_value(float(val), float(sig), factor, False),
                        term_text(unit))
            continue
        for idx in np.ndindex(val.shape):
            name = f"{key}[{','.join(map(str, idx))}]"
            tab.add_row(term_text(name), fmt_value(val[idx], sig[idx], factor, matrix_key),
                        term_text(unit) if not matrix_key else "-")
    return tab


def render_summary(res) -> None:
    """A short terminal summary of a fit (stderr; silent with --quiet)."""
    if Ctx.quiet:
        return
    err_console.print(params_table(res.params, res.sigma, res.units,
                                   title=f"calibration ({res.method})"))
    st = res.stats
    if "g_error_rms_after" in st and st["g_error_rms_after"] is not None:
        before = st.get("g_error_rms_before")
        b = "n/a (counts)" if before is None else f"{before * 1e3 / 9.80665:.3f} mg"
        floor = st.get("g_error_floor")
        floor = "" if floor is None else f" (noise floor {floor * 1e3 / 9.80665:.4f} mg)"
        err_console.print(f"|g| error RMS: before {b}, after "
                          f"{st['g_error_rms_after'] * 1e3 / 9.80665:.4f} mg{floor}")
        if g_figures_line(st):
            err_console.print(g_figures_line(st))
    if st.get("unobservable"):
        err_console.print(f"[yellow]unobservable:[/] {', '.join(st['unobservable'])}")
    if st.get("sigma_inflation", 1.0) != 1.0:
        err_console.print(f"[yellow]sigma inflated by sqrt({st['sigma_inflation']:.2f}):[/] the "
                          "residuals scatter more than the noise explains")
