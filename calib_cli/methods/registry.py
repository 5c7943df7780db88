"""The method table: every calibration method, registered once (``methods/method.py``
says what a method holds). ``calib fit``, ``calib batch``, ``calib_cli.api``, ``calib
plan check``, ``calib diagnose`` and ``calib report`` iterate over ``FITS`` and hold no
list of method names of their own; every fit, whichever way in, goes through ``run``:
options checked, the recording checked, the method's own preparation, the fit (plain or
``--with``), the gross-error screen, the impossible-result check -- in that order, so
the same recording gives the same result, exit code and message.

Rules (CONTRACT.md section 5):

- the wrong kind of recording for the method (a redundant unit given to a triad
  fit or the reverse, no data of a sensor the method needs, raw counts where the
  method needs SI) is bad input, exit 3, and the message names the right command;
- too few positions for the method (or degenerate ones, found by the fit itself)
  is exit 4.

Start-up: the command line builds its options from this table, so this module
imports no numpy or SciPy at the top: the fits below import their modules when
called (those function-level imports buy the start-up time of ``calib fit --help``).
"""

from __future__ import annotations

import dataclasses
import inspect
from dataclasses import dataclass
from typing import TYPE_CHECKING

from calib_cli.errors import EstimationError, InputError
from calib_cli.methods.method import (
    AtLeast,
    Diagnose,
    FileInput,
    Method,
    Option,
    OptionsBase,
    Requires,
    resolve,
)

if TYPE_CHECKING:
    from calib_cli.data import CalibrationResult, Recording

__all__ = ["FITS", "AtLeast", "Diagnose", "FileInput", "Method", "Option", "Requires",
           "WithRequest", "check_recording", "get", "information", "method_of_plan_kind",
           "method_of_result", "options_from", "register", "run"]

FITS: dict[str, Method] = {}


def register(method: Method) -> Method:
    """Add a method to the table (the one registration line of a new method)."""
    if method.name in FITS:
        raise ValueError(f"a method {method.name!r} is registered already")
    FITS[method.name] = method
    globals()[method.options_type.__name__] = method.options_type
    return method


def get(method: str) -> Method:
    if method not in FITS:
        raise InputError(f"unknown fit method {method!r}; known: {', '.join(sorted(FITS))}")
    return FITS[method]


def method_of_plan_kind(kind: str) -> str | None:
    """The method a plan kind's records go to by default (batch ``method = "auto"``): the
    one of that kind that claims no particular plans."""
    return next((m.name for m in FITS.values() if kind in m.plan_kinds and m.claims is None),
                None)


def plan_method_names() -> list[str]:
    """What ``plan check --method`` takes: auto, every method and its variants (accel's
    vector and scalar)."""
    out = ["auto"]
    for m in FITS.values():
        out += [m.name, *m.variants]
    return out


def method_of_result(result_method: str) -> Method | None:
    """The method that wrote a calibration (its ``method``: the method's name or one of
    its variants, e.g. "vector" for accel, "align-classic" for align)."""
    for m in FITS.values():
        if result_method == m.name or result_method in m.result_names:
            return m
    return None


# ---------------------------------------------------------------------------
# options


def options_from(method: str, mapping: dict | None = None, /, **kw):
    """The method's options from a mapping of the command line's names (a batch
    step's table, API keywords); an unknown name or a bad value is an InputError
    naming it."""
    m = get(method)
    given = {**(mapping or {}), **kw}
    names = {o.name for o in m.options}
    unknown = sorted(set(given) - names)
    if unknown:
        known = ", ".join(m.option_names()) or "none"
        raise InputError(f"fit {method} takes no option {unknown[0]!r} (known: {known})")
    opts = m.options_type(**given)
    opts.check()
    return opts


def _options(m: Method, options):
    if options is None or isinstance(options, dict):
        return options_from(m.name, options)
    if not isinstance(options, m.options_type):
        raise TypeError(f"fit {m.name}: options must be {m.options_type.__name__}")
    options.check()
    return options


# ---------------------------------------------------------------------------
# the recording


