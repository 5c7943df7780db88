"""Values, sigmas and units for people: the one place that turns a number of a
file into text. `calib show`, the fit summary, `plan check`, `show A B`,
`history` and the report all format through here, so a parameter reads the
same everywhere.

Files and JSON keep SI -- or the units the recording declared: data in counts
give biases and noise in counts and scale factors in count/(m/s^2), and those
stay counts here, never multiplied by an SI display factor. SI values are
shown in engineering units (mg, deg/h, ppm, mm, ...): a parameter's from the
table below or its effect's ``ParamSpec.display``, a statistic's from its key
(``stat_unit``). A unit with the polynomial power ``^k`` (thermal
coefficients, ``m/s^2/degC^k``) gets the power of each entry: column k of a
thermal polynomial is the coefficient of dT^(k+1).
"""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

import numpy as np

G0 = 9.80665
MG = 1e3 / G0  # m/s^2 -> mg
UG = 1e6 / G0  # m/s^2 -> ug
DPH = 180.0 / math.pi * 3600.0  # rad/s -> deg/h
DEG = 180.0 / math.pi  # rad -> deg
DSH = 180.0 / math.pi * 60.0  # rad/s/sqrt(Hz) = rad/sqrt(s) -> deg/sqrt(h)
ND = "not determined"
SI_UNIT = {"accel": "m/s^2", "gyro": "rad/s"}

# key -> (factor, unit) of parameters not owned by one effect of the catalogue
DISPLAY = {
    "accel_bias": (MG, "mg"),
    "accel_K": (1.0, ""),
    "gyro_bias": (DPH, "deg/h"),
    "gyro_K": (1.0, ""),
    "gyro_D": (DPH * G0, "deg/h/g"),
    "lever_arm": (1e3, "mm"),
    "proof_mass_offsets": (1e3, "mm"),
    "attitude": (DEG, "deg"),
    "time_offset": (1e3, "ms"),
}
for _s in ("accel", "gyro"):
    DISPLAY[f"{_s}_dEl"] = (1e3, "mrad")
    DISPLAY[f"{_s}_dAz"] = (1e3, "mrad")
    DISPLAY[f"{_s}_scale_error"] = (1e6, "ppm")


# --------------------------------------------------------------------------------------
# numbers


def num(x, digits: int = 4) -> str:
    """A finite number with ``digits`` significant digits, else 'not determined';
    an int stays an int."""
    try:
        v = float(x)
    except (TypeError, ValueError):
        return ND
    if not math.isfinite(v):
        return ND
    if v == int(v) and abs(v) < 1e9 and not isinstance(x, (float, np.floating)):
        return str(int(v))
    return f"{v:.{digits}g}"


def value_str(v: float, sd: float | None = None) -> str:
    """A parameter value in display units: to two significant digits of its sigma
    ``sd`` (same units) when that is known, else 7 significant digits."""
    if not math.isfinite(v):
        return ND
    if sd is not None and math.isfinite(sd) and sd > 0 and 1e-6 <= abs(v) + sd < 1e9:
        decimals = 1 - math.floor(math.log10(sd))
        if 0 <= decimals <= 12:
            return f"{v:.{decimals}f}"
    return f"{v:.7g}"


def sigma_str(s: float, factor: float, unit: str = "") -> str:
    """A 1-sigma: 'fixed' (0: set by convention or by the model), 'unobservable'
    (not finite), else the number in display units with ``unit`` when given."""
    if s is None or not math.isfinite(s):
        return "unobservable"
    if s == 0:
        return "fixed"
    return f"{s * factor:.3g}" + (f" {unit}" if unit else "")


# --------------------------------------------------------------------------------------
# parameters


def _powered(unit: str, power: int) -> str:
    """'mg/degC^k' -> 'mg/degC' (power 1), 'mg/degC^2' (power 2)."""
    return unit.replace("^k", "" if power == 1 else f"^{power}")


def display_of(key: str, unit: str, idx: tuple = ()) -> tuple[float, str]:
    """(factor, unit) to show entry ``idx`` of parameter KEY whose file unit is
    ``unit``: counts (any unit naming 'count') unchanged; else the table above,
    the display units of the catalogue effect that owns the key
    (``ParamSpec.display``), else the file's unit. A '^k' in the unit is the
    entry's polynomial power (idx[-1] + 1 for a 2-D key, else 1)."""
    power = idx[-1] + 1 if len(idx) == 2 else 1
    if "count" in unit:
        return 1.0, _powered(unit, power)
    if key in DISPLAY:
        f, u = DISPLAY[key]
    else:
        spec = catalogue_specs().get(key)
        if spec is not None and spec.display != (1.0, "") and spec.unit == unit:
            f, u = spec.display
        else:
            f, u = si_display(unit)
    return f, _powered(u, power)


