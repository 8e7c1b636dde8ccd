"""Voxel grids: which occupied cell each point falls in, and the cells' centroids."""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray


def voxel_cells(
    points: NDArray[np.float64], voxel_size: float
) -> tuple[NDArray[np.float64], NDArray[np.intp]]:
    """Centroids of the occupied voxel cells and the cell of each point.

    Parameters
    ----------
    points
        (N, 3) points, any frame (m).
    voxel_size
        Cell edge (m).

    Returns
    -------
    centroids, cell
        (M, 3) mean point of each occupied cell, ordered by cell key; (N,) cell index of each
        point.
    """
    grid = np.floor(points / voxel_size).astype(np.int64)
    grid -= grid.min(axis=0)
    size = grid.max(axis=0) + 1
    # One integer key per cell: a 1-D unique is several times faster than unique(axis=0).
    keys = (grid[:, 0] * size[1] + grid[:, 1]) * size[2] + grid[:, 2]
    _, cell, counts = np.unique(keys, return_inverse=True, return_counts=True)
    cell = cell.reshape(-1)
    sums = np.stack([np.bincount(cell, weights=c, minlength=len(counts)) for c in points.T], 1)
    return sums / counts[:, None], cell
