"""What a calibration method is: one object, registered once in ``methods/registry.py``
(docs/architecture.md, "A new fit method").

A ``Method`` holds everything the ways in need: the plan kinds it serves, its options
(declared once as ``Option``s: the click options of ``calib fit NAME`` and ``calib plan
check``, the keys of a batch step and the keyword arguments of ``calib_cli.api.fit`` are
generated from them), its requirements on a recording, its fit and gross-error screen,
its information at a given noise (what ``plan check`` reports), its ``--with`` and
diagnose engines, its report sections and its export policy.

This module imports nothing heavy on purpose: the command line reads the table at
start-up to build its options. Functions that need numpy or SciPy are named by
"module:function" strings (``resolve``) and imported only when called; a hook named
that way may live in a higher layer (``calib_cli.design``, ``calib_cli.report``), which
imports it itself, so ``methods/`` never imports upwards.
"""

from __future__ import annotations

import dataclasses
import importlib
import math
from dataclasses import dataclass, field
from typing import Any, Callable

from calib_cli.errors import InputError

# option kinds: what the value is, how the command line parses it, how it is checked
KINDS = ("choice", "float", "int", "auto_float", "key_values", "calibration", "text", "bool")


def resolve(target):
    """A callable, or the object a "module:attribute" string names (imported now)."""
    if target is None or callable(target):
        return target
    mod, _, attr = str(target).partition(":")
    return getattr(importlib.import_module(mod), attr)


@dataclass(frozen=True)
class FileInput:
    """A calibration given to a fit as a file (``calib fit gyro --accel CAL``, a batch
    step's ``accel = "CAL"``): the calibration, its path, and whether it was made from
    the very recording being fitted (its input hashes name the recording's SHA-256;
    None where unknown, e.g. a CalibrationResult passed to the API)."""

    value: Any
    path: str | None = None
    from_this_recording: bool | None = None


def _flag(name: str) -> str:
    return "--" + name.replace("_", "-")


