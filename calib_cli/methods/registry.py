"""The fit registry: per method a function, a typed options dataclass and its
requirements, checked in one place. ``calib fit METHOD``, the batch's fit steps and
``calib_cli.api.fit`` all go through ``run`` here, so the same recording gives the
same result, exit code and message whichever way it is fitted.

Rules (CONTRACT.md section 5):

- the wrong kind of recording for the method (a redundant unit given to a triad
  fit or the reverse, no data of a sensor the method needs, raw counts where the
  method needs SI) is bad input, exit 3, and the message names the right command;
- too few positions for the method (or degenerate ones, found by the fit itself)
  is exit 4.

Options carry the command line's names and units (``table_tilt_deg``,
``axis_sigma_mrad``, ...): a batch pipeline writes ``table_tilt_deg = 0.1`` where the
command line says ``--table-tilt-deg 0.1``. A bad value is exit 3 naming the option.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Callable

from calib_cli.data import CalibrationResult, Recording
from calib_cli.errors import EstimationError, InputError

# plan kind -> the fit made for it (the hint of a wrong-kind message; batch method "auto")
METHOD_OF_PLAN = {"static": "accel", "align": "align", "rimu": "rimu", "turntable": "turntable"}


@dataclass(frozen=True)
class Requires:
    """What a method needs of a recording. layout: "triad" or "redundant"; sensors:
    the data that must be present; si: sensors that must be in SI units (not counts);
    min_static / min_rotating: fewest static positions / rotating segments."""

    layout: str = "triad"
    sensors: tuple = ("accel",)
    si: tuple = ()
    min_static: int = 0
    min_rotating: int = 0
    advice: str = ""  # appended to a too-few-positions message


def _choice(name: str, value, choices) -> None:
    if value not in choices:
        raise InputError(f"--{name.replace('_', '-')} must be one of {', '.join(choices)}, "
                         f"got {value!r}")


def _number(name: str, value, lo: float | None = None, hi: float | None = None,
            lo_open: bool = False, optional: bool = False) -> None:
    if value is None and optional:
        return
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    if ok and lo is not None:
        ok = value > lo if lo_open else value >= lo
    if ok and hi is not None:
        ok = value <= hi
    if not ok:
        lo_s = "" if lo is None else ("(" if lo_open else "[") + f"{lo:g}"
        rng = f" in {lo_s}, {'inf)' if hi is None else f'{hi:g}]'}" if lo is not None else ""
        raise InputError(f"--{name.replace('_', '-')} must be a number{rng}, got {value!r}")


@dataclass(frozen=True)
class AccelOptions:
    """``calib fit accel``: method auto (vector when every static segment has an
    attitude, else scalar), vector or scalar."""

    method: str = "auto"

    def check(self) -> None:
        _choice("method", self.method, ("auto", "vector", "scalar"))


@dataclass(frozen=True)
class GyroOptions:
    """``calib fit gyro``: g_sensitivity auto/on/off; accel: an accelerometer
    calibration to take the gravity directions from (None: fitted from the same
    recording); accel_independent: it was fitted on other data (its uncertainty
    is then propagated)."""

    g_sensitivity: str = "auto"
    accel: CalibrationResult | None = None
    accel_independent: bool = False

    def check(self) -> None:
        _choice("g_sensitivity", self.g_sensitivity, ("auto", "on", "off"))
        if self.accel is not None and "accel_K" not in self.accel.params:
            raise InputError("--accel: not an accelerometer calibration (no accel_K)")


@dataclass(frozen=True)
class AlignOptions:
    """``calib fit align``: method two-position/classic/static, rotation auto/gyro/plan,
    gyro auto/use/ignore, gyro_k_ppm (prior of the gyro K entries, ppm), turn_sigma_deg."""

    method: str = "two-position"
    rotation: str = "auto"
    gyro: str = "auto"
    gyro_k_ppm: float | None = None
    turn_sigma_deg: float = 0.0

    def check(self) -> None:
        _choice("method", self.method, ("two-position", "classic", "static"))
        _choice("rotation", self.rotation, ("auto", "gyro", "plan"))
        _choice("gyro", self.gyro, ("auto", "use", "ignore"))
        _number("gyro_k_ppm", self.gyro_k_ppm, 0.0, optional=True)
        _number("turn_sigma_deg", self.turn_sigma_deg, 0.0)


@dataclass(frozen=True)
class RimuOptions:
    """``calib fit rimu``: no options."""

    def check(self) -> None:
        pass


@dataclass(frozen=True)
class TurntableFitOptions:
    """``calib fit turntable`` in the command line's names and units; ``to_method()``
    gives the estimator's ``TurntableOptions`` (SI)."""

    lever_arm: str = "estimate"
    proof_mass: str = "auto"
    tangential: str = "on"
    block_s: float = 0.2
    axis_sigma_mrad: float | str = "auto"  # "auto": estimated from the data
    runout_mrad: float = 0.5
    table_tilt_deg: float = 0.05
    grade: str = "mems"
    prior: dict | None = None  # key -> 1-sigma (SI)
    noise: dict | None = None  # {"accel": sigma, "gyro": sigma} per sample (SI)
    table_encoder: str = "auto"

    def check(self) -> None:
        _choice("lever_arm", self.lever_arm, ("off", "known", "estimate"))
        _choice("proof_mass", self.proof_mass, ("auto", "off", "estimate"))
        _choice("tangential", self.tangential, ("on", "off"))
        _choice("grade", self.grade, ("mems", "tactical", "navigation"))
        _choice("table_encoder", self.table_encoder, ("auto", "off", "angle", "rate", "both"))
        if not (isinstance(self.block_s, (int, float)) and math.isfinite(self.block_s)
                and 0 < self.block_s <= 5):
            raise InputError(f"--block must be in (0, 5] s, got {self.block_s}")
        if self.axis_sigma_mrad != "auto" and not (
                isinstance(self.axis_sigma_mrad, (int, float))
                and math.isfinite(self.axis_sigma_mrad) and self.axis_sigma_mrad > 0):
            raise InputError(f"--axis-sigma-mrad must be auto or > 0, got {self.axis_sigma_mrad}")
        if not (isinstance(self.runout_mrad, (int, float)) and math.isfinite(self.runout_mrad)
                and 0 <= self.runout_mrad <= 50):
            raise InputError(f"--runout-mrad must be in [0, 50], got {self.runout_mrad}")
        if not (isinstance(self.table_tilt_deg, (int, float))
                and math.isfinite(self.table_tilt_deg) and 0 <= self.table_tilt_deg <= 10):
            raise InputError(f"--table-tilt-deg must be in [0, 10], got {self.table_tilt_deg}")
        from calib_cli.methods.turntable import PRIOR_KEYS

        for k, v in (self.prior or {}).items():
            if k not in PRIOR_KEYS:
                raise InputError(f"--prior: unknown key {k!r}; expected one of "
                                 f"{', '.join(PRIOR_KEYS)}")
            _number(f"prior {k}", v, 0.0, lo_open=True)
        if self.noise is not None:
            if set(self.noise) != {"accel", "gyro"}:
                raise InputError("--noise needs accel=SIGMA,gyro=SIGMA")
            for k, v in self.noise.items():
                _number(f"noise {k}", v, 0.0, lo_open=True)

    def to_method(self):
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


