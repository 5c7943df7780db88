"""Display units of parameters: values stay SI in files and JSON; terminals,
reports and plots show them scaled (mg, deg/h, ppm, ...)."""

from __future__ import annotations

import numpy as np

# key -> (factor, unit) for the terminal; values stay SI in files and JSON
DISPLAY = {
    "accel_bias": (1e3 / 9.80665, "mg"),
    "accel_K": (1.0, ""),
    "gyro_bias": (180 / np.pi * 3600, "deg/h"),
    "gyro_K": (1.0, ""),
    "gyro_D": (180 / np.pi * 3600 * 9.80665, "deg/h/g"),
    "lever_arm": (1e3, "mm"),
    "proof_mass_offsets": (1e3, "mm"),
    "attitude": (180 / np.pi, "deg"),
    "time_offset": (1e3, "ms"),
}
for _s in ("accel", "gyro"):
    DISPLAY[f"{_s}_dEl"] = (1e3, "mrad")
    DISPLAY[f"{_s}_dAz"] = (1e3, "mrad")
    DISPLAY[f"{_s}_scale_error"] = (1e6, "ppm")


def display_of(key: str, unit: str) -> tuple[float, str]:
    """(factor, unit) to show parameter KEY: the table above, else the display units
    of the catalogue effect that owns the key (``ParamSpec.display``), else SI."""
    if "count" in unit:
        return 1.0, unit
    if key in DISPLAY:
        return DISPLAY[key]
    spec = _catalogue_specs().get(key)
    if spec is not None and spec.display != (1.0, "") and spec.unit == unit:
        return spec.display
    return 1.0, unit


def _catalogue_specs() -> dict:
    """key -> ParamSpec over every catalogue effect (triad and redundant layouts)."""
    from calib_cli.model.effects import CATALOGUE, Layout, make_effect

    out = {}
    for layout in (Layout(), Layout(n=6, el0=np.zeros(6), az0=np.zeros(6))):
        for name, cls in CATALOGUE.items():
            for sensor in (("",) if cls.sensorless else ("accel", "gyro")):
                try:
                    e = make_effect(name, sensor or "accel")
                except (TypeError, ValueError):
                    continue
                for sp in e.specs(layout):
                    out.setdefault(sp.key, sp)
    return out
