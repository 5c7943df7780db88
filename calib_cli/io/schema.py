"""One registry of the keys of the files users write (issue 15, CONTRACT.md s. 7).

Plans and truth files allow extra keys (CONTRACT.md section 3), so an
unknown key is checked against the known keys of the same table:

- a key within Damerau-Levenshtein distance 1 (known keys of at most 5
  characters) or 2 (longer known keys) of a known key, compared without
  case, is a typo: exit 3 naming the file, the key and the known key
  ("did you mean attitude_deg?");
- keys starting ``x_`` are never checked (the user's own annotations);
- any other unknown key is listed in one warning line on stderr.

The project's own formats (tolerance, pipeline, device and geometry
profiles) are strict: ``strict_keys`` refuses any unknown key with the
closest known name. Later work extends the registry here, in one place.
"""

from __future__ import annotations

from calib_cli.errors import InputError

# -- plans (CONTRACT.md section 3; simulate's keys: docs/simulate.md) -------
PLAN_TOP = {"name", "kind", "protocol", "description", "site", "unit", "segment", "rimu",
            "sample_rate_hz", "transition_s", "temperature_profile", "temperature_c",
            "sim_table_rate_error", "sim_table_wobble_dps", "sim_table_wobble_hz", "sim_grade",
            "sim_proof_mass_sigma_m", "sim_oversample", "sample_kind",
            "sim_table_encoder_counts", "sim_table_encoder_opr_deg",
            "sim_table_encoder_opr_phase_deg", "sim_table_rate_scale_error", "generator",
            # climatic chamber (issue 21, docs/thermal.md): ramp-rate limit and soak rule
            # (record), the unit's thermal time constant (simulate)
            "chamber_ramp_dpm", "unit_tau_s", "chamber_soak_tol_degC", "chamber_soak_s",
            "chamber_soak_timeout_s",
            # parameters in force for `simulate --out LOG.ulg|.bin` (docs/simulate.md)
            "autopilot"}
CHAMBER_KEYS = ("chamber_ramp_dpm", "unit_tau_s", "chamber_soak_tol_degC", "chamber_soak_s",
                "chamber_soak_timeout_s")
PLAN_SITE = {"latitude_deg", "height_m", "g", "longitude_deg", "name", "allow_any_g"}
PLAN_UNIT = {"serial", "model", "name", "profile", "accel_range_g", "gyro_range_dps",
             "accel_axis_sign", "gyro_axis_sign"}
PLAN_RIMU = {"el0_deg", "az0_deg", "profile"}
PLAN_SEGMENT = {"label", "attitude_deg", "attitude_sigma_deg", "table_axis_enu",
                "table_rate_dps", "lever_arm_m", "duration_s", "rotation_axis_body",
                "rotation_angle_deg", "repeat", "rate_profile", "rate_shape", "rate_jerk_dps3",
                "rate_oscillation", "transition_s",
                "chamber_temp_degC", "chamber_soak", "chamber_ramp_dpm", "chamber_soak_tol_degC",
                "chamber_soak_s", "chamber_soak_timeout_s", "sample_kind", "sim_attitude_deg", "sim_repeat",
                "sim_table_axis_enu", "sim_lever_arm_m"}
PLAN_TABLES = {"": PLAN_TOP, "site": PLAN_SITE, "unit": PLAN_UNIT, "rimu": PLAN_RIMU,
               "segment": PLAN_SEGMENT}

# -- truth files (docs/simulate.md) -----------------------------------------
TRUTH_TOP = {"params", "noise", "output", "options"}
TRUTH_NOISE = {f"{s}_{k}" for s in ("accel", "gyro") for k in ("white", "white_density")}
TRUTH_OUTPUT = {"units", "quantize"}
TRUTH_OPTIONS = {"tangential"}


