"""Export a calibration's correction for firmware and other tools (docs/export.md).

The correction is the contract's (section 2):

    f = K^-1 (A - b)            accelerometers
    w = G^-1 (W - d - D f)      gyroscopes, f the corrected specific force

b, K, d, G, D are not copied blindly from the parameters: they are read off
the calibration's own forward model (``ImuModel.predict``) by probing it with
zero and unit inputs, so whatever effects the fit used (full or triangular
K, a separate misalignment, g-sensitivity) end up in the one affine map that
``calib apply`` inverts. Terms that are not affine in the input are
exported as what they are: nonlinearity and scale asymmetry as their
per-axis coefficients with the formula (A_i = b_i + (K f)_i + k2_i f_i^2 +
a_i |f_i|, inverted by the fixed-point iteration written in the header and
the JSON), temperature drift as its polynomial coefficients with T_ref
(docs/thermal.md). A time offset is no correction of the outputs (listed as
not applied, with the shift to give the timestamps); the noise-model terms of
``stats.noise_model`` are never exported. Anything else the affine map cannot
express is refused rather than dropped silently.
Proof-mass offsets are exported as the size-effect compensation that `calib
apply` makes (accelerometer i brought to the triad's reference point, from the
corrected rates w and their derivative dw/dt: f_i -= (w x (w x p_i) + dw/dt x
p_i)_i); the header gets a function taking w and dw/dt. Lever arms belong to
the table, not to the unit: listed but not applied.

Formats: json, yaml (written here, no dependency), csv (long format, one row
per entry), c-header (K^-1, b, G^-1, d, D as literals with full precision,
%.17g for double, %.9g for float).

Text from the calibration file (serial, method, command line, units,
parameter names) is untrusted: it reaches each format only through that
format's escaper in ``calib_cli.io.escape`` (docs/security.md). The C header
carries it only inside string constants, never in a comment or in code.
"""

from __future__ import annotations

import math

import numpy as np

from calib_cli import __version__
from calib_cli.data import CalibrationResult
from calib_cli.errors import InputError, OutputError
from calib_cli.io import escape
from calib_cli.methods.apply import model_of
from calib_cli.model.kinematics import Kinematics

FORMATS = ("json", "yaml", "c-header", "csv")
def _effects(export: str) -> set:
    """Catalogue effects by how export writes them (``Effect.export``)."""
    from calib_cli.model.effects import CATALOGUE

    return {n for n, c in CATALOGUE.items() if c.export == export}


LINEAR_EFFECTS = _effects("linear")  # bias, scale_misalignment, misalignment, g_sensitivity
THERMAL_EFFECTS = _effects("thermal")  # evaluated first (docs/thermal.md)
NOT_APPLIED = _effects("input")  # input-side terms (lever arm, proof masses), not in the correction
FORMULA = {"accel": "f = K^-1 (A - b)", "gyro": "w = G^-1 (W - d - D f)"}
SIZE_EFFECT_FORMULA = ("f_i -= (w x (w x p_i) + dw/dt x p_i)_i with w = G^-1 (W - d - D f) and "
                       "dw/dt its time derivative, p_i row i of proof_mass_offsets; then "
                       "w = G^-1 (W - d - D f) again with the new f (as calib apply)")
# terms on each channel's own input, exported as coefficients: model name -> key suffix
NONAFFINE = {"accel_nonlinearity": "nonlinearity", "scale_asymmetry": "scale_asymmetry"}
NONAFFINE_ITER = 3  # fixed-point iterations of the inverse (converged for |k2 f| << 1)
NONAFFINE_FORMULA = {
    "accel": ("A_i = b_i + (K f)_i + k2_i f_i^2 + a_i |f_i|; correction: f = K^-1 (A - b), "
              f"then {NONAFFINE_ITER} times f = K^-1 (A - b - k2 f^2 - a |f|) (per axis i)"),
    "gyro": ("W_i = d_i + (G w)_i + (D f)_i + a_i |w_i|; correction: w = G^-1 (W - d - D f), "
             f"then {NONAFFINE_ITER} times w = G^-1 (W - d - D f - a |w|) (per axis i)"),
}
NOT_APPLIED_WHY = {
    "lever_arm": "the table's geometry during calibration, not a property of the unit",
    "proof_mass_offsets": "input-side size effect: needs the rates and their derivative "
                          "(calib apply corrects it; exported as the size-effect function "
                          "where the offsets were determined)",
    "time_offset": "not a correction of the outputs: shift the IMU timestamps by "
                   "-time_offset s (params.time_offset)",
}


def _predict(model, params, sensor, f, w):
    n = len(f)
    kin = Kinematics(np.zeros(n), np.asarray(f, float), np.asarray(w, float), np.zeros((n, 3)))
    return model.predict(params, kin, sensors=(sensor,))[sensor]


