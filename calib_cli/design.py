"""Experiment design: what a plan will deliver before it is run (docs/plan.md).

The prediction is the fit's own covariance at the truth, computed by the fit's
own code: the plan is simulated without noise from a nominal unit (neutral
parameters, or a given truth), and the method's fit is run on that record with
the stated noise as its weights (the fits' ``noise=`` option) and without
failing on unobservable entries (``strict=False``). The fit then stops at the
truth with zero residuals, and its covariance is (J^T W J)^-1 of its own
whitened residuals, J its own Jacobian there: the inverse Fisher information of
the same model, the same equations and the same options (nuisance parameters,
priors, D auto-selection, grade check) as the fit on a real record. Its
``stats.unobservable`` is the fit's rank rule applied to that Jacobian.

Pure: plans and recordings in, a Prediction out; no files, no printing.
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from calib_cli.data import CalibrationResult, Recording
from calib_cli.errors import EstimationError, InputError
from calib_cli.model.effects import Bias, Layout, ScaleMisalignment
from calib_cli.model.imu_model import ImuModel
from calib_cli.model.truth import DEFAULT_NOISE, Truth, default_truth
from calib_cli.plan import Plan, PlanSegment

D2R = np.pi / 180.0
WEAK_TYPICAL = 0.3  # sigma above 0.3 x the catalogue's typical size of the entry: weak
WEAK_SPREAD = 3.0  # ... or above 3 x the median sigma of the same key
N_SUGGEST = 5


@dataclass(frozen=True)
class Noise:
    """Per-sample 1-sigma white noise of each channel at ``rate`` Hz, SI."""

    accel: np.ndarray
    gyro: np.ndarray
    rate: float
    source: str = "stated"
    # the recording the levels come from (--like): the turntable prediction takes from it
    # which table channels the fit's checks accept, cycle by cycle
    like: Recording | None = field(default=None, repr=False, compare=False)

    def as_dict(self) -> dict:
        return {"accel": self.accel, "gyro": self.gyro}


@dataclass(frozen=True)
class Prediction:
    method: str
    result: CalibrationResult  # params at the truth, sigma predicted, stats.unobservable
    noise: Noise
    duration: float  # s, the plan's recorded time (segments and transitions)
    condition: float
    weak: list = field(default_factory=list)
    suggestions: list = field(default_factory=list)

    @property
    def unobservable(self) -> list:
        return list(self.result.stats.get("unobservable", []))


# ---------------------------------------------------------------------------
# inputs


def method_of(name: str):
    """(Method, options) of a ``plan check --method`` name (a variant sets options);
    KeyError for an unknown name."""
    from calib_cli.methods.registry import FITS

    for m in FITS.values():
        if name == m.name:
            return m, {}
        if name in m.variants:
            return m, dict(m.variants[name])
    raise KeyError(name)


def _claims(m, plan: Plan) -> bool:
    from calib_cli.methods.method import resolve

    return m.claims is not None and bool(resolve(m.claims)(plan))


def resolve_method(plan: Plan, method: str = "auto") -> str:
    """The fit a plan's record goes to, as the table says (methods/registry.py): a
    method whose ``claims`` takes the plan (a static plan with chamber setpoints goes to
    the thermal fit, one with turns of known angle to the gyro fit), else the method of
    the plan's kind; where the method has variants, the one its ``variant_of`` names (the
    accelerometer fit: vector with attitudes, else scalar, as ``fit accel --method auto``)."""
    from calib_cli.methods.registry import FITS, method_of_plan_kind, plan_method_names

    names = plan_method_names()
    if method not in names:
        raise InputError(f"unknown method {method!r}; expected one of {', '.join(names)}",
                         plan.path)
    default = method_of_plan_kind(plan.kind)
    if default is None:
        raise InputError(f"no method takes plans of kind {plan.kind!r}", plan.path)
    if method == "auto":
        m = next((m for m in FITS.values() if plan.kind in m.plan_kinds and _claims(m, plan)),
                 FITS[default])
    else:
        m = method_of(method)[0]
        if plan.kind not in m.plan_kinds:
            raise InputError(f"a plan of kind {plan.kind!r} goes to the {default} fit, not "
                             f"{method!r}", plan.path)
        if m.name != method:  # a variant named explicitly
            return method
    from calib_cli.methods.method import resolve

    return resolve(m.variant_of)(plan) if m.variant_of else m.name


def default_noise(plan: Plan, rate: float | None = None, truth: Truth | None = None) -> Noise:
    """The noise of the truth model where given (its [noise] table), else the
    simulator's default for the plan (docs/simulate.md): MEMS for static and
    rimu plans, the navigation-grade unit for align plans."""
    rate = float(rate or plan.sample_rate)
    n = len(plan.rimu_el0) if plan.kind == "rimu" else 3
    if truth is not None and truth.noise:
        out = []
        for sensor in ("accel", "gyro"):
            v = np.asarray(truth.noise.get(f"{sensor}_white", 0.0), float)
            if f"{sensor}_white_density" in truth.noise:
                v = np.asarray(truth.noise[f"{sensor}_white_density"], float) * np.sqrt(rate)
            out.append(np.broadcast_to(v, (n,)).astype(float))
        return Noise(out[0], out[1], rate, "the truth model's")
    if plan.kind == "turntable":
        from calib_cli.sim.turntable_plans import MEMS_NOISE

        return Noise(np.full(3, MEMS_NOISE["accel_white"]), np.full(3, MEMS_NOISE["gyro_white"]),
                     rate, "simulator default (turntable MEMS)")
    if plan.kind == "align" and plan.extra.get("sim_grade", "navigation") != "mems":
        from calib_cli.sim.grades import ACCEL_NOISE, ARW

        return Noise(np.full(3, ACCEL_NOISE * np.sqrt(rate)), np.full(3, ARW * np.sqrt(rate)),
                     rate, "simulator default (navigation grade)")
    return Noise(np.full(n, DEFAULT_NOISE["accel_white"]), np.full(n, DEFAULT_NOISE["gyro_white"]),
                 rate, "simulator default (MEMS)")


def noise_like(rec: Recording, path: str = "<raw>") -> Noise:
    """Noise levels and sample rate of a recording: the pooled within-segment
    standard deviation of its static positions (the statistic the fits use)."""
    from calib_cli.methods.segstats import static_stats

    rot = [s for s in rec.segments if s.kind == "rotating"]
    if (rot and not rec.layout.redundant and rec.accel is not None and rec.gyro is not None
            and (rec.plan_kind == "turntable" or not rec.static_segments())):
        # a turntable record: the fit's own estimate (third differences over its cycles,
        # robust to the corners: methods/noise.py, as methods/turntable.py)
        from calib_cli.methods.noise import difference_sigma

        if rec.in_counts("accel") or rec.in_counts("gyro"):
            raise InputError("the recording is in raw counts: give --accel-noise/--gyro-noise "
                             "in SI instead", path)
        on = np.concatenate([np.arange(s.start, s.stop) for s in rot])
        return Noise(difference_sigma(rec.accel[on], 3, robust="mad"),
                     difference_sigma(rec.gyro[on], 3, robust="mad"),
                     rec.sample_rate, f"like {path}", rec)
    out = {}
    for sensor in ("accel", "gyro"):
        data = rec.accel if sensor == "accel" else rec.gyro
        if data is None:
            out[sensor] = np.full(rec.layout.n, np.nan)
            continue
        if rec.layout.redundant:
            from calib_cli.methods.rimu import position_means, usable_segments

            segs = usable_segments(rec)[0]
            out[sensor] = position_means(rec, sensor, segs)[3] if segs else np.full(
                data.shape[1], np.nan)
        else:
            st = rec.static_segments()
            out[sensor] = static_stats(rec, sensor).sigma if st else np.full(3, np.nan)
    if not np.all(np.isfinite(out["accel"])):
        raise InputError("no static positions to take the noise level from", path)
    if rec.in_counts("accel") or rec.in_counts("gyro"):
        raise InputError("the recording is in raw counts: give --accel-noise/--gyro-noise "
                         "in SI instead", path)
    return Noise(out["accel"], out["gyro"], rec.sample_rate, f"like {path}", rec)


def nominal_truth(plan: Plan, truth: Truth | None = None) -> Truth:
    """The unit the prediction is made at, without noise: the given truth, or
    neutral parameters (K = I, biases 0) of the method's base model."""
    from calib_cli.plan import plan_layout, same_layout

    layout = plan_layout(plan)
    if truth is None and plan.kind == "turntable":
        return _turntable_nominal(plan)
    if truth is None:
        if layout.redundant:
            model = default_truth(layout, np.random.default_rng(0)).model
            params = model.neutral_params()
            # a sensor along the body z axis: its (dEl, dAz) pair is singular at zero
            # tilt (CONTRACT.md section 2), so predict at a tilt of the typical size
            from calib_cli.methods.rimu import TYPICAL as RT

            polar = np.abs(np.abs(layout.el0) - np.pi / 2) < 1e-9
            for sensor in ("accel", "gyro"):
                key = f"{sensor}_dEl"
                if key in params and polar.any():
                    v = np.array(params[key], float)
                    v[polar] = -np.sign(layout.el0[polar]) * RT[sensor][2]
                    params[key] = v
            return Truth(model, params, {"accel_white": 0.0, "gyro_white": 0.0})
        else:
            model = ImuModel((Bias("accel"), ScaleMisalignment("accel", "full"), Bias("gyro"),
                              ScaleMisalignment("gyro", "full")), layout)
        truth = Truth(model, model.neutral_params(), {})
    elif not same_layout(truth.model.layout, layout):
        truth = Truth(truth.model.__class__(truth.model.effects, layout), truth.params, {})
    zero = {"accel_white": 0.0, "gyro_white": 0.0}
    return Truth(truth.model, truth.params, zero, truth.counts, False)


