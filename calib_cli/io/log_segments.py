"""What every log importer shares (CSV, text, bags, flight logs; streamed or in memory):
the block of samples a reader yields (``Chunk``), the declared units and their
conversion to SI, the time check, and the segments of a recording from a segment column
or from the detected static intervals and rotation cycles, matched to the plan
(docs/import.md). Below csvlog.py, textlog.py and stream_import.py, which all import it."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from calib_cli.data import Segment
from calib_cli.errors import InputError, num
from calib_cli.methods.cycle_detect import CycleDetection, detect_cycles, trim_intervals
from calib_cli.methods.static_detect import DetectionReport
from calib_cli.plan import Plan, PlanSegment

TIME_MAX = 1e12  # s (31,700 years): a time beyond this is no recording's (or not in seconds)
G0 = 9.80665
ACCEL_UNITS = {"count": None, "m/s^2": 1.0, "g": G0}
GYRO_UNITS = {"count": None, "rad/s": 1.0, "deg/s": np.pi / 180.0}


@dataclass
class Chunk:
    time: np.ndarray
    accel: np.ndarray
    gyro: np.ndarray | None = None
    opt: dict = field(default_factory=dict)  # temp, table_angle, table_rate -> (m,)
    segment: np.ndarray | None = None  # plan segment index per sample (int)


def convert_units(accel, gyro, accel_units: str, gyro_units: str, path: str = ""):
    """(accel, gyro, units dict): g -> m/s^2 and deg/s -> rad/s; counts kept."""
    if accel_units not in ACCEL_UNITS:
        raise InputError(f"unknown accelerometer unit {accel_units!r}; use one of "
                         f"{', '.join(ACCEL_UNITS)}", path)
    if gyro_units not in GYRO_UNITS:
        raise InputError(f"unknown gyro unit {gyro_units!r}; use one of "
                         f"{', '.join(GYRO_UNITS)}", path)
    fa, fg = ACCEL_UNITS[accel_units], GYRO_UNITS[gyro_units]
    units = {"accel": "count" if fa is None else "m/s^2",
             "gyro": "count" if fg is None else "rad/s"}
    accel = accel if fa in (None, 1.0) else accel * fa
    gyro = None if gyro is None else (gyro if fg in (None, 1.0) else gyro * fg)
    return accel, gyro, units


def check_time_range(t, path, unit_hint: str = "") -> None:
    """Exit 3 on a time value no recording has (|t| > TIME_MAX s): at 1e20 s
    the float steps are 16384 s and every rate and duration would be garbage."""
    t = np.asarray(t, dtype=float)
    if len(t) and not np.all(np.abs(t) <= TIME_MAX):
        v = t[np.flatnonzero(~(np.abs(t) <= TIME_MAX))[0]]
        raise InputError(f"time value {num(v)} s is beyond any recording (|t| <= "
                         f"{TIME_MAX:g} s){unit_hint}", path)


def raw_segment(ps: PlanSegment, plan_index: int, start: int, stop: int,
                 label: str | None = None) -> Segment:
    return Segment(label=label or ps.label, kind=ps.kind if not ps.repeat_auto else "static",
                   start=int(start), stop=int(stop), plan_index=plan_index,
                   attitude=ps.attitude, attitude_sigma=ps.attitude_sigma,
                   table_axis_enu=ps.table_axis_enu, table_rate=ps.table_rate,
                   lever_arm=ps.lever_arm, rotation_axis_body=ps.rotation_axis_body,
                   rotation_angle=ps.rotation_angle)


def segments_from_column(seg: np.ndarray, plan: Plan, path: str) -> list[Segment]:
    """Contiguous runs of the same segment index become segments."""
    n_plan = len(plan.segments)
    bad = (seg < -1) | (seg >= n_plan)
    if bad.any():
        raise InputError(f"segment index {num(seg[bad][0])} out of range: the plan has "
                         f"{n_plan} segments (use -1 between segments)", path)
    out, counts = [], {}
    d = np.flatnonzero(np.diff(seg)) + 1
    starts = np.concatenate([[0], d])
    stops = np.concatenate([d, [len(seg)]])
    for a, b in zip(starts, stops):
        k = int(seg[a])
        if k < 0:
            continue
        ps = plan.segments[k]
        counts[k] = counts.get(k, 0) + 1
        label = plan.visit_labels[k]
        if ps.repeat_auto or counts[k] > 1:
            label = f"{label}#{counts[k]}"
        out.append(raw_segment(ps, k, a, b, label))
    return out


def segments_from_detection(report: DetectionReport, plan: Plan, n: int, path: str,
                            cycles: CycleDetection | None = None) -> list[Segment]:
    """Match detected static intervals to the plan's static segments in order;
    a repeat = "auto" segment absorbs any number; turn segments are the spans
    between the intervals around them. Rotating segments take the detected
    rotation cycles (``cycles``, methods/cycle_detect.py) in order; holds inside
    a cycle are not static positions."""
    rotating = [(i, s) for i, s in enumerate(plan.segments) if s.kind == "rotating"]
    intervals = list(report.intervals)
    by_plan: dict[int, list[Segment]] = {}
    if rotating:
        if cycles is None or len(cycles.cycles) != len(rotating):
            found = 0 if cycles is None else len(cycles.cycles)
            why = "" if cycles is None else f": {cycles.explain(len(rotating))}"
            raise InputError(f"the plan has {len(rotating)} rotating segments but the data show "
                             f"{found}{why}", path)
        for (i, s), (a, b) in zip(rotating, cycles.cycles):
            by_plan[i] = [raw_segment(s, i, a, b, plan.visit_labels[i])]
        intervals = trim_intervals(intervals, cycles.cycles, 1)
    statics = [(i, s) for i, s in enumerate(plan.segments) if s.kind == "static"]
    fixed = sum(1 for _, s in statics if not s.repeat_auto)
    auto = any(s.repeat_auto for _, s in statics)
    if rotating and not statics:
        intervals = []  # quiet spans between cycles (remounts) are no plan positions
    found = len(intervals)
    if (found != fixed and not auto) or (auto and found < fixed):
        expect = f"{fixed}" + (" or more" if auto else "")
        raise InputError(f"detected {found} static intervals but the plan has {expect} static "
                         f"segments; {report.explain(fixed, at_least=auto)}", path)
    n_auto = found - fixed
    # static plan segments expanded to one entry per detected interval
    assigned: list[tuple[int, PlanSegment, str]] = []
    for i, s in statics:
        if s.repeat_auto:
            assigned += [(i, s, f"{s.label}#{k + 1}") for k in range(n_auto)]
        else:
            assigned.append((i, s, plan.visit_labels[i]))
    out: list[Segment] = []
    for (i, s, label), (a, b) in zip(assigned, intervals):
        seg = raw_segment(s, i, a, b, label)
        by_plan.setdefault(i, []).append(seg)
    # walk the plan; turn segments take the span between neighbouring intervals
    prev_stop = 0
    pending_turn: tuple[int, PlanSegment] | None = None
    for i, s in enumerate(plan.segments):
        if s.kind == "turn":
            if pending_turn is not None:
                raise InputError(f"turn segments {plan.segments[pending_turn[0]].label!r} and "
                                 f"{s.label!r} follow each other with no static position between "
                                 "them: they cannot be separated without a 'segment' column", path)
            pending_turn = (i, s)
            continue
        segs = by_plan.get(i, [])
        if pending_turn is not None:
            start = segs[0].start if segs else n
            out.append(raw_segment(pending_turn[1], pending_turn[0], prev_stop, start,
                                    plan.visit_labels[pending_turn[0]]))
            pending_turn = None
        out += segs
        if segs:
            prev_stop = segs[-1].stop
    if pending_turn is not None:
        out.append(raw_segment(pending_turn[1], pending_turn[0], prev_stop, n,
                                plan.visit_labels[pending_turn[0]]))
    return out


def plan_cycles(plan: Plan, t, gyro, table_rate=None) -> CycleDetection | None:
    """The rotation cycles of the data where the plan has rotating segments."""
    if gyro is None or not any(s.kind == "rotating" for s in plan.segments):
        return None
    return detect_cycles(t, gyro, table_rate)