def affine_correction(cal: CalibrationResult, path: str = "<calibration>") -> dict:
    """{"accel": {"b", "K", "K_inv"}, "gyro": {"d", "G", "G_inv", "D"}} for the
    sensors the calibration covers, read off its forward model."""
    from calib_cli.methods.registry import method_of_result

    m = method_of_result(cal.method)  # the method's export policy (methods/registry.py)
    if cal.layout.redundant or (m is not None and m.export != "firmware"):
        what = ("a redundant-unit (RIMU) calibration" if cal.layout.redundant
                else f"a {cal.method} calibration")
        raise InputError(f"{what} has no triad K^-1; export it as json, yaml or csv", path)
    names = {d.get("name") for d in cal.model}
    bad = sorted(names - _effects("linear") - _effects("input") - _effects("thermal")
                 - set(NONAFFINE) - {"time_offset"})
    if names & set(NONAFFINE) and names & _effects("thermal"):
        bad.append("nonlinearity or scale asymmetry with temperature_drift")
    if "temperature_drift" in names and "misalignment" in names:
        bad.append("misalignment with temperature_drift")
    if any(d.get("name") == "temperature_drift" and d.get("order") is None for d in cal.model):
        bad.append("temperature_drift of the previous form (scale on the nominal input)")
    if bad:
        raise InputError(f"the calibration's model includes {', '.join(bad)}, which the linear "
                         "correction f = K^-1 (A - b) cannot express; use `calib apply`", path)
    model = model_of(cal)
    params = {k: np.asarray(v, dtype=float) for k, v in cal.params.items()}
    nonaffine = {}  # sensor -> {"k2": ..., "a": ...}: read off, then zeroed for the probes
    for s in ("accel", "gyro"):
        for key, short in ((f"{s}_nonlinearity", "k2"), (f"{s}_scale_asymmetry", "a")):
            if key in params:
                nonaffine.setdefault(s, {})[short] = params[key].copy()
                params[key] = np.zeros_like(params[key])
    if "time_offset" in params:
        params["time_offset"] = np.zeros_like(params["time_offset"])
    I3, Z = np.eye(3), np.zeros((4, 3))
    probe = np.vstack([np.zeros(3), I3])
    out = {}
    for sensor in ("accel", "gyro"):
        if f"{sensor}_bias" not in params and f"{sensor}_K" not in params:
            continue
        if sensor == "accel":
            y = _predict(model, params, "accel", probe, Z)
            b, K = y[0], (y[1:] - y[0]).T
            D = None
        else:
            yw = _predict(model, params, "gyro", Z, probe)
            yf = _predict(model, params, "gyro", probe, Z)
            b, K, D = yw[0], (yw[1:] - yw[0]).T, (yf[1:] - yf[0]).T
        if not np.all(np.isfinite(K)) or np.linalg.cond(K) > 1e12:
            raise InputError(f"the calibration's {sensor} model gives a singular scale "
                             "matrix; nothing to invert", path)
        # the map must be affine: check on inputs of realistic size
        rng = np.random.default_rng(0)
        x = rng.standard_normal((8, 3)) * (10.0 if sensor == "accel" else 1.0)
        fx = rng.standard_normal((8, 3)) * 10.0 if sensor == "gyro" else x
        y = (_predict(model, params, "accel", x, np.zeros((8, 3))) if sensor == "accel"
             else _predict(model, params, "gyro", fx, x))
        lin = b + x @ K.T + (fx @ D.T if D is not None else 0.0)
        if np.max(np.abs(y - lin)) > 1e-9 * (np.max(np.abs(y)) + 1e-300):
            raise InputError(f"the {sensor} model is not affine in its input; the linear "
                             "correction cannot express it (use `calib apply`)", path)
        # named as in the formula: accel b, K, K_inv; gyro d, G, G_inv, D
        if sensor == "accel":
            out[sensor] = {"b": b, "K": K, "K_inv": np.linalg.inv(K)}
        else:
            out[sensor] = {"d": b, "G": K, "G_inv": np.linalg.inv(K), "D": D}
        td = _thermal_of(cal, sensor)
        if td is not None:
            out[sensor].update(td)
        if sensor in nonaffine:
            na = nonaffine[sensor]
            out[sensor]["k2"] = na.get("k2", np.zeros(3))
            out[sensor]["a"] = na.get("a", np.zeros(3))
    if not out:
        raise InputError("the calibration holds no accelerometer or gyroscope correction", path)
    return out


def _thermal_of(cal: CalibrationResult, sensor: str) -> dict | None:
    """The sensor's temperature polynomial as (3, N) arrays, zeros where null."""
    d = next((d for d in cal.model if d.get("name") == "temperature_drift"
              and d.get("sensor") == sensor), None)
    if d is None:
        return None
    out = {}
    for name in ("temp_bias", "temp_scale"):
        v = np.asarray(cal.params.get(f"{sensor}_{name}", np.zeros(3)), dtype=float)
        v = np.where(np.isfinite(v), v, 0.0)
        out[name] = v[:, None] if v.ndim == 1 else v
    out["temp_ref"] = float(d.get("temp_ref", 25.0))
    return out


def size_effect_offsets(cal: CalibrationResult) -> np.ndarray | None:
    """The proof-mass offsets p (3, 3), m, that `calib apply` compensates (entries not
    determined taken as 0), when the calibration corrects both sensors; else None."""
    from calib_cli.methods.apply import corrected_channels, proof_mass_offsets

    if cal.layout.redundant or corrected_channels(cal) != ["accel", "gyro"]:
        return None
    return proof_mass_offsets(cal)


