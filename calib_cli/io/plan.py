"""Experiment plans (TOML, CONTRACT.md section 3): load, validate, convert to SI.

Unit suffixes in plans (_deg, _dps, _m, _s, _hz) are converted here, at the
edge; everything after this module is SI (rad, rad/s, m, s).
"""

from __future__ import annotations

import tomllib
from pathlib import Path

import numpy as np

from calib_cli.errors import InputError
from calib_cli.geometry import Site
from calib_cli.plan import KINDS, Plan, PlanSegment, plan_layout, same_layout  # noqa: F401  (base layer)

D2R = np.pi / 180.0

def _is_num(v) -> bool:
    return isinstance(v, (int, float)) and not isinstance(v, bool)


def _num_vec(value, n, where, path):
    # a number is a number: not a bool (true is no 1.0), not a string ("90")
    if not isinstance(value, list) or not all(_is_num(x) for x in value):
        raise InputError(f"{where} must be {n} numbers, got {value!r}", path)
    arr = np.asarray(value, dtype=float)
    if arr.shape != (n,) or not np.all(np.isfinite(arr)):
        raise InputError(f"{where} must be {n} finite numbers, got {value!r}", path)
    return arr


# the types of the plan keys calib reads (issue 37): "num" a finite number (not a
# bool, not a string), "vec3" three of them, "str" text, "bool" true/false,
# "sign" a list of +1/-1 per axis; keys not listed are checked where they are read
_TYPES = {
    "": {"name": "str", "kind": "str", "protocol": "str", "description": "str",
         "sample_rate_hz": "num", "transition_s": "num", "temperature_c": "num",
         "sample_kind": "str", "unit_tau_s": "num", "chamber_ramp_dpm": "num",
         "chamber_soak_tol_degC": "num", "chamber_soak_s": "num",
         "chamber_soak_timeout_s": "num", "site": "table", "unit": "table", "rimu": "table",
         "segment": "list"},
    "site": {"latitude_deg": "num", "height_m": "num", "g": "num", "longitude_deg": "num",
             "name": "str", "allow_any_g": "bool"},
    "unit": {"serial": "str", "model": "str", "name": "str", "profile": "str",
             "accel_range_g": "num", "gyro_range_dps": "num", "accel_axis_sign": "sign",
             "gyro_axis_sign": "sign"},
    "rimu": {"profile": "str"},
    "segment": {"label": "str", "attitude_deg": "vec3", "attitude_sigma_deg": "num",
                "table_axis_enu": "vec3", "table_rate_dps": "num", "lever_arm_m": "vec3",
                "duration_s": "num", "rotation_axis_body": "vec3", "rotation_angle_deg": "num",
                "repeat": "str", "rate_shape": "str", "rate_jerk_dps3": "num",
                "transition_s": "num", "chamber_temp_degC": "num", "chamber_soak": "bool",
                "chamber_ramp_dpm": "num", "chamber_soak_tol_degC": "num",
                "chamber_soak_s": "num", "chamber_soak_timeout_s": "num", "sample_kind": "str",
                "sim_attitude_deg": "vec3", "sim_table_axis_enu": "vec3",
                "sim_lever_arm_m": "vec3"},
}
_WORDS = {"num": "a finite number", "vec3": "three finite numbers", "str": "text",
          "bool": "true or false", "table": "a table", "list": "a list of [[segment]] tables",
          "sign": "a list of 1 and -1, one per axis"}


def _type_ok(t: str, v) -> bool:
    if t == "num":
        return _is_num(v) and np.isfinite(v)
    if t == "vec3":
        return isinstance(v, list) and len(v) == 3 and all(_is_num(x) and np.isfinite(x)
                                                           for x in v)
    if t == "sign":
        return isinstance(v, list) and len(v) >= 1 and all(_is_num(x) and x in (1, -1)
                                                           for x in v)
    return isinstance(v, {"str": str, "bool": bool, "table": dict, "list": list}[t])