def _turntable_nominal(plan: Plan) -> Truth:
    """The turntable fit's model (methods/turntable.py) with neutral parameters, the
    plan's lever arms (``lever_arm_m``; else 0) and no proof-mass offsets: the fit's
    prior mean."""
    from calib_cli.sim.turntable_plans import turntable_truth

    t = turntable_truth(plan, np.random.default_rng(0))
    params = t.model.neutral_params()
    rot = [s for s in plan.segments if s.kind == "rotating"]
    params["lever_arm"] = np.array([np.zeros(3) if s.lever_arm is None
                                    else np.asarray(s.lever_arm, float) for s in rot])
    return Truth(t.model, params, {"accel_white": 0.0, "gyro_white": 0.0})


# ---------------------------------------------------------------------------
# the prediction


def _fit(method: str, rec: Recording, noise: Noise, options: dict) -> CalibrationResult:
    """The method's information at this noise (methods/registry.information): its fit's
    covariance on the noise-free record, with the options the prediction was given
    (those the method does not take are left out: plan check offers the options of
    every method)."""
    from calib_cli.methods.registry import information

    m, variant = method_of(method)
    names = {o.name for o in m.options}
    opts = {k: v for k, v in {**options, **variant}.items() if k in names and v is not None}
    return information(m.name, rec, opts, noise.as_dict(), noise.like)


