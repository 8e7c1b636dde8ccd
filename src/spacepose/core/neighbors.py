"""Shared neighbour searches and neighbourhood statistics.

Every stage that needs neighbours (normals, mpp-MLS, FPFH, GICP covariances, ICP) goes through
these few functions so that padding conventions and argument checks are the same everywhere.
Neighbour arrays are padded: an (M, k) index array holds ``-1`` where a query has fewer than k
neighbours, and the matching distances are ``inf``. A search runs on a
:class:`~spacepose.core.grid.VoxelIndex` (built from points by default: exact and 1.2–2× faster
than ``cKDTree`` on lab clouds, more with two threads) or on a ``cKDTree`` the caller passes;
both answer with the same contract. ``workers`` is passed straight to their ``query``; the
results do not depend on it.
"""

from __future__ import annotations

import numba
import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree

from spacepose.core.cloud import as_points
from spacepose.core.grid import VoxelIndex, self_knn_occupancy
from spacepose.core.threads import numba_threads
from spacepose.errors import InputError

SearchIndex = cKDTree | VoxelIndex
TreeOrPoints = SearchIndex | ArrayLike
# Rows per unit of parallel work in the neighbourhood statistics: amortises scheduling.
_BLOCK_ROWS = 256


def as_tree(tree_or_points: TreeOrPoints) -> SearchIndex:
    """Return ``tree_or_points`` if it is a search index, else a VoxelIndex of the (N, 3) points."""
    if isinstance(tree_or_points, cKDTree | VoxelIndex):
        return tree_or_points
    return VoxelIndex(as_points(tree_or_points, "points"))


def knn(
    tree_or_points: TreeOrPoints,
    queries: ArrayLike | None,
    k: int,
    workers: int = -1,
    distance_upper_bound: float = np.inf,
) -> tuple[NDArray[np.float64], NDArray[np.intp]]:
    """The k nearest neighbours of each query point.

    Parameters
    ----------
    tree_or_points
        A search index (``cKDTree``, VoxelIndex) or the (N, 3) points.
    queries
        (M, 3) query points, same frame as the searched points; None for the searched points
        themselves (a VoxelIndex then shares its cell lookups between neighbouring queries,
        :meth:`~spacepose.core.grid.VoxelIndex.query_self`; one built here from points has
        cells of :func:`~spacepose.core.grid.self_knn_occupancy` points).
    k
        Number of neighbours, ``1 <= k <= N``. A query that is itself one of the points gets
        itself as its first neighbour.
    workers
        Threads for the search (-1: all cores).
    distance_upper_bound
        Only neighbours strictly nearer than this (m) are returned (a local neighbourhood:
        a point far from every other then costs nothing to search).

    Returns
    -------
    dist, idx
        (M, k) Euclidean distances, ascending, and the (M, k) indices into the searched points;
        a missing neighbour has distance ``inf`` and index N.
    """
    k = int(k)
    if not distance_upper_bound > 0:
        # cKDTree takes a NaN bound and finds nothing: refused here for every index alike.
        raise InputError(f"distance_upper_bound must be positive, got {distance_upper_bound}")
    if queries is None and not isinstance(tree_or_points, cKDTree | VoxelIndex):
        # Its own index, with cells sized for this k (the same answer, sooner).
        tree = VoxelIndex(as_points(tree_or_points, "points"), occupancy=self_knn_occupancy(k))
    else:
        tree = as_tree(tree_or_points)
    if not 1 <= k <= tree.n:
        raise InputError(f"knn: k must be in 1..{tree.n} (number of points), got {k}")
    if queries is None and isinstance(tree, VoxelIndex):
        return tree.query_self(k, workers, distance_upper_bound)
    q = tree.data if queries is None else as_points(queries, "queries")
    dist, idx = tree.query(q, k=k, distance_upper_bound=distance_upper_bound, workers=workers)
    # The indices drop the k axis for k = 1; keep (M, k) whatever k is.
    return dist.reshape(len(q), k), idx.reshape(len(q), k)


def hybrid(
    tree_or_points: TreeOrPoints,
    queries: ArrayLike,
    radius: float,
    max_nn: int,
    workers: int = -1,
) -> tuple[NDArray[np.intp], NDArray[np.float64]]:
    """Radius search capped at the ``max_nn`` nearest (Open3D's ``KDTreeSearchParamHybrid``).

    Parameters
    ----------
    tree_or_points
        A search index (``cKDTree``, VoxelIndex) or the (N, 3) points.
    queries
        (M, 3) query points.
    radius
        Search radius in metres (> 0).
    max_nn
        Largest number of neighbours kept per query (>= 1); the nearest ones are kept.
    workers
        Threads for the search (-1: all cores).

    Returns
    -------
    idx, dist
        (M, max_nn) indices, ascending by distance, padded with ``-1``; (M, max_nn) distances
        padded with ``inf``. ``idx >= 0`` is the validity mask.
    """
    tree = as_tree(tree_or_points)
    q = as_points(queries, "queries")
    if not np.isfinite(radius) or radius <= 0:
        raise InputError(f"hybrid search radius must be a positive number, got {radius}")
    if int(max_nn) < 1:
        raise InputError(f"hybrid search max_nn must be >= 1, got {max_nn}")
    k = int(max_nn)
    dist, idx = tree.query(q, k=k, distance_upper_bound=radius, workers=workers)
    dist, idx = dist.reshape(len(q), k), idx.reshape(len(q), k)
    # The indices mark missing neighbours with index n; use -1 so that a bad index fails loudly.
    idx[idx >= tree.n] = -1
    return idx, dist


