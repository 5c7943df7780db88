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


class CalibWarning(UserWarning):
    """Something the user should know that does not stop the step (an unused key,
    a skipped damaged file). The CLI prints it as one line ``calib: warning: ...``
    (not with -q); a library user gets it through Python's ``warnings``."""


_warning_sink = None  # set per thread/task by warnings_to(); a ContextVar, made on first use


def _sink_var():
    global _warning_sink
    if _warning_sink is None:
        import contextvars

        _warning_sink = contextvars.ContextVar("calib_warning_sink", default=None)
    return _warning_sink


def warn(line: str) -> None:
    """Report a warning line from the core: to the sink of the running context
    (the CLI's printer, a batch step's collector), else as a ``CalibWarning``."""
    sink = _sink_var().get()
    if sink is None:
        import warnings

        warnings.warn(line, CalibWarning, stacklevel=3)
    else:
        sink(line)


class warnings_to:
    """``with warnings_to(fn):`` send warn() lines of this thread/task to fn(line)
    (fn = None: drop them). Context-local, so parallel batch chains do not share it."""

    def __init__(self, sink):
        self.sink = sink if sink is not None else (lambda line: None)

    def __enter__(self):
        self._token = _sink_var().set(self.sink)
        return self

    def __exit__(self, *exc):
        _sink_var().reset(self._token)
        return False