def turntable_information(rec: Recording, o, noise: dict, like: Recording | None = None
                          ) -> CalibrationResult:
    """The turntable method's information hook (methods/registry.py)."""
    nz = Noise(np.asarray(noise["accel"], float), np.asarray(noise["gyro"], float), 0.0,
               like=like)
    return _turntable_prediction(rec, nz, {f: getattr(o, f) for f in TURNTABLE_OPTIONS})


TURNTABLE_OPTIONS = ("lever_arm", "proof_mass", "tangential", "block_s", "axis_sigma_mrad",
                     "table_tilt_deg", "grade", "prior", "table_encoder")


def _turntable_prediction(rec: Recording, noise: Noise, options: dict) -> CalibrationResult:
    """The turntable fit's covariance at the simulated unit: its own rows and noise model
    on the noise-free record, the table's levels and channels from --like's fit
    (methods/turntable/design.py)."""
    from calib_cli.io.plan import parse_plan
    from calib_cli.methods.turntable.design import covariance_at

    # (rec is the plan's simulated record: its plan text is the plan's)
    per_cycle = noise.like is None or not rec.plan_text or \
        recorded_from(parse_plan(rec.plan_text), noise.like)
    return covariance_at(rec, _turntable_options(options),
                         {"accel": noise.accel, "gyro": noise.gyro}, like=noise.like,
                         per_cycle=per_cycle)


def _turntable_options(options: dict):
    """The turntable fit's options (methods/turntable/options.py) from plan check's."""
    from calib_cli.methods.registry import options_from

    return options_from("turntable", {k: v for k, v in options.items()
                                      if k in TURNTABLE_OPTIONS and v is not None}).to_method()


def recorded_from(plan: Plan, like: Recording) -> bool:
    """Whether the recording --like names was recorded from this plan: the same segments
    (kind and label, in order) in the plan text it carries; one without a plan text
    (imported) is taken as the plan's. Only then are its per-segment findings (the static
    positions' attitudes, the lever arms, the channels cycle by cycle) the plan's: from a
    recording of another plan, segment i is some other segment, and only its noise levels
    carry over."""
    if not like.plan_text:
        return True
    from calib_cli.io.plan import parse_plan

    try:
        rec_plan = parse_plan(like.plan_text)
    except InputError:  # a plan text this version does not read: not the same plan
        return False
    return [(s.kind, s.label) for s in rec_plan.segments] == \
        [(s.kind, s.label) for s in plan.segments]


def attitudes_like(plan: Plan, like: Recording) -> Plan:
    """The plan with the attitudes it leaves unknown taken from the recording ``--like``
    names: each static position without attitude_deg is simulated at the attitude the
    recording's mean specific force (and, where its gyros resolve the earth rate, its
    mean rate) shows at that position. The information of a fit depends on the
    positions' directions; a plan that does not state them would otherwise be predicted
    at random ones (the simulator's) instead of the recorded ones."""
    if like.accel is None or like.layout.redundant or like.in_counts("accel"):
        return plan
    from calib_cli.model.earth import EARTH_RATE
    from calib_cli.model.frames import attitude_from_static

    seen = {}
    for s in like.segments:
        if s.kind == "static" and s.plan_index >= 0 and s.plan_index not in seen and s.n > 0:
            w = None
            if like.gyro is not None and not like.in_counts("gyro"):
                w = like.gyro[s.slice].mean(axis=0)
            seen[s.plan_index] = attitude_from_static(like.accel[s.slice].mean(axis=0), w,
                                                      EARTH_RATE, like.site.latitude)
    segs = list(plan.segments)
    for i, seg in enumerate(segs):
        if seg.kind == "static" and seg.attitude is None and i in seen:
            att = [float(x) for x in np.degrees(seen[i])]
            segs[i] = replace(seg, extra={**seg.extra, "sim_attitude_deg": att})
    return replace(plan, segments=tuple(segs))


def _with_rate(plan: Plan, rate: float) -> Plan:
    return replace(plan, extra={**plan.extra, "sample_rate_hz": float(rate)})


def check_plannable(plan: Plan) -> None:
    auto = [s.label for s in plan.segments if s.repeat_auto]
    if auto:
        raise EstimationError(f"segment {auto[0]!r} has repeat = \"auto\": its positions are "
                              "not known before the recording, so the plan cannot be checked")


def predict_result(plan: Plan, method: str, noise: Noise, truth: Truth | None = None,
                   options: dict | None = None) -> tuple[CalibrationResult, Recording]:
    """The fit's covariance at the truth for this plan and noise (module docstring)."""
    from calib_cli.sim.simulate import simulate

    check_plannable(plan)
    p = _with_rate(plan, noise.rate)
    if noise.like is not None and recorded_from(plan, noise.like):
        p = attitudes_like(p, noise.like)
        if plan.kind == "turntable" and truth is None and method == "turntable":
            from calib_cli.methods.turntable.design import lever_arms_like

            plan = p = lever_arms_like(p, noise.like, _turntable_options(options or {}))
    rec = simulate(p, nominal_truth(plan, truth), seed=0)
    try:
        return _fit(method, rec, noise, options or {}), rec
    except EstimationError as exc:
        # the fit's hint about static detection concerns recordings, not plans
        msg = exc.message.split(" (static detection with the defaults")[0]
        raise EstimationError(f"the {method} fit would fail on this plan: {msg}",
                              plan.path) from None


def condition_number(res: CalibrationResult) -> float:
    """Condition number of the correlation matrix of the determined entries:
    1 for independent parameters, large when the plan only determines
    combinations of them."""
    C = np.asarray(res.covariance, float)
    d = np.diag(C)
    ok = np.isfinite(d) & (d > 0)
    if not ok.any():
        return float("inf")
    C = C[np.ix_(ok, ok)]
    s = np.sqrt(np.diag(C))
    R = C / np.outer(s, s)
    return float(np.linalg.cond(R))


