"""The parts of a report, shared by the builder and the section modules: figures,
tables, sections, what a section builder sees (ReportContext) and the effects a fit
added to its method's base model (AddedEffect)."""

from __future__ import annotations

from dataclasses import dataclass, field

from matplotlib.figure import Figure

from calib_cli.data import CalibrationResult


@dataclass
class FigureItem:
    """A figure with its file stem and caption (what to look for)."""

    name: str
    fig: Figure
    caption: str


@dataclass
class Table:
    caption: str
    header: list
    rows: list  # list of lists of str


@dataclass
class Section:
    title: str
    text: list = field(default_factory=list)  # paragraphs (plain text)
    tables: list = field(default_factory=list)
    figures: list = field(default_factory=list)


@dataclass
class ReportContext:
    """What section builders see. raw_path/raw_kind: the optional second
    input; allan: its Allan analysis when it is a free-running record;
    notes: remarks for the summary."""

    cal: CalibrationResult
    cal_path: str
    prov: dict
    raw_path: str | None = None
    raw_kind: str | None = None
    allan: object | None = None
    notes: list = field(default_factory=list)
    tolerances: dict | None = None  # io.tolerance.load_tolerances(), for the verdict
    tolerances_path: str | None = None
    diagnosis: dict | None = None  # a diagnosis file's summary and arrays (io.diag_h5)
    history: list | None = None  # the unit's calibrations (io.history.scan), for the verdict
    _recording: object | None = None

    def recording(self):
        """The RAW recording, read into memory on first use (None without RAW)."""
        if self._recording is None and self.raw_path and self.raw_kind in ("raw", "corrected"):
            from calib_cli.io.h5 import read_raw

            self._recording = read_raw(self.raw_path)
        return self._recording


@dataclass
class AddedEffect:
    """An effect a fit added to its method's base model: its --with spelling, the
    catalogue name and sensor ('' for the whole unit), its description in the
    calibration's model (None for a noise-model term) and its parameter keys."""

    with_arg: str
    name: str
    sensor: str
    desc: dict | None
    keys: list


def added_effects(cal: CalibrationResult) -> list[AddedEffect]:
    """The effects in ``stats["with"]`` (fit --with, a diagnosis's steps), in order."""
    from calib_cli.methods.fit_with import parse_with
    from calib_cli.model.truth import effect_from_description

    out = []
    for w in cal.stats.get("with") or []:
        try:
            pairs = parse_with(str(w), cal.method, ("accel", "gyro"))
        except ValueError:
            pairs = [(str(w), "")]
        for name, sensor in pairs:
            desc = next((d for d in cal.model if d.get("name") == name and
                         (not sensor or d.get("sensor") in (sensor, None, ""))), None)
            keys = []
            if desc is not None:
                try:
                    keys = [sp.key for sp in effect_from_description(desc).specs(cal.layout)
                            if sp.key in cal.params]
                except (TypeError, ValueError, KeyError):
                    keys = []
            out.append(AddedEffect(str(w), name, sensor, desc, keys))
    return out
