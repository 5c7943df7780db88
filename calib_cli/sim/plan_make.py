"""Plan generators for ``calib plan make`` (docs/plan.md).

Each generator returns the plan as a dict in the TOML layout of CONTRACT.md
section 3 (simulation keys as in docs/simulate.md) with a ``[generator]``
table holding the generator's name and parameters, so that ``plan optimize``
can make the same family again with other parameters. ``to_toml`` writes it.
Pure: no files.
"""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from calib_cli.errors import InputError
from calib_cli.model.frames import attitude_to_rotation

FACES = [("x-up", [0.0, -90.0, 0.0]), ("x-down", [0.0, 90.0, 0.0]),
         ("y-up", [90.0, 0.0, 0.0]), ("y-down", [-90.0, 0.0, 0.0]),
         ("z-up", [0.0, 0.0, 0.0]), ("z-down", [180.0, 0.0, 0.0])]
STATIC_COUNTS = (6, 12, 18, 24)
EW_TOL_DEG = 2.0  # as methods/align.EW_TOL
SITE = {"latitude_deg": 50.45, "height_m": 180.0}


def _r(x, nd=6):
    return [round(float(v), nd) + 0.0 for v in np.ravel(x)]


def attitude_up(u) -> list:
    """[roll, pitch, 0] deg that puts body direction u up."""
    u = np.asarray(u, float) / np.linalg.norm(u)
    return _r([np.degrees(np.arctan2(u[1], u[2])),
               np.degrees(np.arctan2(-u[0], np.hypot(u[1], u[2]))), 0.0], 4)


def fibonacci(n: int) -> np.ndarray:
    """n directions spread evenly over the sphere (a Fibonacci lattice, turned
    so that no three fall on a great circle through the body axes)."""
    k = np.arange(n) + 0.5
    z = 1 - 2 * k / n
    phi = np.pi * (1 + 5 ** 0.5) * k
    r = np.sqrt(1 - z * z)
    v = np.column_stack([r * np.cos(phi), r * np.sin(phi), z])
    return Rotation.from_rotvec([0.31, -0.47, 0.23]).apply(v)


def _vector_directions(n: int):
    """Faces first, then the 8 corners, then the 12 edges."""
    out = [(lab, att) for lab, att in FACES]
    corners = [np.array(c, float) for c in np.ndindex(2, 2, 2)]
    for c in corners:
        d = 2 * c - 1
        out.append(("corner" + "".join("+" if x > 0 else "-" for x in d), attitude_up(d)))
    for i in range(3):
        for sa in (1, -1):
            for sb in (1, -1):
                d = np.zeros(3)
                d[i] = sa
                d[(i + 1) % 3] = sb
                out.append((f"edge-{i}{'+' if sa > 0 else '-'}{'+' if sb > 0 else '-'}",
                            attitude_up(d)))
    return out[:n]


def _base(name: str, kind: str, rate: float, generator: dict, protocol=None) -> dict:
    d = {"name": name, "kind": kind}
    if protocol:
        d["protocol"] = protocol
    d.update({"sample_rate_hz": float(rate), "transition_s": 4.0, "site": dict(SITE),
              "generator": generator, "segment": []})
    return d


def static_plan(n: int = 12, method: str = "vector", duration: float = 10.0,
                rate: float = 100.0) -> dict:
    """N-position static plan: known attitudes (vector: faces, corners, edges) or
    unknown ones spread over the sphere (scalar, true attitudes as
    sim_attitude_deg)."""
    if n not in STATIC_COUNTS:
        raise InputError(f"--positions must be one of {', '.join(map(str, STATIC_COUNTS))}")
    if method == "scalar" and n < 9:
        raise InputError("the scalar method needs >= 9 positions (use --positions 12 or more)")
    gen = {"method": "static", "positions": n, "fit": method, "duration_s": duration,
           "sample_rate_hz": rate}
    d = _base(f"static-{n}-{method}", "static", rate, gen, "multi-position")
    if method == "vector":
        for lab, att in _vector_directions(n):
            d["segment"].append({"label": lab, "attitude_deg": _r(att, 4),
                                 "duration_s": float(duration)})
    else:
        for i, u in enumerate(fibonacci(n)):
            d["segment"].append({"label": f"position-{i + 1}", "sim_attitude_deg": attitude_up(u),
                                 "duration_s": float(duration)})
    return d