def thermal_info(cal: CalibrationResult) -> dict | None:
    """T_ref, order, calibrated range and lag of a thermal calibration (None otherwise)."""
    ds = [d for d in cal.model if d.get("name") == "temperature_drift"]
    if not ds:
        return None
    rng = cal.stats.get("temp_range_degC") or [None, None]
    lag = any(d.get("name") == "thermal_lag" for d in cal.model)
    return {"temp_ref_degC": float(ds[0].get("temp_ref", 25.0)),
            "order": int(ds[0].get("order", 1)),
            "temp_range_degC": [None if x is None else float(x) for x in rng],
            "thermal_lag_tau_s": float(cal.params["thermal_lag_tau"]) if lag else None}


THERMAL_FORMULA = {
    "accel": "dT = T - T_ref; u_i = (A_i - b_i - sum_k bT_ik dT^(k+1)) / "
             "(1 + sum_k sT_ik dT^(k+1)); f = K^-1 u",
    "gyro": "dT = T - T_ref; u_i = (W_i - d_i - sum_k dT_ik dT^(k+1) - (D f)_i) / "
            "(1 + sum_k gT_ik dT^(k+1)); w = G^-1 u",
    "lag": "with thermal_lag: T is the recorded temperature through a first-order lag of "
           "time constant tau (first-order hold): Tm_k = a Tm_(k-1) + c T_k + (1 - a - c) "
           "T_(k-1), a = exp(-dt/tau), c = 1 - tau (1 - a) / dt, Tm_0 = T_0",
}


def _num(x) -> float | None:
    x = float(x)
    return x if math.isfinite(x) else None


def _lists(a):
    a = np.asarray(a, dtype=float)
    if a.ndim == 0:
        return _num(a)
    return [_lists(v) for v in a]


def _text(v) -> str | None:
    """A provenance value as text (None stays None): what a file holds in an
    attribute may be any type; the export writes strings."""
    if v is None:
        return None
    if isinstance(v, bytes):
        return v.decode("utf-8", "backslashreplace")
    return str(v)


def _raw_units(cal: CalibrationResult) -> dict:
    ru = cal.raw_units if isinstance(cal.raw_units, dict) else {}
    return {str(k): _text(v) for k, v in ru.items()}


def export_object(cal: CalibrationResult, prov: dict, source: str) -> dict:
    """The JSON/YAML object: provenance, formula, correction, all parameters."""
    obj = {
        "format": "calib-correction", "format_version": 1,
        "source": {"file": _text(source), "sha256": _text(prov.get("sha256")),
                   "created_utc": _text(prov.get("created_utc")),
                   "command": _text(prov.get("command")),
                   "tool_version": _text(prov.get("tool_version"))},
        "method": _text(cal.method), "unit": {"serial": _text(cal.serial)},
        "raw_units": _raw_units(cal),
    }
    if not cal.layout.redundant:
        corr = affine_correction(cal, source)
        th = thermal_info(cal)
        obj["formula"] = {s: (THERMAL_FORMULA[s] if th else
                              NONAFFINE_FORMULA[s] if "k2" in corr[s] else FORMULA[s])
                          for s in corr}
        if th and th["thermal_lag_tau_s"] is not None:
            obj["formula"]["lag"] = THERMAL_FORMULA["lag"]
        obj["correction"] = {s: {k: _lists(v) for k, v in d.items()} for s, d in corr.items()}
        if th:
            obj["thermal"] = th
        p = size_effect_offsets(cal)
        if p is not None:
            obj["formula"]["size_effect"] = SIZE_EFFECT_FORMULA
            obj["correction"]["size_effect"] = {"proof_mass_offsets": _lists(p)}
        not_applied = sorted(({d.get("name") for d in cal.model} & (NOT_APPLIED | {"time_offset"}))
                             - ({"proof_mass_offsets"} if p is not None else set()))
        if not_applied:
            obj["not_applied"] = not_applied
            obj["not_applied_why"] = {k: NOT_APPLIED_WHY[k] for k in not_applied}
    if (cal.stats or {}).get("noise_model"):
        obj["not_exported"] = {"noise_model": sorted(cal.stats["noise_model"]),
                               "why": "noise-model terms widen sigma; no correction applies them"}
    obj["params"] = {k: _lists(v) for k, v in cal.params.items()}
    obj["sigma"] = {k: _lists(v) for k, v in cal.sigma.items()}
    obj["units"] = {str(k): _text(v) for k, v in cal.units.items()}
    return obj


def to_json(obj) -> str:
    return escape.json_text(obj, indent=2) + "\n"


# ---------------------------------------------------------------------------
# YAML, by hand: block mappings, flow sequences, double-quoted strings with
# every character outside printable ASCII escaped (escape.yaml_*)


def _yaml_flow(v) -> str:
    if isinstance(v, (list, tuple)):
        return "[" + ", ".join(_yaml_flow(x) for x in v) + "]"
    if isinstance(v, dict):
        return "{" + ", ".join(f"{escape.yaml_key(k)}: {_yaml_flow(x)}"
                               for k, x in v.items()) + "}"
    return escape.yaml_scalar(v)