def check_recording(method: str, rec: Recording, path: str | None = None) -> None:
    """The method's requirements on a recording: exit 3 for the wrong kind of
    recording (naming the right command), exit 4 for too few positions."""
    m = get(method)
    req = m.requires
    if req.layout == "triad" and rec.layout.redundant:
        raise InputError(f"this is a redundant-unit recording: use `calib fit rimu`, not "
                         f"`calib fit {method}`", path)
    if req.layout == "redundant" and not rec.layout.redundant:
        right = method_of_plan_kind(rec.plan_kind) or "accel"
        raise InputError("not a redundant-unit recording (plan kind \"rimu\" with a [rimu] "
                         f"geometry): use `calib fit {right}`", path)
    for s in req.sensors:
        if getattr(rec, s) is None:
            raise InputError(f"`calib fit {method}` needs {s} data; the recording has none", path)
    for attr, words in req.channels:
        if getattr(rec, attr) is None:
            raise InputError(f"`calib fit {method}` needs {words}; the recording has none", path)
    for s in req.si:
        if rec.in_counts(s):
            raise InputError(f"`calib fit {method}` needs {s} data in SI units, the recording "
                             "is in raw counts (import with a scale)", path)
    if "accel" in req.sensors:  # static positions that do not see gravity (issue 37)
        from calib_cli.methods.segstats import check_gravity_seen

        check_gravity_seen(rec, path)
    n_static = len(rec.static_segments())
    if n_static < req.min_static:
        from calib_cli.methods.static_detect import too_few_hint

        right = method_of_plan_kind(rec.plan_kind)
        if right and right != method and n_static == 0:  # the wrong fit for this plan
            raise EstimationError(f"`calib fit {method}` needs >= {req.min_static} static "
                                  f"position{'s' if req.min_static > 1 else ''}; this is a "
                                  f"{rec.plan_kind} recording: use `calib fit {right}`", path)
        raise EstimationError(f"`calib fit {method}` needs >= {req.min_static} static "
                              f"position{'s' if req.min_static > 1 else ''}; the recording "
                              f"has {n_static}{req.advice}{too_few_hint(rec, req.min_static)}",
                              path)
    n_rot = sum(1 for s in rec.segments if s.kind == "rotating")
    if n_rot < req.min_rotating:
        raise EstimationError(f"`calib fit {method}` needs >= {req.min_rotating} rotating "
                              f"segment{'s' if req.min_rotating > 1 else ''} (table cycles); "
                              f"the recording has {n_rot}", path)


# ---------------------------------------------------------------------------
# the one way to run a fit


@dataclass(frozen=True)
class WithRequest:
    """``--with``: catalogue effects [(name, sensor)] added to the method's base model
    (methods/fit_with.py), the base model's scale factors ("full" or "diagonal") and
    the noise floor ("auto" or "hf")."""

    effects: tuple
    base: str = "full"
    noise: str = "auto"


def check_with(method: str, req: WithRequest) -> None:
    """What a method's ``--with`` accepts (ValueError naming the problem: the command
    line's usage error, the batch's and API's InputError)."""
    m = get(method)
    if m.with_engine is None:
        raise ValueError(f"the {method} method takes no --with")
    if req.base not in ("full", "diagonal") or req.noise not in ("auto", "hf"):
        raise ValueError("base is full or diagonal, the noise floor auto or hf")
    if m.with_engine == "own":
        bad = [n for n, _ in req.effects if n not in m.with_effects]
        if bad:
            raise ValueError(f"{bad[0]}: the {method} fit takes {', '.join(m.with_effects)}")
        return
    from calib_cli.methods import with_effects as fw

    if m.with_engine == "filter":  # catalogue effects on the method's own rows
        bad = [(n, s) for n, s in req.effects if n in m.with_excluded
               and not (n == "misalignment" and req.base == "diagonal")]
        if bad:
            n, s = bad[0]
            raise ValueError(f"{fw.with_arg(n, s)}: {m.with_excluded[n]}")
        if req.noise != "auto":
            raise ValueError(f"the {method} fit's --with takes its own noise estimate")
        return

    if m.with_engine == "gyro":
        bad = [fw.with_arg(n, s) for n, s in req.effects if s != "gyro" or n not in fw.GYRO_WITH]
        if bad:
            raise ValueError(f"{', '.join(bad)}: the gyro method takes "
                             f"{', '.join(fw.GYRO_WITH)} (docs/diagnose.md)")
    if any(n == "misalignment" for n, _ in req.effects):
        if "misalignment" in m.with_excluded:
            raise ValueError(f"the {method} method has no triad misalignment "
                             f"({m.with_excluded['misalignment']})")
        if req.base != "diagonal":
            raise ValueError("--with misalignment needs --base diagonal (the full base model "
                             "already has every misalignment)")


