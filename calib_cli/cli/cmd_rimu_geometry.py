"""calib rimu-geometry PROFILE: figures of merit of a redundant unit's layout
(docs/rimu.md, "Comparing layouts")."""

from __future__ import annotations

import click
import numpy as np
from rich.table import Table

from calib_cli.cli.common import out_console, print_json
from calib_cli.cli.main import cli

COMPLETE_COMMAND = True  # every subcommand lives here: loaded alone (cli/main.py)

D2R = np.pi / 180.0


def _geometry(profile: str) -> tuple[np.ndarray, np.ndarray, str]:
    """el0, az0 (rad) and a name from a profile name or path, or a rimu plan."""
    import tomllib
    from pathlib import Path

    from calib_cli.errors import InputError
    from calib_cli.io.plan import load_plan
    from calib_cli.io.profiles import load_rimu_profile

    p = Path(profile)
    if p.is_file():
        try:
            raw = tomllib.loads(p.read_text(encoding="utf-8"))
        except (OSError, UnicodeDecodeError, tomllib.TOMLDecodeError) as exc:
            raise InputError(f"cannot read: {exc}", profile) from None
        if "kind" in raw:  # a plan of kind rimu
            plan = load_plan(profile)
            if plan.rimu_el0 is None:
                raise InputError("not a plan of kind \"rimu\" (no [rimu] geometry)", profile)
            return np.asarray(plan.rimu_el0), np.asarray(plan.rimu_az0), plan.name
    table = load_rimu_profile(profile, "<command line>")
    try:
        el = np.asarray(table["el0_deg"], float)
        az = np.asarray(table["az0_deg"], float)
    except (TypeError, ValueError):
        raise InputError("el0_deg and az0_deg must be lists of numbers", profile) from None
    if el.ndim != 1 or el.shape != az.shape or not np.all(np.isfinite(el) & np.isfinite(az)):
        raise InputError("el0_deg and az0_deg must be finite lists of equal length", profile)
    el = (el + 180.0) % 360.0 - 180.0
    return el * D2R, (az % 360.0) * D2R, p.stem


def _render(r: dict) -> None:
    t = Table(title=f"geometry {r['name']}: {r['n_sensors']} sensors")
    t.add_column("figure")
    t.add_column("value")
    g = r["accuracy_gain"]
    t.add_row("accuracy gain vs one triad, sqrt(3/tr((H^T H)^-1))",
              "does not span 3-D" if not np.isfinite(g) else f"{g:.4f}")
    s = r["subsets"]
    t.add_row("subsets of >= 3 sensors spanning 3-D", f"{s['spanning']} of {s['total']}")
    t.add_row("  of which detect any single fault", str(s["detect_any_single_fault"]))
    t.add_row("  of which isolate any single fault", str(s["isolate_any_single_fault"]))
    if r["collinear_groups"]:
        t.add_row("collinear sensors", "; ".join(", ".join(map(str, grp))
                                                for grp in r["collinear_groups"]))
    for key, label in (("single_faults", "single"), ("double_faults", "double")):
        f = r[key]
        t.add_row(f"{label} faults tolerated / detectable / isolable",
                  f"{f['tolerated']} / {f['detectable']} / {f['isolable']} of {f['of']}")
    d = r["detection"]
    if d["threshold"] is None:
        t.add_row("parity test", "no redundancy (3 sensors)")
    else:
        pw = d["per_sensor"]
        t.add_row(f"detection power, fault {d['fault_sigma']:g} sigma, alpha {d['alpha']:g} "
                  f"({d['dof']} dof)", f"{min(pw):.3f} .. {max(pw):.3f} over the sensors")
    out_console.print(t)


@cli.command("rimu-geometry")
@click.argument("profile")
@click.option("--fault", type=float, default=5.0, show_default=True,
              help="Fault size for the detection power, in noise sigmas of the tested "
                   "quantity (e.g. a window mean).")
@click.option("--alpha", type=float, default=1e-3, show_default=True,
              help="False-alarm probability of the parity test (per test).")
@click.option("--json", "as_json", is_flag=True, help="Print one JSON object.")
def rimu_geometry_cmd(profile, fault, alpha, as_json):
    """Figures of merit of a redundant layout: accuracy gain against one triad,
    subsets that span 3-D, tolerated/isolable faults, parity-test power.
    PROFILE: a shipped profile name, a profile file, or a plan of kind rimu."""
    from calib_cli.methods.rimu_geometry import geometry_report

    el, az, name = _geometry(profile)
    r = geometry_report(el, az, fault=fault, alpha=alpha, name=name)
    if as_json:
        print_json({"command": "rimu-geometry", **r})
    else:
        _render(r)