def to_yaml(obj, indent: int = 0) -> str:
    lines = ["# calib correction export (docs/export.md)"] if indent == 0 else []
    pad = "  " * indent
    for k, v in obj.items():
        key = escape.yaml_key(k)
        if isinstance(v, dict):
            if not v:
                lines.append(f"{pad}{key}: {{}}")
            else:
                lines.append(f"{pad}{key}:")
                lines.append(to_yaml(v, indent + 1).rstrip("\n"))
        else:
            lines.append(f"{pad}{key}: {_yaml_flow(v)}")
    return "\n".join(lines) + "\n"


# ---------------------------------------------------------------------------
# CSV, long format (the csv module; text cells through escape.csv_cell)


def to_csv(cal: CalibrationResult, obj: dict) -> str:
    rows = [["parameter", "index", "value", "sigma", "unit"]]

    def fmt(x):
        return "" if x is None or not math.isfinite(float(x)) else repr(float(x))

    for k, v in cal.params.items():
        v = np.asarray(v, dtype=float)
        s = np.asarray(cal.sigma.get(k, np.full(v.shape, np.nan)), dtype=float)
        if s.shape != v.shape:
            s = np.full(v.shape, np.nan)
        for idx in np.ndindex(v.shape):
            rows.append([escape.csv_cell(k), " ".join(map(str, idx)), fmt(v[idx]), fmt(s[idx]),
                         escape.csv_cell(_text(cal.units.get(k, "")))])
    for sensor, d in obj.get("correction", {}).items():
        for name in ("K_inv", "G_inv"):
            if name not in d:
                continue
            m = np.asarray(d[name], dtype=float)
            for idx in np.ndindex(m.shape):
                rows.append([f"{sensor}_{name}", " ".join(map(str, idx)), fmt(m[idx]), "",
                             "derived"])
    return escape.csv_text(rows)


# ---------------------------------------------------------------------------
# C header


FLT_MAX = 3.4028234663852886e38
FLT_TRUE_MIN = 1.401298464324817e-45


def _c_lit(x: float, single: bool, what: str = "a value") -> str:
    """A C literal of x: double %.17g (exact round trip); float %.9g of the nearest
    float, which must exist (issue 37): beyond FLT_MAX exit 2 naming the value
    (export without --float); below the smallest float the nearest float, 0,
    written as 0 (gcc -Werror refused the truncated literal)."""
    x = float(x)
    if not math.isfinite(x):
        raise InputError(f"non-finite value in the correction ({what})")
    if single:
        if abs(x) > FLT_MAX:
            raise OutputError(f"{what} is {x:.6g}, beyond what a float holds (3.4e+38): "
                                  "export without --float (double)")
        x = float(np.float32(x))  # the float the compiler would make of it (0 below 1.4e-45)
        s = "%.9g" % x
        return s + ("f" if any(c in s for c in ".eE") else ".0f")
    s = "%.17g" % x
    return s if any(c in s for c in ".eEn") else s + ".0"


def _c_limit(x, single: bool, lo: bool) -> str:
    """A temperature bound of the header: the calibrated one, or the largest value of
    the type where the calibration states none (float: FLT_MAX, not 1e300)."""
    if x is None:
        x = -(FLT_MAX if single else 1e300) if lo else (FLT_MAX if single else 1e300)
    return _c_lit(x, single, "a temperature bound")


def _c_vec(name, v, single, T):
    v = np.asarray(v, dtype=float).reshape(-1)
    return (f"static const {T} {name}[{len(v)}] = "
            f"{{{', '.join(_c_lit(x, single, f'{name}[{i}]') for i, x in enumerate(v))}}};")


def _c_mat(name, m, single, T):
    m = np.asarray(m, dtype=float)
    rows = ",\n    ".join("{" + ", ".join(_c_lit(x, single, f"{name}[{i}][{j}]")
                                           for j, x in enumerate(r)) + "}"
                          for i, r in enumerate(m))
    return f"static const {T} {name}[{m.shape[0]}][{m.shape[1]}] = {{\n    {rows}\n}};"


# the string constants of the header: name suffix -> what it holds
C_STRINGS = ("SOURCE_FILE", "SOURCE_SHA256", "SOURCE_CREATED_UTC", "SOURCE_COMMAND",
             "SOURCE_TOOL_VERSION", "METHOD", "UNIT_SERIAL")


