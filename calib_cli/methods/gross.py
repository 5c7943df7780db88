"""Gross-error detection and sanity of fitted calibrations (issue 15, docs/accel.md).

The rule (documented in docs/commands.md, "Gross errors"):

1. After a fit with stated attitudes, each position k gets z_k, the norm of
   its residual in units of its own noise (the whitened residual). A
   position is a *candidate* when z_k > Z_ABS (30) and its residual is
   physically large, above BIG_G (2 %) of g, about 1.1 deg of tilt (so a
   fixture a few hundredths of a degree off is not accused).
2. When there is a candidate, each position (each candidate when there are
   more than 60) is left out and the fit repeated, where that still leaves
   at least one residual degree of freedom. A position whose leave-one-out
   refit has no candidate left is *isolated* (the best such, when several).
3. The fit never excludes a position silently: it exits 4 naming the
   isolated position (with the angle between the gravity direction it
   measured and the one its attitude_deg states), or, when no single
   position explains it, listing the candidates. The user re-records that
   position or corrects its attitude_deg. The scalar method and
   ``repeat = "auto"`` segments (no stated attitude) are exempt.

Independently, ``check_result`` refuses (exit 4) any calibration that is
physically impossible: a scale factor |K_ii| outside [0.5, 2] (SI data), a
bias beyond the device range (+-16 g, +-2000 deg/s unless the plan's
``[unit]`` says accel_range_g / gyro_range_dps), or a correction that makes
|g| worse: g_error_rms_after > g_error_rms_before + 3 g_error_floor.
"""

from __future__ import annotations

import numpy as np

from calib_cli.errors import EstimationError
from calib_cli.model.earth import EARTH_RATE

Z_ABS = 30.0
Z_REL = 10.0
MAX_LOO = 3  # leave-one-out refits when there are more than MAX_ALL positions
MAX_ALL = 60
BIG_G = 0.02  # a residual is physically large above 2 % of g (about 1.1 deg of tilt)
K_RANGE = (0.5, 2.0)
ACCEL_RANGE_G = 16.0
GYRO_RANGE_DPS = 2000.0
G0 = 9.80665


def candidates(z, big) -> list[int]:
    """Positions whose residual is far beyond the noise (z > Z_ABS) and
    physically large (``big``), worst first."""
    z = np.asarray(z, dtype=float)
    big = np.asarray(big, dtype=bool)
    return [int(i) for i in np.argsort(-z) if z[i] > Z_ABS and big[i]]


def screen(z, big, labels, refit_without, what="position", describe=None,
           cause="the plan's attitude_deg is wrong") -> None:
    """Raise EstimationError (exit 4) when a position is a gross error.

    ``refit_without(k)`` returns (z, big) of the remaining positions of a
    refit without position k, or None when that leaves no residual degree of
    freedom. ``describe(k)`` adds a phrase about position k."""
    cand = candidates(z, big)
    if not cand:
        return
    n = len(z)
    order = list(range(n)) if n <= MAX_ALL else cand[:MAX_LOO]
    isolated, best = None, np.inf
    for k in order:
        rest = refit_without(k)
        if rest is None:
            continue
        zr, br = rest
        if not candidates(zr, br):
            worst = float(np.max(zr)) if len(zr) else 0.0
            if worst < best:
                isolated, best = k, worst
    if isolated is not None:
        k = isolated
        extra = f", {describe(k)}" if describe else ""
        raise EstimationError(
            f"gross error at {what} {k + 1} ({labels[k]!r}): its residual is {z[k]:.0f} times "
            f"its noise{extra}; a refit without it explains the other {what}s. The unit was "
            f"placed wrong there or {cause}: re-record that {what} or correct the plan")
    names = ", ".join(f"{k + 1} ({labels[k]!r}, {z[k]:.0f} sigma)" for k in cand[:8])
    raise EstimationError(
        f"gross errors: the residuals of {what}s {names} are far beyond the noise and no "
        f"single {what} explains them; check the plan's attitudes and segment order against "
        "what was recorded")


