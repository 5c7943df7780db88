"""The one progress bar of every long command (import, simulate, fit, diagnose,
apply, allan, batch, plan).

The core never prints: a long computation takes an optional callback
``progress(done, total)`` (e.g. ``fit_turntable(..., progress=cb)`` calls it
once per cycle and pass) and this module turns it into a rich bar on stderr.
The bar is drawn only on a terminal: when stdout and stderr are both TTYs and
``-q/--quiet`` is not given; otherwise every function here is a no-op, so
logs, pipes and ``--json`` output stay byte-for-byte what they were.
"""

from __future__ import annotations

import sys
from contextlib import contextmanager


def enabled() -> bool:
    """A bar is drawn: stdout and stderr are terminals and not --quiet."""
    from calib_cli.cli.common import Ctx

    if Ctx.quiet:
        return False
    try:
        return sys.stdout.isatty() and sys.stderr.isatty()
    except (AttributeError, ValueError):  # closed or replaced streams
        return False


_ACTIVE = False


def _noop(done=None, total=None) -> None:
    return None


@contextmanager
def bar(description: str, total: float | None = None):
    """``with bar("fit turntable") as cb: fit(..., progress=cb)``.

    ``cb(done, total=None)`` sets the bar (total None keeps the last one); a
    bar without a total is a pulsing one (work of unknown length). Transient:
    the bar is erased when the block ends, the command's own lines stay."""
    global _ACTIVE
    if _ACTIVE or not enabled():  # one bar at a time: an inner step (a batch's fit) is silent
        yield _noop
        return
    from rich.progress import (
        BarColumn,
        Progress,
        SpinnerColumn,
        TaskProgressColumn,
        TextColumn,
        TimeElapsedColumn,
    )

    from calib_cli.cli.common import err_console

    with Progress(SpinnerColumn(), TextColumn("{task.description}"), BarColumn(),
                  TaskProgressColumn(), TimeElapsedColumn(), console=err_console,
                  transient=True) as prog:
        task = prog.add_task(description, total=total)

        def update(done=None, total=None) -> None:
            kw = {}
            if total is not None:
                kw["total"] = float(total)
            if done is not None:
                kw["completed"] = float(done)
            prog.update(task, **kw)

        _ACTIVE = True
        try:
            yield update
        finally:
            _ACTIVE = False


def track(iterable, description: str, total: float | None = None):
    """Iterate, advancing a bar by one per item (total: the number of items,
    None when unknown)."""
    if _ACTIVE or not enabled():
        yield from iterable
        return
    with bar(description, total) as cb:
        for i, item in enumerate(iterable, 1):
            yield item
            cb(i)