def c_header_symbols(prefix: str = "calib", accel: bool = True, gyro: bool = True,
                     thermal: bool = False, lag: bool = False, size_effect: bool = False,
                     redundant: bool = False) -> dict:
    """The names a c-header export defines (docs/export.md): {"macros",
    "types", "objects", "functions"}; the header defines nothing else."""
    P, p = prefix.upper(), prefix.lower()
    objects = [f"{P}_{n}" for n in C_STRINGS]
    macros, functions = [f"{P}_CORRECTION_H"], []
    if redundant:  # a redundant unit (RIMU): per-channel correction and body estimate
        macros.append(f"{P}_RIMU_CHANNELS")
        for s_, on in (("accel", accel), ("gyro", gyro)):
            if on:
                S = s_.upper()
                macros.append(f"{P}_HAS_{S}")
                objects += [f"{P}_{S}_UNITS", f"{P}_{S}_BIAS", f"{P}_{S}_SCALE", f"{P}_{S}_PINV"]
                functions.append(f"{p}_correct_{s_}")
        return {"macros": macros, "types": [f"{p}_real_t"], "objects": objects,
                "functions": functions}
    if thermal:
        macros += [f"{P}_HAS_THERMAL", f"{P}_TEMP_ORDER"]
        objects += [f"{P}_TEMP_REF", f"{P}_TEMP_MIN", f"{P}_TEMP_MAX"]
        objects += [f"{P}_{s}_TEMP_{k}" for s, on in (("ACCEL", accel), ("GYRO", gyro)) if on
                    for k in ("BIAS", "SCALE")]
        functions.append(f"{p}_temp_poly")
        if lag:
            macros.append(f"{P}_HAS_THERMAL_LAG")
            objects.append(f"{P}_THERMAL_LAG_TAU")
            functions.append(f"{p}_lag_temp")
    if accel:
        macros.append(f"{P}_HAS_ACCEL")
        objects += [f"{P}_ACCEL_UNITS", f"{P}_ACCEL_BIAS", f"{P}_ACCEL_KINV"]
        functions.append(f"{p}_correct_accel")
    if gyro:
        macros.append(f"{P}_HAS_GYRO")
        objects += [f"{P}_GYRO_UNITS", f"{P}_GYRO_BIAS", f"{P}_GYRO_GINV", f"{P}_GYRO_D"]
        functions.append(f"{p}_correct_gyro")
    if size_effect:
        macros.append(f"{P}_HAS_SIZE_EFFECT")
        objects.append(f"{P}_PROOF_MASS")
        functions.append(f"{p}_size_effect")
    return {"macros": macros, "types": [f"{p}_real_t"], "objects": objects,
            "functions": functions}


def _c_str_const(name: str, text) -> str:
    return f"static const char {name}[] = {escape.c_string('' if text is None else text)};"


def to_c_header(cal: CalibrationResult, prov: dict, source: str, single: bool = False,
                prefix: str = "calib") -> str:
    """The C99 header. Names come from ``prefix`` (a checked C identifier);
    text from the file appears only inside string constants (escape.c_string);
    comments hold only the tool's own text."""
    escape.c_identifier(prefix, "--prefix")
    if cal.layout.redundant:
        return _c_header_rimu(cal, prov, source, single, prefix)
    corr = affine_correction(cal, source)
    P, p = prefix.upper(), prefix.lower()
    T = f"{p}_real_t"
    units = _raw_units(cal)

    def unit_note(sensor, default):
        u = units.get(sensor) or default
        word = escape.c_comment_word(u)
        return word if word is not None else f"see {P}_{sensor.upper()}_UNITS"

    head = [
        "/*",
        f" * Calibration correction exported by calib {__version__} (docs/export.md).",
        " * Provenance (source file, its sha256, creation time, command, method, unit",
        f" * serial) is in the {P}_SOURCE_*, {P}_METHOD and {P}_UNIT_SERIAL string",
        " * constants below: text from the calibration file never appears in a comment.",
        " *",
        " * Correction (calib contract, section 2):",
    ]
    if "accel" in corr:
        head.append(f" *   f = K^-1 (A - b)          A: accelerometer output "
                    f"({unit_note('accel', 'm/s^2')}), f: specific force (m/s^2)")
    if "gyro" in corr:
        head.append(f" *   w = G^-1 (W - d - D f)    W: gyro output ({unit_note('gyro', 'rad/s')}),"
                    " w: angular rate (rad/s), f: the corrected specific force")
    head += [
        " * Matrices are row-major: M[i][j] is row i, column j. Axes x, y, z = 0, 1, 2.",
        f" * Literals: {'float, %.9g' if single else 'double, %.17g (exact round trip)'}.",
        " */",
        f"#ifndef {P}_CORRECTION_H",
        f"#define {P}_CORRECTION_H",
        "",
        f"typedef {'float' if single else 'double'} {T};",
        "",
    ] + _c_provenance(cal, prov, source, P)
    th = thermal_info(cal)
    size = _c_size_effect(size_effect_offsets(cal), single, P, p, T)
    body = [] if th is None else _c_thermal_common(corr, th, single, P, p, T)
    for sensor in ("accel", "gyro"):
        if sensor in corr:
            body += _c_sensor(sensor, corr[sensor], th is not None, single, P, p, T, units)
    if any("k2" in d for d in corr.values()):  # fabs, and the terms' arrays before use
        head = head + ["#include <math.h>", ""] + [
            line for s_, name in (("accel", "ACCEL"), ("gyro", "GYRO")) if "k2" in corr.get(s_, {})
            for line in _c_nonaffine_arrays(corr[s_], name, single, P, T)]
    return "\n".join(head + body + size + [f"#endif /* {P}_CORRECTION_H */", ""])