def _range_of(rec, key, default):
    """The plan's [unit] range (accel_range_g, gyro_range_dps) where given."""
    try:
        import tomllib

        unit = tomllib.loads(rec.plan_text or "").get("unit", {})
        v = unit.get(key)
        return float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) and v > 0 \
            else default
    except Exception:
        return default


def _axis_sign(rec, sensor: str, n: int) -> np.ndarray:
    """The plan's ``[unit] accel_axis_sign`` / ``gyro_axis_sign`` (+1 or -1 per
    axis: -1 an axis inverted by design); +1 each where not given."""
    try:
        import tomllib

        v = tomllib.loads(rec.plan_text or "").get("unit", {}).get(f"{sensor}_axis_sign")
        if isinstance(v, list) and len(v) == n and all(x in (1, -1) and not isinstance(x, bool)
                                                       for x in v):
            return np.asarray(v, dtype=float)
    except Exception:  # no plan, or one already refused by the plan check
        pass
    return np.ones(n)


def check_result(res, rec=None) -> None:
    """Refuse an impossible calibration (exit 4); see the module docstring."""
    p, st = res.params, res.stats or {}
    raw_units = res.raw_units or {}
    problems = []
    for s in ("accel", "gyro"):
        counts = raw_units.get(s) == "count"
        K = p.get(f"{s}_K")
        if K is not None and not counts:
            K = np.asarray(K, dtype=float)
            if K.ndim == 2 and K.shape[0] == K.shape[1]:
                sign = _axis_sign(rec, s, K.shape[0])
                d = np.diag(K) * sign  # positive unless the plan declares the axis inverted
                bad = np.flatnonzero((d < K_RANGE[0]) | (d > K_RANGE[1]) | ~np.isfinite(d))
                for i in bad:
                    if np.isfinite(d[i]) and K_RANGE[0] <= -d[i] <= K_RANGE[1]:
                        want = [int(x) for x in sign]
                        want[i] = -want[i]
                        problems.append(
                            f"{s}_K[{i},{i}] = {float(K[i, i]):.6g}: axis {i} reads with the "
                            "opposite sign (wired or mounted inverted, or the plan's attitudes "
                            "mirrored); when the unit's axis is inverted by design, the plan "
                            f"says so: [unit] {s}_axis_sign = {want}")
                        continue
                    problems.append(f"{s}_K[{i},{i}] = {float(K[i, i]):.6g} (a scale factor "
                                    f"outside {K_RANGE[0]}..{K_RANGE[1]})")
        b = p.get(f"{s}_bias")
        if b is not None and not counts:
            b = np.asarray(b, dtype=float)
            if s == "accel":
                lim = _range_of(rec, "accel_range_g", ACCEL_RANGE_G) * G0 if rec else \
                    ACCEL_RANGE_G * G0
                unit, f = "g", 1 / G0
            else:
                lim = np.radians(_range_of(rec, "gyro_range_dps", GYRO_RANGE_DPS) if rec else
                                 GYRO_RANGE_DPS)
                unit, f = "deg/s", np.degrees(1.0)
            big = np.flatnonzero(~(np.abs(b) <= lim))
            for i in big[:3]:
                problems.append(f"{s}_bias[{i}] = {float(b[i]) * f:.6g} {unit} (beyond the "
                                f"device range +-{lim * f:.6g} {unit})")
    before, after = st.get("g_error_rms_before"), st.get("g_error_rms_after")
    floor = st.get("g_error_floor")
    # without a stated noise floor (e.g. fit align): worse by half and by more than 1 mg
    margin = 3 * floor if isinstance(floor, (int, float)) and np.isfinite(floor) else \
        max(0.5 * (before or 0.0), 1e-3 * G0)
    if isinstance(before, (int, float)) and isinstance(after, (int, float)) \
            and np.isfinite(before) and (not np.isfinite(after) or after > before + margin):
        problems.append(f"the correction makes |g| worse (RMS error {before * 1e3 / G0:.4g} mg "
                        f"before, {after * 1e3 / G0:.4g} mg after)")
    if problems:
        raise EstimationError(f"{res.method} fit gave an impossible calibration: "
                              + "; ".join(problems[:4]) + ". Check the plan's attitudes and "
                              "segment order against the recording (calib plan check, calib "
                              "detect), and that the right fit is used")


