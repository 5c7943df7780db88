"""Numbers for people: every value a report prints goes through here, so it is
finite with an engineer's unit (mg, ug, ppm, deg/h, deg/sqrt(h), mm, deg) or
the words "not determined" -- never "nan", "None" or a Python repr.

The unit of a statistic is chosen from its key (the same rules as the
parameter table's display units: accelerometer quantities in mg, gyro rates in
deg/h, noise densities in ug/sqrt(Hz) and deg/sqrt(h), angles in deg, lengths
in mm); a key with no rule is printed as a plain number.
"""

from __future__ import annotations

import math
import re

import numpy as np

G0 = 9.80665
MG = 1e3 / G0  # m/s^2 -> mg
UG = 1e6 / G0  # m/s^2 -> ug
DPH = 180.0 / math.pi * 3600.0  # rad/s -> deg/h
DEG = 180.0 / math.pi  # rad -> deg
DSH = 180.0 / math.pi * 60.0  # rad/s/sqrt(Hz) = rad/sqrt(s) -> deg/sqrt(h)
ND = "not determined"


def num(x, digits: int = 4) -> str:
    """A finite number with ``digits`` significant digits, else 'not determined'."""
    try:
        v = float(x)
    except (TypeError, ValueError):
        return ND
    if not math.isfinite(v):
        return ND
    if v == int(v) and abs(v) < 1e9 and not isinstance(x, (float, np.floating)):
        return str(int(v))
    return f"{v:.{digits}g}"


def stat_unit(key: str) -> tuple[float, str]:
    """(factor from SI, display unit) of a statistic named ``key``."""
    k = key.lower()
    if k in ("g_reference", "accel_body_error_input"):
        return 1.0, "m/s^2"
    if k == "gyro_body_error_input":
        return DPH / 3600.0, "deg/s"
    if k.endswith("_mrad"):
        return 1.0, "mrad"
    if k.endswith("_deg") or k in ("rotation_angle", "angle") or k.startswith("attitude"):
        return (1.0, "deg") if k.endswith("_deg") else (DEG, "deg")
    if k.endswith("_rad") or k.endswith("_sigma_rad"):
        return DEG, "deg"
    if k.endswith("_degc"):
        return 1.0, "degC"
    if k.endswith("_hz"):
        return 1.0, "Hz"
    if k.endswith("_s") or k == "block_s":
        return 1.0, "s"
    if "density" in k:
        if k.startswith("gyro") or k.endswith("gyro"):
            return DSH, "deg/sqrt(h)"
        return UG, "ug/sqrt(Hz)"
    if "chi2" in k or "inflation" in k or "normalized" in k or "nis" in k or "dof" in k:
        return 1.0, ""
    acc = k.startswith(("accel", "g_error", "g_norm", "g_mean")) or k.endswith("_accel")
    gyr = k.startswith("gyro") or k.endswith("_gyro")
    if acc and re.search(r"rms|sigma|noise|error|std|bias|predicted|floor|before|after", k):
        return MG, "mg"
    if gyr and re.search(r"rms|sigma|noise|error|bias|predicted", k):
        return DPH, "deg/h"
    if k == "lever_arm" or k.startswith("proof_mass"):
        return 1e3, "mm"
    if k.endswith("_k") or k.endswith("_scale_error"):
        return 1e6, "ppm"
    return 1.0, ""


def value_text(key: str, v, limit: int = 400) -> str:
    """A statistic's value as text with its unit; nested lists and dicts are
    flattened readably (dicts as 'name: value', each with its own unit)."""
    factor, unit = stat_unit(key)
    s = _render(key, v, factor, unit, top=True)
    return s if len(s) <= limit else s[: limit - 3] + "..."