def weighted_moments(
    points: ArrayLike, idx: NDArray[np.intp], weights: ArrayLike, workers: int = 1
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Weighted mean and covariance of each neighbourhood, batched.

    Parameters
    ----------
    points
        (N, 3) points the indices refer to.
    idx
        (M, k) neighbour indices, ``-1`` for padding.
    weights
        (M, k) non-negative weights; padded entries are ignored whatever their weight.
    workers
        Threads (-1: all cores); the result does not depend on it.

    Returns
    -------
    mean, cov, total
        (M, 3) weighted means, (M, 3, 3) weighted covariances ``Σ w (p − μ)(p − μ)ᵀ / Σ w`` and
        the (M,) total weights. Rows with zero total weight get a zero mean and covariance.
    """
    pts = np.ascontiguousarray(as_points(points, "points"), dtype=np.float64)
    idx = np.asarray(idx)
    if idx.ndim != 2 or not np.issubdtype(idx.dtype, np.integer):
        raise InputError(f"neighbour indices must be an (M, k) integer array, got {idx.shape}")
    w = np.asarray(weights, dtype=np.float64)
    if w.shape != idx.shape:
        raise InputError(f"weights must have the shape of the indices {idx.shape}, got {w.shape}")
    mean = np.empty((len(idx), 3))
    cov = np.empty((len(idx), 3, 3))
    total = np.empty(len(idx))
    with numba_threads(workers):
        out_of_range = _moments_kernel(
            pts,
            np.ascontiguousarray(idx, dtype=np.int64),
            np.ascontiguousarray(w),
            mean,
            cov,
            total,
        )
    if out_of_range:
        raise InputError(
            f"{out_of_range} neighbour indices are >= the number of points ({len(pts)})"
        )
    return mean, cov, total


@numba.njit(cache=True, parallel=True)
def _moments_kernel(pts, idx, w, mean, cov, total):
    """Fill ``mean`` (M, 3), ``cov`` (M, 3, 3) and ``total`` (M,) row by row
    (:func:`row_moments`); return the number of indices beyond the points (those entries are
    skipped), for the caller to report."""
    n_rows = len(idx)
    out_of_range = 0
    for chunk in numba.prange((n_rows + _BLOCK_ROWS - 1) // _BLOCK_ROWS):
        for i in range(chunk * _BLOCK_ROWS, min(n_rows, (chunk + 1) * _BLOCK_ROWS)):
            total[i], bad = row_moments(pts, idx[i], w[i], mean[i], cov[i])
            out_of_range += bad
    return out_of_range


@numba.njit(cache=True, inline="always")
def row_moments(pts, idx_row, w_row, mean_row, cov_row):
    """Weighted mean (3,) and covariance (3, 3) of one neighbourhood into ``mean_row`` and
    ``cov_row``, for compiled callers; returns (total weight, number of indices beyond the
    points). ``w_row`` empty: unit weights. Padding (-1) and out-of-range indices are skipped.

    Summed in the row's own fixed order, so the result is the same on any thread count.
    """
    n, k = len(pts), len(idx_row)
    unit = len(w_row) == 0
    s = mx = my = mz = 0.0
    out_of_range = 0
    for j in range(k):
        p = idx_row[j]
        if p >= n:
            out_of_range += 1
        if p < 0 or p >= n:
            continue
        wj = 1.0 if unit else w_row[j]
        s += wj
        mx += wj * pts[p, 0]
        my += wj * pts[p, 1]
        mz += wj * pts[p, 2]
    # Zero total weight (all padding, or zero weights): zero moments, not 0 / 0.
    inv = 1.0 / s if s > 0 else 0.0
    mx *= inv
    my *= inv
    mz *= inv
    # Centre before the outer products: cumulant sums lose digits far from the origin.
    cxx = cxy = cxz = cyy = cyz = czz = 0.0
    for j in range(k):
        p = idx_row[j]
        if p < 0 or p >= n:
            continue
        wj = (1.0 if unit else w_row[j]) * inv
        dx = pts[p, 0] - mx
        dy = pts[p, 1] - my
        dz = pts[p, 2] - mz
        cxx += wj * dx * dx
        cxy += wj * dx * dy
        cxz += wj * dx * dz
        cyy += wj * dy * dy
        cyz += wj * dy * dz
        czz += wj * dz * dz
    mean_row[0], mean_row[1], mean_row[2] = mx, my, mz
    cov_row[0, 0], cov_row[0, 1], cov_row[0, 2] = cxx, cxy, cxz
    cov_row[1, 0], cov_row[1, 1], cov_row[1, 2] = cxy, cyy, cyz
    cov_row[2, 0], cov_row[2, 1], cov_row[2, 2] = cxz, cyz, czz
    return s, out_of_range


def local_covariances(
    points: ArrayLike, idx: NDArray[np.intp], mask: ArrayLike | None = None, workers: int = 1
) -> NDArray[np.float64]:
    """Covariance ``Σ (p − μ)(p − μ)ᵀ / n`` of each point's neighbours, batched.

    Parameters
    ----------
    points
        (N, 3) points the indices refer to.
    idx
        (M, k) neighbour indices (from :func:`knn` or :func:`hybrid`), ``-1`` for padding.
    mask
        Optional (M, k) boolean mask of the neighbours to use (``idx >= 0`` when omitted).
    workers
        Threads (-1: all cores); the result does not depend on it.

    Returns
    -------
    (M, 3, 3) covariances, normalised by the neighbour count (zero for an empty neighbourhood).
    """
    idx = np.asarray(idx)
    use = idx >= 0 if mask is None else np.asarray(mask, dtype=bool) & (idx >= 0)
    _, cov, _ = weighted_moments(points, idx, use.astype(np.float64), workers=workers)
    return cov