def damerau_levenshtein(a: str, b: str, limit: int = 3) -> int:
    """Optimal-string-alignment distance (adjacent transpositions count 1);
    returns ``limit`` or more as soon as the distance is known to exceed it."""
    if abs(len(a) - len(b)) >= limit:
        return limit
    prev2 = None
    prev = list(range(len(b) + 1))
    for i in range(1, len(a) + 1):
        cur = [i] + [0] * len(b)
        for j in range(1, len(b) + 1):
            cost = 0 if a[i - 1] == b[j - 1] else 1
            cur[j] = min(prev[j] + 1, cur[j - 1] + 1, prev[j - 1] + cost)
            if (prev2 is not None and i > 1 and j > 1 and a[i - 1] == b[j - 2]
                    and a[i - 2] == b[j - 1]):
                cur[j] = min(cur[j], prev2[j - 2] + 1)
        if min(cur) >= limit:
            return limit
        prev2, prev = prev, cur
    return prev[-1]


def near_miss(key: str, known) -> str | None:
    """The known key that ``key`` is a typo of, or None."""
    k = key.lower()
    best, best_d = None, 99
    for cand in known:
        c = cand.lower()
        if c == k:
            return cand if cand != key else None  # differs only by case: a typo
        allowed = 1 if len(cand) <= 5 else 2
        d = damerau_levenshtein(k, c, allowed + 1)
        if d <= allowed and d < best_d:
            best, best_d = cand, d
    return best


def closest(key: str, known) -> str | None:
    """The closest known key (for the strict formats' messages)."""
    best, best_d = None, 10**9
    for cand in sorted(known):
        d = damerau_levenshtein(key.lower(), cand.lower(), 10**6)
        if d < best_d:
            best, best_d = cand, d
    return best


def check_table(table: dict, known, path: str, where: str, unknown: list) -> None:
    """Typo check of one table's keys; unknown keys are appended to ``unknown``."""
    for key in table:
        if not isinstance(key, str) or key in known or key.startswith("x_"):
            continue
        typo = near_miss(key, known)
        if typo is not None:
            raise InputError(f"{where}unknown key {key!r}: did you mean {typo}?", path)
        unknown.append(f"{where}{key}")


def warn_unknown(unknown: list, path: str) -> None:
    if unknown:
        from calib_cli.errors import warn

        shown = ", ".join(unknown[:8]) + (f" and {len(unknown) - 8} more" if len(unknown) > 8
                                          else "")
        warn(f"{path}: keys not used by calib: {shown} "
             "(prefix your own keys with x_ to silence this)")


def check_plan_keys(raw: dict, path: str) -> None:
    """Every table of a plan against the registry (linear in the segments)."""
    unknown: list = []
    check_table(raw, PLAN_TOP, path, "", unknown)
    for name in ("site", "unit", "rimu"):
        t = raw.get(name)
        if isinstance(t, dict):
            check_table(t, PLAN_TABLES[name], path, f"[{name}] ", unknown)
    segs = raw.get("segment")
    if isinstance(segs, list):
        seen: dict[str, int] = {}
        for i, s in enumerate(segs):
            if isinstance(s, dict):
                for key in s:
                    if key in PLAN_SEGMENT or not isinstance(key, str) or key.startswith("x_"):
                        continue
                    typo = near_miss(key, PLAN_SEGMENT)
                    if typo is not None:
                        raise InputError(f"segment {i + 1}: unknown key {key!r}: did you mean "
                                         f"{typo}?", path)
                    seen[key] = seen.get(key, 0) + 1
        unknown += [f"segment.{k}" for k in seen]
    warn_unknown(unknown, path)


