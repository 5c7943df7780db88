"""Simulated thermal experiments (tests, validation, docs/thermal.md): plans
for the soak and ramp designs and a random unit with quadratic bias drift
(about 5 mg over -40..+85 degC) and linear-to-quadratic scale drift (about
300 ppm)."""

from __future__ import annotations

import numpy as np

from calib_cli.io.plan import parse_plan
from calib_cli.sim.thermal_unit import thermal_truth  # noqa: F401  (re-exported)

POSITIONS = {"x-up": [0, -90, 0], "x-down": [0, 90, 0], "y-up": [90, 0, 0],
             "y-down": [-90, 0, 0], "z-up": [0, 0, 0], "z-down": [180, 0, 0]}
HEAD = """name = "{name}"
kind = "static"
sample_rate_hz = {fs}
transition_s = 4.0
chamber_ramp_dpm = {ramp}
unit_tau_s = {tau}
[site]
latitude_deg = 50.45
height_m = 180.0
"""


def _seg(label, att, dur, setpoint=None):
    s = f'[[segment]]\nlabel = "{label}"\nattitude_deg = {att}\nduration_s = {dur}\n'
    if setpoint is not None:
        s += f"chamber_temp_degC = {setpoint}\n"
    return s


def soak_plan_text(temps=(-40, -20, 0, 25, 45, 65, 85), soak_s=1800.0, hold_s=60.0,
                   fs=10.0, ramp_dpm=3.0, unit_tau_s=300.0, name="thermal-soak") -> str:
    """At each temperature: a soak (the first position held while the unit
    settles), then the six positions."""
    text = HEAD.format(name=name, fs=fs, ramp=ramp_dpm, tau=unit_tau_s)
    for T in temps:
        labels = list(POSITIONS)
        text += _seg(f"soak{T:+d}", POSITIONS[labels[0]], soak_s, T)
        for lab in labels:
            text += _seg(f"{lab}@{T:+d}", POSITIONS[lab], hold_s)
    return text


def ramp_plan_text(lo=-40.0, hi=85.0, ramp_dpm=1.0, hold_s=120.0, fs=10.0,
                   unit_tau_s=120.0, cycles=("heat", "cool"), name="thermal-ramp") -> str:
    """The chamber ramps lo -> hi (and back) at ramp_dpm while the unit goes
    round the six positions, hold_s each; a soak at lo first."""
    text = HEAD.format(name=name, fs=fs, ramp=ramp_dpm, tau=unit_tau_s)
    labels = list(POSITIONS)
    text += _seg("soak", POSITIONS[labels[0]], 6 * unit_tau_s, lo)
    leg = (hi - lo) / ramp_dpm * 60.0 + 4 * unit_tau_s
    n = int(np.ceil(leg / (hold_s + 4.0)))
    for c in cycles:
        target = hi if c == "heat" else lo
        for k in range(n):
            lab = labels[k % 6]
            text += _seg(f"{lab}-{c}{k}", POSITIONS[lab], hold_s, target if k == 0 else None)
    return text


def plan(text: str):
    return parse_plan(text, "<thermal plan>")
