"""Host helpers of the pipelines (``warpblob._stages``): row and column reductions that stand in for numpy's
slow reductions along the short axis of narrow arrays give numpy's values exactly."""

import numpy as np
import pytest

from warpblob._stages import column_bounds, rows_all, rows_any


@pytest.mark.parametrize("dtype", [bool, np.uint8, np.int8, np.int32, np.float64])
@pytest.mark.parametrize("width", range(10))
def test_row_reductions_are_numpys(dtype, width):
    """Every width (the 1-, 2-, 4- and 8-byte rows read as words, the others by columns), every dtype, and a
    view that is not contiguous: the same as ``any(axis=1)`` and ``all(axis=1)``."""
    rng = np.random.default_rng(width)
    a = rng.integers(-2, 3, (517, width)).astype(dtype)
    a[::7] = 0  # rows of zeros
    a[1::7] = 1  # rows with none
    for arr in (a, a[:, ::-1], a[::2]):
        np.testing.assert_array_equal(rows_any(arr), arr.any(axis=1))
        np.testing.assert_array_equal(rows_all(arr), arr.all(axis=1))


@pytest.mark.parametrize("dtype", [np.float32, np.float64, np.int64])
def test_column_bounds_are_numpys(dtype):
    rng = np.random.default_rng(3)
    a = (rng.standard_normal((1001, 3)) * 100).astype(dtype)
    low, high = column_bounds(a)
    np.testing.assert_array_equal(low, a.min(axis=0))
    np.testing.assert_array_equal(high, a.max(axis=0))
    assert low.dtype == a.dtype == high.dtype
