"""Unit suffixes of human-facing keys (plans, truth files) -> SI factors."""

from __future__ import annotations

import numpy as np

G0 = 9.80665
D2R = np.pi / 180.0

# suffix -> factor to SI. Longest suffixes first when matching.
SUFFIXES = {
    "_deg": D2R,
    "_dps": D2R,
    "_dph": D2R / 3600.0,
    "_dpsh": D2R / 3600.0,  # deg/sqrt(h) (angle random walk) -> rad/sqrt(s)... see below
    "_mrad": 1e-3,
    "_urad": 1e-6,
    "_mg": G0 * 1e-3,
    "_ug": G0 * 1e-6,
    "_ppm": 1e-6,
    "_mm": 1e-3,
    "_cm": 1e-2,
    "_ms": 1e-3,
}
# deg/sqrt(h) -> rad/sqrt(s): D2R / 60
SUFFIXES["_dpsh"] = D2R / 60.0


def split_suffix(key: str) -> tuple[str, float]:
    """("accel_bias_mg") -> ("accel_bias", 9.80665e-3); no suffix -> factor 1."""
    for suf in sorted(SUFFIXES, key=len, reverse=True):
        if key.endswith(suf):
            return key[: -len(suf)], SUFFIXES[suf]
    return key, 1.0
