"""CSV logs (CONTRACT.md section 4): read, segment, write.

Columns: ``time`` (s); a triad ``ax ay az`` (m/s^2) and ``gx gy gz`` (rad/s),
a redundant unit ``a0 .. a{n-1}`` and ``g0 .. g{n-1}``; optional ``temp``
(degC), ``table_angle`` (rad), ``table_rate`` (rad/s), ``segment`` (index
into the plan's segments, -1 between segments). Lines starting with ``#``
are comments; the first other line names the columns.
"""

from __future__ import annotations

import io
from pathlib import Path

import numpy as np

from calib_cli.data import Recording, Segment
from calib_cli.errors import InputError
from calib_cli.io.plan import Plan, PlanSegment
from calib_cli.methods.cycle_detect import CycleDetection, detect_cycles, trim_intervals
from calib_cli.methods.static_detect import DetectionReport, detect_static
from calib_cli.model.effects import Layout

OPTIONAL = ("temp", "table_angle", "table_rate")


def _read_table(path: str):
    """(header names, float array (N, k)) with errors that name row and column."""
    try:
        text = Path(path).read_text(encoding="utf-8")
    except FileNotFoundError:
        raise InputError("no such file", path) from None
    except (OSError, UnicodeDecodeError) as exc:
        raise InputError(f"cannot read: {exc}", path) from None
    lines = text.splitlines()
    body_start, header = None, None
    for i, line in enumerate(lines):
        s = line.strip()
        if not s or s.startswith("#"):
            continue
        header = [c.strip() for c in s.split(",")]
        body_start = i + 1
        break
    if header is None:
        raise InputError("empty file (no header line)", path)
    if len(set(header)) != len(header):
        raise InputError(f"duplicate column names in header: {header}", path)
    rows = [(i + 1, ln) for i, ln in enumerate(lines[body_start:], start=body_start)
            if ln.strip() and not ln.lstrip().startswith("#")]
    if not rows:
        raise InputError("no data rows after the header", path)
    try:
        data = np.loadtxt(io.StringIO("\n".join(r for _, r in rows)), delimiter=",", ndmin=2)
        if data.shape[1] != len(header):
            raise ValueError
    except ValueError:
        for lineno, r in rows:  # find the exact cell, for the message
            cells = r.split(",")
            if len(cells) != len(header):
                raise InputError(f"line {lineno}: {len(cells)} cells, header has "
                                 f"{len(header)}", path) from None
            for name, c in zip(header, cells):
                try:
                    float(c)
                except ValueError:
                    raise InputError(f"line {lineno}, column {name!r}: not a number: "
                                     f"{c.strip()!r}", path) from None
        raise InputError("unreadable numeric data", path) from None
    bad = ~np.isfinite(data)
    if bad.any():
        r, c = np.argwhere(bad)[0]
        raise InputError(f"line {rows[r][0]}, column {header[c]!r}: {data[r, c]} (NaN or "
                         "infinite values are not allowed)", path)
    return header, data


def read_columns(path: str, layout: Layout):
    """Time, accel, gyro, optional columns and segment index from a contract CSV."""
    header, data = _read_table(path)
    col = {name: data[:, i] for i, name in enumerate(header)}
    if "time" not in col:
        raise InputError("missing column 'time'", path)
    if layout.redundant:
        an = [f"a{i}" for i in range(layout.n)]
        gn = [f"g{i}" for i in range(layout.n)]
    else:
        an, gn = ["ax", "ay", "az"], ["gx", "gy", "gz"]
    missing = [c for c in an if c not in col]
    if missing:
        raise InputError(f"missing column{'s' * (len(missing) > 1)} {', '.join(missing)}", path)
    gmiss = [c for c in gn if c not in col]
    if gmiss and len(gmiss) < len(gn):
        raise InputError(f"missing column{'s' * (len(gmiss) > 1)} {', '.join(gmiss)}", path)
    t = col["time"]
    if len(t) > 1 and np.any(np.diff(t) <= 0):
        i = int(np.flatnonzero(np.diff(t) <= 0)[0])
        raise InputError(f"time is not increasing at data row {i + 2} "
                         f"({t[i]!r} then {t[i + 1]!r})", path)
    accel = np.column_stack([col[c] for c in an])
    gyro = None if gmiss else np.column_stack([col[c] for c in gn])
    opt = {k: col.get(k) for k in OPTIONAL}
    seg = col.get("segment")
    if seg is not None and np.any(seg != np.round(seg)):
        raise InputError("column 'segment' must hold integers", path)
    return t, accel, gyro, opt, None if seg is None else seg.astype(int)