def parse_with(method: str, text: str, base: str = "full", noise: str = "auto") -> WithRequest:
    """A WithRequest from the ``--with`` text ("A,B.c"); ValueError names the problem."""
    m = get(method)
    if m.with_engine == "own":
        effects = tuple((e.strip(), "") for e in str(text).split(",") if e.strip())
        if not effects:
            raise ValueError("no effect named")
    else:
        from calib_cli.methods.with_effects import parse_with as parse_effects

        effects = tuple(parse_effects(text, method))
    req = WithRequest(effects, base, noise)
    check_with(method, req)
    return req


def _call_fit(m: Method, rec, options, progress=None):
    fn = resolve(m.fit)
    kw = ({"progress": progress} if progress is not None
          and "progress" in inspect.signature(fn).parameters else {})
    return fn(rec, options, **kw)


def _fit_with(m: Method, rec, options, req: WithRequest):
    if m.with_engine == "filter":
        return resolve(m.with_fit)(rec, options, req.effects, req.base)
    if m.with_engine == "own":
        return resolve(m.with_fit)(rec, options, req.effects)
    from calib_cli.methods import fit_with as fw

    if m.with_engine == "gyro":
        acc = options.accel.value if options.accel is not None else None
        return fw.fit_with_gyro(rec, list(req.effects), req.base, acc, options.accel_independent)
    return fw.fit_with(rec, m.name, list(req.effects), base=req.base, noise=req.noise)[0]


def run(method: str, rec: Recording, options=None, path: str | None = None,
        progress=None, with_: WithRequest | None = None) -> CalibrationResult:
    """Check the options and the recording, prepare, fit (plain, or with the catalogue
    effects of ``with_``), screen for gross errors, refuse an impossible result
    (exit 4). ``options``: the method's options dataclass, a mapping of its names, or
    None for the defaults. ``path`` names the recording in errors. ``progress(done,
    total)``: optional, passed to fits that report progress. With ``with_`` the gross-
    error screen is the plain fit's (a position the plain fit accuses is accused before
    any effect can absorb it)."""
    m = get(method)
    try:
        options = _options(m, options)
        if with_ is not None:
            try:
                check_with(method, with_)
            except ValueError as exc:
                raise InputError(f"--with: {exc}") from None
        check_recording(method, rec, path)
        if m.prepare is not None:
            options = resolve(m.prepare)(options, rec)
        if with_ is not None and m.screen is not None:
            _screened_fit(m, rec, options)  # the plain fit's screen; its result is not used
        if with_ is not None:
            res = _fit_with(m, rec, options, with_)
        else:
            res = _screened_fit(m, rec, options, progress)
        from calib_cli.methods.gross import check_result

        check_result(res, rec)
    except (InputError, EstimationError) as exc:
        exc.path = exc.path or path
        raise
    except __import__("numpy").linalg.LinAlgError as exc:  # degenerate data the checks let through
        raise EstimationError(f"`calib fit {method}`: the data do not determine the "
                              f"parameters (a singular system: {exc}); check that the "
                              "positions differ as the plan says", path) from None
    return res


def _screened_fit(m: Method, rec, options, progress=None):
    res = _call_fit(m, rec, options, progress)
    if m.screen == "after":
        from calib_cli.methods.gross import screen_fit

        screen_fit(res, rec, lambda r: _call_fit(m, r, options))
    return res


def information(method: str, rec: Recording, options=None, noise: dict | None = None,
                like: Recording | None = None) -> CalibrationResult:
    """The method's covariance on a noise-free record at per-sample noise ``noise``
    ({"accel", "gyro"}, SI): the fit's own rows and weights at the truth, i.e. the
    inverse Fisher information ``plan check`` reports (``like``: the recording the
    noise came from, for methods whose fit takes more than its noise from it)."""
    m = get(method)
    o = _options(m, options)
    if m.information is not None:
        return resolve(m.information)(rec, o, noise, like)
    fn = resolve(m.fit)
    if "noise" not in inspect.signature(fn).parameters:
        raise EstimationError(f"the {method} method predicts nothing (its fit takes no noise=)")
    return fn(rec, o, noise=noise)