def condition_details(res: CalibrationResult, exact: float = 1e-9) -> dict:
    """The correlation matrix of the determined entries, explained: its condition
    number; the exact linear dependencies in it (eigenvalues below ``exact`` times
    the size: combinations the model itself fixes, e.g. a cycle's lever arm, two
    free components written in three body axes, not something the plan could
    determine) with the keys they involve; the condition number without them; the
    most correlated pair of entries."""
    C = np.asarray(res.covariance, float)
    d = np.diag(C) if C.size else np.zeros(0)
    ok = np.isfinite(d) & (d > 0)
    out = {"condition": condition_number(res), "condition_determined": float("inf"),
           "dependencies": 0, "dependent_keys": [], "most_correlated": None}
    if ok.sum() < 2:
        return out
    names = []
    for k, flat in np.asarray(res.cov_order, dtype=object)[ok]:
        k = k.decode() if isinstance(k, bytes) else str(k)
        shape = np.shape(res.params.get(k, 0))
        idx = np.unravel_index(int(flat), shape) if shape else ()
        names.append((k, f"{k}[{','.join(map(str, idx))}]" if idx else k))
    C = C[np.ix_(ok, ok)]
    s = np.sqrt(np.diag(C))
    R = C / np.outer(s, s)
    w, V = np.linalg.eigh((R + R.T) / 2)
    null = w < exact * len(w)
    keys = sorted({names[j][0] for i in np.flatnonzero(null)
                   for j in np.flatnonzero(np.abs(V[:, i]) > 1e-6)})
    kept = w[~null]
    out.update(dependencies=int(null.sum()), dependent_keys=keys,
               condition_determined=float(kept.max() / kept.min()) if len(kept) else
               float("inf"))
    off = np.abs(R - np.diag(np.diag(R)))
    off[off > 1.0 - 1e-9] = 0.0  # pairs of an exact dependency
    i, j = np.unravel_index(int(np.argmax(off)), off.shape)
    out["most_correlated"] = [names[i][1], names[j][1], float(R[i, j])]
    return out


# the catalogue's typical sizes (model/effects.py) of the keys plan check ranks
TYPICAL: dict = {}


def _fill_typical():
    if TYPICAL:
        return
    for sensor in ("accel", "gyro"):
        for eff in (Bias(sensor), ScaleMisalignment(sensor, "full")):
            for spec in eff.specs(Layout()):
                TYPICAL[spec.key] = float(np.max(spec.typical))
    from calib_cli.methods.rimu import NAMES
    from calib_cli.methods.rimu import TYPICAL as RT

    for sensor in ("accel", "gyro"):
        for k, nm in enumerate(NAMES):
            TYPICAL[f"{sensor}_{nm}"] = float(RT[sensor][k])


def entries(res: CalibrationResult) -> list[tuple[str, tuple, float]]:
    """(key, index, sigma) of every entry the fit reports (NaN: unobservable),
    without the entries fixed by convention (sigma 0)."""
    out = []
    for k, s in res.sigma.items():
        s = np.asarray(s, float)
        for idx in np.ndindex(s.shape):
            v = float(s[idx])
            if v == 0.0:
                continue
            out.append((k, idx, v))
    return out


def entry_label(key: str, idx: tuple) -> str:
    return f"{key}[{','.join(str(i) for i in idx)}]" if idx else key


def weak_entries(res: CalibrationResult) -> list[str]:
    """Determined entries whose predicted sigma is large: above WEAK_TYPICAL x
    the catalogue's typical size of the key, or WEAK_SPREAD x the median sigma
    of the same key's entries (not for the attitude or a RIMU's dAz, whose
    entries differ by nature)."""
    _fill_typical()
    out = []
    for k, s in res.sigma.items():
        s = np.asarray(s, float)
        good = s[np.isfinite(s) & (s > 0)]
        if not len(good):
            continue
        med = float(np.median(good))
        typ = TYPICAL.get(k)
        # entries that differ by nature: heading against tilt, a RIMU's dAz (1/tilt
        # for a sensor along z)
        spread = k != "attitude" and not k.endswith("_dAz")
        for idx in np.ndindex(s.shape):
            v = float(s[idx])
            if not np.isfinite(v) or v == 0:
                continue
            if (typ is not None and v > WEAK_TYPICAL * typ) or (spread and v > WEAK_SPREAD * med):
                out.append(entry_label(k, idx))
    return out


def _sigma_of(res: CalibrationResult, label: str) -> float:
    key, _, rest = label.partition("[")
    if key not in res.sigma:
        return float("nan")
    s = np.asarray(res.sigma[key], float)
    idx = tuple(int(i) for i in rest.rstrip("]").split(",")) if rest else ()
    return float(s[idx])


def plan_duration(rec: Recording) -> float:
    return float(rec.time[-1] - rec.time[0]) if len(rec.time) > 1 else 0.0


# ---------------------------------------------------------------------------
# suggestions


def _attitude_up(u) -> list:
    """[roll, pitch, 0] deg that puts body direction u up (CONTRACT.md section 1)."""
    u = np.asarray(u, float) / np.linalg.norm(u)
    roll = np.degrees(np.arctan2(u[1], u[2]))
    pitch = np.degrees(np.arctan2(-u[0], np.hypot(u[1], u[2])))
    return [round(float(roll), 4), round(float(pitch), 4), 0.0]


def candidate_directions() -> list[tuple[str, np.ndarray]]:
    """The 26 body directions of faces, edges and corners of a cube."""
    out = []
    names = "xyz"
    for v in np.ndindex(3, 3, 3):
        d = np.array(v) - 1
        if not d.any():
            continue
        lab = "".join(("+" if c > 0 else "-") + names[i] for i, c in enumerate(d) if c)
        out.append((lab + " up", d.astype(float)))
    return out


