"""one_blas_thread covers numpy's and SciPy's bundled OpenBLAS (scipy.linalg uses its
own copy; the gyro wander likelihood's Cholesky and triangular solves run there)."""

from calib_cli.methods import blas_threads as B


def test_one_blas_thread_sets_every_bundled_openblas_and_restores():
    import glob
    import os

    import numpy
    import scipy

    libs = B._libs()
    # every bundled copy present is found (its thread symbols resolved), not skipped
    bundled = sum(bool(glob.glob(os.path.join(os.path.dirname(m.__file__), os.pardir,
                                              f"{m.__name__}.libs", "*openblas*")))
                  for m in (numpy, scipy))
    assert len(libs) == bundled
    before = [int(get()) for _, get in libs]
    with B.one_blas_thread():
        assert all(int(get()) == 1 for _, get in libs)
    assert [int(get()) for _, get in libs] == before