def diagnose(method: str, rec: Recording, base: str = "full", alpha: float | None = None,
             noise: str = "auto"):
    """``calib diagnose --method METHOD``: the method's diagnosis as its ``Diagnose``
    description says (engine "engine": the catalogue refit engine of methods/diagnose.py
    on the description's base model; else the method's own, e.g. the gyro fit's
    equations, methods/diagnose_gyro.py). A method without one: InputError (exit 3)."""
    m = get(method)
    if m.diagnose is None:
        raise InputError(f"diagnose --method {method}: the {method} method has no diagnosis "
                         f"(diagnose takes {', '.join(diagnosable())})")
    kw = {} if alpha is None else {"alpha": alpha}
    if m.diagnose.own:
        return resolve(m.diagnose.engine)(rec, base=base, **kw)
    from calib_cli.methods.diagnose import diagnose as run_engine

    return run_engine(rec, m, base=base, noise=noise, **kw)


def diagnosable() -> list[str]:
    """The methods ``calib diagnose --method`` takes."""
    return [m.name for m in FITS.values() if m.diagnose]


# ---------------------------------------------------------------------------
# the built-in methods' fits (numpy and SciPy imported when a fit runs)


def _fit_accel(rec, o, noise=None):
    from calib_cli.methods.accel_lsq import fit_accel

    if noise is not None:
        return fit_accel(rec, o.method, noise=noise["accel"], strict=False)
    return fit_accel(rec, o.method)


def _fit_gyro(rec, o, noise=None):
    from calib_cli.methods.gyro import fit_gyro

    acc = None if o.accel is None else o.accel.value
    if noise is not None:
        return fit_gyro(rec, acc, o.g_sensitivity, noise=noise, strict=False)
    return fit_gyro(rec, acc, o.g_sensitivity, accel_independent=o.accel_independent)


def _prepare_gyro(o, rec):
    """An accelerometer calibration read from a file made from other data than this
    recording is independent of it: its uncertainty is propagated (docs/gyro.md)."""
    if o.accel is not None and o.accel.from_this_recording is not None:
        return dataclasses.replace(o, accel_independent=not o.accel.from_this_recording)
    return o


def _fit_align(rec, o, noise=None):
    import numpy as np

    if o.method == "classic":
        from calib_cli.methods.align_classic import fit_classic

        return fit_classic(rec, rotation=o.rotation)
    if o.method == "static":
        from calib_cli.methods.align_static import fit_align_static

        return fit_align_static(rec)
    from calib_cli.methods.align import fit_align

    return fit_align(rec, rotation=o.rotation, gyro=o.gyro,
                     gyro_k_prior=None if o.gyro_k_ppm is None else float(o.gyro_k_ppm) * 1e-6,
                     turn_sigma=float(np.radians(o.turn_sigma_deg)), noise=noise)


def _fit_rimu(rec, o, noise=None):
    from calib_cli.methods.rimu import fit_rimu

    if noise is not None:
        return fit_rimu(rec, noise=noise, strict=False)
    return fit_rimu(rec)


def _fit_turntable(rec, o, progress=None):
    from calib_cli.methods.turntable import fit_turntable

    return fit_turntable(rec, o.to_method(), progress=progress)


THERMAL_ORDER = 2  # plan check predicts the thermal fit at this order when --order is auto


def _fit_thermal(rec, o, noise=None, lag: bool = False):
    from calib_cli.methods.thermal import fit_thermal

    sensors = ("accel", "gyro") if o.sensor == "both" else (o.sensor,)
    base = None if o.base is None else o.base.value
    if noise is not None:
        return fit_thermal(rec, order=o.order or THERMAL_ORDER, temp_ref=o.temp_ref,
                           sensors=sensors, base=base, noise=noise)
    return fit_thermal(rec, order=o.order, temp_ref=o.temp_ref, sensors=sensors, base=base,
                       lag=lag)


def _thermal_with(rec, o, effects):
    return _fit_thermal(rec, o, lag=any(n == "thermal_lag" for n, _ in effects))


def _accel_variant(plan) -> str:
    """``fit accel --method auto`` on a plan: vector when every static position has an
    attitude, else scalar (CONTRACT.md section 5)."""
    statics = [s for s in plan.segments if s.kind == "static"]
    return "vector" if statics and all(s.attitude is not None for s in statics) else "scalar"


