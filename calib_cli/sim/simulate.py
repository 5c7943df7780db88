"""Simulate a plan: the unit's motion, the true inputs, the sensor outputs.

Timeline: the plan's segments in order, with a smooth turn (minimum-jerk,
``transition_s``, default 4 s) between consecutive segments, recorded
continuously (transition samples have segment index -1). Per segment kind:

- static: held at ``sim_attitude_deg`` (the true attitude, where the plan's
  ``attitude_deg`` is nominal or absent), else ``attitude_deg``, else the
  attitude reached by a preceding turn segment, else a random one.
  ``repeat = "auto"`` gives ``sim_repeat`` (default 12) random positions.
- turn: ``rotation_angle_deg`` about ``rotation_axis_body``, minimum-jerk
  over ``duration_s`` (default 10 s).
- rotating: about ``table_axis_enu`` at ``table_rate_dps`` or along
  ``rate_profile = [[t_s, rate_dps], ...]`` (piecewise linear knots from the
  segment start; the duration is the last knot). Each rotating segment is a
  lever-arm cycle. ``rate_shape = "smooth"`` joins the knots with smoothsteps
  (continuous angular acceleration) instead of straight ramps. Without any
  rate key (CONTRACT.md section 3: the rate keys are optional) the default
  profile ``turntable_plans.rate_profile(duration_s or 120 s)`` is run: holds
  at 0, +-200, +-100, +-150, +-50 deg/s with 1 s straight ramps.
  ``sim_table_axis_enu``: the true table axis where it differs from the plan's.

Top-level simulation keys: ``sample_rate_hz`` (100), ``transition_s`` (4),
``temperature_c`` (constant) or ``temperature_profile = [[t_s, degC], ...]``,
or a chamber setpoint per segment ``chamber_temp_degC`` (sim/chamber.py),
``sim_grade`` ("navigation" for plans of kind align, the default truth then
being a random navigation-grade unit, docs/align.md; "mems" for the MEMS default).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from scipy.spatial.transform import Rotation

from calib_cli.data import SAMPLE_KINDS, Recording, Segment
from calib_cli.errors import InputError
from calib_cli.model import kinematics as kn
from calib_cli.model.frames import attitude_to_rotation, axis_angle, rotation_to_attitude
from calib_cli.model.truth import Truth, default_truth
from calib_cli.plan import Plan, PlanSegment, plan_layout, same_layout  # noqa: F401  (re-exported)
from calib_cli.sim import rate_profiles as rp

D2R = np.pi / 180.0
DEFAULT_ROTATING_S = 120.0  # a rotating segment without duration_s or rate keys


def _times(t0: float, duration: float, fs: float) -> np.ndarray:
    n = max(int(round(duration * fs)), 1)
    return t0 + np.arange(n) / fs


def _rate_profile(seg: PlanSegment, fs: float, t0: float):
    """Table angle, rate and angular acceleration along a segment's profile
    (sim/rate_profiles.py: the families and their keys)."""
    if "rate_oscillation" in seg.extra:
        try:
            amp, freq = (float(v) for v in seg.extra["rate_oscillation"])
        except (TypeError, ValueError):
            raise InputError(f"segment {seg.label!r}: rate_oscillation must be "
                             "[amplitude_dps, frequency_hz]") from None
        if not (freq > 0 and np.isfinite(amp)):
            raise InputError(f"segment {seg.label!r}: rate_oscillation needs a positive frequency")
        t = _times(0.0, seg.duration or DEFAULT_ROTATING_S, fs)
        theta, rate, accel = rp.oscillation(t, amp * D2R, freq)
        return t0 + t, theta, rate, accel
    if "rate_profile" in seg.extra:
        knots = np.asarray(seg.extra["rate_profile"], dtype=float)
        if knots.ndim != 2 or knots.shape[1] != 2 or len(knots) < 2 or np.any(np.diff(knots[:, 0]) <= 0):
            raise InputError(f"segment {seg.label!r}: rate_profile must be [[t_s, rate_dps], ...] "
                             "with increasing times")
        kt, kr = knots[:, 0] - knots[0, 0], knots[:, 1] * D2R
    elif seg.table_rate is not None:
        dur = seg.duration or 36.0
        kt, kr = np.array([0.0, dur]), np.full(2, seg.table_rate)
    else:  # no rate key: the default profile (holds at 0, +-50 .. +-200 deg/s, docs/simulate.md)
        from calib_cli.sim.turntable_plans import rate_profile

        knots = np.asarray(rate_profile(seg.duration or DEFAULT_ROTATING_S), dtype=float)
        kt, kr = knots[:, 0], knots[:, 1] * D2R
    shape = seg.extra.get("rate_shape", "linear")
    jerk = _num_key(seg.extra, "rate_jerk_dps3", 1000.0, f"segment {seg.label!r}",
                    positive=True) * D2R
    try:
        pieces = rp.knot_pieces(kt, kr, shape, jerk)
    except ValueError as exc:
        raise InputError(f"segment {seg.label!r}: {exc}") from None
    t = _times(0.0, kt[-1], fs)
    theta, rate, accel = rp.evaluate(pieces, t)
    return t0 + t, theta, rate, accel


def _table_errors(plan: Plan, tau, theta, rate, accel, rng):
    """The true table motion of a low-grade table: the nominal profile with a
    relative rate error (plan key ``sim_table_rate_error``, 1-sigma, drawn per
    segment) and a smooth rate wobble (``sim_table_wobble_dps``: three random
    sinusoids of this total amplitude, frequencies drawn in ``sim_table_wobble_hz``
    = [low, high], default [0.05, 0.5] Hz). Without the keys the
    motion is the nominal one (and no random numbers are drawn)."""
    scale_sd = float(plan.extra.get("sim_table_rate_error", 0.0))
    wobble = float(plan.extra.get("sim_table_wobble_dps", 0.0)) * D2R
    if scale_sd == 0.0 and wobble == 0.0:
        return theta, rate, accel
    k = 1.0 + scale_sd * rng.standard_normal()
    th, rt, ac = theta * k, rate * k, accel * k
    if wobble > 0:
        band = plan.extra.get("sim_table_wobble_hz", (0.05, 0.5))
        try:
            f_lo, f_hi = (float(v) for v in band)
        except (TypeError, ValueError):
            f_lo = f_hi = float("nan")
        if not (0 < f_lo <= f_hi < np.inf):
            raise InputError(f"sim_table_wobble_hz must be [low, high] in Hz, got {band!r}",
                             plan.path)
        freqs = rng.uniform(f_lo, f_hi, 3)
        phases = rng.uniform(0, 2 * np.pi, 3)
        amp = wobble / np.sqrt(3)
        # the wobble fades in over the first second so the segment starts at the nominal rate
        env = np.clip(tau, 0.0, 1.0)
        for f, p in zip(freqs, phases):
            w = 2 * np.pi * f
            s = np.sin(w * tau + p) - np.sin(p)
            c = np.cos(w * tau + p)
            rt = rt + amp * env * s
            ac = ac + amp * (env * w * c + (tau < 1.0) * s)
        th = theta[0] + k * (theta - theta[0]) + np.concatenate(
            [[0.0], np.cumsum(((rt - k * rate)[1:] + (rt - k * rate)[:-1]) / 2 * np.diff(tau))])
    return th, rt, ac


def _table_channels(plan: Plan, th, rt, theta, rate, rng):
    """What the table logs in its angle and rate columns. By default the nominal
    profile (a controller reporting what it was told). With an encoder
    (``sim_table_encoder_counts``, counts per revolution): the true angle with a
    once-per-revolution error ``sim_table_encoder_opr_deg`` (amplitude) at phase
    ``sim_table_encoder_opr_phase_deg`` (default 30; a property of the encoder disk, the
    same in every cycle) and a white reading noise ``sim_table_angle_noise_deg`` (1-sigma),
    quantised to the counts, and a rate channel that is the true rate times (1 +
    ``sim_table_rate_scale_error``) plus a white noise ``sim_table_rate_noise_dps``."""
    if plan.extra.get("sim_table_encoder_counts") is None:
        return theta, rate
    q = 2 * np.pi / _num_key(plan.extra, "sim_table_encoder_counts", 0, "plan", positive=True)
    opr = _num_key(plan.extra, "sim_table_encoder_opr_deg", 0.0, "plan") * D2R
    phase = _num_key(plan.extra, "sim_table_encoder_opr_phase_deg", 30.0, "plan") * D2R
    ang = th + opr * np.cos(th + phase)
    noise = _num_key(plan.extra, "sim_table_angle_noise_deg", 0.0, "plan") * D2R
    if noise > 0:  # a coarse or jittery reading: white noise before the quantiser
        ang = ang + noise * rng.standard_normal(len(ang))
    ang = np.round(ang / q) * q
    rt = rt * (1.0 + _num_key(plan.extra, "sim_table_rate_scale_error", 0.0, "plan"))
    rnoise = _num_key(plan.extra, "sim_table_rate_noise_dps", 0.0, "plan") * D2R
    if rnoise > 0:
        rt = rt + rnoise * rng.standard_normal(len(rt))
    return ang, rt


def _num_key(table: dict, key: str, default: float, where: str, positive: bool = False) -> float:
    """A numeric simulation key; a bad value is one line naming the key (exit 3)."""
    v = table.get(key, default)
    ok = isinstance(v, (int, float)) and not isinstance(v, bool) and np.isfinite(v)
    if not ok or (positive and v <= 0):
        raise InputError(f"{where}: {key} must be a {'positive ' if positive else ''}number, "
                         f"got {v!r}")
    return float(v)


def _temperature(plan: Plan, t: np.ndarray):
    if "temperature_profile" in plan.extra:
        knots = np.asarray(plan.extra["temperature_profile"], dtype=float)
        return np.interp(t, knots[:, 0], knots[:, 1])
    if "temperature_c" in plan.extra:
        return np.full(len(t), float(plan.extra["temperature_c"]))
    return None


def _random_rotation(rng) -> Rotation:
    return Rotation.from_quat(rng.standard_normal(4))


def simulate(plan: Plan, truth: Truth | None = None, seed: int = 0,
             progress=None) -> Recording:
    """Raw samples of the plan's experiment from a truth model. Pure: no I/O.

    progress: optional callback ``progress(done, total)``: once per plan segment
    of the timeline, then after the forward model and after the noise."""
    rng = np.random.default_rng(seed)
    layout = plan_layout(plan)
    nav = plan.kind == "align" and plan.extra.get("sim_grade", "navigation") != "mems"
    if truth is None and nav:
        from calib_cli.sim.grades import nav_truth  # alignment needs a navigation-grade unit

        truth = nav_truth(rng)
    if truth is None and plan.kind == "turntable":
        from calib_cli.sim.turntable_plans import turntable_truth  # lever arms, proof masses, D

        truth = turntable_truth(plan, rng)
    truth = truth or default_truth(layout, rng)
    if not same_layout(truth.model.layout, layout):
        truth = Truth(truth.model.__class__(truth.model.effects, layout), truth.params,
                      truth.noise, truth.counts, truth.quantize)
    kind = plan.extra.get("sample_kind", "instant")
    if kind not in SAMPLE_KINDS:
        raise InputError(f"sample_kind must be one of {', '.join(SAMPLE_KINDS)}, got {kind!r}",
                         plan.path)
    fs = plan.sample_rate
    if kind == "instant":
        kin, segments, true_att, angle, rate = _timeline(plan, fs, rng, progress)
        out = truth.model.predict(truth.params, kin)
    else:
        # interval-mean: each sample is the mean over [t_k - 1/fs, t_k], from the forward
        # model evaluated at n_sub points per period (trapezoid rule), stamped at t_k
        n_sub = int(_num_key(plan.extra, "sim_oversample", 16, "plan", positive=True))
        kin_hi, seg_hi, true_att, angle_hi, rate_hi = _timeline(plan, fs * n_sub, rng, progress)
        out_hi = truth.model.predict(truth.params, kin_hi)
        stamps = np.arange(n_sub, len(kin_hi), n_sub)
        out = {k: _interval_means(v, n_sub, len(stamps)) for k, v in out_hi.items()
               if v is not None}
        kin = kin_hi.take(stamps)
        angle = None if angle_hi is None else angle_hi[stamps]
        rate = None if rate_hi is None else rate_hi[stamps]
        segments = [replace(sg, start=-(-sg.start // n_sub) - 1, stop=-(-sg.stop // n_sub) - 1)
                    for sg in seg_hi]
        segments = [sg if sg.start >= 0 else replace(sg, start=0) for sg in segments]
    n_steps = len(plan.segments) + 2
    if progress is not None:
        progress(n_steps - 1, n_steps)
    # every noise term (white, random walk, flicker) is an effect with a seeded stream:
    # the emulator draws the same numbers for the same truth and seed (acquire/emulator.py)
    noise_model, noise_params = truth.noise_model()
    stoch = noise_model.noise_realisation(noise_params, fs, seed).next(kin)
    noisy = {}
    for s in ("accel", "gyro"):
        y = out[s] + stoch[s]
        if truth.quantize:
            y = np.round(y)
        noisy[s] = y
    if progress is not None:
        progress(n_steps, n_steps)
    units = {"accel": "count", "gyro": "count"} if truth.counts else {"accel": "m/s^2",
                                                                       "gyro": "rad/s"}
    return Recording(
        time=kin.t, accel=noisy["accel"], gyro=noisy["gyro"], segments=tuple(segments),
        site=plan.site, plan_kind=plan.kind, plan_text=plan.text, serial=plan.serial,
        units=units, layout=layout, temp=kin.temp, table_angle=angle, table_rate=rate,
        sample_kind=kind,
        truth={"params": truth.params, "noise": truth.noise,
               "attitudes": np.array(true_att), "effects": truth.effect_list()},
    )


def _interval_means(y: np.ndarray, n_sub: int, n_out: int) -> np.ndarray:
    """Trapezoid means of y over n_sub steps ending at samples n_sub, 2 n_sub, ..."""
    c = np.concatenate([np.zeros((1,) + y.shape[1:]),
                        np.cumsum(0.5 * (y[1:] + y[:-1]), axis=0)])
    ends = np.arange(1, n_out + 1) * n_sub
    return (c[ends] - c[ends - n_sub]) / n_sub


def _timeline(plan: Plan, fs: float, rng, progress=None):
    """The plan's motion sampled at fs: (Kinematics, segments, true start attitudes,
    table angle, table rate) -- the last two None without rotating segments."""
    site = plan.site
    trans_default = float(plan.extra.get("transition_s", 4.0))

    parts: list[kn.Kinematics] = []
    segments: list[Segment] = []
    true_att: list[np.ndarray] = []
    angle_parts, rate_parts = [], []
    t_next = 0.0
    current: Rotation | None = None
    prev_was_turn = False
    cycle = 0
    n_samples = 0

    def add(kin, seg_index, cyc, angle=None, rate=None):
        nonlocal n_samples, t_next
        m = len(kin)
        kin = kin.with_(segment=np.full(m, seg_index), cycle=np.full(m, cyc))
        parts.append(kin)
        angle_parts.append(np.full(m, np.nan) if angle is None else angle)
        rate_parts.append(np.zeros(m) if rate is None else rate)
        n_samples += m
        t_next = kin.t[-1] + 1.0 / fs

    expanded: list[tuple[int, PlanSegment, str]] = []
    for i, seg in enumerate(plan.segments):
        if seg.repeat_auto:
            reps = int(seg.extra.get("sim_repeat", 12))
            expanded += [(i, seg, f"{seg.label}#{k + 1}") for k in range(reps)]
        else:
            expanded.append((i, seg, plan.visit_labels[i]))

    for plan_index, seg, label in expanded:
        if progress is not None:
            progress(plan_index, len(plan.segments) + 2)
        kind = seg.kind
        # where this segment starts
        if "sim_attitude_deg" in seg.extra:  # the true attitude (a fixture error, or unknown)
            start = attitude_to_rotation(np.asarray(seg.extra["sim_attitude_deg"], float) * D2R)
        elif seg.attitude is not None:
            start = attitude_to_rotation(seg.attitude)
        elif (prev_was_turn or kind != "static") and current is not None:
            start = current
        else:
            start = _random_rotation(rng)
        if current is not None:
            dur = float(seg.extra.get("transition_s", trans_default))
            if dur > 0:
                t = _times(t_next, dur, fs)
                add(kn.slew_kinematics(t, current, start, site), -1, -1)
        current = start
        index = len(segments)
        first = n_samples
        if kind == "static":
            t = _times(t_next, seg.duration or 10.0, fs)
            rot = Rotation.from_quat(np.tile(start.as_quat(), (len(t), 1)))
            add(kn.from_attitude(t, rot, site), index, -1)
        elif kind == "turn":
            t = _times(t_next, seg.duration or 10.0, fs)
            phi = seg.rotation_axis_body * seg.rotation_angle
            kin = kn.slew_kinematics(t, start, start * Rotation.from_rotvec(phi), site, phi=phi)
            add(kin, index, -1)
            current = start * Rotation.from_rotvec(phi)
        else:  # rotating
            t, theta, rate, acc = _rate_profile(seg, fs, t_next)
            th, rt, ac = _table_errors(plan, t - t_next, theta, rate, acc, rng)
            axis = np.asarray(seg.extra.get("sim_table_axis_enu", seg.table_axis_enu), float)
            wob = _num_key(plan.extra, "sim_table_axis_wobble_urad", 0.0, "plan") * 1e-6
            wob_phase = _num_key(plan.extra, "sim_table_axis_wobble_phase_deg", 0.0, "plan") * D2R
            kin = kn.table_kinematics(t, axis, th, rt, ac, start, site,
                                      axis_wobble=(wob, wob_phase) if wob else None)
            angle_ch, rate_ch = _table_channels(plan, th, rt, theta, rate, rng)
            add(kin, index, cycle, angle_ch, rate_ch)
            current = axis_angle(axis, th[-1] - th[0]) * start
            cycle += 1
        prev_was_turn = kind == "turn"
        true_att.append(rotation_to_attitude(start))
        segments.append(Segment(label=label, kind=kind, start=first, stop=n_samples,
                                plan_index=plan_index, attitude=seg.attitude,
                                attitude_sigma=seg.attitude_sigma,
                                table_axis_enu=seg.table_axis_enu, table_rate=seg.table_rate,
                                lever_arm=seg.lever_arm,
                                rotation_axis_body=seg.rotation_axis_body,
                                rotation_angle=seg.rotation_angle))

    kin = kn.Kinematics.concatenate(parts)
    kin = kin.with_(temp=_temperature(plan, kin.t))  # the forward model sees the temperature
    from calib_cli.sim.chamber import chamber_temperature, has_chamber  # docs/thermal.md

    if has_chamber(plan):
        pidx = np.array([-1] + [sg.plan_index for sg in segments])[kin.segment + 1]
        kin = kin.with_(temp=chamber_temperature(plan, kin.t, pidx)[1])
    rotating = any(s.kind == "rotating" for s in segments)
    return (kin, segments, true_att, np.concatenate(angle_parts) if rotating else None,
            np.concatenate(rate_parts) if rotating else None)
