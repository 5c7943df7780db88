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

def _num_vec(value, n, where, path):
    try:
        arr = np.asarray(value, dtype=float)
    except (TypeError, ValueError):
        raise InputError(f"{where} must be {n} numbers, got {value!r}", path) from None
    if arr.shape != (n,) or not np.all(np.isfinite(arr)):
        raise InputError(f"{where} must be {n} finite numbers, got {value!r}", path)
    return arr


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
    g = site_raw.get("g")
    if g is not None:
        g = _num(g, "site.g", path, positive=True)
    site = Site(latitude=lat * D2R, height=height, g=g)
    unit = raw.get("unit", {})
    serial = unit.get("serial") if isinstance(unit, dict) else None
    if serial is not None:
        serial = str(serial)
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
