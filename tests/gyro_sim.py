"""Shared helpers for the gyro simulated-truth tests."""

from __future__ import annotations

import numpy as np

from calib_cli.io.plan import parse_plan
from calib_cli.model.imu_model import base_model
from calib_cli.model.truth import Truth
from calib_cli.sim.simulate import simulate

ATTITUDES = [[0, 0, 0], [180, 0, 0], [90, 0, 0], [-90, 0, 0], [0, -90, 0], [0, 90, 0],
             [45, 30, 10], [-30, 60, 100], [120, -40, 200], [-150, 20, 300],
             [60, -70, 45], [10, 45, 250]]


def plan_text(turns: bool = True, static_s: float = 8.0, rate: float = 100.0,
              counts: bool = False) -> str:
    lines = ['name = "gyro-sim"', 'kind = "static"', f"sample_rate_hz = {rate}",
             "transition_s = 4.0", "[site]", "latitude_deg = 48.0", "height_m = 300.0"]
    for i, a in enumerate(ATTITUDES):
        lines += ["[[segment]]", f'label = "p{i}"', f"attitude_deg = {a}",
                  f"duration_s = {static_s}"]
    if turns:
        for ax, att in (([1, 0, 0], [0, -90, 0]), ([0, 1, 0], [90, 0, 0]), ([0, 0, 1], [0, 0, 0])):
            lines += ["[[segment]]", f'label = "q{ax}"', f"attitude_deg = {att}",
                      f"duration_s = {static_s}"]
            lines += ["[[segment]]", f'label = "turn{ax}"', f"attitude_deg = {att}",
                      f"rotation_axis_body = {ax}", "rotation_angle_deg = 360.0",
                      "duration_s = 8.0"]
    return "\n".join(lines) + "\n"


def truth(rng, g_sensitivity: bool = True) -> Truth:
    model = base_model(g_sensitivity=g_sensitivity)
    params = {}
    for spec in model.specs():
        free = ~spec.fixed_mask()
        params[spec.key] = spec.neutral() + rng.standard_normal(spec.shape) * spec.typical * free
    return Truth(model, params, {"accel_white": 3e-3, "gyro_white": 1e-3})


def simulated(seed: int, turns: bool = True, g_sensitivity: bool = True):
    plan = parse_plan(plan_text(turns))
    rng = np.random.default_rng(1000 + seed)
    tr = truth(rng, g_sensitivity)
    return simulate(plan, tr, seed), tr


def normalized_errors(res, tr) -> np.ndarray:
    out = []
    for key in ("gyro_bias", "gyro_K", "gyro_D"):
        if key not in res.params or key not in tr.params:
            continue
        est, sig = np.asarray(res.params[key]), np.asarray(res.sigma[key])
        ok = np.isfinite(sig) & (sig > 0)
        out.append(((est - tr.params[key])[ok] / sig[ok]).ravel())
    return np.concatenate(out)


HAND_PLAN = ('name = "hand"\nkind = "static"\nsample_rate_hz = 100.0\ntransition_s = 3.0\n'
             '[site]\nlatitude_deg = 45.0\n[[segment]]\nlabel = "pos"\nrepeat = "auto"\n'
             'sim_repeat = 20\nduration_s = 6.0\n')


def hand_placed(seed: int):
    """A hand-placed session: 20 positions of unknown attitude (scalar
    accelerometer fit, lower-triangular K), transitions between them."""
    plan = parse_plan(HAND_PLAN)
    tr = truth(np.random.default_rng(2000 + seed), True)
    return simulate(plan, tr, seed), tr


def normalized_errors_hand(res, tr) -> np.ndarray:
    """As normalized_errors, with the truth expressed in the frame the
    accelerometers fix (truth accel K = L Q: G and D in that frame are G Q^T, D Q^T)."""
    from calib_cli.validation.validate_datasets import lower_times_rotation

    _, Q = lower_times_rotation(tr.params["accel_K"])
    want = {"gyro_bias": tr.params["gyro_bias"], "gyro_K": tr.params["gyro_K"] @ Q.T,
            "gyro_D": tr.params["gyro_D"] @ Q.T}
    return np.concatenate([((np.asarray(res.params[k]) - v) / res.sigma[k]).ravel()
                           for k, v in want.items()])
