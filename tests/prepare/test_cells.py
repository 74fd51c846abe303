"""unique_cells against numpy's row-wise unique (the slow, obviously right way)."""
from __future__ import annotations

import numpy as np

from pd_tool.prepare.cells import unique_cells


def test_unique_cells_matches_numpy_rows():
    rng = np.random.default_rng(0)
    cells = rng.integers(-40, 40, (5000, 3))
    cells[::7] = cells[1::7][: len(cells[::7])]  # repeats
    uniq, inverse, counts, first = unique_cells(cells, index=True)
    ref_u, ref_inv, ref_c = np.unique(cells, axis=0, return_inverse=True, return_counts=True)
    assert np.array_equal(uniq, ref_u) and np.array_equal(inverse, ref_inv.reshape(-1))
    assert np.array_equal(counts, ref_c) and np.array_equal(cells[first], uniq)
    assert np.array_equal(uniq[inverse], cells)


def test_unique_cells_of_nothing():
    uniq, inverse, counts = unique_cells(np.zeros((0, 3)))
    assert uniq.shape == (0, 3) and len(inverse) == 0 and len(counts) == 0
