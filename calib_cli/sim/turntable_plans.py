"""Plans and truths for the rotating-table experiment (docs/turntable.md).

The table axis is horizontal and fixed (East, ENU [1, 0, 0]). Standard cycle
k puts instrument axis k along the table axis; a tilted cycle (k, j) tilts
axis k by ``tilt_deg`` towards axis j, the third axis staying orthogonal to
the table axis (six such cycles: every ordered pair k != j).

Plan keys written here and read by ``calib simulate``:

- ``rate_profile`` (per segment): table rate knots, joined by smoothsteps
  (``rate_shape = "smooth"``: the angular acceleration is continuous).
- ``sim_attitude_deg``: the true attitude at the cycle start (mounting error
  and unknown start angle of the table), ``attitude_deg`` being the nominal.
- ``sim_table_axis_enu``: the table's true axis, tilted from the plan's
  horizontal one by up to ``axis_tilt_deg`` (default 0: the fit takes the plan's
  axis as exact, docs/turntable.md), the same in every cycle.
- ``sim_lever_arm_m``: the true lever arm; ``lever_arm_m`` is the value
  "measured on the housing" (truth + a random error per component).
- plan level ``sim_proof_mass_sigma_m``: 1-sigma of the random true proof-mass
  offsets (default 5 mm).
- plan level ``sim_table_rate_error`` (relative 1-sigma scale error of the
  table rate) and ``sim_table_wobble_dps`` (rate wobble amplitude): the
  recorded table angle/rate is the nominal profile, not the true motion.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from calib_cli.model.frames import attitude_to_rotation, rotation_to_attitude
from calib_cli.model.imu_model import ImuModel
from calib_cli.model.truth import Truth

TABLE_AXIS = np.array([1.0, 0.0, 0.0])
STD_ATTITUDES_DEG = ([0.0, 0.0, 0.0], [0.0, 0.0, -90.0], [0.0, 90.0, 0.0])  # x, y, z along East
MEMS_NOISE = {"accel_white": 8e-3 * 9.80665, "gyro_white": np.radians(0.05)}  # per sample, 100 Hz
AXES = "xyz"


def rate_profile(duration_s: float, max_dps: float = 200.0, ramp_s: float = 1.0,
                 hold_s: float = 20.0) -> list[list[float]]:
    """Holds and short ramps between -max and +max deg/s, starting and ending at rest.

    Levels cycle through 0, +-max, +-max/2, +-3max/4, +-max/4 so that the
    centripetal term (omega^2) varies and separates from the biases.
    """
    levels = [0.0, 1.0, -1.0, 0.5, -0.5, 0.0, 0.75, -0.75, 0.25, -0.25]
    knots = [[0.0, 0.0], [min(5.0, duration_s / 4), 0.0]]
    t = knots[-1][0]
    k = 1
    while True:
        r = levels[k % len(levels)] * max_dps
        if t + 2 * ramp_s + hold_s + 5.0 > duration_s:
            break
        t += ramp_s
        knots.append([t, r])
        t += hold_s
        knots.append([t, r])
        k += 1
    t += ramp_s
    knots.append([t, 0.0])
    if duration_s > t:
        knots.append([duration_s, 0.0])
    return [[round(a, 6), round(b, 6)] for a, b in knots]


def cycle_attitudes(tilted: bool = False, tilt_deg: float = 5.0):
    """[(label, attitude_deg, axis_in_body)] of the 3 standard (and 6 tilted) cycles."""
    out = []
    for k in range(3):
        out.append((f"{AXES[k]}-axis", np.array(STD_ATTITUDES_DEG[k]), np.eye(3)[k]))
    if tilted:
        tl = np.radians(tilt_deg)
        for k in range(3):
            for j in range(3):
                if j == k:
                    continue
                a_b = np.cos(tl) * np.eye(3)[k] + np.sin(tl) * np.eye(3)[j]
                # the body turn taking a_b onto e_k (about the third axis), then the standard pose
                rot_b = Rotation.align_vectors([np.eye(3)[k]], [a_b])[0]
                rot = attitude_to_rotation(np.radians(STD_ATTITUDES_DEG[k])) * rot_b
                out.append((f"{AXES[k]}-tilt-{AXES[j]}", np.degrees(rotation_to_attitude(rot)), a_b))
    return out


def true_lever_arms(n: int, axes_body, rng) -> np.ndarray:
    """Lever arms up to 30 cm: one large (20-29.5 cm) and one small (1-3 cm) component
    perpendicular to the axis, random signs, different in each cycle; s . a = 0 for the
    given (nominal) axes."""
    out = np.zeros((n, 3))
    for c in range(n):
        a = np.asarray(axes_body[c], float)
        k = int(np.argmax(np.abs(a)))
        perp = [j for j in range(3) if j != k]
        rng.shuffle(perp)
        s = np.zeros(3)
        s[perp[0]] = rng.choice([-1, 1]) * rng.uniform(0.20, 0.295)
        s[perp[1]] = rng.choice([-1, 1]) * rng.uniform(0.01, 0.03)
        out[c] = s - a * (s @ a) / (a @ a)
    return out


def _fmt(v) -> str:
    return "[" + ", ".join(f"{float(x):.9g}" for x in np.ravel(v)) + "]"


def turntable_plan_text(seed: int = 0, duration_s: float = 600.0, tilted: bool = False,
                        tilt_deg: float = 5.0, tilted_duration_s: float = 300.0,
                        sample_rate_hz: float = 100.0, housing_error_m: float = 5e-3,
                        mount_error_deg: float = 0.3, start_error_deg: float = 3.0,
                        rate_error: float = 2e-3, wobble_dps: float = 0.5,
                        max_dps: float = 200.0, latitude_deg: float = 50.45,
                        proof_mass_sigma_m: float = 5e-3, axis_tilt_deg: float = 0.0,
                        transition_s: float = 4.0, table_axis=None) -> str:
    """A turntable plan with random true lever arms, mounting errors and housing
    measurements (all drawn from ``seed``); ``transition_s``: the remount between cycles;
    ``table_axis`` (ENU): the table's axis (default east, horizontal): the whole set-up
    turned with it (the cycles' axes in body axes stay the same; gravity sees another
    geometry: [0, 0, 1] is the classic vertical rate table)."""
    rng = np.random.default_rng(10_000 + seed)
    cycles = cycle_attitudes(tilted, tilt_deg)
    # the set-up turned so that the east axis goes to table_axis (ENU)
    turn = Rotation.identity() if table_axis is None else Rotation.align_vectors(
        [np.asarray(table_axis, float) / np.linalg.norm(table_axis)], [TABLE_AXIS])[0]
    # the table's true axis: tilted from the horizontal by up to axis_tilt_deg, the same for
    # every cycle (one table); the unit sits on it as the plan says, up to the mounting error
    tilt = np.radians(rng.uniform(-1, 1) * axis_tilt_deg)
    true_axis = np.array([np.cos(tilt), 0.0, np.sin(tilt)])
    to_true = Rotation.align_vectors([true_axis], [TABLE_AXIS])[0]
    sim_att = []
    for _label, att, _a in cycles:
        rot = attitude_to_rotation(np.radians(att))
        start = Rotation.from_rotvec(TABLE_AXIS * np.radians(rng.uniform(-1, 1) * start_error_deg))
        mount = Rotation.from_rotvec(rng.standard_normal(3) * np.radians(mount_error_deg))
        true = turn * to_true * start * rot * mount
        sim_att.append(np.degrees(rotation_to_attitude(true)))
    # the point on the table axis is any: take the one that makes s . a_nominal = 0, the
    # convention of the fit (the component along the axis is unobservable)
    s_true = true_lever_arms(len(cycles), [a for _l, _att, a in cycles], rng)
    lines = ["name = 'turntable'", "kind = 'turntable'", f"sample_rate_hz = {sample_rate_hz}",
             f"transition_s = {transition_s}", f"sim_table_rate_error = {rate_error}",
             f"sim_table_wobble_dps = {wobble_dps}",
             f"sim_proof_mass_sigma_m = {proof_mass_sigma_m}",
             "[site]", f"latitude_deg = {latitude_deg}", "height_m = 180.0",
             "[unit]", "serial = 'SN-TT1'"]
    for c, (label, att, a_nom) in enumerate(cycles):
        dur = duration_s if c < 3 else tilted_duration_s
        housing = s_true[c] + rng.uniform(-1, 1, 3) * housing_error_m
        housing = housing - a_nom * (housing @ a_nom)
        att_plan = np.degrees(rotation_to_attitude(turn * attitude_to_rotation(np.radians(att))))
        lines += ["[[segment]]", f"label = '{label}'", f"attitude_deg = {_fmt(att_plan)}",
                  f"sim_attitude_deg = {_fmt(sim_att[c])}",
                  f"table_axis_enu = {_fmt(turn.apply(TABLE_AXIS))}",
                  f"sim_table_axis_enu = {_fmt(turn.apply(true_axis))}",
                  f"lever_arm_m = {_fmt(housing)}", f"sim_lever_arm_m = {_fmt(s_true[c])}",
                  "rate_shape = 'smooth'", f"rate_profile = {rate_profile(dur, max_dps)}"]
    return "\n".join(lines) + "\n"


def turntable_truth(plan, rng, noise=None, proof_mass_sigma: float | None = None) -> Truth:
    """A random MEMS unit on the table: biases, lower-triangular accelerometer K,
    full gyro G, g-sensitivity D, the plan's true lever arms (``sim_lever_arm_m``,
    else ``lever_arm_m``, else 0) and random proof-mass offsets."""
    from calib_cli.model.effects import Layout, make_effect

    rotating = [s for s in plan.segments if s.kind == "rotating"]
    layout = Layout(n_cycles=len(rotating))
    effects = (make_effect("bias", "accel"), make_effect("scale_misalignment", "accel",
                                                         structure="lower"),
               make_effect("bias", "gyro"), make_effect("scale_misalignment", "gyro"),
               make_effect("g_sensitivity"), make_effect("lever_arm"),
               make_effect("proof_mass_offsets"))
    model = ImuModel(effects, layout)
    if proof_mass_sigma is None:
        proof_mass_sigma = float(plan.extra.get("sim_proof_mass_sigma_m", 5e-3))
    params = model.random_params(rng, {"proof_mass_offsets": proof_mass_sigma}, skip=("lever_arm",))
    s = np.zeros((len(rotating), 3))
    for c, seg in enumerate(rotating):
        v = seg.extra.get("sim_lever_arm_m", seg.extra.get("lever_arm_m"))
        if v is not None:
            s[c] = np.asarray(v, float)
    params["lever_arm"] = s
    return Truth(model, params, dict(noise or MEMS_NOISE))