def ferraris_plan(duration: float = 10.0, turn_duration: float = 10.0,
                  rate: float = 100.0) -> dict:
    """Ferraris et al.: six positions (each axis up and down) and three 360 deg
    turns, each about an axis while it points up (between its up and down
    positions)."""
    gen = {"method": "ferraris", "duration_s": duration, "turn_duration_s": turn_duration,
           "sample_rate_hz": rate}
    d = _base("ferraris", "static", rate, gen, "ferraris")
    faces = dict(FACES)
    for i, ax in enumerate("xyz"):
        up = faces[f"{ax}-up"]
        d["segment"].append({"label": f"{ax}-up", "attitude_deg": up, "duration_s": duration})
        d["segment"].append({"label": f"{ax}-turn", "attitude_deg": up,
                             "rotation_axis_body": _r(np.eye(3)[i]), "rotation_angle_deg": 360.0,
                             "duration_s": turn_duration})
        d["segment"].append({"label": f"{ax}-down", "attitude_deg": faces[f"{ax}-down"],
                             "duration_s": duration})
    return d


def align_warning(axis, angle_deg: float, start_deg, latitude_deg: float) -> str | None:
    """The observability warning of a two-position plan (docs/align.md)."""
    ang = abs(float(angle_deg)) % 360.0
    if min(ang, 360.0 - ang) < 5.0:
        return (f"a turn of {angle_deg:g} deg is too near 0 or 360 deg: nothing is "
                "observable")
    a_enu = attitude_to_rotation(np.radians(start_deg)).apply(np.asarray(axis, float)
                                                              / np.linalg.norm(axis))
    off = np.degrees(np.arccos(min(abs(a_enu[0]), 1.0)))
    if off <= EW_TOL_DEG:
        return ("the turn axis is horizontal East-West: the biases along it, the heading and "
                "the tilt about North are unobservable; turn about the vertical or a "
                "North axis")
    return None


def align_plan(axis=(0.0, 0.0, 1.0), angle: float = 120.0, start=(0.8, -0.5, 30.0),
               duration: float = 300.0, rate: float = 50.0,
               latitude: float = 32.0) -> tuple[dict, str | None]:
    """Two-position alignment: position 1 at the (true) start attitude, a turn of
    ``angle`` deg about body ``axis``, position 2. Returns (plan, warning)."""
    axis = np.asarray(axis, float)
    if axis.shape != (3,) or np.linalg.norm(axis) < 1e-9:
        raise InputError("--axis must be three numbers, not all zero")
    axis = axis / np.linalg.norm(axis)
    gen = {"method": "align", "axis": _r(axis), "angle_deg": float(angle),
           "start_deg": _r(start, 4), "duration_s": duration, "sample_rate_hz": rate}
    d = _base("align-two-position", "align", rate, gen, "two-position")
    d["site"]["latitude_deg"] = float(latitude)
    d["segment"] = [
        {"label": "position-1", "sim_attitude_deg": _r(start, 4), "duration_s": duration},
        {"label": "turn", "rotation_axis_body": _r(axis), "rotation_angle_deg": float(angle),
         "duration_s": 10.0},
        {"label": "position-2", "duration_s": duration}]
    return d, align_warning(axis, angle, start, latitude)


def rimu_plan(profile: str = "tetrahedron", duration: float = 10.0, table_rate: float = 10.0,
              rate: float = 100.0) -> dict:
    """Six-position test of a redundant unit: each reference axis up and down,
    the table turning about the vertical at ``table_rate`` deg/s (0: static)."""
    gen = {"method": "rimu", "profile": profile, "duration_s": duration,
           "table_rate_dps": table_rate, "sample_rate_hz": rate}
    d = _base("rimu-six-position", "rimu", rate, gen, "six-position-rotating")
    d["rimu"] = {"profile": profile}
    for lab, att in FACES:
        seg = {"label": lab, "attitude_deg": att, "duration_s": duration}
        if table_rate:
            seg.update({"table_axis_enu": [0.0, 0.0, 1.0], "table_rate_dps": float(table_rate)})
        d["segment"].append(seg)
    return d


