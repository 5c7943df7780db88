"""Rich rendering of results: parameters with sigma in engineering units."""

from __future__ import annotations

from rich.table import Table

from calib_cli.cli.common import Ctx, err_console
from calib_cli.model.display import (  # noqa: F401  (display_of re-exported)
    counts_note,
    display_of,
    entries,
    g_error_line,
    g_figures_line,
)


def params_table(params: dict, sigma: dict, units: dict, title: str = "parameters") -> Table:
    """Names, units and title come from files: shown through escape.term_text."""
    from calib_cli.io.escape import term_text

    tab = Table(title=term_text(title), show_lines=False)
    tab.add_column("parameter")
    tab.add_column("value +- 1 sigma")
    tab.add_column("unit")
    for e in entries(params, sigma, units):
        tab.add_row(term_text(e.name), e.value_sigma(), term_text(e.unit))
    return tab


def render_summary(res) -> None:
    """A short terminal summary of a fit (stderr; silent with --quiet)."""
    if Ctx.quiet:
        return
    err_console.print(params_table(res.params, res.sigma, res.units,
                                   title=f"calibration ({res.method})"))
    st = res.stats
    line = g_error_line(st)
    if line:
        err_console.print(line, markup=False)
        if g_figures_line(st):
            err_console.print(g_figures_line(st), markup=False)
    note = counts_note(res.params, res.units)
    if note:
        err_console.print(note, markup=False)
    if st.get("unobservable"):
        err_console.print(f"[yellow]unobservable:[/] {', '.join(st['unobservable'])}")
    if st.get("sigma_inflation", 1.0) != 1.0:
        err_console.print(f"[yellow]sigma inflated by sqrt({st['sigma_inflation']:.2f}):[/] the "
                          "residuals scatter more than the noise explains")