def _median_duration(plan: Plan, kind: str = "static") -> float:
    d = [s.duration for s in plan.segments if s.kind == kind and s.duration]
    return float(np.median(d)) if d else 10.0


def candidates(plan: Plan, method: str) -> list[tuple[str, tuple]]:
    """Candidate additions: (description, segments to append), from the method's
    ``plan_candidates`` hook (methods/registry.py); none where it has none."""
    from calib_cli.methods.method import resolve

    m = method_of(method)[0]
    return list(resolve(m.plan_candidates)(plan, method)) if m.plan_candidates else []


def position_candidates(plan: Plan, method: str, axes_only: bool = False
                        ) -> list[tuple[str, tuple]]:
    """A static position with each of 26 body directions up (the faces only with
    ``axes_only``): the accelerometer and RIMU fits' candidates (a RIMU plan on a
    turning table gets them on the turning table; the scalar fit's carry their
    attitude for the simulation only)."""
    out = []
    dur = _median_duration(plan)
    scalar = method == "scalar"
    spin = next((s for s in plan.segments if s.kind == "rotating"), None)
    if method != "rimu":
        spin = None
    dirs = candidate_directions()
    if axes_only:
        dirs = [d for d in dirs if np.count_nonzero(d[1]) == 1]
    for lab, u in dirs:
        att = _attitude_up(u)
        name = f"add-{lab.replace(' ', '-')}"
        if scalar:  # unknown attitude: only the simulation needs it
            seg = PlanSegment(label=name, duration=dur,
                              extra={"sim_attitude_deg": att, "duration_s": dur})
        else:
            seg = PlanSegment(label=name, attitude=np.array(att) * D2R, duration=dur,
                              extra={"attitude_deg": att, "duration_s": dur})
        if spin is not None:
            seg = replace(seg, table_axis_enu=spin.table_axis_enu, table_rate=spin.table_rate)
        out.append((f"add a static position with body {lab} ({dur:g} s)", (seg,)))
    return out


def gyro_candidates(plan: Plan, method: str) -> list[tuple[str, tuple]]:
    """The gyro fit's: a position with a body axis up, or a 360 deg turn about a body
    axis and a position after it."""
    out = position_candidates(plan, method, axes_only=True)
    dur = _median_duration(plan)
    last = next((s for s in reversed(plan.segments) if s.kind == "static"
                 and s.attitude is not None), None)
    att = last.attitude if last is not None else np.zeros(3)
    tdur = _median_duration(plan, "turn")
    for i, ax in enumerate("xyz"):
        axis = np.eye(3)[i]
        turn = PlanSegment(label=f"add-turn-{ax}", attitude=att, rotation_axis_body=axis,
                           rotation_angle=2 * np.pi, duration=tdur)
        hold = PlanSegment(label=f"add-after-turn-{ax}", attitude=att, duration=dur)
        out.append((f"add a 360 deg turn about body {ax} ({tdur:g} s) and a position after "
                    "it", (turn, hold)))
    return out


def align_candidates(plan: Plan, method: str) -> list[tuple[str, tuple]]:
    """The alignment's: a third position after a 90 deg turn about a body axis."""
    out = []
    dur_a = _median_duration(plan)
    for i, ax in enumerate("xyz"):
        axis = np.eye(3)[i]
        turn = PlanSegment(label=f"add-turn-{ax}", rotation_axis_body=axis,
                           rotation_angle=np.pi / 2, duration=10.0)
        hold = PlanSegment(label=f"add-position-{ax}", duration=dur_a)
        out.append((f"add a third position after a 90 deg turn about body {ax}", (turn, hold)))
    return out


def turntable_candidates(plan: Plan, method: str) -> list[tuple[str, tuple]]:
    """The turntable fit's candidate additions (methods/registry.py): tilted cycles."""
    return _tilted_cycles(plan)


def _tilted_cycles(plan: Plan) -> list[tuple[str, tuple]]:
    """The six tilted cycles of ``plan make turntable --tilted`` (with the plan's
    generator parameters where it has them) that the plan lacks, one candidate each."""
    import tomllib

    from calib_cli.io.plan import parse_plan
    from calib_cli.sim import plan_make as pm

    try:
        gen = tomllib.loads(plan.text).get("generator", {}) if plan.text else {}
    except (tomllib.TOMLDecodeError, TypeError):
        gen = {}
    kw = {}
    if isinstance(gen, dict) and gen.get("method") == "turntable":
        for k, g in (("tilt_deg", "tilt_deg"), ("tilted_duration", "tilted_duration_s"),
                     ("max_rate", "max_rate_dps"), ("max_accel", "max_accel_dps2"),
                     ("profile", "profile")):
            if g in gen:
                kw[k] = gen[g]
    try:
        full = parse_plan(pm.to_toml(pm.turntable_plan(tilted=True, **kw)), "<tilted>")
    except InputError:
        return []
    have = {s.label for s in plan.segments}
    axis = next((s.table_axis_enu for s in plan.segments if s.kind == "rotating"), None)
    out = []
    for seg in full.segments[3:]:
        if seg.label in have:
            continue
        if axis is not None:
            seg = replace(seg, table_axis_enu=np.asarray(axis, float))
        out.append((f"add the tilted cycle {seg.label} ({seg.duration:g} s)", (seg,)))
    return out