# ---------------------------------------------------------------------------
# the screen after a whole fit (redundant units, gyro turns): leave-one-out by
# refitting the recording without one segment


def _without(rec, seg):
    import dataclasses

    return dataclasses.replace(rec, segments=tuple(s for s in rec.segments if s is not seg))


def _rimu_z(res, rec, segs):
    r = np.asarray(res.residuals.get("accel_segment"), dtype=float)
    sig = np.asarray(res.stats.get("accel_noise_sigma"), dtype=float)
    if r.ndim != 2 or r.shape[0] != len(segs) or sig.shape != (r.shape[1],):
        return None
    n = np.array([max(s.n, 1) for s in segs], dtype=float)
    z = np.sqrt(np.mean((r * np.sqrt(n)[:, None] / np.maximum(sig, 1e-300)) ** 2, axis=1))
    big = np.max(np.abs(r), axis=1) > BIG_G * rec.site.gravity
    return z, big


def _screen_rimu(res, rec, refit) -> None:
    from calib_cli.methods.rimu import usable_segments

    segs = usable_segments(rec)[0]
    zb = _rimu_z(res, rec, segs)
    if zb is None or len(segs) <= 5:  # 4 unknowns per sensor: >= 5 positions after one out
        return

    def without(k):
        rec2 = _without(rec, segs[k])
        try:
            r2 = refit(rec2)
        except EstimationError:
            return None
        return _rimu_z(r2, rec2, usable_segments(rec2)[0])

    screen(zb[0], zb[1], [s.label for s in segs], without, "position")


TURN_BIG_DEG = 5.0


def _screen_gyro_turns(res, rec, refit) -> None:
    """A turn whose integrated angle misses its rotation_angle_deg by more than
    TURN_BIG_DEG and 10 times the median miss of the turns."""
    err = np.degrees(np.asarray(res.residuals.get("turn_angle", []), dtype=float))
    turns = [s for s in rec.segments if s.kind == "turn"]
    if len(err) != len(turns) or len(err) < 3:
        return
    thr = max(TURN_BIG_DEG, 10 * float(np.median(err)))
    cand = [int(i) for i in np.argsort(-err) if err[i] > thr]
    if not cand:
        return
    for k in cand[:MAX_LOO]:
        try:
            r2 = refit(_without(rec, turns[k]))
        except EstimationError:
            continue
        e2 = np.degrees(np.asarray(r2.residuals.get("turn_angle", []), dtype=float))
        if len(e2) and not np.any(e2 > max(TURN_BIG_DEG, 10 * float(np.median(e2)))):
            raise EstimationError(
                f"gross error at turn {turns[k].label!r}: the gyros integrate an angle "
                f"{err[k]:.1f} deg away from its rotation_angle_deg and axis; a refit without "
                "it explains the other turns. Check that turn's angle, axis and sign (right-hand "
                "rule) in the plan, or re-record it")
    names = ", ".join(f"{turns[k].label!r} ({err[k]:.1f} deg)" for k in cand[:8])
    raise EstimationError(f"gross errors: turns {names} miss their stated angles and no single "
                          "turn explains it; check the plan's turn angles and axes")


MISFIT_G = 2e-3  # align: residuals beyond 2 mg at z > Z_ABS are a model misfit
GYRO_MISFIT = 0.05  # ... or gyro residuals beyond 5 % of the earth rate (0.75 deg/h)



