"""What a file is, from its first bytes: for error messages that say what to do
when a command is given the wrong kind of file (an HDF5 recording to `import
csv`, a plan to `fit`)."""

from __future__ import annotations

import re
from pathlib import Path

HDF5_MAGIC = b"\x89HDF\r\n\x1a\n"
_PLAN = re.compile(r'^\s*(\[\[segment\]\]|kind\s*=\s*"|\[generator\]|\[site\])', re.M)
_TRUTH = re.compile(r"^\s*\[(params|noise)\]", re.M)


def what_is(path) -> str | None:
    """'hdf5', 'plan', 'truth', 'ulog', 'text' or None (unknown, unreadable)."""
    try:
        with open(path, "rb") as fh:
            head = fh.read(4096)
    except OSError:
        return None
    if head.startswith(HDF5_MAGIC):
        return "hdf5"
    if head.startswith(b"ULog"):
        return "ulog"
    try:
        text = head.decode("utf-8")
    except UnicodeDecodeError:
        return None
    if Path(str(path)).suffix.lower() == ".toml" or _PLAN.search(text) or _TRUTH.search(text):
        return "truth" if _TRUTH.search(text) and not _PLAN.search(text) else "plan"
    return "text"


def not_a_text_log(path, exc: Exception) -> str:
    """The message of a text reader that met a file it cannot decode."""
    kind = what_is(path)
    if kind == "hdf5":
        return ("an HDF5 file, not a text log: a calib raw.h5 needs no import (fit, show, "
                "report and apply take it as it is)")
    if kind == "ulog":
        return "a PX4 ULog file, not a text log: calib import ulog FILE --plan PLAN --out RAW.h5"
    return f"not a text log ({exc})"


def hint_for_non_hdf5(path) -> str:
    """'; ...' naming what a file that is not HDF5 is and what to do with it ('' if unknown)."""
    kind = what_is(path)
    if kind == "plan":
        return ("; it is a plan (TOML), not a recording: record or simulate it first "
                "(calib simulate PLAN.toml --out raw.h5, calib record ...), then give raw.h5")
    if kind == "truth":
        return ("; it is a truth file (TOML): give it to calib simulate PLAN.toml --truth "
                "TRUTH.toml --out raw.h5")
    if kind == "ulog":
        return "; it is a PX4 ULog file: calib import ulog FILE --plan PLAN --out raw.h5 first"
    if kind == "text":
        return ("; a text log is imported first: calib import csv FILE --plan PLAN.toml "
                "--out raw.h5 (or calib import text, docs/import.md)")
    return ""