def segment_toml(seg: PlanSegment) -> dict:
    """A plan segment as the [[segment]] keys to paste into a plan."""
    d = {"label": seg.label}
    if seg.attitude is not None:
        d["attitude_deg"] = [round(float(x), 4) for x in np.degrees(seg.attitude)]
    if "sim_attitude_deg" in seg.extra:
        d["sim_attitude_deg"] = seg.extra["sim_attitude_deg"]
    if seg.rotation_axis_body is not None:
        d["rotation_axis_body"] = [float(x) for x in seg.rotation_axis_body]
        d["rotation_angle_deg"] = round(float(np.degrees(seg.rotation_angle)), 4)
    if seg.table_axis_enu is not None:
        d["table_axis_enu"] = [float(x) for x in seg.table_axis_enu]
        if seg.table_rate is not None:
            d["table_rate_dps"] = round(float(np.degrees(seg.table_rate)), 6)
    for k in ("rate_profile", "rate_shape"):  # a turntable cycle
        if k in seg.extra:
            d[k] = seg.extra[k]
    if seg.duration is not None:
        d["duration_s"] = float(seg.duration)
    return d


def _scaled(plan: Plan, factor: float) -> Plan:
    segs = tuple(replace(s, duration=(s.duration or 10.0) * factor) if s.kind == "static" else s
                 for s in plan.segments)
    return replace(plan, segments=segs)


def suggest(plan: Plan, method: str, noise: Noise, base: CalibrationResult,
            targets: list[str], truth: Truth | None = None, options: dict | None = None,
            limit: int = N_SUGGEST) -> list[dict]:
    """Candidate additions ranked by how much they reduce the targets' sigma:
    each unobservable target made observable counts first, then the mean
    log-reduction of the targets' sigma, then (between candidates that fix the
    same number) the smaller sigma of the entries they fix."""
    if not targets:
        return []
    before = {t: _sigma_of(base, t) for t in targets}
    trials = [(desc, segs, replace(plan, segments=plan.segments + segs))
              for desc, segs in candidates(plan, method)]
    if any(s.kind == "static" for s in plan.segments):
        trials.append(("double the duration of every static position", (), _scaled(plan, 2.0)))
    ranked = []
    for desc, segs, p in trials:
        try:
            res, _ = predict_result(p, method, noise, truth, options)
        except EstimationError:
            continue
        after = {t: _sigma_of(res, t) for t in targets}
        fixed = [t for t in targets if not np.isfinite(before[t]) and np.isfinite(after[t])]
        ratios = {t: after[t] / before[t] for t in targets
                  if np.isfinite(before[t]) and np.isfinite(after[t]) and before[t] > 0}
        gain = -float(np.mean(np.log(list(ratios.values())))) if ratios else 0.0
        if not fixed and gain < 0.01:
            continue
        ranked.append({"add": desc, "segments": [segment_toml(x) for x in segs],
                       "fixes": fixed,
                       "sigma_after": {t: (after[t] if np.isfinite(after[t]) else None)
                                       for t in targets},
                       "score": len(fixed) * 100.0 + gain,
                       # among candidates fixing the same entries: the smaller sigma first
                       "tie": float(np.mean(np.log([after[t] for t in fixed]))) if fixed
                       else 0.0})
    ranked.sort(key=lambda d: (-d["score"], d["tie"]))
    for d in ranked:
        del d["tie"]
    return ranked[:limit]


def check(plan: Plan, method: str = "auto", noise: Noise | None = None,
          truth: Truth | None = None, options: dict | None = None,
          suggestions: bool = True) -> Prediction:
    """``calib plan check``: predicted sigma, unobservable entries, condition,
    weak entries and the ranked additions that help them."""
    m = resolve_method(plan, method)
    noise = noise or default_noise(plan, truth=truth)
    if noise.like is not None and not recorded_from(plan, noise.like):
        noise = replace(noise, source=f"{noise.source}, a recording of another plan: its "
                                      "noise levels only")
    res, rec = predict_result(plan, m, noise, truth, options)
    weak = weak_entries(res)
    targets = list(res.stats.get("unobservable", [])) + weak
    # no candidate additions where the method has none (thermal, yet)
    sug = suggest(plan, m, noise, res, targets, truth, options) \
        if suggestions and method_of(m)[0].plan_candidates else []
    return Prediction(res.method, res, noise, plan_duration(rec), condition_number(res), weak,
                      sug)


# ---------------------------------------------------------------------------
# plan optimize

MIN_SEGMENT_S = 2.0  # the shortest static position plan optimize proposes


@dataclass(frozen=True)
class Target:
    key: str
    select: str  # "all", "diag", "offdiag"
    sigma: float

    @property
    def text(self) -> str:
        return f"{self.key}{'' if self.select == 'all' else '.' + self.select}={self.sigma:g}"


def parse_target(text: str) -> Target:
    """KEY[.diag|.offdiag]=SIGMA (SI)."""
    lhs, eq, rhs = text.partition("=")
    if not eq:
        raise ValueError(f"{text!r}: expected KEY[.diag|.offdiag]=SIGMA")
    key, _, sel = lhs.strip().partition(".")
    sel = sel or "all"
    if sel not in ("all", "diag", "offdiag"):
        raise ValueError(f"{text!r}: the selector must be .diag or .offdiag")
    try:
        v = float(rhs)
    except ValueError:
        raise ValueError(f"{text!r}: SIGMA must be a number (SI)") from None
    if not np.isfinite(v) or v <= 0:
        raise ValueError(f"{text!r}: SIGMA must be positive")
    return Target(key, sel, v)


def target_sigmas(res: CalibrationResult, t: Target) -> np.ndarray:
    """The predicted sigma of the entries a target names (NaN: unobservable);
    entries fixed by convention (sigma 0) are left out."""
    if t.key not in res.sigma:
        raise EstimationError(f"the fit of this plan ({res.method}) does not report {t.key}; "
                              f"it reports {', '.join(res.sigma)}")
    s = np.asarray(res.sigma[t.key], float)
    if t.select != "all":
        if s.ndim != 2 or s.shape[0] != s.shape[1]:
            raise EstimationError(f"{t.key} is not a square matrix: .{t.select} does not apply")
        eye = np.eye(s.shape[0], dtype=bool)
        s = s[eye] if t.select == "diag" else s[~eye]
    s = s.ravel()
    return s[s != 0.0]