def _has_turns(plan) -> bool:
    """A static plan with turns of known angle goes to the gyro fit (Ferraris)."""
    return any(s.kind == "turn" for s in plan.segments)


# ---------------------------------------------------------------------------
# lines the command line prints after a fit (pure: from the result)


def _notes_gyro(res, o) -> list:
    st = res.stats
    out = []
    if o.accel is not None and o.accel.from_this_recording is not None:
        out.append("accelerometer calibration " + (
            "from other data: its uncertainty is propagated into the gyro parameters"
            if not o.accel.from_this_recording else "from this recording"))
    out += [f"[yellow]warning:[/] {w}" for w in st.get("warnings", [])]
    tr = st.get("transition_residual_rms_rad")
    if "n_transitions" in st:
        out.append(f"{st['n_transitions']} transitions, {st['n_turns']} turns, "
                   f"{st['n_positions']} static positions; transition residual RMS "
                   f"{'n/a' if tr is None else f'{tr * 180 / 3.141592653589793:.3f} deg'}")
    return out


def _notes_align(res, o) -> list:
    st, out = res.stats, []
    if o.method == "static" and st.get("degeneracy"):
        out.append(f"[yellow]degenerate positions:[/] {st['degeneracy']}; not observable: "
                   + ", ".join(st["unobservable"]))
    if not st.get("earth_rate_used", True):
        out.append(f"[yellow]earth rate not used:[/] {st.get('grade_check')}; heading not "
                   "estimated, accelerometer biases and tilt only")
    if st.get("observability"):
        out.append(st["observability"])
    return out


def _notes_turntable(res, o) -> list:
    st, out = res.stats, []
    clipped = st.get("accel_clipped_samples") or []
    if any(clipped):
        out.append(f"[yellow]warning:[/] {sum(clipped)} accelerometer samples sit at full scale "
                   "(saturated?): the centripetal and tangential terms may exceed the range; "
                   "the fit does not model clipping")
    if st.get("accel_noise_inflation", 1.0) > 1.0:
        out.append(f"[yellow]the model does not explain the accelerometer data:[/] noise "
                   f"widened x{st['accel_noise_inflation']:.1f}: an effect the data show is "
                   "missing from the model (calib diagnose --method turntable names it)")
    if str(st.get("gravity_reference", "")).startswith("none"):
        out.append("[yellow]warning:[/] every table axis is vertical and nothing gives the "
                   "accelerometers a gravity reference: their biases and K, the lever arms and "
                   "the gyros' misalignment are not determined (reported null), and the gyro "
                   "biases and g-sensitivity only through the centripetal terms: a record at "
                   "one rate per cycle, and most records without the table's channels, end "
                   "in exit 4 (docs/turntable.md, \"Known limits on a vertical axis\"); the "
                   "gyro scale factors hold only for mountings within a few tenths of a "
                   "degree of the plan's (3 deg off: half such fits end in exit 4, the rest "
                   "with sigma up to 1.4x small); log the table's channels, state "
                   "attitude_sigma_deg, add static positions or a tilted cycle")
    return out


def _notes_thermal(res, o) -> list:
    st = res.stats
    if "temp_order" not in st:
        return []
    return [f"order {st['temp_order']} (T_ref {st['temp_ref_degC']:g} degC, range "
            f"{st['temp_range_degC'][0]:.1f}..{st['temp_range_degC'][1]:.1f} degC)"]


# ---------------------------------------------------------------------------
# the built-in methods


class TurntableOptionsBase(OptionsBase):
    def to_method(self):
        """The estimator's ``TurntableOptions`` (SI) of these options."""
        import numpy as np

        from calib_cli.methods.turntable import TurntableOptions

        return TurntableOptions(
            lever_arm=self.lever_arm, proof_mass=self.proof_mass,
            tangential=self.tangential in ("on", True), block_s=float(self.block_s),
            axis_sigma=(None if self.axis_sigma_mrad == "auto"
                        else float(self.axis_sigma_mrad) * 1e-3),
            runout_sigma=float(self.runout_mrad) * 1e-3,
            table_tilt_sigma=float(np.radians(self.table_tilt_deg)), grade=self.grade,
            priors=dict(self.prior) if self.prior else None,
            noise=None if self.noise is None else {k: np.full(3, float(v))
                                                   for k, v in self.noise.items()},
            table_encoder=self.table_encoder)