def _fit_accel(rec, o: AccelOptions):
    from calib_cli.methods.accel_lsq import fit_accel

    return fit_accel(rec, o.method)


def _fit_gyro(rec, o: GyroOptions):
    from calib_cli.methods.gyro import fit_gyro

    return fit_gyro(rec, o.accel, o.g_sensitivity, accel_independent=o.accel_independent)


def _fit_align(rec, o: AlignOptions):
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
                     turn_sigma=float(np.radians(o.turn_sigma_deg)))


def _fit_rimu(rec, o: RimuOptions):
    from calib_cli.methods.rimu import fit_rimu

    return fit_rimu(rec)


def _fit_turntable(rec, o: TurntableFitOptions, progress=None):
    from calib_cli.methods.turntable import fit_turntable

    return fit_turntable(rec, o.to_method(), progress=progress)


@dataclass(frozen=True)
class FitMethod:
    """One fit: ``function(rec, options) -> CalibrationResult``, its options type,
    its requirements, and whether the gross-error screen refits it (rimu, gyro, align)."""

    name: str
    function: Callable
    options: type
    requires: Requires
    screened: bool = False
    summary: str = ""
    aliases: dict = field(default_factory=dict)  # batch/CLI name -> options field

    def option_names(self) -> tuple:
        return tuple(f.name for f in dataclasses.fields(self.options)
                     if f.name not in ("accel", "accel_independent"))


FITS: dict[str, FitMethod] = {}