def worst_ratio(res: CalibrationResult, targets: list[Target]) -> float:
    """max over the targets' entries of predicted sigma / target (inf: unobservable)."""
    r = 0.0
    for t in targets:
        s = target_sigmas(res, t)
        if not len(s) or not np.all(np.isfinite(s)):
            return float("inf")
        r = max(r, float(s.max() / t.sigma))
    return r


def _durations_scaled(plan_dict: dict, factor: float) -> dict:
    d = dict(plan_dict)
    segs = []
    for s in plan_dict["segment"]:
        s = dict(s)
        turn = "rotation_angle_deg" in s
        if not turn and "rate_profile" not in s:
            s["duration_s"] = round(max(MIN_SEGMENT_S, float(s.get("duration_s", 10.0)) * factor),
                                    3)
        segs.append(s)
    d["segment"] = segs
    return d


def family(plan_dict: dict) -> list[tuple[str, dict]]:
    """The members of a generated plan's family (other position counts) as plan
    dicts at the generator's durations; [(description, dict)]. A plan without
    a [generator] table is its own family (durations only)."""
    from calib_cli.sim import plan_make as pm

    gen = plan_dict.get("generator")
    if isinstance(gen, dict) and gen.get("method") == "ferraris":
        td = float(gen.get("turn_duration_s", 10.0))
        return [(f"turns of {t:g} s", pm.ferraris_plan(float(gen.get("duration_s", 10.0)), t,
                                                       float(gen.get("sample_rate_hz", 100.0))))
                for t in sorted({max(4.0, td / 2), td, 2 * td})]
    if not isinstance(gen, dict) or gen.get("method") != "static":
        return [("this plan", plan_dict)]
    fitm = gen.get("fit", "vector")
    out = []
    for n in pm.STATIC_COUNTS:
        if fitm == "scalar" and n < 9:
            continue
        d = pm.static_plan(n, fitm, float(gen.get("duration_s", 10.0)),
                           float(gen.get("sample_rate_hz", 100.0)))
        out.append((f"{n} positions", d))
    return out


def _plan_from_dict(d: dict, path: str) -> Plan:
    from calib_cli.io.plan import parse_plan
    from calib_cli.sim import plan_make as pm

    return parse_plan(pm.to_toml(d), path)


def plan_total(plan: Plan) -> float:
    """Recorded time of a plan as simulate runs it: segments and transitions, s."""
    from calib_cli.sim.simulate import DEFAULT_ROTATING_S

    trans = float(plan.extra.get("transition_s", 4.0))
    total = 0.0
    for i, s in enumerate(plan.segments):
        if s.kind == "rotating" and "rate_profile" in s.extra:
            total += float(np.asarray(s.extra["rate_profile"], float)[-1, 0])
        else:
            total += s.duration or (DEFAULT_ROTATING_S if s.kind == "rotating" else 10.0)
        if i:
            total += float(s.extra.get("transition_s", trans))
    return total


@dataclass(frozen=True)
class Optimized:
    plan_dict: dict
    plan: Plan
    prediction: Prediction
    member: str
    duration_before: float
    duration_after: float
    tried: list


def optimize(plan: Plan, plan_dict: dict, targets: list[Target], method: str = "auto",
             noise: Noise | None = None, truth: Truth | None = None,
             max_duration: float | None = None, options: dict | None = None) -> Optimized:
    """The shortest member of the plan's family (position count, then the
    common duration scale of its static positions, by bisection on the
    predicted sigma) whose predicted sigma meets every target."""
    m = resolve_method(plan, method)
    noise = noise or default_noise(plan, truth=truth)
    before = plan_total(plan)

    def ratio(d):
        p = _plan_from_dict(d, plan.path)
        res, _ = predict_result(p, m, noise, truth, options)
        return worst_ratio(res, targets), p

    gen = plan_dict.get("generator")
    turntable = isinstance(gen, dict) and gen.get("method") == "turntable"
    if m == "turntable" and not turntable:
        raise EstimationError("plan optimize scales a turntable plan's cycles through its "
                              "generator: give a plan made by `calib plan make turntable`",
                              plan.path)
    # log2 of the duration factor: its range, the bisection's tolerance, the rounding step
    # (a turntable prediction is a filter pass over the record: fewer and nearer)
    lo0, hi0, tol, step = (-8.0, 6.0, 0.01, 0.01) if not turntable else (None, 1.0, 0.05, 0.05)
    scaled = _turntable_scaled if turntable else _durations_scaled
    best, tried = None, []
    for desc, d0 in (_turntable_family(gen) if turntable else family(plan_dict)):
        lo, hi = (lo0 if lo0 is not None else _turntable_lowest(d0)), hi0
        r_hi, _ = ratio(scaled(d0, 2.0 ** hi))
        if not np.isfinite(r_hi) or r_hi > 1.0:
            tried.append((desc, None))
            continue
        if ratio(scaled(d0, 2.0 ** lo))[0] <= 1.0:
            hi = lo
        for _ in range(14):
            if hi - lo < tol:
                break
            mid = 0.5 * (lo + hi)
            if ratio(scaled(d0, 2.0 ** mid))[0] <= 1.0:
                hi = mid
            else:
                lo = mid
        d = scaled(d0, 2.0 ** hi)
        r, p = ratio(d)
        while r > 1.0:  # rounding of the durations: a little more
            hi += step
            d = scaled(d0, 2.0 ** hi)
            r, p = ratio(d)
        tot = plan_total(p)
        tried.append((desc, tot))
        if best is None or tot < best[2]:
            best = (desc, d, tot, p)
    if best is None:
        names = ", ".join(t.text for t in targets)
        far = "2 x the cycle durations" if turntable else "64 x the durations"
        raise EstimationError(f"no plan of this family meets {names} (unobservable, or beyond "
                              f"{far}): change the plan's positions")
    desc, d, tot, p = best
    if max_duration is not None and tot > max_duration:
        raise EstimationError(f"the shortest plan that meets the targets takes {tot:.0f} s, "
                              f"over --max-duration {max_duration:g} s")
    if turntable:
        d["generator"] = {**d["generator"], "optimized_for": [t.text for t in targets]}
    elif isinstance(d.get("generator"), dict):
        d["generator"] = {**d["generator"], "optimized_for": [t.text for t in targets],
                          "duration_scale": round(_duration_scale(d), 4)}
    pred = check(p, m, noise, truth, options, suggestions=False)
    return Optimized(d, p, pred, desc, before, tot, tried)


