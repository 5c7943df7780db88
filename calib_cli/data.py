"""The in-memory forms of what flows between steps: a recording and a
calibration result. Pure containers; ``io/`` reads and writes them."""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np

from calib_cli.geometry import Layout, Site

SI_UNITS = {"accel": "m/s^2", "gyro": "rad/s"}
SAMPLE_KINDS = ("instant", "interval-mean")


@dataclass(frozen=True)
class Segment:
    """A labelled span [start, stop) of samples. Angles in rad, SI units.

    kind: "static" (a position), "turn" (known-angle turn about a body axis),
    "rotating" (the table turns about table_axis_enu).
    plan_index: the plan segment it came from (a repeat = "auto" segment
    gives several raw segments with the same plan_index).
    """

    label: str
    kind: str
    start: int
    stop: int
    plan_index: int = -1
    attitude: np.ndarray | None = None
    attitude_sigma: float | None = None
    table_axis_enu: np.ndarray | None = None
    table_rate: float | None = None
    lever_arm: np.ndarray | None = None
    rotation_axis_body: np.ndarray | None = None
    rotation_angle: float | None = None

    @property
    def n(self) -> int:
        return self.stop - self.start

    @property
    def slice(self) -> slice:
        return slice(self.start, self.stop)


@dataclass(frozen=True)
class Recording:
    """Samples of one experiment with its segments, site and plan.

    time (N,) s; accel, gyro (N, n) in ``units`` (SI or raw counts); temp
    (N,) degC, table_angle (N,) rad, table_rate (N,) rad/s where recorded.
    truth: for simulated data, {"params": {...}, "noise": {...},
    "attitudes": (n_seg, 3) rad}.
    """

    time: np.ndarray
    accel: np.ndarray
    gyro: np.ndarray | None
    segments: tuple[Segment, ...]
    site: Site = Site()
    plan_kind: str = "static"
    plan_text: str = ""
    serial: str | None = None
    units: dict = field(default_factory=lambda: dict(SI_UNITS))
    layout: Layout = Layout()
    temp: np.ndarray | None = None
    table_angle: np.ndarray | None = None
    table_rate: np.ndarray | None = None
    truth: dict | None = None
    counters: dict = field(default_factory=dict)
    # "instant": each sample is the value at its stamp; "interval-mean": the mean over
    # [t_k - 1/fs, t_k] (many MEMS parts output filtered data), docs/import.md
    sample_kind: str = "instant"

    def __len__(self) -> int:
        return len(self.time)

    @property
    def sample_rate(self) -> float:
        """Median sample rate, Hz, to 10 significant digits (100 Hz, not the
        100.00000000000213 of float time stamps)."""
        if len(self.time) < 2:
            return 0.0
        return float(f"{1.0 / float(np.median(np.diff(self.time))):.10g}")

    def static_segments(self) -> list[Segment]:
        return [s for s in self.segments if s.kind == "static"]

    def in_counts(self, sensor: str) -> bool:
        return self.units.get(sensor) == "count"

    def with_(self, **changes) -> "Recording":
        return replace(self, **changes)


@dataclass(frozen=True)
class CalibrationResult:
    """What a fit returns: parameters with covariance, residuals and stats.

    params/sigma: arrays by contract key; sigma NaN marks an unobservable
    entry (``null`` in JSON), 0 an entry fixed by convention.
    covariance: over the free entries, in ``cov_order`` [(key, flat index)].
    units: unit string of every params key. stats: JSON-able dict.
    tables: named arrays for reports (e.g. the per-position |g| table).
    model: the effects fitted, as [{"name", "sensor", ...options}].
    """

    method: str
    params: dict
    sigma: dict
    units: dict
    covariance: np.ndarray
    cov_order: list
    stats: dict
    residuals: dict = field(default_factory=dict)
    tables: dict = field(default_factory=dict)
    model: list = field(default_factory=list)
    raw_units: dict = field(default_factory=lambda: dict(SI_UNITS))
    layout: Layout = Layout()
    serial: str | None = None
