"""`calib show A.h5 B.h5`: two calibrations side by side, differences in sigma."""

from __future__ import annotations

import numpy as np
from rich.table import Table

from calib_cli.cli.common import info, out_console, print_json
from calib_cli.io.h5 import provenance, read_calibration
from calib_cli.methods.compare import compare
from calib_cli.model.display import display_of, is_matrix


def show_compare(files, as_json: bool) -> int:
    pa, pb = files[0], files[1]
    a, b = read_calibration(pa), read_calibration(pb)
    res = compare(a, b, pb)
    ta, tb = provenance(pa).get("created_utc"), provenance(pb).get("created_utc")
    if a.serial != b.serial:
        info(f"[yellow]note:[/] unit serials differ ({a.serial} vs {b.serial})")
    if a.method != b.method:
        info(f"[yellow]note:[/] methods differ ({a.method} vs {b.method})")
    if as_json:
        print_json({"kind": "comparison", "files": [pa, pb], "methods": [a.method, b.method],
                    "unit": {"serial": [a.serial, b.serial]}, "created_utc": [ta, tb], **res})
        return 0
    t = Table(title=f"B - A: {pb} ({tb}) minus {pa} ({ta}); z = difference / combined sigma")
    for col in ("parameter", "A", "B", "B - A", "sigma", "z", "unit"):
        t.add_column(col, justify="left" if col in ("parameter", "unit") else "right")
    for k, d in res["params"].items():
        for idx in np.ndindex(d.shape):
            factor, unit = display_of(k, res["units"][k], idx)
            # a dimensionless matrix: values as they are, differences and sigma in ppm
            dfac, dunit = (1e6, "ppm") if is_matrix(k, res["units"][k]) else (factor, unit)
            s, z = res["sigma"][k][idx], res["z"][k][idx]
            if s == 0 and d[idx] == 0:
                continue  # fixed by convention in both
            name = f"{k}[{','.join(map(str, idx))}]" if d.ndim else k
            zs = "not determined" if np.isnan(z) else f"{z:+.2f}"
            if np.isfinite(z) and abs(z) > 3:
                zs = f"[bold red]{zs}[/]"
            t.add_row(name, f"{res['a'][k][idx] * factor:.7g}", f"{res['b'][k][idx] * factor:.7g}",
                      f"{d[idx] * dfac:+.3g}", "unobservable" if np.isnan(s) else
                      f"{s * dfac:.3g}", zs, unit if dunit == unit else f"{unit or '-'} "
                      f"(B - A, sigma: {dunit})")
    out_console.print(t)
    for key in ("only_in_a", "only_in_b", "incomparable"):
        if res[key]:
            out_console.print(f"{key.replace('_', ' ')}: {', '.join(res[key])}")
    if res["worst"]:
        out_console.print(f"largest change: {res['worst']} at {res['max_abs_z']:.2f} sigma")
    return 0
