"""Exceptions that map onto the contract's exit codes (CONTRACT.md section 5).

The core raises these; only the CLI turns them into exit codes and one-line
messages, so library users get ordinary exceptions.
"""

from __future__ import annotations

import re

# numpy scalars formatted with repr() read "np.float64(1.98)": a message shows numbers
_NP_REPR = re.compile(r"np\.(?:float|int|uint|complex)\d*\(([^()]*)\)|np\.(?:True|False)_")


def num(x) -> str:
    """A number as a message shows it: ``1.98``, ``1e+20``, ``-3``, ``nan``
    (never ``np.float64(1.98)``, never an overflowed integer)."""
    try:
        f = float(x)
    except (TypeError, ValueError):
        return str(x)
    if f.is_integer() and abs(f) < 1e15:
        return str(int(f))
    return f"{f:.10g}"


def plain_numbers(text: str) -> str:
    """Strip numpy's scalar reprs from a message (a safety net; sites use num())."""
    return _NP_REPR.sub(lambda m: m.group(1) if m.group(1) is not None
                        else m.group(0)[3:-1], text)


class CalibError(Exception):
    """Base class. ``exit_code`` is the contract's exit status."""

    exit_code = 1

    def __init__(self, message: str, path: str | None = None):
        super().__init__(message)
        self.message = message
        self.path = path

    def line(self) -> str:
        """The one line printed on stderr."""
        msg = plain_numbers(self.message)
        return f"{self.path}: {msg}" if self.path else msg


class InputError(CalibError):
    """Bad or unreadable input (exit 3). Always names the file where known."""

    exit_code = 3


class DamagedInput(InputError):
    """Damaged content (checksum mismatch, NaN/inf samples, broken HDF5
    structure): exit 3 wherever it is found, never turned into a note."""


class EstimationError(CalibError):
    """The estimate failed: too few or degenerate positions, no convergence,
    nothing observable (exit 4). The message says what the experiment lacks."""

    exit_code = 4


class ToleranceError(CalibError):
    """A tolerance check failed (exit 5, the CI gate)."""

    exit_code = 5


class FaultDetected(CalibError):
    """A sensor fault was detected (exit 6)."""

    exit_code = 6


class OutputError(CalibError):
    """An output that must not or cannot be written: it is an input of the same
    command, its directory is missing, no permission (exit 2, like a usage
    error, raised before anything is written)."""

    exit_code = 2