def _no_nul(v, where: str, path: str) -> None:
    """No NUL character in any text of the plan (HDF5 cannot store it)."""
    if isinstance(v, str):
        if "\x00" in v:
            raise InputError(f"{where} holds a NUL character (\\u0000); calib stores plan text "
                             "in HDF5, which cannot hold it", path)
    elif isinstance(v, dict):
        for k, x in v.items():
            _no_nul(k, f"the key {where + '.' if where else ''}{k!r}", path)
            _no_nul(x, f"{where + '.' if where else ''}{k}", path)
    elif isinstance(v, list):
        for i, x in enumerate(v):
            _no_nul(x, f"{where}[{i}]", path)


def check_plan_types(raw: dict, path: str) -> None:
    """Every key calib reads of its type (_TYPES), no NUL anywhere (issue 37)."""
    _no_nul(raw, "", path)

    def table(t: dict, known: dict, where: str):
        for k, ty in known.items():
            if k in t and not _type_ok(ty, t[k]):
                raise InputError(f"{where}{k} must be {_WORDS[ty]}, got {t[k]!r}", path)

    table(raw, _TYPES[""], "")
    for name in ("site", "unit", "rimu"):
        if isinstance(raw.get(name), dict):
            table(raw[name], _TYPES[name], f"{name}.")
    for i, seg in enumerate(raw.get("segment") or []):
        if not isinstance(seg, dict):
            raise InputError(f"segment {i + 1} is not a table", path)
        table(seg, _TYPES["segment"], f"segment {i + 1}: ")


def _num(value, where, path, positive=False):
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not np.isfinite(value):
        raise InputError(f"{where} must be a number, got {value!r}", path)
    if positive and value <= 0:
        raise InputError(f"{where} must be positive, got {value!r}", path)
    return float(value)


def _unit_axis(value, where, path):
    a = _num_vec(value, 3, where, path)
    n = np.linalg.norm(a)
    if n < 1e-9:
        raise InputError(f"{where} must not be the zero vector", path)
    return a / n


def _segment(i: int, raw: dict, path: str) -> PlanSegment:
    if not isinstance(raw, dict):
        raise InputError(f"segment {i + 1} is not a table", path)
    label = raw.get("label", f"segment-{i + 1}")
    if not isinstance(label, str) or not label:
        raise InputError(f"segment {i + 1}: label must be a non-empty string", path)
    where = f"segment {i + 1} ({label!r})"
    seg = {"label": label, "extra": dict(raw)}
    if "attitude_deg" in raw:
        seg["attitude"] = _num_vec(raw["attitude_deg"], 3, f"{where}: attitude_deg", path) * D2R
    if "attitude_sigma_deg" in raw:
        seg["attitude_sigma"] = _num(raw["attitude_sigma_deg"], f"{where}: attitude_sigma_deg",
                                     path) * D2R
    if "table_axis_enu" in raw:
        seg["table_axis_enu"] = _unit_axis(raw["table_axis_enu"], f"{where}: table_axis_enu", path)
    if "table_rate_dps" in raw:
        seg["table_rate"] = _num(raw["table_rate_dps"], f"{where}: table_rate_dps", path) * D2R
    if "lever_arm_m" in raw:
        seg["lever_arm"] = _num_vec(raw["lever_arm_m"], 3, f"{where}: lever_arm_m", path)
    if "duration_s" in raw:
        seg["duration"] = _num(raw["duration_s"], f"{where}: duration_s", path, positive=True)
    if "rotation_angle_deg" in raw:
        seg["rotation_angle"] = _num(raw["rotation_angle_deg"], f"{where}: rotation_angle_deg",
                                     path) * D2R
        if "rotation_axis_body" not in raw:
            raise InputError(f"{where}: rotation_angle_deg needs rotation_axis_body", path)
    if "rotation_axis_body" in raw:
        seg["rotation_axis_body"] = _unit_axis(raw["rotation_axis_body"],
                                               f"{where}: rotation_axis_body", path)
    if "repeat" in raw:
        if raw["repeat"] != "auto":
            raise InputError(f"{where}: repeat must be \"auto\", got {raw['repeat']!r}", path)
        seg["repeat_auto"] = True
    return PlanSegment(**seg)