def turntable_plan(tilted: bool = False, tilt_deg: float = 5.0, duration: float = 600.0,
                   tilted_duration: float = 300.0, max_rate: float = 200.0,
                   max_accel: float = 200.0, max_duration: float | None = None,
                   profile: str = "steps", rate: float = 100.0) -> dict:
    """Three axial cycles (x, y, z along the horizontal East table axis) and
    optionally six tilted ones, with a rate profile within the table's limits:
    max rate (deg/s), max angular acceleration (deg/s^2, sets the ramps) and a
    max total duration (s). profile: "steps" (holds at 0, +-max .. +-max/4,
    docs/simulate.md) or "smooth" (the same knots joined by smoothsteps)."""
    from calib_cli.sim.turntable_plans import TABLE_AXIS, cycle_attitudes

    if profile not in ("steps", "smooth"):
        raise InputError(f"--profile must be steps or smooth, got {profile!r}")
    if max_rate <= 0 or max_accel <= 0:
        raise InputError("--max-rate and --max-accel must be positive")
    cycles = cycle_attitudes(tilted, tilt_deg)
    durs = [duration if c < 3 else tilted_duration for c in range(len(cycles))]
    total = sum(durs) + 4.0 * (len(cycles) - 1)
    if max_duration is not None and total > max_duration:
        f = (max_duration - 4.0 * (len(cycles) - 1)) / sum(durs)
        if f * min(durs) < 60.0:
            raise InputError(f"--max-duration {max_duration:g} s leaves under 60 s per cycle")
        durs = [x * f for x in durs]
    # the largest step is +max -> -max; the smoothstep peaks at 1.5 x the straight ramp's
    ramp = 2.0 * max_rate / max_accel * (1.5 if profile == "smooth" else 1.0)
    gen = {"method": "turntable", "tilted": bool(tilted), "tilt_deg": tilt_deg,
           "duration_s": duration, "tilted_duration_s": tilted_duration,
           "max_rate_dps": max_rate, "max_accel_dps2": max_accel,
           "max_duration_s": max_duration, "profile": profile, "sample_rate_hz": rate}
    gen = {k: v for k, v in gen.items() if v is not None}
    d = _base("turntable-" + ("9" if tilted else "3") + "-cycle", "turntable", rate, gen,
              "rotating-table")
    for c, (label, att, _a) in enumerate(cycles):
        knots = _profile(durs[c], max_rate, ramp)
        seg = {"label": label, "attitude_deg": _r(att, 6), "table_axis_enu": _r(TABLE_AXIS),
               "rate_profile": knots, "duration_s": knots[-1][0]}
        if profile == "smooth":
            seg["rate_shape"] = "smooth"
        d["segment"].append(seg)
    return d


def _profile(duration: float, max_dps: float, ramp_s: float) -> list:
    from calib_cli.sim.turntable_plans import rate_profile

    hold = max(5.0, min(20.0, duration / 12.0))
    return rate_profile(duration, max_dps, ramp_s=ramp_s, hold_s=hold)


