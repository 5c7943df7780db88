"""Report-only text: the Allan terms' display and the check-position rows.
Every value, sigma and unit is formatted by ``calib_cli.model.display`` (the
one formatting module of show, report, plan check and the fit summary),
re-exported here for the section modules."""

from __future__ import annotations

from calib_cli.model.display import (  # noqa: F401  (re-exported)
    DEG,
    DPH,
    DSH,
    G0,
    MG,
    ND,
    UG,
    StatUnits,
    num,
    stat_unit,
    value_text,
)


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