def _c_provenance(cal, prov, source, P) -> list[str]:
    return ["/* provenance: the calibration file this header was exported from */",
            _c_str_const(f"{P}_SOURCE_FILE", _text(source)),
            _c_str_const(f"{P}_SOURCE_SHA256", _text(prov.get("sha256"))),
            _c_str_const(f"{P}_SOURCE_CREATED_UTC", _text(prov.get("created_utc"))),
            _c_str_const(f"{P}_SOURCE_COMMAND", _text(prov.get("command"))),
            _c_str_const(f"{P}_SOURCE_TOOL_VERSION", _text(prov.get("tool_version"))),
            _c_str_const(f"{P}_METHOD", _text(cal.method)),
            _c_str_const(f"{P}_UNIT_SERIAL", _text(cal.serial) or "unknown"), ""]


def _c_header_rimu(cal, prov, source, single, prefix) -> str:
    """The header of a redundant unit (issue 37): per channel i the corrected
    single-axis input a_i = (A_i - b_i) / (1 + ks_i), and the least-squares body
    vector f = PINV a, PINV = (H^T H)^-1 H^T of the calibrated directions H, as
    ``calib apply`` computes them (methods/rimu.py). A model with further effects
    (fit rimu --with) is applied by calib apply only."""
    from calib_cli.methods.apply import redundant_extra
    from calib_cli.methods.rimu import measurement_matrix

    if redundant_extra(cal):
        raise InputError("the redundant unit's model has effects beyond bias and installation "
                         "(fit rimu --with), which the header's per-channel correction cannot "
                         "express; use `calib apply`", source)
    P, p = prefix.upper(), prefix.lower()
    T = f"{p}_real_t"
    n = cal.layout.n
    units = _raw_units(cal)
    lines = ["/*",
             f" * Calibration correction of a redundant unit ({n} single-axis channels per "
             "sensor)",
             f" * exported by calib {__version__} (docs/export.md). Provenance is in the",
             f" * {P}_SOURCE_*, {P}_METHOD and {P}_UNIT_SERIAL string constants below.",
             " *",
             " *   a_i = (A_i - b_i) / (1 + ks_i)   the input along channel i's axis",
             " *   f = PINV a                       least-squares body vector, PINV = (H^T H)^-1 H^T",
             f" * Literals: {'float, %.9g' if single else 'double, %.17g (exact round trip)'}.",
             " */",
             f"#ifndef {P}_CORRECTION_H", f"#define {P}_CORRECTION_H", "",
             f"typedef {'float' if single else 'double'} {T};", "",
             f"#define {P}_RIMU_CHANNELS {n}", ""] + _c_provenance(cal, prov, source, P)
    done = 0
    for s_ in ("accel", "gyro"):
        if f"{s_}_bias" not in cal.params:
            continue
        S = s_.upper()
        b = np.asarray(cal.params[f"{s_}_bias"], float)
        scale = 1.0 + np.asarray(cal.params[f"{s_}_scale_error"], float)
        H = measurement_matrix(cal.params, cal.layout, s_)
        if np.linalg.matrix_rank(H) < 3:
            raise InputError(f"the {s_} channel directions do not span three axes: no body "
                             "estimate", source)
        pinv = np.linalg.pinv(H)
        lines += [f"#define {P}_HAS_{S} 1",
                  _c_str_const(f"{P}_{S}_UNITS", units.get(s_) or ("m/s^2" if s_ == "accel"
                                                                    else "rad/s")),
                  "/* per-channel bias b and scale 1 + ks */",
                  _c_vec(f"{P}_{S}_BIAS", b, single, T),
                  _c_vec(f"{P}_{S}_SCALE", scale, single, T),
                  "/* body estimate: PINV[r][i], row r = body axis x, y, z */",
                  _c_mat(f"{P}_{S}_PINV", pinv, single, T),
                  f"static inline void {p}_correct_{s_}(const {T} A[{n}], {T} a[{n}], "
                  f"{T} f[3])",
                  "{",
                  f"    for (int i = 0; i < {n}; ++i) a[i] = (A[i] - {P}_{S}_BIAS[i]) / "
                  f"{P}_{S}_SCALE[i];",
                  "    for (int r = 0; r < 3; ++r) {",
                  f"        {T} s = 0;",
                  f"        for (int i = 0; i < {n}; ++i) s += {P}_{S}_PINV[r][i] * a[i];",
                  "        f[r] = s;",
                  "    }",
                  "}", ""]
        done += 1
    if not done:
        raise InputError("the calibration holds no accelerometer or gyroscope correction",
                         source)
    return "\n".join(lines + [f"#endif /* {P}_CORRECTION_H */", ""])