ENGINE_EXCLUDED = {"misalignment": "align: K is the identity; rimu: each sensor's direction "
                                   "is in the base model"}

register(Method(
    "accel", "static multi-position accelerometer fit", _fit_accel,
    help="Static multi-position accelerometer fit: A = b + K f.",
    options=(Option("method", "auto", "vector: known attitudes; scalar: |a| = g.", "choice",
                    ("auto", "vector", "scalar")),),
    requires=Requires("triad", ("accel",), min_static=1),
    screen="inside", information=lambda rec, o, noise, like: _fit_accel(rec, o, noise),
    plan_kinds=("static",), variants={"vector": {"method": "vector"},
                                      "scalar": {"method": "scalar"}},
    variant_of=_accel_variant,
    result_names=("vector", "scalar"), plan_candidates="calib_cli.design:position_candidates",
    with_engine="engine", report=("calib_cli.report.sections_static",),
    diagnose=Diagnose(
        base="calib_cli.methods.diagnose_models:accel_base", sensors=("accel",),
        unknown_attitudes=True,
        needs=(AtLeast("static", 6, "{count} static segments with a known attitude; the "
                       "accel base model needs at least 6 positions", attitudes="known"),
               AtLeast("static", 9, "{count} static segments; the accel base model needs at "
                       "least 9 positions", attitudes="unknown"))),
    options_name="AccelOptions", docs="docs/accel.md"))

register(Method(
    "thermal", "bias and scale factor polynomials in temperature", _fit_thermal,
    help="Bias and scale factor polynomial in temperature on top of the static model, from "
         "soak steps and/or ramps in known positions (docs/thermal.md).",
    options=(
        Option("order", None, "Polynomial order in T - T_ref (default: by BIC over 1..3).",
               "int", lo=1, hi=3, optional=True, plan_check=False),
        Option("temp_ref", 25.0, "Reference temperature T_ref, degC.", "float", lo=-100,
               hi=200),
        Option("sensor", "both", "The sensors whose temperature terms are fitted.", "choice",
               ("accel", "gyro", "both")),
        Option("base", None, "A room-temperature calibration whose K (and gyro G) are held.",
               "calibration", needs_keys=("accel_K", "gyro_K"), metavar="CAL"),
    ),
    requires=Requires("triad", ("accel",), channels=(("temp", "the unit's temperature "
                                                               "(samples/temp)"),)),
    information=lambda rec, o, noise, like: _fit_thermal(rec, o, noise),
    plan_kinds=("static",), claims="calib_cli.sim.chamber:has_chamber",
    with_engine="own", with_fit=_thermal_with, with_effects=("thermal_lag",),
    notes=_notes_thermal, report=("calib_cli.report.sections_thermal",),
    options_name="ThermalOptions", docs="docs/thermal.md"))

register(Method(
    "gyro", "gyro bias, K (and D) from rotations between static positions", _fit_gyro,
    help="Gyro bias, scale factors and misalignments (and g-sensitivity) from the rotations "
         "between static positions and turns of known angle (docs/gyro.md).",
    options=(
        Option("g_sensitivity", "auto", "Fit gyro_D (auto: when the static positions make it "
               "observable).", "choice", ("auto", "on", "off"), plan_check=True),
        Option("accel", None, "Accelerometer calibration to take the gravity directions from "
               "(default: fit it from RAW, `fit accel --method auto`).", "calibration",
               needs_keys=("accel_K",), metavar="ACCEL_CAL"),
        Option("accel_independent", False, "The accelerometer calibration was fitted on other "
               "data (its uncertainty is propagated); read from its file's input hashes.",
               "bool", cli=False, batch=False),
    ),
    requires=Requires("triad", ("accel", "gyro"), min_static=2),
    screen="after", information=lambda rec, o, noise, like: _fit_gyro(rec, o, noise),
    plan_kinds=("static",), claims=_has_turns, prepare=_prepare_gyro, notes=_notes_gyro,
    with_uses=("accel", "accel_independent"), plan_candidates="calib_cli.design:gyro_candidates",
    with_engine="gyro", report=("calib_cli.report.sections_gyro",),
    # its own diagnosis: the gyro fit's equations (a table-free record has no per-sample
    # truth for the rates, so the bin engine does not apply)
    diagnose=Diagnose("calib_cli.methods.diagnose_gyro:diagnose_gyro", sensors=("gyro",)),
    options_name="GyroOptions", docs="docs/gyro.md"))

