"""Tolerance files: the CI gate of `calib batch --tolerances TOL.toml` and the verdict of
`calib report CAL --tolerances TOL.toml`. One evaluator (``evaluate``) serves both, so the
same files give the same verdict; a rule it cannot evaluate (``max_change_sigma``
without the unit's earlier calibrations, or without a serial) is named, and the verdict
is then "incomplete", never "pass".

    [param.accel_bias]
    min_mg = -20              # allowed range, every element (unit suffix or SI)
    max_mg = 20
    max_change_sigma = 5      # |new - previous| / sqrt(s_new^2 + s_prev^2)

    [param.accel_K]
    min = [[0.99, -0.01, -0.01], [-0.01, 0.99, -0.01], [-0.01, -0.01, 0.99]]
    max = [[1.01,  0.01,  0.01], [ 0.01, 1.01,  0.01], [ 0.01,  0.01, 1.01]]

min/max are a number (every element) or an array of the parameter's shape
(nan = no bound there). ``max_change_sigma`` compares with the unit's
previous calibration (known by its serial, see history.py) that reports the
parameter; entries fixed by convention (sigma 0) or unobservable (sigma
NaN) are not compared. A parameter the calibration does not report is not
checked (and is named as not reported). All values SI unless a suffix (_mg, _ug, _deg,
_dps, _dph, _ppm, _mm, ...) says otherwise.

Typed and finite: a bound is a number or an array of numbers (not a bool, not a
string); a bound that is not finite (inf, -inf, 1e400) is exit 3 naming the file and the
key -- an infinite bound would pass everything or nothing -- except nan inside an array,
which marks an entry without a bound; ``max_change_sigma`` is a finite number > 0.
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from calib_cli.errors import InputError
from calib_cli.io.history import CalEntry, element_names, previous
from calib_cli.units import split_suffix


@dataclass(frozen=True)
class ParamTolerance:
    key: str
    lo: np.ndarray | None
    hi: np.ndarray | None
    max_change_sigma: float | None
    # the units the limits were written in (suffix, factor to SI), for the failure lines
    lo_unit: tuple[str, float] | None = None
    hi_unit: tuple[str, float] | None = None


UNIT_NAMES = {"_deg": "deg", "_dps": "deg/s", "_dph": "deg/h", "_dpsqrth": "deg/sqrt(h)",
              "_mrad": "mrad", "_urad": "urad", "_mg": "mg", "_ug": "ug", "_ppm": "ppm",
              "_mm": "mm", "_cm": "cm", "_ms": "ms"}


def load_tolerances(path) -> dict[str, ParamTolerance]:
    p = str(path)
    try:
        raw = tomllib.loads(Path(p).read_text(encoding="utf-8"))
    except FileNotFoundError:
        raise InputError("no such file", p) from None
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"not valid TOML: {exc}", p) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"cannot read: {exc}", p) from None
    except RecursionError:
        raise InputError("not valid TOML: nested too deeply", p) from None
    from calib_cli.io.schema import closest, known_param_keys, param_shape, strict_keys

    strict_keys(raw, {"param"}, p)
    known = known_param_keys()
    table = raw.get("param")
    if not isinstance(table, dict) or not table:
        raise InputError("no [param.NAME] tables", p)
    out = {}
    for key, spec in table.items():
        if key not in known:  # a typo would silently disable the gate
            raise InputError(f"[param.{key}]: no method reports a parameter {key!r}; did you "
                             f"mean {closest(key, known)}?", p)
        if not isinstance(spec, dict):
            raise InputError(f"param.{key} must be a table", p)
        lo = hi = change = None
        units = {}
        for k, v in spec.items():
            base, factor = split_suffix(k)
            units[base] = (UNIT_NAMES.get(k[len(base):], ""), factor)
            where = f"param.{key}.{k}"
            if base in ("min", "max"):
                arr = _bound_value(v, factor, where, p)
                if base == "min":
                    lo = arr
                else:
                    hi = arr
            elif k == "max_change_sigma":
                if (isinstance(v, bool) or not isinstance(v, (int, float))
                        or not math.isfinite(v) or v <= 0):
                    raise InputError(f"{where} must be a finite number > 0, got {v!r}", p)
                change = float(v)
            else:
                raise InputError(f"{where}: unknown key (min, max, max_change_sigma, with an "
                                 "optional unit suffix on min/max)", p)
        shape = param_shape(key)
        for b, word in ((lo, "min"), (hi, "max")):
            if b is not None and shape is not None and b.ndim and b.shape != shape:
                raise InputError(f"param.{key}.{word} has shape {b.shape}, the parameter "
                                 f"{shape}", p)
        if lo is not None and hi is not None:
            try:
                inverted = np.any(np.asarray(lo > hi))
            except ValueError:
                raise InputError(f"param.{key}: min and max have different shapes", p) from None
            if inverted:
                raise InputError(f"param.{key}: min is above max", p)
        out[key] = ParamTolerance(key, lo, hi, change, units.get("min"), units.get("max"))
    return out


def _bound_value(v, factor: float, where: str, path: str) -> np.ndarray:
    """A min/max value in SI: a finite number, or an array of numbers (nan: no bound
    at that entry); anything else is exit 3 naming the key."""
    def bad(why):
        return InputError(f"{where} must be {why}, got {v!r}", path)

    if isinstance(v, bool) or isinstance(v, str):
        raise bad("a number or an array of numbers")
    if isinstance(v, (int, float)):
        if not math.isfinite(v):
            raise bad("a finite number (an infinite bound passes everything or nothing)")
        return np.asarray(float(v) * factor)
    flat = []

    def walk(x):
        if isinstance(x, list):
            for y in x:
                walk(y)
        elif isinstance(x, (int, float)) and not isinstance(x, bool):
            flat.append(float(x))
        else:
            raise bad("a number or an array of numbers")

    walk(v)
    try:
        arr = np.asarray(v, dtype=float)
    except (TypeError, ValueError):
        raise bad("a rectangular array of numbers") from None
    if arr.dtype == object or arr.size != len(flat):
        raise bad("a rectangular array of numbers")
    if np.isinf(arr).any():
        raise bad("finite numbers (nan, not inf, marks an entry without a bound)")
    return arr * factor


def _bound(arr, shape, where):
    try:
        return np.broadcast_to(arr, shape)
    except ValueError:
        raise InputError(f"{where}: bound of shape {np.shape(arr)} does not fit the parameter's "
                         f"shape {shape}") from None


def evaluate(entry: CalEntry, history: list[CalEntry] | None, tols: dict) -> dict:
    """The verdict of one calibration against the tolerances, for the batch and the
    report alike: {"status": "pass" | "fail" | "incomplete", "failures": [lines],
    "not_evaluated": [lines naming each rule that could not be evaluated and why],
    "not_reported": [keys of the file this calibration does not report], "notes":
    [lines], "previous": {key: file compared with}}. ``history``: the unit's
    calibrations (any units; those of other serials are ignored), or None where none is
    at hand (then ``max_change_sigma`` cannot be evaluated)."""
    fails, prev_used, not_eval, notes = [], {}, [], []
    not_reported = [k for k in tols if k not in entry.params]
    for key, tol in tols.items():
        if key not in entry.params:
            continue
        v = np.asarray(entry.params[key], dtype=float)
        s = np.asarray(entry.sigma.get(key, np.full(v.shape, np.nan)), dtype=float)
        names = element_names(key, v.shape)
        unit = entry.units.get(key, "")
        for bound, op, word, bunit in ((tol.lo, np.less, "below min", tol.lo_unit),
                                       (tol.hi, np.greater, "above max", tol.hi_unit)):
            if bound is None:
                continue
            b = _bound(bound, v.shape, f"param.{key}")
            # a value that is not finite is outside every bound
            bad = (op(v, b) | ~np.isfinite(v)) & np.isfinite(b)
            # in the unit the limit was written in (min_mg: mg), else the parameter's
            shown, f = (bunit if bunit and bunit[0] else (unit, 1.0))
            for i in np.flatnonzero(bad.ravel()):
                fails.append(f"{names[i]} = {v.ravel()[i] / f:.6g} {shown} {word} "
                             f"{b.ravel()[i] / f:.6g} {shown}".replace("  ", " ").strip())
        if tol.max_change_sigma is None:
            continue
        rule = f"param.{key}.max_change_sigma"
        if not entry.serial:
            not_eval.append(f"{rule}: the calibration names no unit serial, so it has no history")
            continue
        if history is None:
            not_eval.append(f"{rule}: needs the unit's earlier calibrations (calib report "
                            "--history DIR, as calib batch has its output directory)")
            continue
        p = previous(history, entry, key)
        if p is None:
            notes.append(f"{rule}: no earlier calibration of {entry.serial} reports {key}: "
                         "nothing to compare")
            continue
        prev_used[key] = p.rel
        pv = np.asarray(p.params[key], dtype=float)
        if pv.shape != v.shape:
            not_eval.append(f"{rule}: {p.rel} has {key} of another shape {pv.shape}")
            continue
        ps = np.asarray(p.sigma.get(key, np.full(v.shape, np.nan)), dtype=float)
        comb = np.sqrt(s**2 + ps**2)
        ok = np.isfinite(comb) & (s > 0) & (ps > 0)
        z = np.where(ok, np.abs(v - pv) / np.where(ok, comb, 1.0), 0.0)
        for i in np.flatnonzero((z > tol.max_change_sigma).ravel()):
            fails.append(f"{names[i]} changed by {z.ravel()[i]:.1f} sigma since {p.rel} "
                         f"(limit {tol.max_change_sigma:g})")
    status = "fail" if fails else ("incomplete" if not_eval else "pass")
    return {"status": status, "failures": fails, "not_evaluated": not_eval,
            "not_reported": not_reported, "notes": notes, "previous": prev_used}


def check(entry: CalEntry, entries: list[CalEntry], tols: dict) -> dict:
    """``evaluate`` with the history ``entries`` (the batch's output directory)."""
    return evaluate(entry, entries, tols)