def _raw_segment(ps: PlanSegment, plan_index: int, start: int, stop: int,
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
        raise InputError(f"segment index {int(seg[bad][0])} out of range: the plan has "
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
        out.append(_raw_segment(ps, k, a, b, label))
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
            by_plan[i] = [_raw_segment(s, i, a, b, plan.visit_labels[i])]
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
        seg = _raw_segment(s, i, a, b, label)
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
            out.append(_raw_segment(pending_turn[1], pending_turn[0], prev_stop, start,
                                    plan.visit_labels[pending_turn[0]]))
            pending_turn = None
        out += segs
        if segs:
            prev_stop = segs[-1].stop
    if pending_turn is not None:
        out.append(_raw_segment(pending_turn[1], pending_turn[0], prev_stop, n,
                                plan.visit_labels[pending_turn[0]]))
    return out


def plan_cycles(plan: Plan, t, gyro, table_rate=None) -> CycleDetection | None:
    """The rotation cycles of the data where the plan has rotating segments."""
    if gyro is None or not any(s.kind == "rotating" for s in plan.segments):
        return None
    return detect_cycles(t, gyro, table_rate)


def import_csv(path, plan: Plan, window_s: float = 1.0, multiplier: float = 3.0,
               min_static_s: float = 1.0, units: dict | None = None) -> Recording:
    """A contract CSV and its plan -> Recording. Raises InputError naming the file."""
    path = str(path)
    from calib_cli.sim.simulate import plan_layout

    layout = plan_layout(plan)
    t, accel, gyro, opt, seg = read_columns(path, layout)
    if seg is not None:
        segments = segments_from_column(seg, plan, path)
    else:
        report = detect_static(t, accel, gyro, window_s, multiplier, min_static_s)
        cycles = plan_cycles(plan, t, gyro, opt.get("table_rate"))
        segments = segments_from_detection(report, plan, len(t), path, cycles)
    if not segments:
        raise InputError("no segments found in the data", path)
    n_cycles = sum(1 for s in segments if s.kind == "rotating")
    layout = Layout(layout.n, layout.el0, layout.az0, n_cycles)
    return Recording(time=t, accel=accel, gyro=gyro, segments=tuple(segments), site=plan.site,
                     plan_kind=plan.kind, plan_text=plan.text, serial=plan.serial,
                     units=units or {"accel": "m/s^2", "gyro": "rad/s"}, layout=layout,
                     temp=opt["temp"], table_angle=opt["table_angle"],
                     table_rate=opt["table_rate"])


def write_csv(path, rec: Recording) -> None:
    """The contract's CSV columns, with the segment index of each sample."""
    from calib_cli.io.h5 import atomic_path

    n = len(rec)
    seg = np.full(n, -1)
    for s in rec.segments:
        seg[s.start:s.stop] = s.plan_index
    if rec.layout.redundant:
        names = [f"a{i}" for i in range(rec.layout.n)] + [f"g{i}" for i in range(rec.layout.n)]
    else:
        names = ["ax", "ay", "az", "gx", "gy", "gz"]
    cols = [rec.time, rec.accel, rec.gyro]
    for k in OPTIONAL:
        v = getattr(rec, k)
        if v is not None:
            names.append(k)
            cols.append(np.nan_to_num(v))
    names.append("segment")
    cols.append(seg)
    table = np.column_stack([np.asarray(c, dtype=float).reshape(n, -1) for c in cols])
    with atomic_path(path) as tmp:
        with open(tmp, "w", encoding="utf-8") as fh:
            fh.write(f"# calib simulated log; plan kind {rec.plan_kind}; serial {rec.serial or ''}\n")
            fh.write(",".join(["time"] + names) + "\n")
            fmt = ["%.6f"] + ["%.12g"] * (table.shape[1] - 2) + ["%d"]
            np.savetxt(fh, table, delimiter=",", fmt=fmt)
