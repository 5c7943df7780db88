"""calib show FILE [--json] [--covariance]"""

from __future__ import annotations

import click
import numpy as np
from rich.table import Table

from calib_cli.cli.common import Ctx, out_console, print_json
from calib_cli.cli.main import cli
from calib_cli.cli.render import params_table
from calib_cli.io.contract_json import calibration_json  # noqa: F401  (re-exported)
from calib_cli.io.escape import term_text
from calib_cli.io.h5 import file_kind, provenance, read_calibration, read_raw
from calib_cli.model.display import MG, StatUnits, counts_note, g_figures_line, value_text
from calib_cli.report.format import CHECK_POSITION_HEADER, check_position_rows


def raw_json(path) -> dict:
    r = read_raw(path)
    return {"kind": provenance(path)["kind"], "unit": {"serial": r.serial},
            "samples": len(r), "sample_rate_hz": r.sample_rate, "units": r.units,
            "plan_kind": r.plan_kind, "channels": r.layout.n,
            "segments": [{"label": s.label, "kind": s.kind, "start": s.start, "stop": s.stop,
                          "attitude": s.attitude} for s in r.segments],
            "counters": r.counters}


# kind -> show(files, as_json, covariance); other modules add their kinds. The static
# tree (cli/_tree.py, "showers") names the module of each, imported when that kind is
# shown: `calib show` loads one module, not every command's (COMPLETE_COMMAND)
SHOWERS: dict = {}
COMPLETE_COMMAND = True


def _shower(kind: str):
    if kind not in SHOWERS:
        import importlib

        from calib_cli.cli.tree import tree

        mod = tree().get("showers", {}).get(kind)
        if mod:
            importlib.import_module(mod)
    return SHOWERS.get(kind)


def _render_provenance(path):
    prov = provenance(path)
    t = Table(title=term_text(path), show_header=False)
    for k in ("kind", "format_version", "tool_version", "created_utc", "unit_serial", "command"):
        if k in prov:
            t.add_row(k, term_text(prov[k]))
    out_console.print(t)


def _render_calibration(path, covariance):
    c = read_calibration(path)
    out_console.print(params_table(c.params, c.sigma, c.units, title=f"calibration ({c.method})"))
    note = counts_note(c.params, c.units)
    if note:
        out_console.print(term_text(note), markup=False)
    su = StatUnits.of(c)
    st = Table(title="stats (display units; data in counts stay counts)", show_header=False)
    for k, v in c.stats.items():
        if k == "check_positions" and isinstance(v, dict):  # a table of its own, below
            v = (f"{v.get('verdict')}: {v.get('n', 0)} static positions, max |z| "
                 f"{v['max_abs_z']:.2f}" if "max_abs_z" in v
                 else f"{v.get('verdict')}: {v.get('note', '')}")
        else:
            v = value_text(k, v, limit=160, units=su)
        st.add_row(term_text(k), term_text(v))
    out_console.print(st)
    if "g_table" in c.tables:
        gt = Table(title="|g| per position (m/s^2; after - g in mg)")
        for col in ("position", "samples", "before", "after", "after - g (mg)"):
            gt.add_column(col)
        labels = c.tables.get("segment_labels", [])
        for lab, row in zip(labels, np.asarray(c.tables["g_table"])):
            gt.add_row(term_text(lab), f"{row[0]:.0f}", "-" if np.isnan(row[1]) else f"{row[1]:.6f}",
                       f"{row[2]:.6f}", f"{row[3] * MG:+.4f}")
        out_console.print(gt)
        line = g_figures_line(c.stats)
        if line:
            out_console.print(line)
    cp_rows = check_position_rows(c.stats.get("check_positions"))
    if cp_rows:
        ct = Table(title="check positions (static segments the fit did not use)")
        for col in CHECK_POSITION_HEADER:
            ct.add_column(col)
        for row in cp_rows:
            ct.add_row(*(term_text(x) for x in row))
        out_console.print(ct)
    if covariance:
        out_console.print(f"covariance: {c.covariance.shape[0]} free entries (use --json)")


def _render_raw(path):
    r = read_raw(path)
    units = ", ".join(f"{k} {v}" for k, v in r.units.items() if v)
    t = Table(title=term_text(f"{len(r)} samples at {r.sample_rate:.4g} Hz, units: {units}"))
    for col in ("segment", "kind", "samples", "duration s", "attitude deg"):
        t.add_column(col)
    for s in r.segments:
        att = "unknown" if s.attitude is None else ", ".join(f"{x:.4g}" for x in np.degrees(s.attitude))
        t.add_row(term_text(s.label), term_text(s.kind), str(s.n),
                  f"{s.n / max(r.sample_rate, 1e-9):.1f}", att)
    out_console.print(t)
    if r.counters:  # acquisition counts (calib record)
        out_console.print(term_text("counters: " + ", ".join(f"{k} {v}"
                                                             for k, v in r.counters.items())))


@cli.command("show")
@click.argument("files", nargs=-1, required=True, type=click.Path(dir_okay=False))
@click.option("--json", "as_json", is_flag=True, help="One JSON object (docs/contract.md section 5).")
@click.option("--covariance", is_flag=True, help="Include the covariance matrix.")
def show_cmd(files, as_json, covariance):
    """Summarise a calib HDF5 file (raw, calibration, corrected, ...).

    With two calibration files A B: the parameter differences B - A in units
    of their combined sigma (e.g. one unit calibrated on two dates)."""
    path = files[0]
    kind = file_kind(path)
    cal_kinds = ("calibration", "diagnosis")  # a diagnosis file holds a calibration too
    if len(files) == 2 and kind in cal_kinds and file_kind(files[1]) in cal_kinds:
        from calib_cli.cli.compare import show_compare  # A.h5 B.h5: differences in sigma

        return show_compare(files, as_json)
    shower = _shower(kind)
    if shower is not None:
        return shower(files, as_json, covariance)
    if as_json:
        print_json(calibration_json(path, covariance) if kind == "calibration" else raw_json(path))
        return 0
    if not Ctx.quiet:
        _render_provenance(path)
    if kind == "calibration":
        _render_calibration(path, covariance)
    else:
        _render_raw(path)
    return 0
