"""Navigation-grade alignment scenarios for tests and validation (docs/align.md).

A plan text for two static positions related by a turn, and truth models of a
navigation-grade unit whose gyro scale-factor/misalignment errors are drawn
from the stated prior (``K_PRIOR`` per entry) for each seed.
"""

from __future__ import annotations

import numpy as np

from calib_cli.io.plan import parse_plan
from calib_cli.sim.grades import ACCEL_NOISE, ARW, DPH, K_PRIOR, UG, nav_truth  # noqa: F401

START_ATT_DEG = (0.8, -0.5, 30.0)

# (label, axis in body axes of position 1, angle deg): axes spread over the
# sphere, one about the (near-)vertical body z; none East-West horizontal
ROTATIONS = [
    ("vertical-120", (0.0, 0.0, 1.0), 120.0),
    ("x-90", (1.0, 0.0, 0.0), 90.0),
    ("diag-130", (1.0, 1.0, 1.0), 130.0),
    ("yz-170", (0.0, 1.0, -0.6), 170.0),
    ("mixed-60", (-1.0, 0.5, 1.0), 60.0),
    ("xy-150", (0.6, -1.0, 0.3), 150.0),
]


def _segments(positions: list[dict], duration: float) -> str:
    out = []
    for i, p in enumerate(positions):
        if "turn" in p:
            ax, ang = p["turn"]
            out.append(f'[[segment]]\nlabel = "turn-{i}"\nrotation_axis_body = {list(ax)}\n'
                       f'rotation_angle_deg = {ang}\nduration_s = 10.0\n')
        else:
            att = p.get("att")
            line = f"sim_attitude_deg = {list(att)}\n" if att is not None else ""
            out.append(f'[[segment]]\nlabel = "{p["label"]}"\nduration_s = {duration}\n{line}')
    return "\n".join(out)


def plan_text(turns, duration: float = 300.0, rate: float = 50.0, lat: float = 32.0,
              start=START_ATT_DEG) -> str:
    """A plan of kind align: position 1 at ``start`` (simulated truth), then for
    each (axis, angle_deg) in turns a turn segment and a further position."""
    pos = [{"label": "position-1", "att": start}]
    for k, t in enumerate(turns):
        pos.append({"turn": t})
        pos.append({"label": f"position-{k + 2}"})
    return (f'name = "align-sim"\nkind = "align"\nsample_rate_hz = {rate}\ntransition_s = 4.0\n'
            f"[site]\nlatitude_deg = {lat}\nheight_m = 0.0\n\n" + _segments(pos, duration))


def plan(turns, **kw):
    return parse_plan(plan_text(turns, **kw), "<align-sim>")


def wrap(a):
    """Angles (rad) into [-pi, pi)."""
    return (np.asarray(a) + np.pi) % (2 * np.pi) - np.pi


def run_case(turns, seeds, fit, duration: float = 300.0, rate: float = 50.0,
             k_prior: float = K_PRIOR, start=START_ATT_DEG, **fit_kw) -> dict:
    """Simulate and fit one rotation schedule over seeds (matched: seed s
    gives the same unit and noise stream whatever the schedule). Returns
    arrays over seeds: "err" (S, 9) estimate - truth for [nabla, eps,
    roll/pitch/yaw], "sigma" (S, 9)."""
    p = plan(turns, duration=duration, rate=rate, start=start)
    err, sig = [], []
    for s in seeds:
        truth = nav_truth(np.random.default_rng(10_000 + s), k_prior=k_prior)
        from calib_cli.sim.simulate import simulate

        rec = simulate(p, truth, seed=s)
        res = fit(rec, **fit_kw)
        e = np.concatenate([res.params["accel_bias"] - truth.params["accel_bias"],
                            res.params["gyro_bias"] - truth.params["gyro_bias"],
                            wrap(res.params["attitude"] - rec.truth["attitudes"][0])])
        err.append(e)
        sig.append(np.concatenate([res.sigma[k] for k in ("accel_bias", "gyro_bias",
                                                           "attitude")]))
    return {"err": np.array(err), "sigma": np.array(sig)}


