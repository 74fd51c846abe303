"""Integer cells on each device: unique_cells against numpy's row-wise unique (the slow,
obviously right way), components and block sums against a dict of cells."""
from __future__ import annotations

import numpy as np

from pd_tool.prepare.cells import unique_cells


def test_unique_cells_matches_numpy_rows(device):
    rng = np.random.default_rng(0)
    cells = rng.integers(-40, 40, (5000, 3))
    cells[::7] = cells[1::7][: len(cells[::7])]  # repeats
    uniq, inverse, counts, first = unique_cells(cells, index=True, device=device)
    ref_u, ref_inv, ref_c = np.unique(cells, axis=0, return_inverse=True, return_counts=True)
    assert np.array_equal(uniq, ref_u) and np.array_equal(inverse, ref_inv.reshape(-1))
    assert np.array_equal(counts, ref_c) and np.array_equal(cells[first], uniq)
    assert np.array_equal(uniq[inverse], cells)


def test_unique_cells_of_nothing(device):
    uniq, inverse, counts = unique_cells(np.zeros((0, 3)), device=device)
    assert uniq.shape == (0, 3) and len(inverse) == 0 and len(counts) == 0


def test_cell_components_match_a_breadth_first_search(device):
    from pd_tool.prepare.cells import cell_components, cell_components_ref

    rng = np.random.default_rng(1)
    for trial in range(30):
        n = int(rng.integers(1, 600))
        cells = unique_cells(rng.integers(0, int(rng.integers(3, 16)), (n, 3)))[0]
        assert np.array_equal(cell_components(cells, device=device), cell_components_ref(cells)), trial


def test_cell_components_join_corners_and_split_gaps(device):
    from pd_tool.prepare.cells import cell_components

    # a diagonal chain touches at corners only; a cell two steps away is its own group
    cells = np.array([[0, 0, 0], [1, 1, 1], [2, 2, 2], [4, 2, 2], [0, 0, 600]])
    assert cell_components(cells, device=device).tolist() == [0, 0, 0, 3, 4]
    stem = np.stack([np.zeros(3000, int), np.zeros(3000, int), np.arange(3000)], 1)[::-1]
    assert (cell_components(stem, device=device) == 0).all()  # one group, rooted at its smallest index
    assert len(cell_components(np.zeros((0, 3)))) == 0


def test_block_sums_match_a_dict_of_cells(device):
    import torch

    from pd_tool.prepare.cells import block_sums, block_sums_ref

    def sums(cells, values):
        t = lambda a: torch.as_tensor(np.ascontiguousarray(a), device=device)  # noqa: E731
        return block_sums(t(cells), t(values)).cpu().numpy()

    rng = np.random.default_rng(2)
    for trial in range(20):
        n = int(rng.integers(1, 500))
        cells = unique_cells(rng.integers(-5, int(rng.integers(2, 12)), (n, 3)))[0]
        values = rng.uniform(0, 3, (len(cells), 2))
        np.testing.assert_allclose(sums(cells, values), block_sums_ref(cells, values), rtol=1e-12, err_msg=str(trial))
    # a lone cell sums only itself; a full 3x3x3 block's centre sums all 27
    block = np.array([(a, b, c) for a in range(3) for b in range(3) for c in range(3)] + [[9, 9, 9]])
    out = sums(block, np.ones(len(block), np.int64))
    assert out[13] == 27 and out[-1] == 1 and out[0] == 8
