"""Run small dense linear algebra on one BLAS thread.

The fits of ``diagnose`` solve many small systems (tens to a few hundred
unknowns). A multi-threaded OpenBLAS gains nothing there and, on a loaded
machine, loses up to two orders of magnitude to thread contention (measured:
eigh of 100 x 100, 250 ms with the default threads under load, 3 ms on one).
``one_blas_thread`` sets numpy's bundled OpenBLAS to one thread for the
duration of a block and restores the previous count; where that library or
its symbols are not found it does nothing.
"""

from __future__ import annotations

import contextlib
import ctypes
import glob
import os

_LIB = None
_TRIED = False


def _lib():
    global _LIB, _TRIED
    if _TRIED:
        return _LIB
    _TRIED = True
    try:
        import numpy as np

        pattern = os.path.join(os.path.dirname(np.__file__), os.pardir, "numpy.libs",
                               "*openblas*")
        for path in glob.glob(pattern):
            lib = ctypes.CDLL(path)
            if hasattr(lib, "scipy_openblas_set_num_threads64_") and hasattr(
                    lib, "scipy_openblas_get_num_threads64_"):
                _LIB = lib
                break
    except OSError:
        _LIB = None
    return _LIB


@contextlib.contextmanager
def one_blas_thread():
    lib = _lib()
    if lib is None:
        yield
        return
    before = int(lib.scipy_openblas_get_num_threads64_())
    lib.scipy_openblas_set_num_threads64_(1)
    try:
        yield
    finally:
        lib.scipy_openblas_set_num_threads64_(before)
