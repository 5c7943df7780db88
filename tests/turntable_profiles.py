"""Turntable records over the rate-profile families a real table runs (issue 14).

Plans are written as TOML the way a user would, from the contract plus the
simulation keys of docs/simulate.md; the truths vary what the project's own
generator does not: lever arms from 0 to 0.5 m, proof-mass offsets uniform in
+-1 cm, and in a third of the seeds every other parameter at 3x the size the
default truth draws.
"""

from __future__ import annotations

import re

import numpy as np

from calib_cli.io.plan import parse_plan
from calib_cli.sim.rate_profiles import trapezoid_knots
from calib_cli.sim.simulate import simulate
from calib_cli.sim.turntable_plans import cycle_attitudes, turntable_plan_text, turntable_truth

LEVELS = (50, -50, 100, -100, 150, -150, 200, -200)
# family -> (rate_shape or "sine", ramp acceleration deg/s^2)
FAMILIES = {
    "trapezoid-50": ("linear", 50.0), "trapezoid-100": ("linear", 100.0),
    "trapezoid-300": ("linear", 300.0), "trapezoid-1000": ("linear", 1000.0),
    "smooth": ("smooth", 100.0), "s-curve": ("scurve", 100.0), "sinusoid": ("sine", 0.0),
}


def _knots(duration_s: float, ramp: float, rng) -> list:
    return [[round(a, 6), round(b, 6)] for a, b in
            trapezoid_knots(duration_s, ramp, LEVELS, lambda: rng.uniform(30.0, 45.0))]


# the table axis of a geometry (ENU): horizontal (east), vertical (the classic rate table),
# 30 deg up from the horizontal
GEOMETRIES = {"horizontal": None, "vertical": (0.0, 0.0, 1.0),
              "tilt30": (float(np.cos(np.radians(30.0))), 0.0, float(np.sin(np.radians(30.0))))}
# per-sample white noise (m/s^2, rad/s) at 100 Hz: the generator's MEMS unit, a tactical one
# and 1 % of the MEMS unit's (issue 32's low-noise reproducers: model errors show there)
NOISE = {"mems": None, "tactical": (0.5e-3 * 9.80665, float(np.radians(0.005))),
         "low": (0.08e-3 * 9.80665, float(np.radians(5e-4)))}


def profile_plan_text(seed: int, family: str, kind: str = "instant", duration_s: float = 600.0,
                      wobble_dps: float = 0.5, tilted: bool = False,
                      tilted_duration_s: float = 300.0, geometry: str = "horizontal",
                      attitude_sigma_deg: float | None = None,
                      mount_error_deg: float = 0.3) -> str:
    """A turntable plan of the family: the generator's mounting and housing keys with the
    family's rate keys in every cycle (holds of 30-45 s at +-50 .. +-200 deg/s), the table
    axis of ``geometry`` (GEOMETRIES); the true mountings off the plan's by
    ``mount_error_deg`` per axis (1 sigma), stated as ``attitude_sigma_deg`` if given."""
    shape, ramp = FAMILIES[family]
    txt = turntable_plan_text(seed, duration_s=duration_s, tilted=tilted,
                              tilted_duration_s=tilted_duration_s, wobble_dps=wobble_dps,
                              table_axis=GEOMETRIES[geometry],
                              mount_error_deg=mount_error_deg)
    rng = np.random.default_rng(seed)
    out, c = [], 0
    for line in txt.splitlines():
        if line.startswith("rate_shape"):
            continue
        if line.startswith("attitude_deg") and attitude_sigma_deg is not None:
            line += f"\nattitude_sigma_deg = {attitude_sigma_deg}"
        if line.startswith("rate_profile"):
            dur = duration_s if c < 3 else tilted_duration_s
            c += 1
            if shape == "sine":
                f = rng.uniform(0.05, 0.15)
                line = f"rate_oscillation = [200.0, {f:.6f}]\nduration_s = {dur}"
            else:
                line = (f"rate_shape = '{shape}'\nrate_jerk_dps3 = 300.0\n"
                        f"rate_profile = {_knots(dur, ramp, rng)}")
        out.append(line)
    text = "\n".join(out) + "\n"
    return f'sample_kind = "{kind}"\n' + text