def _render(key, v, factor, unit, top=False) -> str:
    if v is None:
        return ND
    if isinstance(v, (bool, np.bool_)):
        return "yes" if v else "no"
    if isinstance(v, (str, bytes)):
        s = v.decode() if isinstance(v, bytes) else v
        return s if s.strip() else "-"
    if isinstance(v, dict):
        if not v:
            return "-"
        parts = []
        scalar_map = all(isinstance(x, (int, float, np.integer, np.floating)) for x in v.values())
        for k, x in v.items():
            f, u = stat_unit(str(k))
            if not u and scalar_map:  # {"x-turn": 360.0} of turn_angles_deg: the parent's unit
                f, u = factor, unit
            parts.append(f"{k}: {_render(str(k), x, f, u, top=True)}")
        return "; ".join(parts)
    if isinstance(v, (list, tuple, np.ndarray)):
        arr = list(v)
        if not arr:
            return "-"
        if all(isinstance(x, (int, float, np.integer, np.floating)) and
               not isinstance(x, (bool, np.bool_)) or x is None for x in arr):
            body = ", ".join(num(None if x is None else float(x) * factor
                                 if isinstance(x, (float, np.floating)) or factor != 1.0
                                 else x) for x in arr)
            return body + (f" {unit}" if top and unit else "")
        inner = [_render(key, x, factor, unit, top=False) for x in arr]
        body = "; ".join(f"[{s}]" if isinstance(x, (list, tuple, np.ndarray)) else s
                         for s, x in zip(inner, arr, strict=True))
        return body + (f" {unit}" if top and unit and all(
            isinstance(x, (list, tuple, np.ndarray)) for x in arr) else "")
    if isinstance(v, (int, np.integer)) and factor == 1.0:
        return str(int(v))
    try:
        x = float(v) * factor
    except (TypeError, ValueError):
        return str(v)
    t = num(x)
    return t + (f" {unit}" if unit and t != ND and top else "")


def allan_display(unit: str) -> tuple[float, str, dict]:
    """Display of an Allan analysis of a channel in SI ``unit``: (factor of the
    deviation, its unit, {term: (factor, unit)}). Gyros in deg/h with the random
    walk in deg/sqrt(h); accelerometers in ug with the random walk in
    ug/sqrt(Hz); anything else (counts) unchanged."""
    from calib_cli.methods.allan import term_units

    if unit == "rad/s":
        return DPH, "deg/h", {"quantization": (DEG * 3600.0, "arcsec"),
                              "random_walk": (DSH, "deg/sqrt(h)"),
                              "bias_instability": (DPH, "deg/h"),
                              "rate_random_walk": (DPH * 60.0, "deg/h/sqrt(h)")}
    if unit == "m/s^2":
        return UG, "ug", {"quantization": (1e3, "mm/s"),
                          "random_walk": (UG, "ug/sqrt(Hz)"),
                          "bias_instability": (UG, "ug"),
                          "rate_random_walk": (UG, "ug/sqrt(s)")}
    tu = term_units(unit)
    return 1.0, unit, {k: (1.0, u) for k, u in tu.items()}


CHECK_POSITION_HEADER = ["position", "axis up (tilt)", "|f| - g (ug)", "z",
                         "w_up - W sin(lat) (deg/h)", "z"]


def check_position_rows(cp: dict | None) -> list[list[str]]:
    """Rows of stats.check_positions (the turntable fit's check positions) for a table:
    CHECK_POSITION_HEADER's columns, text."""
    def z(v):
        return "-" if v is None else f"{v:+.2f}"

    rows = []
    for p in (cp or {}).get("positions", []):
        rows.append([str(p["label"]), f"{p['vertical_axis']} ({p['axis_tilt_deg']:.1f} deg)",
                     f"{p['g_error'] * UG:+.1f} +- {p['g_error_sigma'] * UG:.1f}",
                     z(p["g_error_z"]),
                     f"{p['earth_rate_up_error'] * DPH:+.3f} +- "
                     f"{p['earth_rate_up_error_sigma'] * DPH:.3f}",
                     z(p["earth_rate_up_error_z"])])
    return rows
