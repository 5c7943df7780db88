"""Simulated thermal experiments (tests, validation, docs/thermal.md): plans
for the soak and ramp designs and a random unit with quadratic bias drift
(about 5 mg over -40..+85 degC) and linear-to-quadratic scale drift (about
300 ppm)."""

from __future__ import annotations

import numpy as np

from calib_cli.io.plan import parse_plan
from calib_cli.model.effects import ThermalLag, make_effect
from calib_cli.model.imu_model import ImuModel
from calib_cli.model.truth import Truth, default_truth

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


def thermal_truth(rng, order: int = 2, lag_tau: float | None = None,
                  bias_mg: float = 5.0, scale_ppm: float = 300.0, temp_ref: float = 25.0) -> Truth:
    """A random MEMS unit (bias, K for both sensors) with temperature drift:
    per axis, accel bias moving by about bias_mg over -40..85 degC (linear and
    quadratic parts), scale by about scale_ppm, gyro bias by ~ 50 deg/h."""
    from calib_cli.model.effects import Layout

    base = default_truth(Layout(), rng)
    g0 = 9.80665
    lo, hi = -40.0 - temp_ref, 85.0 - temp_ref
    span2 = max(lo * lo, hi * hi)

    def drift(total):
        c1 = rng.choice([-1, 1], 3) * rng.uniform(0.3, 0.6, 3) * total / (hi - lo)
        c2 = rng.choice([-1, 1], 3) * rng.uniform(0.3, 0.6, 3) * total / span2
        return np.column_stack([c1, c2])[:, :order]

    params = dict(base.params)
    params["accel_temp_bias"] = drift(bias_mg * 1e-3 * g0)
    params["accel_temp_scale"] = drift(scale_ppm * 1e-6)
    params["gyro_temp_bias"] = drift(50.0 / 3600 * np.pi / 180)
    params["gyro_temp_scale"] = np.zeros((3, order))
    if order == 1:
        for k in ("accel_temp_bias", "accel_temp_scale", "gyro_temp_bias", "gyro_temp_scale"):
            params[k] = params[k][:, 0]
    effects = base.model.effects + (
        make_effect("temperature_drift", "accel", order=order, temp_ref=temp_ref),
        make_effect("temperature_drift", "gyro", order=order, temp_ref=temp_ref))
    if lag_tau:
        effects = effects + (ThermalLag(),)
        params["thermal_lag_tau"] = np.array(float(lag_tau))
    noise = {"accel_white": 1e-3, "gyro_white": 3e-4}  # per sample at 10 Hz
    return Truth(ImuModel(effects, base.model.layout), params, noise)