def register(method: FitMethod) -> None:
    FITS[method.name] = method


register(FitMethod("accel", _fit_accel, AccelOptions,
                   Requires("triad", ("accel",), min_static=1),
                   summary="static multi-position accelerometer fit"))
register(FitMethod("gyro", _fit_gyro, GyroOptions,
                   Requires("triad", ("accel", "gyro"), min_static=2), screened=True,
                   summary="gyro bias, K (and D) from rotations between static positions"))
register(FitMethod("align", _fit_align, AlignOptions,
                   Requires("triad", ("accel", "gyro"), min_static=2,
                            advice=": add a second position after a turn of 60-180 deg"),
                   screened=True,  # two-position method: static positions (methods/gross.py)
                   summary="biases and attitude from two or more static positions"))
register(FitMethod("rimu", _fit_rimu, RimuOptions,
                   Requires("redundant", ("accel",)), screened=True,
                   summary="redundant unit: b, ks, dEl, dAz per sensor"))
register(FitMethod("turntable", _fit_turntable, TurntableFitOptions,
                   Requires("triad", ("accel", "gyro"), si=("accel", "gyro"), min_rotating=1),
                   summary="rotating-table calibration with lever arms and proof masses"))


def get(method: str) -> FitMethod:
    if method not in FITS:
        raise InputError(f"unknown fit method {method!r}; known: {', '.join(sorted(FITS))}")
    return FITS[method]


def options_from(method: str, mapping: dict | None = None, /, **kw):
    """The method's options from a mapping of the command line's names (a batch
    step's table); an unknown name or a bad value is an InputError naming it."""
    m = get(method)
    given = {**(mapping or {}), **kw}
    names = {f.name for f in dataclasses.fields(m.options)}
    unknown = sorted(set(given) - names)
    if unknown:
        known = ", ".join(m.option_names()) or "none"
        raise InputError(f"fit {method} takes no option {unknown[0]!r} (known: {known})")
    opts = m.options(**given)
    opts.check()
    return opts


def check_recording(method: str, rec: Recording, path: str | None = None) -> None:
    """The method's requirements on a recording: exit 3 for the wrong kind of
    recording (naming the right command), exit 4 for too few positions."""
    m = get(method)
    req = m.requires
    if req.layout == "triad" and rec.layout.redundant:
        raise InputError(f"this is a redundant-unit recording: use `calib fit rimu`, not "
                         f"`calib fit {method}`", path)
    if req.layout == "redundant" and not rec.layout.redundant:
        right = METHOD_OF_PLAN.get(rec.plan_kind, "accel")
        raise InputError("not a redundant-unit recording (plan kind \"rimu\" with a [rimu] "
                         f"geometry): use `calib fit {right}`", path)
    for s in req.sensors:
        if getattr(rec, s) is None:
            raise InputError(f"`calib fit {method}` needs {s} data; the recording has none"
                             + ("" if s == "gyro" else ""), path)
    for s in req.si:
        if rec.in_counts(s):
            raise InputError(f"`calib fit {method}` needs {s} data in SI units, the recording "
                             "is in raw counts (import with a scale)", path)
    n_static = len(rec.static_segments())
    if n_static < req.min_static:
        from calib_cli.methods.static_detect import too_few_hint

        right = METHOD_OF_PLAN.get(rec.plan_kind)
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


def run(method: str, rec: Recording, options=None, path: str | None = None,
        progress=None) -> CalibrationResult:
    """Check the recording, fit, screen for gross errors, refuse an impossible
    result (exit 4). ``options``: the method's options dataclass, a mapping of
    its names, or None for the defaults. ``path`` names the recording in errors.
    ``progress(done, total)``: optional, passed to fits that report progress."""
    m = get(method)
    if options is None or isinstance(options, dict):
        options = options_from(method, options)
    elif not isinstance(options, m.options):
        raise TypeError(f"fit {method}: options must be {m.options.__name__}")
    else:
        options.check()
    check_recording(method, rec, path)
    try:
        import inspect

        kw = ({"progress": progress} if progress is not None
              and "progress" in inspect.signature(m.function).parameters else {})
        res = m.function(rec, options, **kw)
        from calib_cli.methods.gross import check_result, screen_fit

        if m.screened:
            screen_fit(res, rec, lambda r: m.function(r, options))
        check_result(res, rec)
    except (InputError, EstimationError) as exc:
        exc.path = exc.path or path
        raise
    return res