@dataclass(frozen=True)
class Option:
    """One option of a method, in the command line's names and units.

    name: the batch key and API keyword (``table_tilt_deg``); ``flag`` the command
    line's flag where it is not ``--`` + name with dashes. kind: one of KINDS.
    choice: ``choices``. float/int: [lo, hi] (``lo_open``: lo excluded), ``optional``:
    None allowed. auto_float: "auto" or a number > lo. key_values: {KEY: number > 0}
    with ``keys`` allowed (a tuple or a "module:NAME" string), ``exact_keys``: all of
    them required; on the command line repeated KEY=V items (``multiple``) or one
    comma-separated list. calibration: a calibration file (API: a CalibrationResult
    or a path) holding at least one of ``needs_keys``. ``cli``/``batch``: offered
    there; ``plan_check``: also an option of ``calib plan check`` (it changes the
    prediction).
    """

    name: str
    default: Any = None
    help: str = ""
    kind: str = "float"
    choices: tuple = ()
    lo: float | None = None
    hi: float | None = None
    lo_open: bool = False
    optional: bool = False
    flag: str | None = None
    metavar: str | None = None
    keys: Any = ()
    exact_keys: bool = False
    multiple: bool = False
    needs_keys: tuple = ()
    cli: bool = True
    batch: bool = True
    plan_check: bool = False

    def __post_init__(self):
        if self.kind not in KINDS:
            raise ValueError(f"option {self.name}: unknown kind {self.kind!r}")

    @property
    def cli_flag(self) -> str:
        return self.flag or _flag(self.name)

    def _range(self) -> str:
        if self.lo is None and self.hi is None:
            return ""
        lo = "(-inf" if self.lo is None else ("(" if self.lo_open else "[") + f"{self.lo:g}"
        hi = "inf)" if self.hi is None else f"{self.hi:g}]"
        return f" in {lo}, {hi}"

    def _number_ok(self, v) -> bool:
        ok = isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)
        if ok and self.kind == "int":
            ok = float(v).is_integer()
        if ok and self.lo is not None:
            ok = v > self.lo if self.lo_open else v >= self.lo
        if ok and self.hi is not None:
            ok = v <= self.hi
        return ok

    def check(self, value):
        """The value, checked (and normalised: ints of int options, FileInput of
        calibrations); a bad one is an InputError naming the option (exit 3)."""
        f = self.cli_flag
        if self.kind == "choice":
            if value not in self.choices:
                raise InputError(f"{f} must be one of {', '.join(map(str, self.choices))}, "
                                 f"got {value!r}")
            return value
        if self.kind in ("float", "int"):
            if value is None and self.optional:
                return None
            if not self._number_ok(value):
                what = "an integer" if self.kind == "int" else "a number"
                raise InputError(f"{f} must be {what}{self._range()}, got {value!r}")
            return int(value) if self.kind == "int" else value
        if self.kind == "auto_float":
            if value == "auto" or (value is None and self.optional):
                return value
            if not self._number_ok(value):
                raise InputError(f"{f} must be auto or a number{self._range()}, got {value!r}")
            return value
        if self.kind == "key_values":
            if value is None or value == {}:
                if self.exact_keys and not self.optional:
                    raise InputError(f"{f} needs {','.join(f'{k}=SIGMA' for k in self.key_names())}")
                return None
            if not isinstance(value, dict):
                raise InputError(f"{f} must be a table of KEY = number, got {value!r}")
            keys = self.key_names()
            if self.exact_keys and set(value) != set(keys):
                raise InputError(f"{f} needs {','.join(f'{k}=SIGMA' for k in keys)}")
            for k, v in value.items():
                if keys and k not in keys:
                    raise InputError(f"{f}: unknown key {k!r}; expected one of {', '.join(keys)}")
                if not (isinstance(v, (int, float)) and not isinstance(v, bool)
                        and math.isfinite(v) and v > 0):
                    raise InputError(f"{f} {k} must be a number in (0, inf), got {v!r}")
            return dict(value)
        if self.kind == "calibration":
            if value is None:
                return None
            fi = value if isinstance(value, FileInput) else FileInput(value)
            cal = fi.value
            if isinstance(cal, str):
                raise InputError(f"{f}: a calibration file must be read first "
                                 "(calib_cli.io.fit_inputs)")
            params = getattr(cal, "params", None)
            if params is None:
                raise InputError(f"{f}: not a calibration", fi.path)
            if self.needs_keys and not any(k in params for k in self.needs_keys):
                raise InputError(f"{f}: not a calibration holding "
                                 f"{' or '.join(self.needs_keys)}", fi.path)
            return fi
        if self.kind == "bool":
            if not isinstance(value, bool):
                raise InputError(f"{f} must be true or false, got {value!r}")
            return value
        if self.kind == "text":
            if value is not None and not isinstance(value, str):
                raise InputError(f"{f} must be text, got {value!r}")
            return value
        raise AssertionError(self.kind)

    def key_names(self) -> tuple:
        keys = self.keys
        if isinstance(keys, str):
            keys = resolve(keys)
        return tuple(keys)


@dataclass(frozen=True)
class Requires:
    """What a method needs of a recording. layout: "triad" or "redundant"; sensors:
    the data that must be present; si: sensors that must be in SI units (not counts);
    channels: further columns (``temp``, ``table_angle``) with the words naming them;
    min_static / min_rotating: fewest static positions / rotating segments."""

    layout: str = "triad"
    sensors: tuple = ("accel",)
    si: tuple = ()
    channels: tuple = ()  # ((attribute, words), ...)
    min_static: int = 0
    min_rotating: int = 0
    advice: str = ""  # appended to a too-few-positions message


@dataclass(frozen=True)
class AtLeast:
    """One requirement of a diagnosis on the segments it uses: at least ``n`` of ``kind``
    ("static", "rotating" or "any"), else EstimationError (exit 4) with ``message``
    formatted with ``count`` (how many there are). attitudes: "known" (the positions
    have attitudes), "unknown" (some have none: the scalar problem) or "any"."""

    kind: str
    n: int
    message: str
    attitudes: str = "any"