def _c_size_effect(pm, single, P, p, T) -> list[str]:
    """The size-effect compensation (docs/export.md): the proof-mass offsets and a
    function taking the corrected rate w and its derivative dw/dt, as `calib apply`."""
    if pm is None:
        return []
    return [f"#define {P}_HAS_SIZE_EFFECT 1",
            "/* proof-mass offsets, m: row i is accelerometer i's proof mass relative to the",
            " * triad's reference point (entries the calibration did not determine are 0) */",
            _c_mat(f"{P}_PROOF_MASS", pm, single, T), "",
            "/* Size effect: accelerometer i to the triad's reference point,",
            " *   f_i -= (w x (w x p_i) + dw x p_i)_i",
            " * w: corrected angular rate (rad/s), dw: its time derivative (rad/s^2), f: the",
            f" * corrected specific force, changed in place. Then call {p}_correct_gyro again",
            " * with the new f (its D term sees the force at the reference point). */",
            f"static inline void {p}_size_effect(const {T} w[3], const {T} dw[3], {T} f[3])",
            "{",
            f"    {T} ww = w[0] * w[0] + w[1] * w[1] + w[2] * w[2];",
            "    for (int i = 0; i < 3; ++i) {",
            f"        const {T} *r = {P}_PROOF_MASS[i];",
            "        int j = (i + 1) % 3, k = (i + 2) % 3;",
            f"        {T} wr = w[0] * r[0] + w[1] * r[1] + w[2] * r[2];",
            "        f[i] -= (w[i] * wr - r[i] * ww) + (dw[j] * r[k] - dw[k] * r[j]);",
            "    }",
            "}", ""]


def _c_nonaffine_arrays(d, NAME, single, P, T) -> list[str]:
    return [f"#define {P}_{NAME}_HAS_NONLINEAR 1",
            "/* per-axis terms on the axis's own input x (not affine):",
            f" * output_i = affine_i + {NAME}_K2[i] x_i^2 + {NAME}_ASYM[i] |x_i|;",
            f" * inverted by {NONAFFINE_ITER} fixed-point iterations in the correction below */",
            _c_vec(f"{P}_{NAME}_K2", d["k2"], single, T),
            _c_vec(f"{P}_{NAME}_ASYM", d["a"], single, T), ""]


def _c_nonaffine(d, NAME, INV, x, single, P, T) -> list[str]:
    """The fixed-point iterations of the non-affine terms inside a correction function
    (u: the output minus the affine offsets; x: the input being solved for)."""
    if "k2" not in d:
        return []
    return [f"    for (int it = 0; it < {NONAFFINE_ITER}; ++it) {{",
            f"        {T} v[3];",
            "        for (int i = 0; i < 3; ++i)",
            f"            v[i] = u[i] - {P}_{NAME}_K2[i] * {x}[i] * {x}[i]"
            f" - {P}_{NAME}_ASYM[i] * fabs({x}[i]);",
            "        for (int i = 0; i < 3; ++i)",
            f"            {x}[i] = {P}_{NAME}_{INV}[i][0] * v[0] + {P}_{NAME}_{INV}[i][1] * v[1]"
            f" + {P}_{NAME}_{INV}[i][2] * v[2];",
            "    }"]


def _c_rows(name, m, single, T):
    return _c_mat(name, m, single, T)


def _c_thermal_common(corr, th, single, P, p, T) -> list[str]:
    """What a thermal header adds before the sensors (docs/thermal.md): T_ref,
    the range, the polynomial and (thermal_lag) the filter of the reading."""
    N = int(next(iter(corr.values()))["temp_bias"].shape[1])
    lo, hi = th["temp_range_degC"]
    out = [f"#define {P}_HAS_THERMAL 1",
           f"#define {P}_TEMP_ORDER {N}",
           "/* reference temperature T_ref and the calibrated range, degC */",
           f"static const {T} {P}_TEMP_REF = {_c_lit(th['temp_ref_degC'], single)};",
           f"static const {T} {P}_TEMP_MIN = {_c_limit(lo, single, True)};",
           f"static const {T} {P}_TEMP_MAX = {_c_limit(hi, single, False)};",
           "",
           "/* sum_k c[k] dT^(k+1), k = 0 .. ORDER-1 (Horner) */",
           f"static inline {T} {p}_temp_poly(const {T} c[{N}], {T} dT)",
           "{",
           f"    {T} s = 0;",
           f"    for (int k = {N} - 1; k >= 0; --k) s = (s + c[k]) * dT;",
           "    return s;",
           "}", ""]
    if th["thermal_lag_tau_s"] is not None:
        out += ["#include <math.h>", f"#define {P}_HAS_THERMAL_LAG 1",
                "/* thermal lag time constant tau, s */",
                f"static const {T} {P}_THERMAL_LAG_TAU = "
                f"{_c_lit(th['thermal_lag_tau_s'], single)};",
                "/* the temperature the sensing elements see: first-order lag of the recorded",
                " * temperature T, first-order hold; state[0] = lagged value, state[1] = the",
                " * previous T; start both at the first T. dt: sample interval, s. */",
                f"static inline {T} {p}_lag_temp({T} state[2], {T} T_now, {T} dt)",
                "{",
                f"    {T} a = exp(-dt / {P}_THERMAL_LAG_TAU);",
                f"    {T} c = 1 - {P}_THERMAL_LAG_TAU * (1 - a) / dt;",
                "    state[0] = a * state[0] + c * T_now + (1 - a - c) * state[1];",
                "    state[1] = T_now;",
                "    return state[0];",
                "}", ""]
    return out


