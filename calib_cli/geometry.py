"""The base geometry every layer shares: where an experiment runs (``Site``,
WGS-84 gravity and earth rate) and the channel geometry of a unit (``Layout``).

Pure containers and closed-form constants; ``model/earth.py`` and
``model/effects.py`` re-export them (docs/architecture.md: the base layer).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

EARTH_RATE = 7.292115e-5  # rad/s, WGS-84
G0 = 9.80665  # m/s^2, standard gravity: only for display units (mg, g)

# WGS-84 normal gravity (Somigliana) constants
_GE = 9.7803253359  # m/s^2 at the equator
_K = 0.00193185265241
_E2 = 0.00669437999013
_A = 6378137.0  # m
_F = 1.0 / 298.257223563
_M = 0.00344978650684  # omega^2 a^2 b / GM


def normal_gravity(latitude_rad: float, height_m: float = 0.0) -> float:
    """WGS-84 normal gravity magnitude (m/s^2) at geodetic latitude and height.

    Somigliana's formula on the ellipsoid with the second-order free-air
    correction for height (NIMA TR8350.2, eq. 4-1 and 4-3).
    """
    s2 = np.sin(latitude_rad) ** 2
    g_ell = _GE * (1.0 + _K * s2) / np.sqrt(1.0 - _E2 * s2)
    h = height_m
    corr = 1.0 - 2.0 / _A * (1.0 + _F + _M - 2.0 * _F * s2) * h + 3.0 / _A**2 * h**2
    return float(g_ell * corr)


@dataclass(frozen=True)
class Site:
    """Where an experiment runs. Angles in rad, height in m, g in m/s^2."""

    latitude: float = 0.0
    height: float = 0.0
    g: float | None = None  # the plan's g where given, else normal gravity

    @property
    def gravity(self) -> float:
        """Magnitude of gravity (m/s^2) used for this site."""
        return self.g if self.g is not None else normal_gravity(self.latitude, self.height)

    @property
    def specific_force_enu(self) -> np.ndarray:
        """Specific force at rest in ENU: [0, 0, +g]."""
        return np.array([0.0, 0.0, self.gravity])

    @property
    def earth_rate_enu(self) -> np.ndarray:
        """Earth rate in ENU (rad/s): [0, W cos(lat), W sin(lat)]."""
        return EARTH_RATE * np.array([0.0, np.cos(self.latitude), np.sin(self.latitude)])


@dataclass(frozen=True)
class Layout:
    """Channel geometry of a unit.

    A triad has three orthogonal channels per sensor. A redundant unit (RIMU)
    has n single-axis channels with nominal elevation/azimuth (rad).
    ``n_cycles`` is the number of lever-arm rows (rotating segments).
    """

    n: int = 3
    el0: np.ndarray | None = None
    az0: np.ndarray | None = None
    n_cycles: int = 0

    @property
    def redundant(self) -> bool:
        return self.el0 is not None

    def axes(self, del_=None, daz=None) -> np.ndarray:
        """(n, 3) unit sensing directions; nominal, or with errors dEl, dAz (rad)."""
        if not self.redundant:
            return np.eye(3)
        el = self.el0 + (0.0 if del_ is None else del_)
        az = self.az0 - (0.0 if daz is None else daz)
        return np.stack([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)], axis=1)