def lever_arm_lines(text: str, seed: int) -> str:
    """Replace the true lever arms by ones of 0-0.5 m perpendicular to each cycle's axis."""
    rng = np.random.default_rng(50_000 + seed)
    axes = [a for _l, _att, a in cycle_attitudes(tilted=True)]
    lines, c = [], 0
    for line in text.splitlines():
        if line.startswith("sim_lever_arm_m"):
            a = axes[c]
            v = rng.standard_normal(3)
            v -= a * (v @ a)
            v *= rng.uniform(0.0, 0.5) / np.linalg.norm(v)
            line = "sim_lever_arm_m = [" + ", ".join(f"{x:.9g}" for x in v) + "]"
            c += 1
        lines.append(line)
    return "\n".join(lines) + "\n"


ENCODER_KEYS = ("sim_table_encoder_counts = 65536\nsim_table_encoder_opr_deg = 0.05\n"
                "sim_table_rate_scale_error = 2e-3\n")


def profile_record(seed: int, family: str, kind: str = "instant", duration_s: float = 600.0,
                   tilted: bool = False, wobble: bool | None = None, wide: bool | None = None,
                   encoder: bool = False, geometry: str = "horizontal", noise: str = "mems",
                   full: bool = False, attitude_sigma_deg: float | None = None,
                   mount_error_deg: float = 0.3):
    """(Recording, truth params) for one validation case. ``wobble`` defaults to every
    other seed, ``wide`` (truths at 3x) to every third. ``encoder``: the log's table
    channels are a 2^16-count angle encoder with a 0.05 deg once-per-revolution error and
    a rate channel with a 2e-3 scale error (else the nominal profile, not an encoder).
    ``geometry``: the table axis (GEOMETRIES); ``noise``: the unit's white noise (NOISE).
    full: also the plan and the Truth (rec, params, plan, truth)."""
    wobble = (seed % 2 == 1) if wobble is None else wobble
    wide = (seed % 3 == 2) if wide is None else wide
    text = profile_plan_text(seed, family, kind, duration_s, 0.5 if wobble else 0.0, tilted,
                             geometry=geometry, attitude_sigma_deg=attitude_sigma_deg,
                             mount_error_deg=mount_error_deg)
    if encoder:
        text = ENCODER_KEYS + text
    text = lever_arm_lines(text, seed)
    plan = parse_plan(text)
    rng = np.random.default_rng(seed)
    truth = turntable_truth(plan, rng)
    params = dict(truth.params)
    prng = np.random.default_rng(90_000 + seed)
    P = prng.uniform(-0.01, 0.01, (3, 3))
    np.fill_diagonal(P, 0.0)
    params["proof_mass_offsets"] = P
    if wide:
        for spec in truth.model.specs():
            if spec.key in ("lever_arm", "proof_mass_offsets"):
                continue
            params[spec.key] = spec.neutral() + 3.0 * (params[spec.key] - spec.neutral())
    tnoise = dict(truth.noise)
    if NOISE[noise] is not None:
        tnoise["accel_white"], tnoise["gyro_white"] = NOISE[noise]
    truth = type(truth)(truth.model, params, tnoise, truth.counts, truth.quantize)
    rec = simulate(plan, truth, seed)
    return (rec, params, plan, truth) if full else (rec, params)


def normalized_errors(res, truth: dict) -> dict:
    """(estimate - truth) / sigma per parameter group, over the entries with a sigma."""
    out = {}
    for k, v in res.params.items():
        s = np.asarray(res.sigma[k], float)
        m = np.isfinite(s) & (s > 0)
        if m.any():
            out[k] = ((np.asarray(v) - np.asarray(truth[k]))[m] / s[m]).ravel()
    return out


def strip_rate_keys(text: str) -> str:
    """The plan as a user of a recorded log writes it: no rate or simulation keys."""
    keep = [ln for ln in text.splitlines()
            if not re.match(r"(rate_|sim_|sample_|transition_s|duration_s)", ln)]
    return "\n".join(keep) + "\n"
