"""forcecal.blas: the parent's BLAS threads for a block, restored after it, results unchanged."""
import numpy as np
import pytest

from forcecal.blas import _openblas, available_cores, blas_threads


def test_blas_threads_are_lent_for_the_block_and_restored():
    calls = _openblas()
    if calls is None:
        pytest.skip("numpy's BLAS is not OpenBLAS: blas_threads does nothing here")
    get, _ = calls
    before = get()
    a = np.random.default_rng(0).normal(size=(300, 300))
    with blas_threads(64):
        assert get() == min(64, available_cores())
        inside = a @ a
    assert get() == before

    @blas_threads()  # as a decorator: every available core during each call
    def threads_inside() -> int:
        return get()
    assert threads_inside() == available_cores() and threads_inside() == available_cores()
    assert get() == before
    with pytest.raises(ZeroDivisionError):
        with blas_threads(2):
            1 / 0
    assert get() == before
    # a product of this size splits over threads by blocks of rows: same numbers
    np.testing.assert_allclose(inside, a @ a, rtol=0, atol=1e-12 * np.abs(inside).max())