@dataclass(frozen=True)
class Diagnose:
    """How ``calib diagnose --method NAME`` sees a method, and ``calib fit NAME --with``
    where the method's ``with_engine`` is "engine" (docs/architecture.md, "A new fit
    method").

    engine: "engine" -- the catalogue refit engine of methods/diagnose.py on 0.5 s bin
    means of the recording (methods/diagnose_problem.py), from the base model below; or
    a "module:function(rec, base=, alpha=) -> diagnosis" of the method's own (the gyro
    fit's equations, methods/diagnose_gyro.py).
    base: "module:function(pb, base) -> (effects, names, mount)": the base model, the
    fit's own model in catalogue effects (``base``: "full" or "diagonal" scale factors),
    its names for the JSON, and whether the unit's mount angles are a nuisance.
    sensors: the data the base model fits, each required; optional_sensors: also fitted
    where the recording has them. layout: "triad" or "redundant"; wrong_layout: the
    message for a recording of the other (default: generated from the table).
    segments: the segment kinds the engine uses ("static"; "rotating": those with a
    table axis), each with a known attitude and >= 3 samples; unknown_attitudes: static
    positions without an attitude are taken, each gravity direction a nuisance (the
    scalar problem). needs: ``AtLeast`` requirements on the segments used.
    prepare: "module:function(rec) -> (rec, {Problem attribute: value})", the recording
    before binning (align: each position's attitude from the two-position alignment).
    misalignment: the structure of the accelerometer misalignment candidate ("lower"
    where the accelerometers fix the instrument frame). fixed_scale: why the base model
    has no scale factors ("" where it has). without: catalogue effects the method never
    takes (left out of ``calib fit NAME --list-effects`` without a record). nuisance:
    what the base model's nuisance angles are, in a calibration's ``stats.nuisance``.
    """

    engine: str = "engine"
    base: Any = None
    sensors: tuple = ("accel", "gyro")
    optional_sensors: tuple = ()
    layout: str = "triad"
    wrong_layout: str = ""
    segments: tuple = ("static",)
    unknown_attitudes: bool = False
    needs: tuple = ()
    prepare: Any = None
    misalignment: str = "full"
    fixed_scale: str = ""
    without: tuple = ()
    nuisance: str = "gravity-direction nuisance of each position (rad)"

    def __post_init__(self):
        if self.engine == "engine" and self.base is None:
            raise ValueError("a diagnosis on the refit engine needs its base model (base=)")
        if self.layout not in ("triad", "redundant"):
            raise ValueError(f"layout: triad or redundant, got {self.layout!r}")

    @property
    def own(self) -> bool:
        """The method's own diagnosis (not the refit engine's bins)."""
        return self.engine != "engine"

    @property
    def with_sensors(self) -> tuple:
        """The sensors an unqualified ``--with`` effect goes to."""
        return tuple(self.sensors) + tuple(self.optional_sensors)


def table() -> dict:
    """The method table {name: Method}. It sits above the engines that read it
    (methods/registry.py imports their modules to run them), so they reach it by a
    "module:attribute" string rather than an import (tests/test_import_cycles.py)."""
    return resolve("calib_cli.methods.registry:FITS")


def method_named(name: str) -> "Method":
    """The registered method of that name (InputError naming the known ones)."""
    return resolve("calib_cli.methods.registry:get")(name)


class OptionsBase:
    """Base of the options dataclasses generated from a method's ``Option``s: the
    values in the command line's names and units; ``check()`` raises InputError
    naming the option."""

    _options: tuple = ()
    _cross_check: Callable | None = None

    def check(self) -> None:
        for o in self._options:
            object.__setattr__(self, o.name, o.check(getattr(self, o.name)))
        if self._cross_check is not None:
            type(self)._cross_check(self)


