"""Isolated floaters in a capture: points with too few neighbours in their block of voxels,
found on a voxel grid in O(N log N) instead of by pairwise distances."""
from __future__ import annotations

import numpy as np

from pd_tool.prepare.cells import unique_cells

OUTLIER_CELLS = 64  # voxels along the longest axis for the outlier test


def _neighbourhood_counts(points: np.ndarray, lo: np.ndarray, h: float) -> np.ndarray:
    """Points [N] in each point's 3x3x3 block of voxels of size h (self included)."""
    keys = np.floor((points - lo) / h).astype(np.int64)
    uniq, inverse, counts = unique_cells(keys)
    base = uniq.min(axis=0) - 1
    span = uniq.max(axis=0) - base + 2

    def lin(k: np.ndarray) -> np.ndarray:
        return ((k[:, 0] - base[0]) * span[1] + (k[:, 1] - base[1])) * span[2] + (k[:, 2] - base[2])

    ukeys = lin(uniq)
    order = np.argsort(ukeys)
    sorted_keys = ukeys[order]
    total = np.zeros(len(uniq), np.int64)
    for d in np.stack(np.meshgrid([-1, 0, 1], [-1, 0, 1], [-1, 0, 1], indexing="ij"), -1).reshape(-1, 3):
        q = lin(uniq + d)
        pos = np.clip(np.searchsorted(sorted_keys, q), 0, len(sorted_keys) - 1)
        hit = sorted_keys[pos] == q
        total[hit] += counts[order[pos[hit]]]
    return total[inverse]


def select_outliers(points: np.ndarray, min_neighbors: int = 3, max_cells: int = OUTLIER_CELLS) -> np.ndarray:
    """Mask [N] of isolated points: fewer than `min_neighbors` points (self included) in
    their 3x3x3 voxel neighbourhood. The voxel size adapts to the point density: the finest
    of max_cells, max_cells/2, ... voxels along the robust extent at which the median point
    has at least 8 * min_neighbors neighbours. O(N log N), no pairwise distances."""
    if len(points) == 0:
        return np.zeros(0, bool)
    lo = np.quantile(points, 0.01, axis=0)
    hi = np.quantile(points, 0.99, axis=0)
    extent = max(float((hi - lo).max()), 1e-12)
    cells = max_cells
    while True:
        total = _neighbourhood_counts(points, lo, extent / cells)
        if cells <= 4 or np.median(total) >= 8 * min_neighbors:
            return total < min_neighbors
        cells //= 2
