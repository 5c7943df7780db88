"""A unit's calibrations in an output directory, in order.

Order: the calibration's ``recorded_utc`` root attribute where a recorder
wrote one, then the file's path relative to the directory (name archive
files by date, e.g. 2026-05-01.csv, and the order is chronological).
Only HDF5 attributes and datasets are read: nothing is unpickled.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from calib_cli.errors import InputError


@dataclass(frozen=True)
class CalEntry:
    path: str
    rel: str
    serial: str
    method: str
    recorded_utc: str
    created_utc: str
    params: dict
    sigma: dict
    units: dict

    @property
    def order(self) -> tuple:
        return (self.recorded_utc, self.rel)


def _attr(h5, k):
    v = h5.attrs.get(k, "")
    return v.decode() if isinstance(v, bytes) else str(v)


def scan(directory, serial: str | None = None) -> list[CalEntry]:
    """Every calibration file under ``directory`` (of one unit if ``serial``), ordered."""
    import h5py

    from calib_cli.io.h5 import read_calibration

    root = Path(directory)
    if not root.is_dir():
        raise InputError("not a directory", str(directory))
    out = []
    for dirpath, dirnames, files in os.walk(root):
        dirnames[:] = sorted(d for d in dirnames if not d.startswith("."))
        for f in sorted(files):
            if f.startswith(".") or not f.endswith((".h5", ".hdf5")):
                continue
            p = Path(dirpath, f)
            try:
                with h5py.File(p, "r") as h5:
                    if _attr(h5, "kind") != "calibration":
                        continue
                    ser, rec, cre = (_attr(h5, "unit_serial"), _attr(h5, "recorded_utc"),
                                     _attr(h5, "created_utc"))
            except OSError:
                continue  # not HDF5: not ours
            if serial is not None and ser != serial:
                continue
            try:
                c = read_calibration(p)
            except InputError as exc:  # one damaged file must not fail every unit's check
                from calib_cli.errors import warn

                warn(f"skipped {exc.line()}")
                continue
            out.append(CalEntry(str(p), p.relative_to(root).as_posix(), ser, c.method, rec, cre,
                                c.params, c.sigma, c.units))
    return sorted(out, key=lambda e: e.order)


def entry_of(path, cal, prov: dict, history: list[CalEntry] | None = None) -> CalEntry:
    """The CalEntry of one calibration (``cal`` read from ``path``, ``prov`` its root
    attributes): the history's own entry when the file is in it (so a report ranks it
    among the unit's calibrations exactly as the batch does), else one made from its
    attributes."""
    here = Path(path).resolve()
    for e in history or ():
        if Path(e.path).resolve() == here:
            return e
    return CalEntry(str(path), Path(path).name, str(prov.get("unit_serial") or cal.serial or ""),
                    cal.method, str(prov.get("recorded_utc", "")), str(prov.get("created_utc", "")),
                    cal.params, cal.sigma, cal.units)


def previous(entries: list[CalEntry], entry: CalEntry, key: str) -> CalEntry | None:
    """The unit's last calibration before ``entry`` that reports parameter ``key``."""
    prior = [e for e in entries if e.serial == entry.serial and e.order < entry.order
             and key in e.params and e.path != entry.path]
    return prior[-1] if prior else None


def element_names(key: str, shape: tuple) -> list[str]:
    if not shape:
        return [key]
    return [f"{key}[{','.join(map(str, idx))}]" for idx in np.ndindex(*shape)]