def si_display(unit: str) -> tuple[float, str]:
    """An SI unit no table names, in engineering units by its leading quantity:
    m/s^2... -> mg..., rad/s... -> deg/h... (a toy method's or a new effect's
    parameter); anything else unchanged."""
    for si, (f, u) in (("m/s^2", (MG, "mg")), ("rad/s", (DPH, "deg/h"))):
        rest = unit[len(si):]
        if unit.startswith(si) and not rest.startswith("^"):
            return f, u + rest
    return 1.0, unit


def is_matrix(key: str, unit: str) -> bool:
    """A dimensionless scale/misalignment matrix (K, G): value as is, sigma in ppm."""
    return key.endswith("_K") and unit in ("", "-")


@dataclass
class Entry:
    """One displayed entry of a parameter: name 'key[i,j]', value and 1-sigma as text,
    the unit of the value; ``sigma_unit`` is set where the sigma has its own unit
    (ppm of a dimensionless matrix)."""

    name: str
    key: str
    idx: tuple
    value: str
    sigma: str
    unit: str

    def value_sigma(self) -> str:
        s = self.sigma if self.sigma in ("fixed", "unobservable") else f"+- {self.sigma}"
        return f"{self.value}  {s}"


def entries(params: dict, sigma: dict, units: dict) -> list[Entry]:
    """Every entry of every parameter, in file order, formatted for display."""
    out = []
    for key, val in params.items():
        val = np.asarray(val, dtype=float)
        sig = np.asarray(sigma.get(key, np.full(val.shape, np.nan)), dtype=float)
        if sig.shape != val.shape:
            sig = np.full(val.shape, np.nan)
        unit = units.get(key, "") or ""
        out += sigma_entries(key, val, sig, unit)
    return out


def sigma_entries(key: str, val, sig, unit: str) -> list[Entry]:
    """The entries of one parameter (``val`` None: sigma only, as plan check)."""
    sig = np.asarray(sig, dtype=float)
    val = None if val is None else np.asarray(val, dtype=float)
    mat = is_matrix(key, unit)
    out = []
    for idx in np.ndindex(sig.shape):
        f, u = display_of(key, unit, idx)
        s = float(sig[idx])
        name = f"{key}[{','.join(map(str, idx))}]" if sig.ndim else key
        if mat:
            ss = sigma_str(s, 1e6, "ppm")
        else:
            ss = sigma_str(s, f)
        v = "" if val is None else value_str(float(val[idx]) * f, s * f if not mat else s)
        out.append(Entry(name, key, idx, v, ss, "-" if mat or not u else u))
    return out


def catalogue_specs() -> dict:
    """key -> ParamSpec over every catalogue effect (triad and redundant layouts);
    rebuilt when an effect is registered."""
    from calib_cli.model.effects import CATALOGUE, Layout, make_effect

    names = tuple(CATALOGUE)
    if _SPECS.get("__names__") == names:
        return _SPECS
    _SPECS.clear()
    _SPECS["__names__"] = names

    for layout in (Layout(), Layout(n=6, el0=np.zeros(6), az0=np.zeros(6))):
        for name, cls in CATALOGUE.items():
            for sensor in (("",) if cls.sensorless else ("accel", "gyro")):
                try:
                    e = make_effect(name, sensor or "accel")
                except (TypeError, ValueError):
                    continue
                for sp in e.specs(layout):
                    _SPECS.setdefault(sp.key, sp)
    return _SPECS


_SPECS: dict = {}


def data_units(units: dict) -> dict:
    """{'accel': unit, 'gyro': unit}: the recorded units of each sensor, as a
    calibration file declares them (the unit of the sensor's bias; SI when absent)."""
    return {s: (units.get(f"{s}_bias") or si) for s, si in SI_UNIT.items()}


