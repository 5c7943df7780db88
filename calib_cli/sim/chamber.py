"""Chamber temperature for simulated plans (docs/thermal.md).

A plan segment may carry ``chamber_temp_degC``: the chamber's setpoint from
the start of that segment (the setpoint holds through the following
transitions and segments until another segment sets one). The chamber air
moves towards the setpoint at the plan's ``chamber_ramp_dpm`` (degC/min,
default 2), and the unit follows the air with a first-order response of
time constant ``unit_tau_s`` (default 300 s; the same first-order physics as
the catalogue's ``thermal_lag``, effects.lag_temperature). The unit starts
soaked at ``temperature_c`` where given, else at the first setpoint.
"""

from __future__ import annotations

import numpy as np

from calib_cli.model.effects import lag_temperature


def has_chamber(plan) -> bool:
    return any("chamber_temp_degC" in s.extra for s in plan.segments)


def setpoints(plan, plan_index: np.ndarray) -> np.ndarray:
    """(N,) chamber setpoint per sample from each sample's plan segment index
    (-1 between segments: the previous setpoint holds)."""
    sp = np.array([float(s.extra["chamber_temp_degC"]) if "chamber_temp_degC" in s.extra
                   else np.nan for s in plan.segments])
    v = np.where(plan_index >= 0, sp[np.clip(plan_index, 0, len(sp) - 1)], np.nan)
    # forward fill, then back fill the start with the first setpoint
    idx = np.where(np.isfinite(v), np.arange(len(v)), 0)
    np.maximum.accumulate(idx, out=idx)
    v = v[idx]
    first = np.flatnonzero(np.isfinite(v))
    v[:first[0]] = v[first[0]]
    return v


def chamber_temperature(plan, t: np.ndarray, plan_index: np.ndarray):
    """(air, unit) temperature per sample, degC."""
    sp = setpoints(plan, plan_index)
    rate = float(plan.extra.get("chamber_ramp_dpm", 2.0)) / 60.0
    tau = float(plan.extra.get("unit_tau_s", 300.0))
    air = np.empty(len(t))
    a0 = float(plan.extra.get("temperature_c", sp[0]))
    change = np.flatnonzero(np.diff(sp) != 0) + 1
    bounds = np.concatenate([[0], change, [len(t)]])
    for a, b in zip(bounds[:-1], bounds[1:]):
        target = sp[a]
        dt = t[a:b] - t[a]
        step = np.minimum(rate * dt, abs(target - a0))
        air[a:b] = a0 + np.sign(target - a0) * step
        a0 = float(air[b - 1]) if b > a else a0
        # the ramp continues from where the air is at the next change
    unit = lag_temperature(t, air, tau)
    start = float(plan.extra.get("temperature_c", sp[0]))
    if start != air[0]:
        unit = unit  # soaked at the start value: air[0] is that value already
    return air, unit
