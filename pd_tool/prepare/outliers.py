"""Isolated floaters in a capture: points with too few neighbours in their block of voxels,
found on a voxel grid in O(N log N) instead of by pairwise distances."""
from __future__ import annotations

import numpy as np
import torch

from pd_tool.prepare.cells import Device, block_sums, unique_rows

OUTLIER_CELLS = 64  # voxels along the longest axis for the outlier test


def _neighbourhood_counts(points: np.ndarray, lo: np.ndarray, h: float, device: Device = "cpu") -> np.ndarray:
    """Points [N] (N > 0) in each point's 3x3x3 block of voxels of size h (self included)."""
    keys = torch.as_tensor(np.floor((points - lo) / h).astype(np.int64), device=device)
    uniq, inverse, counts, _ = unique_rows(keys)
    return block_sums(uniq, counts)[inverse].cpu().numpy()


def select_outliers(points: np.ndarray, min_neighbors: int = 3, max_cells: int = OUTLIER_CELLS, *,
                    device: Device = "cpu") -> np.ndarray:
    """Mask [N] of isolated points: fewer than `min_neighbors` points (self included) in
    their 3x3x3 voxel neighbourhood. The voxel size adapts to the point density: the finest
    of max_cells, max_cells/2, ... voxels along the robust extent at which the median point
    has at least 8 * min_neighbors neighbours. O(N log N), no pairwise distances; the
    cells are sorted on `device`."""
    if len(points) == 0:
        return np.zeros(0, bool)
    lo = np.quantile(points, 0.01, axis=0)
    hi = np.quantile(points, 0.99, axis=0)
    extent = max(float((hi - lo).max()), 1e-12)
    cells = max_cells
    while True:
        total = _neighbourhood_counts(points, lo, extent / cells, device)
        if cells <= 4 or np.median(total) >= 8 * min_neighbors:
            return total < min_neighbors
        cells //= 2