def counts_note(params: dict, units: dict) -> str | None:
    """One line naming the scale of data recorded in counts (None for SI data):
    'accel in counts: K diagonal 414.4, 412.1, 414.5 count/(m/s^2), 1 count = 0.2461,
    ... mg'."""
    parts = []
    for s in SI_UNIT:
        u = units.get(f"{s}_bias", "")
        if "count" not in u:
            continue
        k = params.get(f"{s}_K")
        if k is None:
            parts.append(f"{s} in {u}s (no scale factor in this file)")
            continue
        d = np.abs(np.diag(np.atleast_2d(np.asarray(k, float))))
        f, du = (MG, "mg") if s == "accel" else (DPH, "deg/h")
        per = ", ".join(num(f / x, 4) if x > 0 else ND for x in d)
        parts.append(f"{s} in {u}s: scale {', '.join(num(x, 5) for x in d)} "
                     f"{units.get(f'{s}_K', '')}, so 1 {u} = {per} {du}")
    if not parts:
        return None
    return ("Recorded in counts (values in counts stay counts; the scale factors convert): "
            + "; ".join(parts) + ".")


# --------------------------------------------------------------------------------------
# statistics

# statistics in the recorded units of a sensor (counts stay counts), by key
_DATA_STATS = re.compile(r"^(accel|gyro)_(noise_sigma|residual_rms|noise_density)$|"
                         r"^static_residual_rms$|^noise_(accel|gyro)$")
# (method, key) -> the statistic's SI unit where its key's rule does not hold
_STAT_EXCEPTIONS = {
    ("gyro", "gyro_residual_rms"): "rad",  # angles of the transitions and turns
    ("scalar", "accel_residual_rms"): "m/s^2",  # of |f| after correction
}


def _sensor_of(key: str) -> str:
    return "gyro" if "gyro" in key or key == "static_residual_rms" else "accel"


@dataclass
class StatUnits:
    """The units of a calibration's statistics: built from its parameter units
    (which say whether the data were counts) and its method."""

    method: str = ""
    data: dict | None = None  # data_units(...)
    accel_method: str = ""

    @classmethod
    def of(cls, cal) -> StatUnits:
        st = getattr(cal, "stats", {}) or {}
        return cls(cal.method, data_units(cal.units), str(st.get("accel_method") or ""))

    def __call__(self, key: str) -> tuple[float, str]:
        si = _STAT_EXCEPTIONS.get((self.method, key))
        if key == "accel_residual_rms" and self.accel_method == "scalar":
            si = "m/s^2"
        if si == "rad":
            return DEG, "deg"
        if si is None and _DATA_STATS.match(key) and self.data:
            u = self.data.get(_sensor_of(key), "")
            if u and u != SI_UNIT[_sensor_of(key)]:
                return 1.0, u + ("/sqrt(Hz)" if key.endswith("density") else "")
        return stat_unit(key)


def stat_unit(key: str) -> tuple[float, str]:
    """(factor from SI, display unit) of a statistic named ``key`` of SI data."""
    k = key.lower()
    if k in ("g_reference", "accel_body_error_input"):
        return 1.0, "m/s^2"
    if k == "gyro_body_error_input":
        return DPH / 3600.0, "deg/s"
    if k.endswith("_mrad"):
        return 1.0, "mrad"
    if k.endswith("_urad"):
        return 1.0, "urad"
    if k.endswith("_deg") or k in ("rotation_angle", "angle") or k.startswith("attitude"):
        return (1.0, "deg") if k.endswith("_deg") else (DEG, "deg")
    if k.endswith("_rad") or k.endswith("_sigma_rad"):
        return DEG, "deg"
    if k.endswith("_degc"):
        return 1.0, "degC"
    if k.endswith("_hz"):
        return 1.0, "Hz"
    if k.endswith("_s") or k == "block_s":
        return 1.0, "s"
    if "density" in k:
        if k.startswith("gyro") or k.endswith("gyro"):
            return DSH, "deg/sqrt(h)"
        return UG, "ug/sqrt(Hz)"
    if "chi2" in k or "inflation" in k or "normalized" in k or "nis" in k or "dof" in k:
        return 1.0, ""
    acc = k.startswith(("accel", "g_error", "g_norm", "g_mean")) or k.endswith("_accel")
    gyr = k.startswith("gyro") or k.endswith("_gyro")
    if acc and re.search(r"rms|sigma|noise|error|std|bias|predicted|floor|before|after", k):
        return MG, "mg"
    if gyr and re.search(r"rms|sigma|noise|error|bias|predicted", k):
        return DPH, "deg/h"
    if k == "lever_arm" or k.startswith("proof_mass"):
        return 1e3, "mm"
    if k.endswith("_k") or k.endswith("_scale_error"):
        return 1e6, "ppm"
    return 1.0, ""


# statistics whose null means "nothing found", not "not determined"
NONE_MEANS = {"degeneracy": "none", "warnings": "none", "transitions_skipped": "none"}


