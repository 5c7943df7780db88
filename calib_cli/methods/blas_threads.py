"""Run small dense linear algebra on one BLAS thread.

The fits of ``diagnose`` solve many small systems (tens to a few hundred
unknowns). A multi-threaded OpenBLAS gains nothing there and, on a loaded
machine, loses up to two orders of magnitude to thread contention (measured:
eigh of 100 x 100, 250 ms with the default threads under load, 3 ms on one).
``one_blas_thread`` sets the bundled OpenBLAS of numpy and of SciPy (scipy.linalg
has its own copy; the gyro wander likelihood's Cholesky runs there: 45 s of CPU a
gyro diagnosis with two workers on two cores, 5.2 s on one thread) to one thread
for the duration of a block and restores the previous counts; a library or
symbol that is not found is left alone.
"""

from __future__ import annotations

import contextlib
import ctypes
import glob
import os

_LIBS = None


def _libs() -> list:
    """(set, get) of each bundled OpenBLAS found: numpy's (64-bit integers) and
    SciPy's (scipy.linalg uses its own copy)."""
    global _LIBS
    if _LIBS is not None:
        return _LIBS
    _LIBS = []
    for mod, suffix in (("numpy", "64_"), ("scipy", "")):
        try:
            m = __import__(mod)
            pattern = os.path.join(os.path.dirname(m.__file__), os.pardir, f"{mod}.libs",
                                   "*openblas*")
            for path in glob.glob(pattern):
                lib = ctypes.CDLL(path)
                set_, get = (getattr(lib, f"scipy_openblas_{n}_num_threads{suffix}", None)
                             for n in ("set", "get"))
                if set_ is not None and get is not None:
                    _LIBS.append((set_, get))
                    break
        except (OSError, ImportError):
            continue
    return _LIBS


@contextlib.contextmanager
def one_blas_thread():
    libs = _libs()
    before = [int(get()) for _, get in libs]
    for set_, _ in libs:
        set_(1)
    try:
        yield
    finally:
        for (set_, _), n in zip(libs, before):
            set_(n)