def parse_plan(text: str, path: str = "<plan>") -> Plan:
    """Parse and validate plan TOML text. Raises InputError naming ``path``."""
    try:
        raw = tomllib.loads(text)
    except tomllib.TOMLDecodeError as exc:
        raise InputError(f"not valid TOML: {exc}", path) from None
    except RecursionError:
        raise InputError("not valid TOML: nested too deeply", path) from None
    from calib_cli.io.schema import check_plan_values  # issue 15: range checks

    check_plan_types(raw, path)
    check_plan_values(raw, path)
    kind = raw.get("kind")
    if kind not in KINDS:
        raise InputError(f"unknown plan kind {kind!r}; expected one of {', '.join(KINDS)}", path)
    site_raw = raw.get("site", {})
    if not isinstance(site_raw, dict):
        raise InputError("[site] must be a table", path)
    lat = _num(site_raw.get("latitude_deg", 0.0), "site.latitude_deg", path)
    if abs(lat) > 90:
        raise InputError(f"site.latitude_deg must lie in [-90, 90], got {lat}", path)
    height = _num(site_raw.get("height_m", 0.0), "site.height_m", path)
    if not -1e3 <= height <= 1e4:  # where a bench stands (normal gravity overflowed at 1e300)
        raise InputError(f"site.height_m must lie in [-1000, 10000] m, got {height:g}", path)
    g = site_raw.get("g")
    if g is not None:
        g = _num(g, "site.g", path, positive=True)
    site = Site(latitude=lat * D2R, height=height, g=g)
    unit = raw.get("unit", {})
    serial = unit.get("serial") if isinstance(unit, dict) else None
    segs_raw = raw.get("segment")
    if not isinstance(segs_raw, list) or not segs_raw:
        raise InputError("plan has no [[segment]] entries", path)
    segments = tuple(_segment(i, s, path) for i, s in enumerate(segs_raw))
    # labels may repeat (a plan may revisit a position): segments are told apart by index
    if sum(s.repeat_auto for s in segments) > 1:
        raise InputError("at most one segment may have repeat = \"auto\"", path)
    el0 = az0 = None
    if kind == "rimu":
        el0, az0 = _rimu_geometry(raw.get("rimu"), path)
    known = {"name", "kind", "protocol", "site", "unit", "segment", "rimu"}
    return Plan(name=str(raw.get("name", Path(path).stem)), kind=kind, site=site, serial=serial,
                segments=segments, text=text, protocol=raw.get("protocol"),
                rimu_el0=el0, rimu_az0=az0,
                extra={k: v for k, v in raw.items() if k not in known}, path=path)


def _rimu_geometry(table, path):
    if not isinstance(table, dict):
        raise InputError("a plan of kind \"rimu\" needs a [rimu] table (el0_deg, az0_deg "
                         "or profile)", path)
    if "profile" in table and "el0_deg" not in table:
        from calib_cli.io.profiles import load_rimu_profile

        table = load_rimu_profile(table["profile"], path)
    el = table.get("el0_deg")
    az = table.get("az0_deg")
    if not isinstance(el, list) or not isinstance(az, list) or len(el) != len(az) or len(el) < 1:
        raise InputError("[rimu] needs el0_deg and az0_deg lists of equal length", path)
    el = _num_vec(el, len(el), "rimu.el0_deg", path)
    az = _num_vec(az, len(az), "rimu.az0_deg", path)
    # modulo 360, elevation into [-180, 180) (289.4692 deg is -70.5308 deg)
    el = (el + 180.0) % 360.0 - 180.0
    return el * D2R, (az % 360.0) * D2R


def load_plan(path) -> Plan:
    """Load a plan file; any problem is an InputError naming the file."""
    p = str(path)
    try:
        text = Path(path).read_text(encoding="utf-8")
    except FileNotFoundError:
        raise InputError("no such file", p) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"cannot read: {exc}", p) from None
    from calib_cli.io.schema import check_plan_keys  # issue 15: typos are exit 3

    try:
        check_plan_keys(tomllib.loads(text), p)
    except (tomllib.TOMLDecodeError, RecursionError):
        pass  # parse_plan says what is wrong
    return parse_plan(text, p)