TURNTABLE_MIN_CYCLE_S = 60.0  # the shortest cycle plan make turntable writes


def _turntable_family(gen: dict) -> list[tuple[str, dict]]:
    """The members of a generated turntable plan's family: with and without the six
    tilted cycles, as ``plan_make.turntable_plan`` keyword arguments at the
    generator's durations (scaled by ``_turntable_scaled``)."""
    kw = {"tilt_deg": float(gen.get("tilt_deg", 5.0)),
          "duration": float(gen.get("duration_s", 600.0)),
          "tilted_duration": float(gen.get("tilted_duration_s", 300.0)),
          "max_rate": float(gen.get("max_rate_dps", 200.0)),
          "max_accel": float(gen.get("max_accel_dps2", 200.0)),
          "profile": str(gen.get("profile", "steps")),
          "rate": float(gen.get("sample_rate_hz", 100.0))}
    return [("3 axial and 6 tilted cycles", {**kw, "tilted": True}),
            ("3 axial cycles", {**kw, "tilted": False})]


def _turntable_lowest(kw: dict) -> float:
    """log2 of the smallest duration factor that keeps every cycle >= the shortest."""
    shortest = min(kw["duration"], kw["tilted_duration"]) if kw["tilted"] else kw["duration"]
    return float(np.log2(TURNTABLE_MIN_CYCLE_S / shortest))


def _turntable_scaled(kw: dict, factor: float) -> dict:
    from calib_cli.sim import plan_make as pm

    return pm.turntable_plan(**{**kw, "duration": round(kw["duration"] * factor),
                                "tilted_duration": round(kw["tilted_duration"] * factor)})


def _duration_scale(d: dict) -> float:
    gen = d.get("generator", {})
    base = float(gen.get("duration_s", 10.0))
    durs = [s.get("duration_s") for s in d["segment"] if "rotation_angle_deg" not in s]
    durs = [x for x in durs if x]
    return float(np.median(durs)) / base if durs and base else 1.0


def operator_sheet(plan: Plan) -> list[dict]:
    """What the operator does, in order: position/turn, attitude, duration."""
    rows = []
    for i, s in enumerate(plan.segments):
        row = {"step": i + 1, "label": s.label, "kind": s.kind,
               "duration_s": s.duration}
        if s.attitude is not None:
            row["attitude_deg"] = [round(float(x), 3) for x in np.degrees(s.attitude)]
        elif "sim_attitude_deg" in s.extra:
            row["attitude_deg"] = list(s.extra["sim_attitude_deg"])
            row["note"] = "any attitude near this one (not used by the fit)"
        if s.kind == "turn":
            row["turn"] = (f"{np.degrees(s.rotation_angle):g} deg about body "
                           f"{[round(float(x), 3) for x in s.rotation_axis_body]}")
        rows.append(row)
    return rows


def record_warning(plan: Plan, rate: float | None = None) -> str | None:
    """The one line ``calib record`` prints before it starts when the plan
    cannot deliver what its method reports (unobservable entries, or the fit
    would fail); None when it can, for ``repeat = "auto"`` plans and for plans
    plan check does not cover yet. Never raises."""
    if any(s.repeat_auto for s in plan.segments):
        return None
    try:
        pr = check(plan, noise=default_noise(plan, rate), suggestions=False)
    except EstimationError as exc:
        return f"plan check: {exc.message}"
    except Exception:  # noqa: BLE001 - a warning must never stop a recording
        return None
    lost = plan_unobservable(pr.result)
    if lost:
        return (f"plan check: this plan leaves {compact_labels(lost)} unobservable (calib plan "
                f"check {plan.path} for the additions that help; --no-check to skip)")
    return None


def plan_unobservable(res: CalibrationResult) -> list[str]:
    """The unobservable entries the plan is to blame for: those of parameters the fit
    estimates (in its covariance). Entries the method never determines (the thermal
    fit's gyro_temp_scale without a rate table, proof masses held at 0 by an option)
    are the method's, whatever the plan."""
    est = {k for k, *_ in (res.cov_order or [])}
    return [u for u in res.stats.get("unobservable", []) if u.partition("[")[0] in est]


def compact_labels(labels: list[str]) -> str:
    """Entry labels, a key with more than three of them as one item:
    'proof_mass_offsets (6 entries), gyro_bias[0]'."""
    keys: dict = {}
    for u in labels:
        keys.setdefault(u.partition("[")[0], []).append(u)
    return ", ".join(", ".join(v) if len(v) <= 3 else f"{k} ({len(v)} entries)"
                     for k, v in keys.items())
