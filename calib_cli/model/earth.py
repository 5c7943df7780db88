"""Gravity and earth rate at a site (WGS-84), in ENU.

Defined in the base layer (``calib_cli/geometry.py``) so that the plan types
and data containers can hold a ``Site``; this module is the model's name for them.
"""

from __future__ import annotations

from calib_cli.geometry import EARTH_RATE, G0, Site, normal_gravity

__all__ = ["EARTH_RATE", "G0", "Site", "normal_gravity"]
