"""The batch step registry.

A step turns named artifacts of one input's chain into one new artifact:

    source (the CSV given) -> import -> raw -> fit -> calibration -> apply -> corrected
                                                  \\-> export -> export (JSON)

A step is a StepDef: the artifacts it needs, the artifact it makes, the file
suffix of its output, the options it accepts, and a function run(StepRun)
that writes ``run.out``. Functions are named by "module:attribute" strings
and imported only when a step runs, so registering a method costs nothing
and never creates import cycles. Every method of the method table
(methods/registry.py) is a fit step by itself, its keys the method's options; a fit
from outside the table registers with one line:

    register_fit("mine", "my_package.fits:fit_mine", options=("accel",))

where the function is ``fit(rec: Recording, **options) -> CalibrationResult``.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass, field
from typing import Callable

from calib_cli.errors import InputError
from calib_cli.methods.registry import FITS as METHOD_TABLE


@dataclass
class StepRun:
    """What a step function gets: its input artifacts (paths), the path to
    write (a temporary file, renamed into place on success), its options, the
    chain's original input, and provenance attributes to embed where the
    output is not HDF5 (the runner stamps HDF5 outputs itself)."""

    inputs: dict
    out: str
    options: dict
    source: str
    stamp: dict = field(default_factory=dict)


@dataclass(frozen=True)
class StepDef:
    name: str  # as in the pipeline: "import", "fit", "apply", "export", ...
    needs: tuple  # artifact names consumed, e.g. ("raw",)
    makes: str  # artifact name produced
    suffix: str  # ".h5" or ".json", ...
    target: str | Callable  # "module:function" or a callable taking StepRun
    options: tuple | None = None  # accepted option names (None: any)
    file_options: tuple = ()  # options naming files: their content is hashed
    optional_files: tuple = ()  # those of file_options a step may leave out
    method: str | None = None  # fit method name, for "fit" steps
    applies_to_raw_input: bool = True  # False: skipped when the input already is a raw.h5

    def function(self) -> Callable:
        if callable(self.target):
            return self.target
        mod, _, attr = self.target.partition(":")
        return getattr(importlib.import_module(mod), attr)

    @property
    def label(self) -> str:
        return f"{self.name} {self.method}" if self.method else self.name


STEPS: dict[str, StepDef] = {}
FITS: dict[str, StepDef] = {}


def register_step(name: str, target, *, needs=(), makes: str, suffix: str = ".h5",
                  options=None, file_options=(), applies_to_raw_input: bool = True) -> None:
    """Register a pipeline step ``[[step]] step = NAME``."""
    STEPS[name] = StepDef(name, tuple(needs), makes, suffix, target,
                          None if options is None else tuple(options), tuple(file_options),
                          applies_to_raw_input=applies_to_raw_input)


def register_fit(method: str, target, *, options=(), needs=("raw",), file_options=()) -> None:
    """Register a fit method ``[[step]] step = "fit", method = METHOD``.

    ``target`` is "module:function" with ``function(rec, **options) ->
    CalibrationResult``; extra ``needs`` (e.g. "calibration" for a gyro fit
    that uses an earlier accelerometer calibration) arrive as the keyword
    argument ``<artifact>_path``.
    """
    FITS[method] = StepDef("fit", tuple(needs), "calibration", ".h5", target,
                           tuple(options), tuple(file_options), tuple(file_options),
                           method=method)


def lookup(name: str, method: str | None, where: str, path: str) -> StepDef:
    """The StepDef for a pipeline entry; unknown names are an InputError."""
    if name == "fit":
        if not method:
            raise InputError(f"{where}: a fit step needs method = \"...\" (known: "
                             f"{', '.join(sorted(FITS))})", path)
        if method not in FITS:
            raise InputError(f"{where}: unknown fit method {method!r}; known: "
                             f"{', '.join(sorted(FITS))}", path)
        return FITS[method]
    if name not in STEPS:
        raise InputError(f"{where}: unknown step {name!r}; known: "
                         f"{', '.join(sorted([*STEPS, 'fit']))}", path)
    return STEPS[name]


# the built-in steps (batch/steps.py, imported when a step runs)
register_step("import", "calib_cli.batch.steps:import_step", needs=("source",), makes="raw",
              options=("plan", "window_s", "threshold", "min_static_s"), file_options=("plan",),
              applies_to_raw_input=False)
register_step("apply", "calib_cli.batch.steps:apply_step", needs=("calibration", "raw"),
              makes="corrected")
register_step("export", "calib_cli.batch.steps:export_step", needs=("calibration",),
              makes="export", suffix=".json", options=("covariance",))

# the batch keys of --with (`calib fit METHOD --with E --base B --noise-floor N`)
WITH_KEYS = ("with", "with_base", "with_noise_floor")


def _register_fits() -> None:
    """A fit step per method of the method table (methods/registry.py), its keys the
    method's options, and "auto" (the method of the recording's plan kind)."""
    names = set()
    for name, m in METHOD_TABLE.items():
        register_fit(name, "calib_cli.batch.steps:registry_fit",
                     options=m.option_names() + WITH_KEYS, file_options=m.file_option_names())
        names |= set(m.option_names())
    # any option name is passed on: the chosen fit checks it
    register_fit("auto", "calib_cli.batch.steps:fit_auto",
                 options=tuple(sorted(names)) + WITH_KEYS)


_register_fits()
