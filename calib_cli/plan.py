"""The plan types (CONTRACT.md section 3), in SI units: what a plan says once
parsed. Base layer: pure containers and the layout a plan implies. Parsing and
validation of the TOML are in ``io/plan.py`` (which re-exports these names).
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np

from calib_cli.geometry import Layout, Site

KINDS = ("static", "align", "turntable", "rimu")
D2R = np.pi / 180.0


@dataclass(frozen=True)
class PlanSegment:
    """One segment of a plan, SI units. ``extra`` keeps every key as written
    (simulation keys such as rate profiles live there)."""

    label: str
    attitude: np.ndarray | None = None  # rad, [roll, pitch, yaw] at the segment start
    attitude_sigma: float | None = None  # rad
    table_axis_enu: np.ndarray | None = None
    table_rate: float | None = None  # rad/s
    lever_arm: np.ndarray | None = None  # m, body axes
    duration: float | None = None  # s
    rotation_axis_body: np.ndarray | None = None
    rotation_angle: float | None = None  # rad
    repeat_auto: bool = False
    extra: dict = field(default_factory=dict)

    @property
    def kind(self) -> str:
        """"turn" (known-angle turn), "rotating" (table turning), or "static".

        CONTRACT.md section 3: a segment with ``table_axis_enu`` is a rotating
        segment whatever its rate keys (a recorded log carries the motion in its
        own columns); ``table_rate_dps = 0`` marks a segment on the table that
        does not turn."""
        if self.rotation_angle is not None:
            return "turn"
        if self.table_axis_enu is not None and self.table_rate != 0.0:
            return "rotating"
        return "static"


@dataclass(frozen=True)
class Plan:
    name: str
    kind: str
    site: Site
    serial: str | None
    segments: tuple[PlanSegment, ...]
    text: str = ""  # the TOML as written, stored in every raw file
    protocol: str | None = None
    rimu_el0: np.ndarray | None = None  # rad
    rimu_az0: np.ndarray | None = None  # rad
    extra: dict = field(default_factory=dict)
    path: str = "<plan>"

    @cached_property
    def visit_labels(self) -> tuple[str, ...]:
        """Each segment's label, with ``#k`` (the k-th visit) where the plan repeats
        a label, so that raw segments, stats and reports keep the visits apart."""
        labels = [s.label for s in self.segments]
        total = Counter(labels)
        seen: Counter = Counter()
        out = []
        for lab in labels:
            seen[lab] += 1
            out.append(f"{lab}#{seen[lab]}" if total[lab] > 1 else lab)
        return tuple(out)

    @property
    def sample_rate(self) -> float:
        """Simulation sample rate, Hz (key ``sample_rate_hz``, default 100)."""
        return float(self.extra.get("sample_rate_hz", 100.0))


def plan_layout(plan: Plan) -> Layout:
    """The channel layout a plan implies: RIMU geometry, one lever-arm row per rotating segment."""
    n_cycles = sum(1 for s in plan.segments if s.kind == "rotating")
    if plan.kind == "rimu":
        return Layout(n=len(plan.rimu_el0), el0=plan.rimu_el0, az0=plan.rimu_az0,
                      n_cycles=n_cycles)
    return Layout(n_cycles=n_cycles)


def same_layout(a: Layout, b: Layout) -> bool:
    """Equal channel geometry and cycle count (Layout holds arrays, so == is ambiguous)."""
    def eq(x, y):
        return (x is None and y is None) or (x is not None and y is not None
                                             and np.array_equal(x, y))
    return a.n == b.n and a.n_cycles == b.n_cycles and eq(a.el0, b.el0) and eq(a.az0, b.az0)