def value_text(key: str, v, limit: int = 400, units: StatUnits | None = None) -> str:
    """A statistic's value as text with its unit; nested lists and dicts are
    flattened readably (dicts as 'name: value', each with its own unit)."""
    if v is None and key in NONE_MEANS:
        return NONE_MEANS[key]
    unit_of = units or stat_unit
    factor, unit = unit_of(key)
    s = _render(key, v, factor, unit, unit_of, top=True)
    return s if len(s) <= limit else s[: limit - 3] + "..."


def _render(key, v, factor, unit, unit_of, top=False) -> str:
    if v is None:
        return ND
    if isinstance(v, (bool, np.bool_)):
        return "yes" if v else "no"
    if isinstance(v, (str, bytes)):
        s = v.decode() if isinstance(v, bytes) else v
        return s if s.strip() else "-"
    if isinstance(v, dict):
        if not v:
            return "-"
        parts = []
        scalar_map = all(isinstance(x, (int, float, np.integer, np.floating)) for x in v.values())
        for k, x in v.items():
            f, u = unit_of(str(k))
            if not u and scalar_map:  # {"x-turn": 360.0} of turn_angles_deg: the parent's unit
                f, u = factor, unit
            parts.append(f"{k}: {_render(str(k), x, f, u, unit_of, top=True)}")
        return "; ".join(parts)
    if isinstance(v, (list, tuple, np.ndarray)):
        arr = list(v)
        if not arr:
            return "-"
        if all(isinstance(x, (int, float, np.integer, np.floating)) and
               not isinstance(x, (bool, np.bool_)) or x is None for x in arr):
            body = ", ".join(num(None if x is None else float(x) * factor
                                 if isinstance(x, (float, np.floating)) or factor != 1.0
                                 else x) for x in arr)
            return body + (f" {unit}" if top and unit else "")
        inner = [_render(key, x, factor, unit, unit_of, top=False) for x in arr]
        body = "; ".join(f"[{s}]" if isinstance(x, (list, tuple, np.ndarray)) else s
                         for s, x in zip(inner, arr, strict=True))
        return body + (f" {unit}" if top and unit and all(
            isinstance(x, (list, tuple, np.ndarray)) for x in arr) else "")
    if isinstance(v, (int, np.integer)) and factor == 1.0:
        return str(int(v))
    try:
        x = float(v) * factor
    except (TypeError, ValueError):
        return str(v)
    t = num(x)
    return t + (f" {unit}" if unit and t != ND and top else "")


def g_figures_line(st: dict) -> str | None:
    """Avrutov et al.'s figures (std of |g| over positions, |mean |g| - g|),
    before and after correction, in mg; None when the fit has none."""
    if st.get("g_norm_std_after") is None:
        return None

    def mg(v):
        return f"{v * MG:.4f}"

    if st.get("g_norm_std_before") is None:  # data in counts: no |g| before correction
        return (f"|g| over the positions after correction: std {mg(st['g_norm_std_after'])} "
                f"mg, |mean - g| {mg(st.get('g_mean_error_after') or 0.0)} mg")
    return (f"|g| over the positions: std {mg(st['g_norm_std_before'])} -> "
            f"{mg(st['g_norm_std_after'])} mg, |mean - g| "
            f"{mg(st.get('g_mean_error_before') or 0.0)} -> "
            f"{mg(st.get('g_mean_error_after') or 0.0)} mg (before -> after correction)")


def g_error_label(st: dict) -> str:
    """What the |g| error RMS of a fit is taken over: its static positions, or what
    the fit's ``g_error_note`` says (the turntable's blocks at rest)."""
    note = st.get("g_error_note")
    if isinstance(note, str) and note.strip():
        return f"|g| error RMS ({note.strip()})"
    return "|g| error RMS over the static positions"


def g_error_line(st: dict) -> str | None:
    """'|g| error RMS over the static positions: before 10.77 mg, after 0.0075 mg
    (noise floor 0.0097 mg)' of a fit's statistics; None when it has none."""
    after = st.get("g_error_rms_after")
    if after is None or not np.isfinite(after):
        return None
    before = st.get("g_error_rms_before")
    b = "not determined (data in counts)" if before is None else f"{num(before * MG)} mg"
    floor = st.get("g_error_floor")
    fl = f" (noise floor {num(floor * MG)} mg)" if floor is not None and np.isfinite(floor) \
        else ""
    return f"{g_error_label(st)}: before {b}, after {num(after * MG)} mg{fl}"