# one template for both sensors, static or thermal: the sensor's names and words
_C_SENSOR = {
    "accel": dict(S="ACCEL", what="accelerometer", In="A", out="f", bias="b", M="K",
                  MINV="KINV", inv="K_inv", unit="m/s^2", args="", dfree="",
                  tb_unit="m/s^2/degC^(k+1)", ts_doc="on row i of K f, 1/degC^(k+1)",
                  static_doc="f = K^-1 (A - b)",
                  thermal_doc="u_i = (A_i - b_i - bT_i(dT)) / (1 + sT_i(dT)), f = K^-1 u, "
                              "dT = temp - T_ref"),
    "gyro": dict(S="GYRO", what="gyro", In="W", out="w", bias="d", M="G", MINV="GINV",
                 inv="G_inv", unit="rad/s", args="const {T} f[3], ", dfree=" - ({P}_GYRO_D[i][0]"
                 " * f[0] + {P}_GYRO_D[i][1] * f[1] + {P}_GYRO_D[i][2] * f[2])",
                 tb_unit="rad/s/degC^(k+1)",
                 ts_doc="on row i of G w (zero where not observable)",
                 static_doc="w = G^-1 (W - d - D f), f the corrected specific force",
                 thermal_doc="u_i = (W_i - d_i - dT_i(dT) - (D f)_i) / (1 + gT_i(dT)), "
                             "w = G^-1 u"),
}


def _c_sensor(sensor, c, thermal, single, P, p, T, units) -> list[str]:
    """One sensor's constants and correction function; with ``thermal`` the
    bias and scale polynomials are evaluated first (as calib apply)."""
    w = _C_SENSOR[sensor]
    S, In, out, MINV = w["S"], w["In"], w["out"], w["MINV"]
    at = " at T_ref" if thermal else ""
    lines = [f"#define {P}_HAS_{S} 1",
             f"/* units of the {w['what']} output {In} */",
             _c_str_const(f"{P}_{S}_UNITS", units.get(sensor) or w["unit"]),
             f"/* {w['what']} bias {w['bias']}{at} */",
             _c_vec(f"{P}_{S}_BIAS", c[w["bias"]], single, T)]
    if thermal:
        lines += [f"/* {w['M']}^-1 at T_ref */", _c_mat(f"{P}_{S}_{MINV}", c[w["inv"]], single, T)]
    else:
        lines += [f"/* {w['M']}^-1, the inverse of the {w['what']} scale/misalignment matrix "
                  f"{w['M']} */", _c_mat(f"{P}_{S}_{MINV}", c[w["inv"]], single, T)]
    if sensor == "gyro":
        lines += ["/* D, g-sensitivity, (rad/s)/(m/s^2) (zero when not estimated) */",
                  _c_mat(f"{P}_GYRO_D", c["D"], single, T)]
    dfree = w["dfree"].format(P=P)
    args = w["args"].format(T=T)
    if thermal:
        if sensor == "accel":
            lines += [f"/* bias polynomial bT[i][k], coefficient of dT^(k+1), {w['tb_unit']} */"]
        else:
            lines += [f"/* bias polynomial, {w['tb_unit']} */"]
        lines += [_c_rows(f"{P}_{S}_TEMP_BIAS", c["temp_bias"], single, T),
                  f"/* scale polynomial {'sT[i][k] ' if sensor == 'accel' else ''}"
                  f"{w['ts_doc']} */",
                  _c_rows(f"{P}_{S}_TEMP_SCALE", c["temp_scale"], single, T), "",
                  f"/* {w['thermal_doc']} */",
                  f"static inline void {p}_correct_{sensor}(const {T} {In}[3], {args}{T} temp, "
                  f"{T} {out}[3])",
                  "{",
                  f"    {T} u[3], dT = temp - {P}_TEMP_REF;",
                  "    for (int i = 0; i < 3; ++i)",
                  f"        u[i] = ({In}[i] - {P}_{S}_BIAS[i] - {p}_temp_poly({P}_{S}_TEMP_BIAS[i],"
                  f" dT){dfree}) / (1 + {p}_temp_poly({P}_{S}_TEMP_SCALE[i], dT));"]
    else:
        lines += ["", f"/* {w['static_doc']} */",
                  f"static inline void {p}_correct_{sensor}(const {T} {In}[3], {args}{T} {out}[3])",
                  "{",
                  f"    {T} u[3];"]
        if sensor == "accel":
            lines += [f"    for (int i = 0; i < 3; ++i) u[i] = A[i] - {P}_ACCEL_BIAS[i];"]
        else:
            lines += ["    for (int i = 0; i < 3; ++i)",
                      f"        u[i] = W[i] - {P}_GYRO_BIAS[i]{dfree};"]
    lines += ["    for (int i = 0; i < 3; ++i)",
              f"        {out}[i] = {P}_{S}_{MINV}[i][0] * u[0] + {P}_{S}_{MINV}[i][1] * u[1]"
              f" + {P}_{S}_{MINV}[i][2] * u[2];",
              *_c_nonaffine(c, S, MINV, out, single, P, T),
              "}", ""]
    return lines


# Formats for other tools (Kalibr imu.yaml, PX4 and ArduPilot parameters) live in
# io/export_autopilot.py; `calib export` dispatches on ALL_FORMATS.
def _tool_formats() -> tuple[str, ...]:
    from calib_cli.io.export_autopilot import AUTOPILOT_FORMATS

    return AUTOPILOT_FORMATS


ALL_FORMATS = FORMATS + _tool_formats()