def thermal_plan(design: str = "soak", temps: int = 7, temp_range=(-40.0, 85.0),
                 soak: float | None = None, duration: float | None = None,
                 ramp_dpm: float | None = None, unit_tau: float | None = None,
                 positions: int = 6, cycles: str = "heat-cool",
                 rate: float = 10.0) -> tuple[dict, str | None]:
    """Thermal calibration in a climatic chamber (docs/thermal.md):

    - ``soak``: at ``temps`` (5..7) temperatures spread over ``temp_range``, a
      soak segment (the first position held ``soak`` s while the unit settles,
      default 1800) then the six positions (each axis up and down, ``duration``
      s each, default 60); the chamber moves at ``ramp_dpm`` (default 3);
    - ``ramp``: a soak at the low end, then the chamber ramps to the high end
      at ``ramp_dpm`` (default 1 degC/min) and, with ``cycles = "heat-cool"``,
      back (hysteresis, thermal lag) while the unit goes round ``positions``
      (3..6) positions, ``duration`` s each (default 120). Its ramp segments
      carry ``chamber_soak = false``: ``calib record`` sets the setpoint and
      records without waiting.

    ``unit_tau`` (s) is the unit's thermal time constant for ``simulate``
    (default 300 soak, 120 ramp). Returns (plan, warning)."""
    if design not in ("soak", "ramp"):
        raise InputError(f"--design must be soak or ramp, got {design!r}")
    lo, hi = (float(x) for x in temp_range)
    if not hi - lo >= 10.0:
        raise InputError("--temp-range must span at least 10 degC (LO,HI)")
    if cycles not in ("heat", "heat-cool"):
        raise InputError(f"--cycles must be heat or heat-cool, got {cycles!r}")
    faces = FACES
    warning = None
    if design == "soak":
        if not 5 <= temps <= 7:
            raise InputError("--temps must be 5, 6 or 7 (soak steps)")
        soak = 1800.0 if soak is None else float(soak)
        duration = 60.0 if duration is None else float(duration)
        ramp_dpm = 3.0 if ramp_dpm is None else float(ramp_dpm)
        unit_tau = 300.0 if unit_tau is None else float(unit_tau)
        if soak < 3 * unit_tau:
            warning = (f"a soak of {soak:g} s is under 3 time constants of the unit "
                       f"({unit_tau:g} s): the positions start before it has settled")
    else:
        if not 3 <= positions <= 6:
            raise InputError("--positions must be 3..6 for a ramp design")
        duration = 120.0 if duration is None else float(duration)
        ramp_dpm = 1.0 if ramp_dpm is None else float(ramp_dpm)
        unit_tau = 120.0 if unit_tau is None else float(unit_tau)
        soak = 6 * unit_tau if soak is None else float(soak)
        faces = FACES[:positions]
        if positions < 6:
            warning = (f"{positions} positions do not determine the full accel_K: fit with "
                       "--base CAL.h5 (a room-temperature calibration)")
    for name, v in (("--soak", soak), ("--duration", duration), ("--ramp-dpm", ramp_dpm),
                    ("--unit-tau", unit_tau), ("--rate", rate)):
        if not v > 0:
            raise InputError(f"{name} must be positive")
    gen = {"method": "thermal", "design": design, "temp_range_degC": [lo, hi],
           "soak_s": soak, "duration_s": duration, "ramp_dpm": ramp_dpm, "unit_tau_s": unit_tau,
           "sample_rate_hz": rate}
    if design == "soak":
        gen["temps"] = int(temps)
    else:
        gen.update(positions=int(positions), cycles=cycles)
    d = _base(f"thermal-{design}", "static", rate, gen, f"thermal-{design}")
    # the chamber keys (docs/plans.md): simulate's ramp and time constant, record's soak rule
    d = {**{k: v for k, v in d.items() if k not in ("site", "generator", "segment")},
         "chamber_ramp_dpm": ramp_dpm, "unit_tau_s": unit_tau,
         "chamber_soak_tol_degC": 0.1, "chamber_soak_s": round(min(600.0, 2 * unit_tau), 3),
         "chamber_soak_timeout_s": round(max(7200.0, 20 * unit_tau), 3),
         "site": d["site"], "generator": gen, "segment": []}
    seg = d["segment"]
    if design == "soak":
        for T in np.round(np.linspace(lo, hi, temps), 1):
            T = float(T) + 0.0
            tag = f"{T:+g}"
            seg.append({"label": f"soak{tag}", "attitude_deg": faces[0][1], "duration_s": soak,
                        "chamber_temp_degC": T})
            for lab, att in faces:
                seg.append({"label": f"{lab}@{tag}", "attitude_deg": att,
                            "duration_s": duration})
        return d, warning
    seg.append({"label": "soak", "attitude_deg": faces[0][1], "duration_s": soak,
                "chamber_temp_degC": lo})
    leg = (hi - lo) / ramp_dpm * 60.0 + 4 * unit_tau  # the ramp and the unit catching up
    n = int(np.ceil(leg / (duration + 4.0)))
    for c in (("heat",) if cycles == "heat" else ("heat", "cool")):
        target = hi if c == "heat" else lo
        for k in range(n):
            lab, att = faces[k % len(faces)]
            s = {"label": f"{lab}-{c}{k}", "attitude_deg": att, "duration_s": duration}
            if k == 0:
                s.update(chamber_temp_degC=target, chamber_soak=False)
            seg.append(s)
    return d, warning


def make(family: str, **kw) -> tuple[dict, str | None]:
    """Dispatch: (plan dict, warning or None)."""
    if family == "static":
        return static_plan(**kw), None
    if family == "ferraris":
        return ferraris_plan(**kw), None
    if family == "align":
        return align_plan(**kw)
    if family == "rimu":
        return rimu_plan(**kw), None
    if family == "turntable":
        return turntable_plan(**kw), None
    if family == "thermal":
        return thermal_plan(**kw)
    raise InputError(f"unknown plan family {family!r}")


# ---------------------------------------------------------------------------
# TOML


def _val(v) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, (int, np.integer)):
        return str(int(v))
    if isinstance(v, (float, np.floating)):
        return repr(float(v))
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"') + '"'
    if isinstance(v, (list, tuple, np.ndarray)):
        return "[" + ", ".join(_val(x) for x in v) + "]"
    raise TypeError(f"cannot write {type(v).__name__} to TOML")


def to_toml(d: dict, header: str = "") -> str:
    """TOML text of a plan dict: top-level keys, then tables, then [[segment]]s."""
    lines = [f"# {x}" for x in header.splitlines()] if header else []
    tables, arrays = {}, {}
    for k, v in d.items():
        if isinstance(v, dict):
            tables[k] = v
        elif isinstance(v, list) and v and isinstance(v[0], dict):
            arrays[k] = v
        else:
            lines.append(f"{k} = {_val(v)}")
    for k, t in tables.items():
        lines += ["", f"[{k}]"] + [f"{kk} = {_val(vv)}" for kk, vv in t.items()]
    for k, rows in arrays.items():
        for row in rows:
            lines += ["", f"[[{k}]]"] + [f"{kk} = {_val(vv)}" for kk, vv in row.items()]
    return "\n".join(lines) + "\n"
