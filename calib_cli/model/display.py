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
    if "count" in unit:
        return 1.0, unit
    return DISPLAY.get(key, (1.0, unit))
