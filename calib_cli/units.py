"""Unit suffixes of human-facing keys (plans, truth files) -> SI factors.

A key such as ``accel_bias_mg`` means the parameter ``accel_bias`` given in
milli-g; it is multiplied by the factor here on loading.
"""

from __future__ import annotations

import numpy as np

G0 = 9.80665  # m/s^2 per g (display unit only)
D2R = np.pi / 180.0

SUFFIXES = {
    "_deg": D2R,  # deg -> rad
    "_dps": D2R,  # deg/s -> rad/s
    "_dph": D2R / 3600.0,  # deg/h -> rad/s
    "_dpsqrth": D2R / 60.0,  # deg/sqrt(h) (angle random walk) -> rad/sqrt(s)
    "_mrad": 1e-3,
    "_urad": 1e-6,
    "_mg": G0 * 1e-3,  # milli-g -> m/s^2
    "_ug": G0 * 1e-6,  # micro-g -> m/s^2
    "_ppm": 1e-6,
    "_mm": 1e-3,
    "_cm": 1e-2,
    "_ms": 1e-3,  # milliseconds -> s
}


def split_suffix(key: str) -> tuple[str, float]:
    """("accel_bias_mg") -> ("accel_bias", 9.80665e-3); no suffix -> factor 1."""
    for suf in sorted(SUFFIXES, key=len, reverse=True):
        if key.endswith(suf):
            return key[: -len(suf)], SUFFIXES[suf]
    return key, 1.0

