"""calib history DIR --unit SERIAL [--plot FILE.png] [--json]: a unit's parameters over time."""

from __future__ import annotations

import click
import numpy as np
from rich.table import Table

from calib_cli.cli.common import out_console, print_json
from calib_cli.cli.main import cli
from calib_cli.errors import InputError
from calib_cli.io.escape import mpl_text, term_text
from calib_cli.model.display import display_of, sigma_entries

COMPLETE_COMMAND = True  # every subcommand lives here: loaded alone (cli/main.py)


def _keys(entries) -> list[str]:
    keys: list[str] = []
    for e in entries:
        keys += [k for k in e.params if k not in keys]
    return keys


def _when(e) -> str:
    """'2026-05-01 14:03' from the ISO time stamps of an entry (recorded, else created);
    the file's name when it has neither."""
    for stamp in (e.recorded_utc, e.created_utc):
        if stamp and len(stamp) >= 16 and stamp[4] == "-":
            return f"{stamp[:10]} {stamp[11:16]}"
    return e.rel


def _plot(entries, keys, path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from calib_cli.io.h5 import atomic_path
    from calib_cli.io.history import element_names
    from calib_cli.report.figures import use_palette

    use_palette()  # the Okabe-Ito colour-blind-safe cycle of every calib figure

    fig, axes = plt.subplots(len(keys), 1, figsize=(8, 2.6 * len(keys)), squeeze=False,
                             sharex=True)
    x = np.arange(len(entries))
    for ax, key in zip(axes[:, 0], keys, strict=True):
        have = [i for i, e in enumerate(entries) if key in e.params]
        first = entries[have[0]]
        matrix = np.ndim(first.params[key]) == 2
        factor, unit = display_of(key, first.units.get(key, ""))
        if matrix:
            factor, unit = 1e6, "ppm"
        v = np.array([np.ravel(entries[i].params[key]) for i in have])
        s = np.array([np.ravel(entries[i].sigma.get(key, np.full(np.size(first.params[key]),
                                                                  np.nan))) for i in have])
        names = element_names(key, np.shape(first.params[key]))
        for j, name in enumerate(names):
            if np.all(s[:, j] == 0):
                continue  # fixed by convention
            ax.errorbar(x[have], (v[:, j] - v[0, j]) * factor, yerr=s[:, j] * factor, marker="o",
                        ms=3, capsize=2, label=mpl_text(name))
        ax.set_ylabel(mpl_text(f"{key}") + f"\nchange [{mpl_text(unit)}]")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=6, ncol=3, loc="best")
    # the date of each calibration (its record's, else the fit's; UTC); the serial comes
    # from the archive: shown through the escaper
    # numbered: two calibrations of one minute stay apart
    axes[-1, 0].set_xticks(x, [f"#{i + 1} " + mpl_text(_when(e)) for i, e in enumerate(entries)],
                           rotation=60, ha="right", fontsize=6)
    recorded = sum(bool(e.recorded_utc) for e in entries)
    what = ("date recorded" if recorded == len(entries) else
            "date fitted (the records carry no date)" if not recorded else
            "date recorded, else fitted")
    axes[-1, 0].set_xlabel(f"calibration #, {what} (UTC), oldest first")
    fig.suptitle(f"unit {mpl_text(entries[0].serial)}: change since its first calibration "
                 "(1 sigma bars)")
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, format="png", dpi=110)
    plt.close(fig)


def _cell(e) -> str:
    if e.sigma in ("fixed", "unobservable"):
        return f"{e.value} ({e.sigma})"
    return f"{e.value} +- {e.sigma}"


@cli.command("history")
@click.argument("directory", type=click.Path(file_okay=False))
@click.option("--unit", "serial", required=True, help="The unit's serial (from its plan).")
@click.option("--plot", "plot_path", type=click.Path(dir_okay=False),
              help="Write a PNG: each parameter's change over the calibrations.")
@click.option("--json", "as_json", is_flag=True, help="One JSON object on stdout.")
def history_cmd(directory, serial, plot_path, as_json):
    """Each parameter of a unit over its calibrations found under DIRECTORY."""
    from calib_cli.io.history import scan

    entries = scan(directory, serial)
    if not entries:
        raise InputError(f"no calibration of unit {serial!r} found", directory)
    keys = _keys(entries)
    if plot_path:
        _plot(entries, keys, plot_path)
    if as_json:
        print_json({"unit": {"serial": serial}, "calibrations": [
            {"file": e.rel, "method": e.method, "recorded_utc": e.recorded_utc or None,
             "created_utc": e.created_utc, "params": e.params, "sigma": e.sigma,
             "units": e.units} for e in entries]})
        return 0
    legend = Table(title=term_text(f"unit {serial}: {len(entries)} calibrations, in order"))
    for col in ("#", "file", "method", "recorded (UTC)"):
        legend.add_column(col)
    for i, e in enumerate(entries):
        legend.add_row(str(i + 1), term_text(e.rel), term_text(e.method),
                       term_text(e.recorded_utc or "-"))
    out_console.print(legend)
    for key in keys:
        first = next(e for e in entries if key in e.params)
        t = Table(title=term_text(f"{key}: value +- 1 sigma (display units)"))
        t.add_column("entry")
        t.add_column("unit")
        have = [(i, e) for i, e in enumerate(entries) if key in e.params]
        for i, _ in have:
            t.add_column(f"#{i + 1}", justify="right")
        # every calibration's entries formatted as show and fit print them
        cols = []
        for _, e in have:
            v = np.asarray(e.params[key], float)
            sg = np.asarray(e.sigma.get(key, np.full(v.shape, np.nan)), float)
            cols.append(sigma_entries(key, v, sg if sg.shape == v.shape else
                                      np.full(v.shape, np.nan), e.units.get(key, "")))
        unit_rows = sigma_entries(key, None, np.zeros(np.shape(first.params[key])),
                                  first.units.get(key, ""))
        for j, row in enumerate(unit_rows):
            cells = [_cell(c[j]) if j < len(c) else "-" for c in cols]
            t.add_row(term_text(row.name), term_text(row.unit), *cells)
        out_console.print(t)
    if plot_path:
        out_console.print(f"-> {plot_path}")
    return 0