register(Method(
    "align", "biases and attitude from two or more static positions", _fit_align,
    help="Accelerometer and gyro biases and the attitude of the first position from two (or "
         "more) static positions related by a known rotation.",
    options=(
        Option("method", "two-position",
               "two-position: any rotation between the positions; classic: the 2- or "
               "4-position baseline (turns of 180 or 90 deg about the vertical body z); "
               "static: static data only, the turn neither recorded nor stated (both "
               "attitudes and the biases from the twelve static equations).", "choice",
               ("two-position", "classic", "static")),
        Option("rotation", "auto", "Rotation between positions: gyros integrated through the "
               "recorded transition, or the plan's turn segments (auto: gyro when recorded).",
               "choice", ("auto", "gyro", "plan"), plan_check=False),
        Option("gyro", "auto", "Earth-rate equations: auto = grade check decides; use = fail "
               "(exit 4) when the gyros cannot resolve the earth rate; ignore = accelerometer "
               "biases and tilt only.", "choice", ("auto", "use", "ignore")),
        Option("gyro_k_ppm", None, "Prior 1-sigma of the gyro scale-factor/misalignment "
               "entries (ppm, urad) that bend the integrated turn [default: 30, or 3000 "
               "without earth rate].", "float", lo=0.0, optional=True),
        Option("turn_sigma_deg", 0.0, "1-sigma error per axis of a plan-stated turn (with "
               "--rotation plan).", "float", lo=0.0),
    ),
    requires=Requires("triad", ("accel", "gyro"), min_static=2,
                      advice=": add a second position after a turn of 60-180 deg"),
    screen="after",  # two-position method: static positions (methods/gross.py)
    information=lambda rec, o, noise, like: _fit_align(rec, o, noise),
    plan_kinds=("align",), result_names=("align-classic",), notes=_notes_align,
    plan_candidates="calib_cli.design:align_candidates",
    with_engine="engine", with_excluded=ENGINE_EXCLUDED,
    diagnose=Diagnose(
        base="calib_cli.methods.diagnose_models:align_base",
        prepare="calib_cli.methods.diagnose_models:align_positions",
        needs=(AtLeast("static", 2, "the alignment needs at least 2 static positions"),),
        fixed_scale="the alignment takes K as the identity (a navigation-grade unit): scale "
                    "and misalignment are not estimated from two positions",
        without=("misalignment", "lever_arm", "proof_mass_offsets", "time_offset"),
        nuisance="attitude correction (rotation of the navigation frame, rad)"),
    report=("calib_cli.report.sections_align_rimu",), options_name="AlignOptions",
    docs="docs/align.md"))

register(Method(
    "rimu", "redundant unit: b, ks, dEl, dAz per sensor", _fit_rimu,
    help="Redundant unit: per sensor bias, scale error, dEl, dAz (docs/rimu.md).",
    requires=Requires("redundant", ("accel",)), screen="after",
    information=lambda rec, o, noise, like: _fit_rimu(rec, o, noise),
    plan_kinds=("rimu",), plan_candidates="calib_cli.design:position_candidates",
    with_engine="engine", with_excluded=ENGINE_EXCLUDED,
    diagnose=Diagnose(
        base="calib_cli.methods.diagnose_models:rimu_base", sensors=("accel",),
        optional_sensors=("gyro",), layout="redundant",
        wrong_layout="--method rimu needs a redundant-unit recording (plan kind \"rimu\" "
                     "with a [rimu] geometry)",
        segments=("static", "rotating"),
        needs=(AtLeast("any", 4, "{count} segments with a known attitude; the RIMU base "
                       "model needs at least 4 positions"),),
        without=("misalignment", "proof_mass_offsets")),
    report=("calib_cli.report.sections_align_rimu",), export="json",
    options_name="RimuOptions", docs="docs/rimu.md"))

