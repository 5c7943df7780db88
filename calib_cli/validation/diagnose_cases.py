"""Hidden-effect cases for validating ``calib diagnose`` (docs/diagnose.md).

Each case: a plan that excites the effect, a random MEMS unit (bias and K of
both sensors, ``default_truth``) plus exactly one hidden effect whose every
observable entry is drawn at U(5, 10) times that entry's own 1-sigma (from
the diagnose refit of base + effect on an effect-free pilot record of the
same plan), with a random sign. The workflow must name the effect first.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from calib_cli.io.plan import parse_plan
from calib_cli.methods.diagnose import base_spec
from calib_cli.methods.diagnose_candidates import effect_key
from calib_cli.methods.diagnose_fit import ModelSpec, fit_model
from calib_cli.methods.diagnose_problem import build_problem
from calib_cli.model.effects import make_effect
from calib_cli.model.imu_model import ImuModel
from calib_cli.model.truth import Truth, default_truth
from calib_cli.sim.simulate import plan_layout, simulate
from calib_cli.validation import align_cases

_SITE = """
[site]
latitude_deg = 50.45
height_m = 180.0
"""

# static multi-position: the six axis positions, eight 45-degree tilts
# and twelve at 30 and 60 degrees (intermediate inputs tell nonlinearity from
# asymmetry), temperature up and down
_STATIC_ATT = [(0, -90, 0), (0, 90, 0), (90, 0, 0), (-90, 0, 0), (0, 0, 0), (180, 0, 0),
               (45, 0, 0), (-45, 0, 0), (0, 45, 0), (0, -45, 0), (135, 0, 0), (-135, 0, 0),
               (0, 135, 0), (45, 45, 0), (30, 0, 0), (-60, 0, 0), (0, 30, 0), (0, -60, 0),
               (150, 0, 0), (0, 120, 0), (-30, -30, 0), (60, 60, 0)]

ACCEL_PLAN = ('name = "diag-static"\nkind = "static"\nsample_rate_hz = 50.0\n'
              'transition_s = 2.0\n'
              'temperature_profile = [[0, 20.0], [80, 35.0], [170, 25.0], [300, 32.0]]\n'
              + _SITE + "".join(
                  f'[[segment]]\nlabel = "p{i}"\nattitude_deg = [{a}, {b}, {c}]\n'
                  'duration_s = 10.0\n' for i, (a, b, c) in enumerate(_STATIC_ATT)))

_PROFILE = "[[0, 30], [8, 30], [10, 150], [18, 150], [20, -90], [28, -90]]"
# six static positions, then four rotating cycles about the vertical (turntable and rimu plans)
_STATIC_AND_ROTATING = (
    "".join(f'[[segment]]\nlabel = "s{i}"\nattitude_deg = [{a}, {b}, {c}]\nduration_s = 6.0\n'
            for i, (a, b, c) in enumerate(_STATIC_ATT[:6]))
    + "".join(f'[[segment]]\nlabel = "r{i}"\nattitude_deg = [{a}, {b}, {c}]\n'
              f'table_axis_enu = [0, 0, 1]\nrate_profile = {_PROFILE}\n'
              for i, (a, b, c) in enumerate([(0, 0, 0), (0, -90, 0), (90, 0, 0), (30, 40, 0)])))
TURNTABLE_PLAN = ('name = "diag-turntable"\nkind = "turntable"\nsample_rate_hz = 50.0\n'
                  'transition_s = 2.0\n'
                  'temperature_profile = [[0, 20.0], [70, 35.0], [140, 24.0], [220, 30.0]]\n'
                  + _SITE + _STATIC_AND_ROTATING)

# the rough stand of the turntable method (issue 32): four rotating cycles about a
# horizontal axis (East), no static positions: gravity turns through the body axes
TURNTABLE_H_PLAN = ('name = "diag-turntable-horizontal"\nkind = "turntable"\n'
                    'sample_rate_hz = 50.0\ntransition_s = 2.0\n'
                    'temperature_profile = [[0, 20.0], [70, 35.0], [140, 24.0], [220, 30.0]]\n'
                    + _SITE + "".join(
                        f'[[segment]]\nlabel = "r{i}"\nattitude_deg = [{a}, {b}, {c}]\n'
                        f'table_axis_enu = [1, 0, 0]\nrate_profile = {_PROFILE}\n'
                        for i, (a, b, c) in enumerate([(0, 0, 0), (0, 0, 90), (90, 0, 0),
                                                       (30, 40, 20)])))

# a redundant unit (tetrahedron profile, 9 sensors) on a rate table: six static
# positions and four rotating cycles, temperature up and down
RIMU_PLAN = ('name = "diag-rimu"\nkind = "rimu"\nsample_rate_hz = 50.0\ntransition_s = 2.0\n'
             'temperature_profile = [[0, 20.0], [70, 35.0], [140, 24.0], [220, 30.0]]\n'
             + _SITE + '[rimu]\nprofile = "tetrahedron"\n' + _STATIC_AND_ROTATING)

# two-position alignment of a navigation-grade unit (validation/align_cases): 2 x 300 s
# related by a 130 deg turn, the temperature going up and down in both positions
# (a thermal drift then differs from a slow wander)
_ALIGN_TEMP = ("temperature_profile = [[0, 20.0], [60, 25.0], [120, 21.0], [180, 26.0], "
               "[240, 22.0], [300, 27.0], [360, 23.0], [420, 28.0], [480, 24.0], "
               "[540, 29.0], [640, 25.0]]\n")
ALIGN_PLAN = align_cases.plan_text([align_cases.ROTATIONS[2][1:]], duration=300.0).replace(
    "transition_s = 4.0\n", "transition_s = 4.0\n" + _ALIGN_TEMP)

# gyro method (`diagnose --method gyro`, no table): the twelve positions of
# tests/gyro_sim.py with the transitions between them (the turns of known angle,
# both ways about every axis) and a 360-degree turn about each axis, temperature
# up and down
_GYRO_ATT = [(0, 0, 0), (180, 0, 0), (90, 0, 0), (-90, 0, 0), (0, -90, 0), (0, 90, 0),
             (45, 30, 10), (-30, 60, 100), (120, -40, 200), (-150, 20, 300),
             (60, -70, 45), (10, 45, 250)]
GYRO_PLAN = ('name = "diag-gyro"\nkind = "static"\nsample_rate_hz = 50.0\ntransition_s = 4.0\n'
             'temperature_profile = [[0, 20.0], [60, 35.0], [130, 24.0], [200, 32.0]]\n'
             + _SITE
             + "".join(f'[[segment]]\nlabel = "p{i}"\nattitude_deg = [{a}, {b}, {c}]\n'
                       'duration_s = 8.0\n' for i, (a, b, c) in enumerate(_GYRO_ATT))
             + "".join(f'[[segment]]\nlabel = "q{k}"\nattitude_deg = {att}\nduration_s = 8.0\n'
                       f'[[segment]]\nlabel = "turn{k}"\nattitude_deg = {att}\n'
                       f'rotation_axis_body = {ax}\nrotation_angle_deg = 360.0\n'
                       'duration_s = 8.0\n'
                       for k, (ax, att) in enumerate((([1, 0, 0], [0, -90, 0]),
                                                      ([0, 1, 0], [90, 0, 0]),
                                                      ([0, 0, 1], [0, 0, 0])))))

BI_BIN_SIGMAS = 0.1  # flicker figure B per unit of scale, in bin-mean sigmas

PLANS = {"accel": ACCEL_PLAN, "turntable": TURNTABLE_PLAN,
         "turntable-horizontal": TURNTABLE_H_PLAN, "rimu": RIMU_PLAN,
         "align": ALIGN_PLAN, "gyro": GYRO_PLAN}

# case key -> (method, effect name, sensor, base, options)
CASES = {
    "accel_nonlinearity": ("accel", "accel_nonlinearity", "accel", "full"),
    "accel scale_asymmetry": ("accel", "scale_asymmetry", "accel", "full"),
    "accel temperature_drift": ("accel", "temperature_drift", "accel", "full"),
    "accel misalignment": ("accel", "misalignment", "accel", "diagonal"),
    "lever_arm": ("turntable", "lever_arm", "", "full"),
    "proof_mass_offsets": ("turntable", "proof_mass_offsets", "", "full"),
    "time_offset": ("turntable", "time_offset", "", "full"),
    "gyro g_sensitivity": ("turntable", "g_sensitivity", "gyro", "full"),
    "gyro temperature_drift": ("turntable", "temperature_drift", "gyro", "full"),
    "gyro scale_asymmetry": ("turntable", "scale_asymmetry", "gyro", "full"),
    "gyro misalignment": ("turntable", "misalignment", "gyro", "diagonal"),
    "accel bias_random_walk": ("accel", "bias_random_walk", "accel", "full"),
    "gyro bias_random_walk": ("turntable", "bias_random_walk", "gyro", "full"),
    "accel bias_instability": ("accel", "bias_instability", "accel", "full"),
    "gyro bias_instability": ("turntable", "bias_instability", "gyro", "full"),
    "rimu: accel_nonlinearity": ("rimu", "accel_nonlinearity", "accel", "full"),
    "rimu: gyro g_sensitivity": ("rimu", "g_sensitivity", "gyro", "full"),
    "rimu: gyro temperature_drift": ("rimu", "temperature_drift", "gyro", "full"),
    "rimu: lever_arm": ("rimu", "lever_arm", "", "full"),
    "align: accel temperature_drift": ("align", "temperature_drift", "accel", "full"),
    "align: gyro temperature_drift": ("align", "temperature_drift", "gyro", "full"),
    "gyro: gyro scale_asymmetry": ("gyro", "scale_asymmetry", "gyro", "full"),
    "gyro: gyro misalignment": ("gyro", "misalignment", "gyro", "diagonal"),
    "gyro: gyro g_sensitivity": ("gyro", "g_sensitivity", "gyro", "full"),
    "gyro: gyro temperature_drift": ("gyro", "temperature_drift", "gyro", "full"),
    "gyro: gyro bias_random_walk": ("gyro", "bias_random_walk", "gyro", "full"),
    "gyro: gyro bias_instability": ("gyro", "bias_instability", "gyro", "full"),
}
# the gyro method's cases are their own validation part (`make validate K=diagnose_gyro`)
GYRO_CASES = [c for c, v in CASES.items() if v[0] == "gyro"]
MAIN_CASES = [c for c, v in CASES.items() if v[0] != "gyro"]


# measured and reported in docs/validation/diagnose.md, not asserted: {case: why}
# (the gyro method's wandering biases are candidates since issue 18's validation:
# methods/diagnose_gyro_wander.py)
REPORTED_ONLY: dict = {}


def expected(case: str) -> str:
    """The effect key the workflow should name first for a case."""
    _, name, sensor, _ = CASES[case]
    return effect_key(name, sensor)


def effect_of(method, name, sensor):
    if method == "gyro":
        from calib_cli.methods.fit_with import gyro_effect

        return gyro_effect(name)
    if name == "misalignment":
        st = "lower" if (method == "turntable" and sensor == "accel") else "full"
        return make_effect(name, sensor, structure=st)
    return make_effect(name, sensor or "accel")


@lru_cache(maxsize=None)
def plan_of(method: str):
    return parse_plan(PLANS[method])


@lru_cache(maxsize=None)
def effect_sigma(case: str, record_as=None, plan_key: str | None = None) -> dict:
    """1-sigma of each entry of the case's effect, from base + effect refit on a pilot.
    record_as: the pilot record as the case logs it (``record_as(rec)``: without the
    table's channels, a noisier encoder), so the effect is sized by its own sigma there;
    plan_key: another plan of PLANS for the method (a horizontal table's)."""
    method, name, sensor, base = CASES[case]
    plan = plan_of(plan_key or method)
    rec = simulate(plan, base_truth(plan, np.random.default_rng(12345), base), seed=12345)
    if record_as is not None:
        rec = record_as(rec)
    if method == "gyro":
        from calib_cli.methods.fit_with import fit_with_gyro

        res = fit_with_gyro(rec, [(name, sensor)], base=base)
        return {s.key: res.sigma[s.key] for s in effect_of(method, name, sensor).specs(rec.layout)}
    if method == "turntable":  # the filter's own sigma (methods/turntable/diagnose.py)
        from calib_cli.methods.turntable import TurntableOptions
        from calib_cli.methods.turntable.diagnose import fit_with

        res = fit_with(rec, TurntableOptions(), [(name, sensor)], base)
        return {s.key: res.sigma[s.key] for s in effect_of(method, name, sensor).specs(rec.layout)}
    pb = build_problem(rec, method)
    spec, _ = base_spec(pb, base)
    eff = effect_of(method, name, sensor)
    f = fit_model(pb, ModelSpec(spec.model.with_effect(eff), spec.mount), refresh=True)
    return {s.key: f.sigma[s.key] for s in eff.specs(pb.layout)}


def base_truth(plan, rng, base: str) -> Truth:
    if plan.kind == "align":  # the alignment's unit: navigation grade
        return align_cases.nav_truth(rng)
    t = default_truth(plan_layout(plan), rng)
    if plan.kind == "rimu":  # installation errors of a real unit: about 1 mrad, 0.1 %
        p = dict(t.params)
        for k in p:
            if k.endswith(("_dEl", "_dAz")):
                p[k] = p[k] * 0.1
            elif k.endswith("_scale_error"):
                p[k] = p[k] * 0.2
        t = Truth(t.model, p, t.noise)
    if base == "diagonal":
        p = dict(t.params)
        for k in ("accel_K", "gyro_K"):
            p[k] = np.diag(np.diag(p[k]))
        t = Truth(t.model, p, t.noise)
    return t


def effect_draws(sigma: dict, rng, scale=(5.0, 10.0)) -> dict:
    """Each observable entry (finite sigma > 0) of an effect U(scale) times its 1-sigma with
    a random sign, the others 0: {key: value}."""
    out = {}
    for key, sig in sigma.items():
        sig = np.asarray(sig, float)
        ok = np.isfinite(sig) & (sig > 0)
        mag = rng.uniform(*scale, size=sig.shape) * rng.choice([-1.0, 1.0], size=sig.shape)
        out[key] = np.where(ok, mag * np.where(ok, sig, 0.0), 0.0)
    return out


def hidden_effect_truth(case: str, rng, scale=(5.0, 10.0), params: dict | None = None,
                        sigma: dict | None = None, plan_key: str | None = None) -> Truth:
    """A random unit with the case's effect hidden in it, each entry U(scale) times its
    1-sigma (``sigma``, else ``effect_sigma(case)``); plan_key: the record's plan where it
    is not the method's (PLANS)."""
    method, name, sensor, base = CASES[case]
    plan = plan_of(plan_key or method)
    t = base_truth(plan, rng, base)
    eff = effect_of(method, name, sensor)
    p = dict(t.params)
    if params is None and name == "bias_random_walk":
        # no refit sigma for a process: a wander over the record of U(5, 10) times
        # the noise of one 0.5 s bin mean, per channel (q / sigma(q) of the fitted
        # walk is then 4-10, docs/diagnose.md)
        n_bin = 0.5 * plan.sample_rate
        white = np.asarray(t.noise[f"{sensor}_white"], float)
        span = _span(plan)
        p[f"{sensor}_bias_rw"] = (rng.uniform(*scale, size=3) * white / np.sqrt(n_bin)
                                  / np.sqrt(span))
    elif params is None and name == "bias_instability":
        # a flicker figure B of U(5, 10) x BI_BIN_SIGMAS times the noise of one 0.5 s bin
        # mean per channel: the truth is then 6-20 times the fitted figure's own sigma
        # (docs/validation/diagnose.md)
        n_bin = 0.5 * plan.sample_rate
        white = np.asarray(t.noise[f"{sensor}_white"], float)
        p[f"{sensor}_bias_instability"] = (rng.uniform(*scale, size=3) * BI_BIN_SIGMAS
                                           * white / np.sqrt(n_bin))
    elif params is None:
        p.update(effect_draws(effect_sigma(case) if sigma is None else sigma, rng, scale))
    else:
        p.update(params)
    return Truth(ImuModel(t.model.effects + (eff,), t.model.layout), p, t.noise)


@lru_cache(maxsize=None)
def _span_of(method: str) -> float:
    rec = simulate(plan_of(method), seed=0)
    return float(rec.time[-1] - rec.time[0])


def _span(plan) -> float:
    return _span_of(next(m for m, txt in PLANS.items() if plan_of(m) is plan))


def run_case(case: str | None, seed: int, method: str | None = None, truth=None):
    """Simulate one case (None: no hidden effect) and diagnose it."""
    from calib_cli.methods.diagnose import diagnose

    if case is not None:
        method = CASES[case][0]
    plan = plan_of(method)
    rng = np.random.default_rng(seed)
    if truth is None:
        truth = hidden_effect_truth(case, rng) if case else base_truth(plan, rng, "full")
    base = CASES[case][3] if case else "full"
    rec = simulate(plan, truth, seed=seed + 1)
    if method == "gyro":
        from calib_cli.methods.diagnose_gyro import diagnose_gyro

        return diagnose_gyro(rec, base=base)
    return diagnose(rec, method, base=base)


def first_key(d) -> str | None:
    if not d.steps:
        return None
    s = d.steps[0]
    return effect_key(s.effect, s.sensor)