def polar_axis_body(start=START_ATT_DEG, lat: float = 32.0) -> tuple:
    """The earth's axis in body axes of a unit at attitude ``start`` (deg)."""
    from calib_cli.model.frames import attitude_to_rotation

    la = np.radians(lat)
    v = attitude_to_rotation(np.radians(start)).inv().apply([0.0, np.cos(la), np.sin(la)])
    return tuple(float(x) for x in v)


def vertical_axis_body(start=START_ATT_DEG) -> tuple:
    """The local vertical in body axes of a unit at attitude ``start`` (deg)."""
    from calib_cli.model.frames import attitude_to_rotation

    v = attitude_to_rotation(np.radians(start)).inv().apply([0.0, 0.0, 1.0])
    return tuple(float(x) for x in v)


# static-only alignment (methods/align_static.py): (label, axis, angle, start).
# vertical-120 of ROTATIONS turns about body z, 0.94 deg off the vertical at
# START_ATT_DEG: near-degenerate for the static method (condition ~5e3)
STATIC_OBSERVABLE = [(lab, ax, ang, START_ATT_DEG) for lab, ax, ang in ROTATIONS[1:]] + [
    ("vertical+2deg-120", None, 120.0, START_ATT_DEG)]
STATIC_DEGENERATE = [
    ("vertical-120", (0.0, 0.0, 1.0), 120.0, START_ATT_DEG),
    ("vertical-exact-120", "vertical", 120.0, (0.0, 0.0, 30.0)),
    ("polar-axis-120", "polar", 120.0, START_ATT_DEG),
]


def static_axis(axis, start):
    """Resolve the named axes of STATIC_* (None: 2 deg off the vertical)."""
    if axis == "vertical":
        return vertical_axis_body(start)
    if axis == "polar":
        return polar_axis_body(start)
    if axis is None:
        from scipy.spatial.transform import Rotation

        v = Rotation.from_rotvec([np.radians(2.0), 0.0, 0.0]).apply(vertical_axis_body(start))
        return tuple(float(x) for x in v)
    return axis


def run_static_pair(axis, angle, seeds, fits, duration: float = 300.0, start=START_ATT_DEG):
    """Simulate one relative attitude per seed and run each of ``fits``
    (name -> function of the recording) on the same data. Returns, per fit,
    "err" (S, 12) estimate - truth over [nabla, eps, attitude_1, attitude_2]
    (attitude_2 NaN where the fit does not report it), "sigma" (S, 12; NaN:
    null) and "failed" (S,) bool (EstimationError, exit 4)."""
    from calib_cli.errors import EstimationError
    from calib_cli.sim.simulate import simulate

    p = plan([(static_axis(axis, start), angle)], duration=duration, start=start)
    out = {k: {"err": [], "sigma": [], "failed": []} for k in fits}
    for s in seeds:
        truth = nav_truth(np.random.default_rng(10_000 + s))
        rec = simulate(p, truth, seed=s)
        att = rec.truth["attitudes"][[i for i, sg in enumerate(rec.segments)
                                      if sg.kind == "static"]]
        for name, fn in fits.items():
            o = out[name]
            try:
                res = fn(rec)
            except EstimationError:
                o["failed"].append(True)
                o["err"].append(np.full(12, np.nan))
                o["sigma"].append(np.full(12, np.nan))
                continue
            a2 = res.stats.get("attitude_2")
            if a2 is None and "attitudes_all" in res.stats:
                a2 = res.stats["attitudes_all"][1]
            s2 = res.stats.get("attitude_2_sigma", [None] * 3)
            o["failed"].append(False)
            o["err"].append(np.concatenate([
                res.params["accel_bias"] - truth.params["accel_bias"],
                res.params["gyro_bias"] - truth.params["gyro_bias"],
                wrap(res.params["attitude"] - att[0]),
                wrap(np.asarray(a2, float) - att[1]) if a2 is not None else np.full(3, np.nan)]))
            o["sigma"].append(np.concatenate(
                [np.asarray(res.sigma[k], float) for k in ("accel_bias", "gyro_bias", "attitude")]
                + [np.array([np.nan if v is None else v for v in s2], float)]))
    return {k: {kk: np.array(vv) for kk, vv in v.items()} for k, v in out.items()}