def check_plan_values(raw: dict, path: str) -> None:
    """Range checks the physics bounds (plan-wide keys; segments in plan.py)."""
    import math

    def num(v):
        return isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v)

    rate = raw.get("sample_rate_hz")
    if rate is not None and (not num(rate) or not 0 < rate <= 1e6):
        raise InputError(f"sample_rate_hz must be a number in (0, 1e6] Hz, got {rate!r}", path)
    tr = raw.get("transition_s")
    if tr is not None and (not num(tr) or not 0 <= tr <= 1e5):
        raise InputError(f"transition_s must be a number in [0, 1e5] s, got {tr!r}", path)
    for key in CHAMBER_KEYS:  # issue 21: > 0 where given, top level or per segment
        for i, t in [(None, raw)] + list(enumerate(raw.get("segment") or [])):
            v = t.get(key) if isinstance(t, dict) else None
            if v is not None and (not num(v) or not v > 0):
                where = "" if i is None else f"segment {i + 1}: "
                raise InputError(f"{where}{key} must be a number > 0, got {v!r}", path)
    for i, t in enumerate(raw.get("segment") or []):
        v = t.get("chamber_soak") if isinstance(t, dict) else None
        if v is not None and not isinstance(v, bool):
            raise InputError(f"segment {i + 1}: chamber_soak must be true or false, got {v!r}",
                             path)
        v = t.get("chamber_temp_degC") if isinstance(t, dict) else None
        if v is not None and (not num(v) or not -273.15 < v <= 1000):
            raise InputError(f"segment {i + 1}: chamber_temp_degC must be a temperature in "
                             f"degC, got {v!r}", path)
    site = raw.get("site")
    if isinstance(site, dict) and site.get("g") is not None and site.get("allow_any_g") is not True:
        g = site["g"]
        lo, hi = 9.7, 9.9
        if not num(g) or not lo <= g <= hi:
            raise InputError(f"site.g must lie in {lo}-{hi} m/s^2 (Earth's gravity), got {g!r}; "
                             "leave it out to use normal gravity at the site (or set "
                             "allow_any_g = true in [site])", path)
    segs = raw.get("segment")
    if isinstance(segs, list):
        total = 0.0
        for i, s in enumerate(segs):
            if not isinstance(s, dict):
                continue
            for key in ("attitude_deg", "table_axis_enu", "lever_arm_m", "rotation_axis_body",
                        "sim_attitude_deg"):
                v = s.get(key)
                if isinstance(v, list) and any(isinstance(x, bool) for x in v):
                    raise InputError(f"segment {i + 1}: {key} must be numbers, got {v!r}", path)
            for key in ("attitude_sigma_deg",):
                v = s.get(key)
                if v is not None and num(v) and v < 0:
                    raise InputError(f"segment {i + 1}: {key} must be >= 0, got {v!r}", path)
            v = s.get("transition_s")
            if v is not None and (not num(v) or not 0 <= v <= 1e5):
                raise InputError(f"segment {i + 1}: transition_s must be a number in [0, 1e5] "
                                 f"s, got {v!r}", path)
            d = s.get("duration_s")
            if d is not None and num(d):
                if not 0 < d <= 1e6:
                    raise InputError(f"segment {i + 1}: duration_s must lie in (0, 1e6] s, got "
                                     f"{d!r}", path)
                total += d
        if num(rate) and total * rate > 2e9:
            raise InputError(f"the plan asks for {total * rate:.3g} samples in all (more than "
                             "2e9): shorten the durations or lower sample_rate_hz", path)


def check_truth_keys(raw: dict, path: str) -> None:
    unknown: list = []
    check_table(raw, TRUTH_TOP, path, "", unknown)
    for name, known in (("noise", TRUTH_NOISE), ("output", TRUTH_OUTPUT),
                        ("options", TRUTH_OPTIONS)):
        t = raw.get(name)
        if isinstance(t, dict):
            bases = set(known)
            if name == "noise":  # unit suffixes are allowed on noise keys
                from calib_cli.units import split_suffix

                t = {split_suffix(k)[0]: v for k, v in t.items()}
            check_table(t, bases, path, f"[{name}] ", unknown)
    warn_unknown(unknown, path)


def strict_keys(table: dict, known, path: str, where: str = "") -> None:
    """The project's own formats: any unknown key is exit 3 naming the closest."""
    for key in table:
        if key not in known:
            near = closest(str(key), known)
            hint = f"; did you mean {near}?" if near else ""
            raise InputError(f"{where}unknown key {key!r}{hint} (known: "
                             f"{', '.join(sorted(known))})", path)


