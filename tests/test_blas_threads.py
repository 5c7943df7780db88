"""one_blas_thread covers numpy's and SciPy's bundled OpenBLAS (scipy.linalg uses its
own copy; the gyro wander likelihood's Cholesky and triangular solves run there)."""

from calib_cli.methods import blas_threads as B


def test_one_blas_thread_sets_every_bundled_openblas_and_restores():
    libs = B._libs()
    before = [int(get()) for _, get in libs]
    with B.one_blas_thread():
        assert all(int(get()) == 1 for _, get in libs)
    assert [int(get()) for _, get in libs] == before
