"""A lock per recording output (issue 15): ``PATH.lock`` held with flock.

A second recorder on the same ``--out`` (or the same journal) fails at once
with exit 3 naming the holder's process id; the kernel releases the lock
when the holder dies (SIGKILL included), so a stale lock file never blocks.
"""

from __future__ import annotations

import contextlib
import fcntl
import os

from calib_cli.errors import InputError


@contextlib.contextmanager
def hold(path: str, what: str = "recorder"):
    lock = f"{path}.lock"
    try:
        fd = os.open(lock, os.O_RDWR | os.O_CREAT, 0o644)
    except OSError as exc:
        raise InputError(f"cannot create the lock file {lock}: {exc.strerror}", path) from None
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
    except BlockingIOError:
        try:
            holder = os.read(fd, 64).decode(errors="replace").strip() or "?"
        except OSError:
            holder = "?"
        os.close(fd)
        raise InputError(f"another {what} (pid {holder}) is writing this file; wait for it "
                         "to end or choose another --out", path) from None
    try:
        with contextlib.suppress(OSError):  # the holder's pid is a courtesy (a full disk)
            os.ftruncate(fd, 0)
            os.write(fd, f"{os.getpid()}\n".encode())
        yield
    finally:
        with contextlib.suppress(OSError):
            os.unlink(lock)
        os.close(fd)