def known_param_keys() -> set[str]:
    """Every parameter name some method reports (for the tolerance files)."""
    import numpy as np

    from calib_cli.model.effects import Layout
    from calib_cli.model.truth import key_owner

    keys = set(key_owner(Layout(), {}))
    keys |= set(key_owner(Layout(n=6, el0=np.zeros(6), az0=np.zeros(6)), {}))
    return keys | {"attitude"}


def param_shape(key: str):
    """The shape of a triad parameter (None where it depends on the unit)."""
    if key in ("accel_K", "gyro_K", "gyro_D", "proof_mass_offsets"):
        return (3, 3)
    if key in ("accel_bias", "gyro_bias", "attitude"):
        return (3,)
    return None


# -- device and geometry profiles (docs/acquisition.md): strict ----------------
# IMU profiles: acquire/profile.py (IMU_KEYS, typed values)
TABLE_PROFILE = {
    "": {"name", "description", "kind", "terminator", "timeout_s", "speed_dps", "transport",
         "commands", "responses", "replies"},
    "transport": {"baudrate", "bytesize", "parity", "stopbits", "timeout_s"},
    "responses": {"ack", "angle", "settled", "status"},
    "replies": {"ack", "angle", "status"},
}
RIMU_PROFILE = {"": {"name", "description", "el0_deg", "az0_deg"}}
TEMPLATE_FIELDS = {"move": {"roll_deg", "pitch_deg", "yaw_deg"}, "rate": {"rate_dps"},
                   "stop": set(), "query_angle": set(), "query_status": set()}
PARITIES = ("N", "E", "O", "M", "S")


def check_profile_keys(raw: dict, registry: dict, path: str) -> None:
    """Strict: every table of a device/geometry profile against the registry."""
    strict_keys(raw, registry[""], path)
    for name, known in registry.items():
        if not name:
            continue
        v = raw.get(name)
        items = v if isinstance(v, list) else [v]
        for j, t in enumerate(items):
            if not isinstance(t, dict):
                continue
            where = f"[{name}] " if not isinstance(v, list) else f"{name} {j + 1}: "
            strict_keys(t, known, path, where)
            if name == "message":
                for k, f in enumerate(t.get("field", []) or []):
                    if isinstance(f, dict):
                        strict_keys(f, registry["field"], path, f"{where}field {k + 1}: ")
                if isinstance(t.get("checksum"), dict):
                    strict_keys(t["checksum"], registry["checksum"], path, f"{where}checksum: ")


def check_transport(tr: dict, path: str) -> None:
    if not isinstance(tr, dict):
        raise InputError("[transport] must be a table", path)
    for key in ("baudrate", "bitrate", "bytesize"):
        v = tr.get(key)
        if v is not None and (isinstance(v, bool) or not isinstance(v, int) or v <= 0):
            raise InputError(f"transport.{key} must be a positive integer, got {v!r}", path)
    p = tr.get("parity")
    if p is not None and p not in PARITIES:
        raise InputError(f"transport.parity must be one of {', '.join(PARITIES)}, got {p!r}",
                         path)
    s = tr.get("stopbits")
    if s is not None and s not in (1, 1.5, 2):
        raise InputError(f"transport.stopbits must be 1, 1.5 or 2, got {s!r}", path)


def check_table_templates(commands: dict, path: str) -> None:
    """Every command template uses only the fields calib fills in."""
    import string

    for name, tpl in commands.items():
        if not isinstance(tpl, str):
            raise InputError(f"commands.{name} must be a string", path)
        allowed = TEMPLATE_FIELDS.get(name, set())
        try:
            fields = [f for _, f, _, _ in string.Formatter().parse(tpl) if f is not None]
        except ValueError as exc:
            raise InputError(f"commands.{name}: bad template {tpl!r}: {exc}", path) from None
        for f in fields:
            base = f.split(".")[0].split("[")[0].split("!")[0]
            if base not in allowed:
                near = closest(base, allowed) if allowed else None
                hint = f"; did you mean {near}?" if near else ""
                raise InputError(f"commands.{name}: unknown template field {{{f}}}{hint} "
                                 f"(known: {', '.join(sorted(allowed)) or 'none'})", path)