def _align_z(res, rec, segs):
    """Whitened residual norm z and 'physically large' per static position of
    a two-position alignment (accelerometer residuals: the positions' gravity)."""
    r = np.asarray(res.residuals.get("accel_segment"), dtype=float)
    sig = np.asarray(res.stats.get("accel_noise_sigma"), dtype=float)
    if r.ndim != 2 or r.shape != (len(segs), 3) or sig.shape != (3,):
        return None
    n = np.array([max(s.n, 1) for s in segs], dtype=float)
    w = (r * np.sqrt(n)[:, None] / np.maximum(sig, 1e-300)) ** 2
    rw = np.asarray(res.residuals.get("gyro_segment", []), dtype=float)
    sw = np.asarray(res.stats.get("gyro_noise_sigma", []), dtype=float)
    if res.stats.get("earth_rate_used") and rw.shape == r.shape and sw.shape == (3,):
        # the gyros resolve the earth rate: their residuals tell a misplaced heading too
        w = np.hstack([w, (rw * np.sqrt(n)[:, None] / np.maximum(sw, 1e-300)) ** 2])
    z = np.sqrt(np.mean(w, axis=1))
    return z, np.max(np.abs(r), axis=1) > BIG_G * rec.site.gravity, np.max(np.abs(r), axis=1)


def _screen_align(res, rec, refit) -> None:
    """``fit align`` (two-position method, any number >= 2 of positions).

    1. The leave-one-out screen of ``screen`` on the accelerometer residual of
       each static position (z > Z_ABS and above BIG_G of g): a refit without
       a position needs two positions left (the 12 equations of two positions
       leave 3 residual degrees of freedom with the earth rate, 1 without), so
       with three or more positions a misplaced one is named; with two, the
       candidates are listed (exit 4).
    2. A model misfit: the alignment model has biases and attitudes only, so
       positions whose residuals are far beyond the noise (RMS z > Z_ABS) and
       above MISFIT_G of g (or, with the earth rate used, gyro residuals above
       GYRO_MISFIT of the earth rate) are scale-factor or misalignment errors it
       does not model (a multi-position recording of an uncalibrated unit), or
       positions not rigidly related by the turns: exit 4 pointing at
       ``fit accel`` instead of biases quietly absorbing them."""
    segs = rec.static_segments()
    labels = [s.label for s in segs]
    zb = _align_z(res, rec, segs)
    if zb is None:
        return
    z, big, size = zb

    def without(k):
        if len(segs) < 3:
            return None  # one position left: nothing to compare
        rec2 = _without(rec, segs[k])
        try:
            r2 = refit(rec2)
        except EstimationError:
            return None
        zb2 = _align_z(r2, rec2, rec2.static_segments())
        return None if zb2 is None else zb2[:2]

    def describe(k):
        return f"{size[k] / rec.site.gravity * 1e3:.0f} mg off the aligned gravity"

    screen(z, big, labels, without, "position", describe,
           cause="a turn (rotation_angle_deg, rotation_axis_body) next to it is wrong")
    zrms = float(np.sqrt(np.mean(z**2)))
    rw = np.asarray(res.residuals.get("gyro_segment", []), dtype=float)
    gyro_big = bool(res.stats.get("earth_rate_used")) and rw.size > 0 and \
        float(np.max(np.abs(rw))) > GYRO_MISFIT * EARTH_RATE
    if zrms > Z_ABS and (float(np.max(size)) > MISFIT_G * rec.site.gravity or gyro_big):
        worst = [int(i) for i in np.argsort(-z)[:3]]
        names = ", ".join(f"{labels[k]!r} ({size[k] / rec.site.gravity * 1e3:.1f} mg, "
                          f"{z[k]:.0f} sigma)" for k in worst)
        raise EstimationError(
            f"the alignment model (biases and attitude) leaves residuals far beyond the noise "
            f"at the static positions (RMS {zrms:.0f} sigma; largest {names}): the unit has "
            "scale-factor or misalignment errors this model does not have, or the positions "
            "are not related by the turns as stated (check rotation_angle_deg and "
            "rotation_axis_body, or record the turns for --rotation gyro). For a "
            "multi-position recording use `calib fit accel` (or apply a scale calibration "
            "first, then align)")


def screen_fit(res, rec, refit) -> None:
    """The gross-error screen for methods screened after the whole fit
    (rimu: static positions; gyro: turns of known angle; align, two-position
    method: static positions). ``refit(rec)`` repeats the same fit on a
    recording with one segment left out."""
    if res.method == "rimu":
        _screen_rimu(res, rec, refit)
    elif res.method == "gyro":
        _screen_gyro_turns(res, rec, refit)
    elif res.method == "align":
        _screen_align(res, rec, refit)
