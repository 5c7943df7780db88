"""calib as a Python library: simulate or read a recording, fit, apply, write.

    from calib_cli import api

    plan = api.load_plan("sample_data/twelve_position.toml")
    rec = api.simulate(plan, seed=1)                 # or api.read_raw("raw.h5")
    cal = api.fit("accel", rec)                      # same checks and result as `calib fit accel`
    corrected = api.apply(cal, rec)                  # in memory; api.apply_file for files
    api.write_calibration("cal.h5", cal, ["raw.h5"])

Stability: the names in ``__all__`` are the supported interface. Within a minor
version (0.x.*) they keep their signatures and meaning; a change is listed in the
changelog of the release that makes it. Everything else in the package (module
paths, private helpers, the options' internal SI forms) may change without notice.
Errors are ``CalibError`` subclasses with the contract's ``exit_code`` (3 bad input,
4 cannot be determined); nothing here prints. docs/api.md has the details.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from calib_cli.data import CalibrationResult, Recording, Segment
from calib_cli.errors import CalibError, EstimationError, FaultDetected, InputError, OutputError
from calib_cli.io.apply_file import apply_file
from calib_cli.io.h5 import read_calibration, read_raw, write_calibration, write_raw
from calib_cli.io.plan import load_plan, parse_plan
from calib_cli.io.truth import load_truth
from calib_cli.methods import registry
from calib_cli.methods.registry import (
    FITS,
    AccelOptions,
    AlignOptions,
    GyroOptions,
    RimuOptions,
    ThermalOptions,
    TurntableFitOptions,
    check_recording,
    options_from,
)
from calib_cli.sim.simulate import simulate

__all__ = [
    "FITS", "AccelOptions", "AlignOptions", "GyroOptions", "RimuOptions", "ThermalOptions",
    "TurntableFitOptions",
    "CalibrationResult", "Recording", "Segment",
    "CalibError", "InputError", "EstimationError", "FaultDetected", "OutputError",
    "apply", "apply_file", "check_recording", "fit", "load_plan", "load_truth", "options_from",
    "parse_plan", "read_calibration", "read_raw", "simulate", "write_calibration", "write_raw",
]


def fit(method: str, rec: Recording, options=None, *, with_=None, base: str = "full",
        noise_floor: str = "auto", **option_values) -> CalibrationResult:
    """Fit METHOD (any name of ``FITS``: "accel", "gyro", "align", "rimu", "turntable",
    "thermal", ...) to a recording.

    ``options``: the method's options dataclass (``AccelOptions(...)``, ...) or None;
    or give the command line's option names as keywords (``table_tilt_deg=0.1``). A
    calibration option (gyro's ``accel``, thermal's ``base``) is a CalibrationResult or
    a calibration file's path. ``with_``: catalogue effects as ``calib fit --with`` takes
    them ("lever_arm,accel.temperature_drift" or a list of names), with ``base`` and
    ``noise_floor`` as ``--base`` and ``--noise-floor``. The same requirement checks,
    gross-error screen and result as ``calib fit``."""
    if option_values:
        if options is not None:
            raise TypeError("give options or keyword option values, not both")
        from calib_cli.io.fit_inputs import read_file_options

        options = options_from(method, read_file_options(method, option_values)[0])
    req = None
    if with_:
        text = with_ if isinstance(with_, str) else ",".join(with_)
        try:
            req = registry.parse_with(method, text, base, noise_floor)
        except ValueError as exc:
            raise InputError(f"--with: {exc}") from None
    return registry.run(method, rec, options, with_=req)


def apply(cal: CalibrationResult, rec: Recording) -> Recording:
    """The recording corrected by a calibration, in memory (``calib apply`` without
    files: f = K^-1 (A - b), w = G^-1 (W - d - D f); a redundant unit's corrected
    single-axis outputs). Units must match the calibration's raw units (exit 3)."""
    from calib_cli.methods import apply as ap
    from calib_cli.methods.rimu import apply_rimu

    ap.check_units(cal, rec.units, "<recording>")
    chans = ap.corrected_channels(cal)
    if cal.layout.redundant:
        res = apply_rimu(cal, rec.accel, rec.gyro)
        f, w = res["accel"], res["gyro"]
    else:
        temp = None
        if ap.is_thermal(cal):
            if rec.temp is None:
                raise InputError("the calibration has temperature terms but the recording has "
                                 "no temperature")
            ap.check_temperature(cal, rec.temp, "<recording>")
            temp = ap.effective_temperature(cal, rec.time, rec.temp)
        f, w = ap.apply_triad(cal, rec.accel, rec.gyro, accel_si=not rec.in_counts("accel"),
                              temp=temp, time=rec.time)
    units = dict(rec.units)
    for s in chans:
        units[s] = "m/s^2" if s == "accel" else "rad/s"
    return replace(rec, accel=np.asarray(f), gyro=None if w is None else np.asarray(w),
                   units=units)