register(Method(
    "turntable", "rotating-table calibration with lever arms and proof masses", _fit_turntable,
    help="Accelerometer b, K (lower triangular), gyro d, G, D, lever arms and proof-mass "
         "offsets from rotation cycles on a single-axis table of imprecise angle and rate.",
    options=(
        Option("lever_arm", "estimate", "off: no centripetal terms; known: each cycle's "
               "lever_arm_m from the plan; estimate: two components per cycle (the axial one "
               "is unobservable).", "choice", ("off", "known", "estimate"), plan_check=True),
        Option("proof_mass", "auto", "Proof-mass offsets p_ij (best with tilted cycles, "
               "docs/turntable.md). auto: estimated, entries the record cannot determine "
               "reported with sigma null; off: held at 0.", "choice",
               ("auto", "off", "estimate"), plan_check=True),
        Option("tangential", "on", "dw/dt x r term from the differentiated gyros (off: blocks "
               "in which the table accelerates are left out of the accelerometer "
               "measurements).", "choice", ("on", "off"), plan_check=True),
        Option("block_s", 0.2, "Measurement block length (s): the data are averaged over "
               "blocks.", "float", lo=0.0, hi=5.0, lo_open=True, flag="--block"),
        Option("axis_sigma_mrad", "auto", "How well the table axis stays fixed (per block, "
               "1-sigma, mrad), or auto: estimated from the data "
               "(stats.table_axis_noise_mrad).", "auto_float", lo=0.0, lo_open=True),
        Option("runout_mrad", 0.5, "Prior 1-sigma of the table bearing's twice-per-revolution "
               "rocking of the axis (estimated per cycle); 0: none.", "float", lo=0.0, hi=50.0),
        Option("table_tilt_deg", 0.05, "Prior 1-sigma of the table axis's tilt from the plan's "
               "direction (estimated, one per table axis); 0: take the plan's axis as exact.",
               "float", lo=0.0, hi=10.0),
        Option("grade", "mems", "Prior widths of the parameters for this grade of unit "
               "(docs/turntable.md).", "choice", ("mems", "tactical", "navigation"),
               plan_check=True),
        Option("prior", None, "Override one prior 1-sigma (SI), e.g. --prior lever_arm=0.1; "
               "keys: accel_bias accel_K gyro_bias gyro_K gyro_D lever_arm "
               "proof_mass_offsets.", "key_values", keys="calib_cli.methods.turntable:PRIOR_KEYS",
               multiple=True, metavar="KEY=SIGMA", plan_check=True),
        Option("noise", None, "Per-sample white noise (SI: m/s^2, rad/s) instead of the "
               "estimate from the data; one value for all axes of a sensor.", "key_values",
               keys=("accel", "gyro"), exact_keys=True, optional=True,
               metavar="accel=SIGMA,gyro=SIGMA"),
        Option("table_encoder", "auto", "The table's angle and/or rate channels as "
               "measurements (angle: zero, once-per-revolution error and clock offset "
               "estimated; rate: scale error and offset estimated): auto uses those the log "
               "has that pass the checks.", "choice", ("auto", "off", "angle", "rate", "both"),
               plan_check=True),
    ),
    requires=Requires("triad", ("accel", "gyro"), si=("accel", "gyro"), min_rotating=1),
    # the prediction keeps the turntable engineer's code path (issue 32 rewrites it)
    information="calib_cli.design:turntable_information",
    plan_kinds=("turntable",), plan_candidates="calib_cli.design:turntable_candidates",
    notes=_notes_turntable, with_engine="filter",
    with_fit="calib_cli.methods.turntable.diagnose:fit_with",
    with_lines="calib_cli.methods.turntable.diagnose:effect_lines",
    with_excluded={"misalignment": "the full base model's K and G already hold every "
                                   "misalignment (--base diagonal takes it)",
                   "bias_random_walk": "a wandering bias is not a state of the turntable "
                                       "filter",
                   "bias_instability": "a wandering bias is not a state of the turntable "
                                       "filter"},
    diagnose=Diagnose(
        engine="calib_cli.methods.turntable.diagnose:diagnose_turntable",
        segments=("static", "rotating"), misalignment="lower",
        nuisance="mounting and trajectory of each cycle"),
    report=("calib_cli.report.sections_turntable",), options_base=TurntableOptionsBase,
    options_name="TurntableFitOptions",
    cli_outputs=((Option("plot", None, "Write the sigma history of the lever arms and "
                         "proof-mass offsets (PNG).", "text", metavar="PNG", batch=False),
                  "calib_cli.report.sections_turntable:sigma_history_plot", "sigma history"),),
    docs="docs/turntable.md"))
