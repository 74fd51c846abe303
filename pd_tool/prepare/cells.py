"""Integer cells of points, grouped fast: np.unique over rows (axis=0) sorts structured
records and takes seconds at 300k points; one int64 key per cell sorts in a tenth of that."""
from __future__ import annotations

import numpy as np


def unique_cells(cells: np.ndarray, *, index: bool = False):
    """The distinct rows of integer cells [N, 3]: (unique cells [M, 3] in key order,
    inverse [N] into them, counts [M]); with index, also the first row of each [M]."""
    cells = np.asarray(cells, np.int64).reshape(-1, 3)
    if len(cells) == 0:
        empty = np.zeros(0, np.int64)
        out = (np.zeros((0, 3), np.int64), empty, empty)
        return out + (empty,) if index else out
    lo = cells.min(axis=0)
    span = cells.max(axis=0) - lo + 1
    key = ((cells[:, 0] - lo[0]) * span[1] + (cells[:, 1] - lo[1])) * span[2] + (cells[:, 2] - lo[2])
    _, first, inverse, counts = np.unique(key, return_index=True, return_inverse=True, return_counts=True)
    out = (cells[first], inverse.reshape(-1), counts)
    return out + (first,) if index else out