def options_class(name: str, options: tuple, cross_check=None, base: type = OptionsBase,
                  doc: str = "") -> type:
    """A frozen dataclass with one field per option (its default), ``check()``."""
    fields = [(o.name, Any, field(default=o.default)) for o in options]
    cls = dataclasses.make_dataclass(name, fields, bases=(base,), frozen=True,
                                     namespace={"_options": tuple(options),
                                                "_cross_check": staticmethod(cross_check)
                                                if cross_check else None,
                                                "__doc__": doc or f"Options of a fit ({name})."})
    cls.__module__ = "calib_cli.methods.registry"
    return cls


@dataclass(frozen=True)
class Method:
    """One calibration method (module docstring).

    fit: ``fit(rec, options, progress=None) -> CalibrationResult`` (callable or
    "module:function"). screen: "inside" (the fit screens itself), "after" (the
    gross-error screen of methods/gross.py refits with one segment left out) or
    None. information: ``information(rec, options, noise) -> CalibrationResult``,
    the fit's covariance on a noise-free record at per-sample noise ``noise``
    ({"accel", "gyro"}: the Fisher information of its own rows); default: the fit
    called with ``noise=`` and ``strict=False``. plan_kinds: plan kinds whose
    records go to this method by default; claims: a "module:function" predicate
    on a Plan for plans of another method's kind this method takes (a static plan
    with turns goes to gyro). with_engine: "engine" (the diagnose engine, methods/
    fit_with.py, on the ``diagnose`` description's base model), "gyro", "own"
    (``with_fit(rec, options, effects)``, the effects ``with_effects`` names), "filter"
    (``with_fit`` on catalogue effects parsed as the engine's, less ``with_excluded``) or
    None; diagnose: its ``Diagnose``
    description (None: ``calib diagnose`` does not take it). report: modules of report
    sections.
    export: "firmware" (affine triad: every format) or "json" (no firmware tables).
    notes(res) -> lines the command line prints after the fit. prepare(options, rec)
    -> options: fills what the options imply (the gyro fit's accel independence).
    """

    name: str
    summary: str
    fit: Any
    options: tuple = ()
    requires: Requires = Requires()
    help: str = ""
    screen: str | None = None
    information: Any = None
    plan_kinds: tuple = ()
    claims: Any = None
    variants: dict = field(default_factory=dict)  # plan check --method NAME -> options
    variant_of: Any = None  # plan -> the variant its records get (auto)
    # plan check's candidate additions: "module:function(plan, name) -> [(words, segments)]"
    plan_candidates: Any = None
    result_names: tuple = ()  # further ``method`` values of its calibrations ("vector")
    with_engine: str | None = None
    with_fit: Any = None
    with_effects: tuple = ()  # with_engine "own": the effects its with_fit takes
    with_excluded: dict = field(default_factory=dict)  # effect -> why this method has none
    with_uses: tuple = ()  # options the --with fit uses (the others apply to the plain fit)
    # with_engine "filter": "module:function(rec or None, base) -> [line]" (--list-effects)
    with_lines: Any = None
    diagnose: Diagnose | None = None
    report: tuple = ()
    export: str = "firmware"
    notes: Any = None
    prepare: Any = None
    cross_check: Any = None
    options_base: type = OptionsBase
    options_name: str = ""
    # files the command line may write besides the calibration: (Option of kind "text"
    # naming the file, "module:writer(res, path)", words for the status line)
    cli_outputs: tuple = ()
    docs: str = ""

    def __post_init__(self):
        if self.with_engine == "engine" and (self.diagnose is None or self.diagnose.own):
            raise ValueError(f"method {self.name}: with_engine \"engine\" fits the diagnose "
                             "description's base model (diagnose=Diagnose(base=...))")
        cls = options_class(self.options_name or f"{self.name.capitalize()}Options",
                            tuple(self.options), self.cross_check, self.options_base,
                            f"``calib fit {self.name}``'s options (command line names and units).")
        object.__setattr__(self, "options_type", cls)

    def option(self, name: str) -> Option:
        return next(o for o in self.options if o.name == name)

    def option_names(self, where: str = "batch") -> tuple:
        return tuple(o.name for o in self.options if getattr(o, where))

    def file_option_names(self) -> tuple:
        return tuple(o.name for o in self.options if o.kind == "calibration")
