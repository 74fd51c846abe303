"""Column bounds against numpy's axis-0 reductions: same values and dtype, NaN included."""
from __future__ import annotations

import numpy as np
import pytest

from pd_tool.core.arrays import bounds, extent, rows_all, rows_max, rows_min


@pytest.mark.parametrize("dtype", [np.float64, np.float32, np.int64])
def test_bounds_and_extent_match_axis_0_reductions(dtype):
    rng = np.random.default_rng(0)
    x = (rng.normal(size=(1000, 3)) * 100).astype(dtype)
    lo, hi = bounds(x)
    assert np.array_equal(lo, x.min(axis=0)) and np.array_equal(hi, x.max(axis=0))
    assert lo.dtype == x.dtype and hi.dtype == x.dtype
    assert np.array_equal(extent(x), np.ptp(x, axis=0))
    assert np.array_equal(bounds(x[::-7])[0], x[::-7].min(axis=0))  # strided rows


def test_bounds_keep_nan_and_refuse_nothing():
    x = np.ones((5, 3))
    x[2, 1] = np.nan
    lo, hi = bounds(x)
    assert np.isnan(lo[1]) and np.isnan(hi[1]) and lo[0] == 1.0
    with pytest.raises(ValueError):
        bounds(np.zeros((0, 3)))


def test_row_reductions_match_axis_1():
    rng = np.random.default_rng(1)
    x = rng.normal(size=(500, 3))
    x[7, 2] = np.nan
    np.testing.assert_array_equal(rows_max(x), x.max(1))
    np.testing.assert_array_equal(rows_min(x), x.min(1))
    m = x > -0.5
    np.testing.assert_array_equal(rows_all(m), m.all(1))
    assert rows_all(np.ones((4, 1), bool)).all() and len(rows_max(np.zeros((0, 3)))) == 0
