"""Shared neighbour searches and neighbourhood statistics on :class:`scipy.spatial.cKDTree`.

Every stage that needs neighbours (normals, mpp-MLS, FPFH, GICP covariances, ICP) goes through
these few functions so that padding conventions and argument checks are the same everywhere.
Neighbour arrays are padded: an (M, k) index array holds ``-1`` where a query has fewer than k
neighbours, and the matching distances are ``inf``. ``workers`` is passed straight to
``cKDTree.query``; the results do not depend on it.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree

from spacepose.core.cloud import as_points
from spacepose.errors import InputError

TreeOrPoints = cKDTree | ArrayLike
# Rows per block of the neighbourhood statistics (measured best of 128..4096 for k = 20..30).
_BLOCK_ROWS = 256


def as_tree(tree_or_points: TreeOrPoints) -> cKDTree:
    """Return ``tree_or_points`` if it is a ``cKDTree``, else a tree built on the (N, 3) points."""
    if isinstance(tree_or_points, cKDTree):
        return tree_or_points
    return cKDTree(as_points(tree_or_points, "points"))


def knn(
    tree_or_points: TreeOrPoints, queries: ArrayLike, k: int, workers: int = -1
) -> tuple[NDArray[np.float64], NDArray[np.intp]]:
    """The k nearest neighbours of each query point.

    Parameters
    ----------
    tree_or_points
        A ``cKDTree`` or the (N, 3) points to search.
    queries
        (M, 3) query points, same frame as the searched points.
    k
        Number of neighbours, ``1 <= k <= N``. A query that is itself one of the points gets
        itself as its first neighbour.
    workers
        Threads for the search (-1: all cores).

    Returns
    -------
    dist, idx
        (M, k) Euclidean distances, ascending, and the (M, k) indices into the searched points.
    """
    tree = as_tree(tree_or_points)
    q = as_points(queries, "queries")
    k = int(k)
    if not 1 <= k <= tree.n:
        raise InputError(f"knn: k must be in 1..{tree.n} (number of points), got {k}")
    dist, idx = tree.query(q, k=k, workers=workers)
    # cKDTree drops the k axis for k = 1; keep (M, k) whatever k is.
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
        A ``cKDTree`` or the (N, 3) points to search.
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
    # cKDTree marks missing neighbours with index n; use -1 so that a bad index fails loudly.
    idx[idx >= tree.n] = -1
    return idx, dist


def weighted_moments(
    points: ArrayLike, idx: NDArray[np.intp], weights: ArrayLike
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

    Returns
    -------
    mean, cov, total
        (M, 3) weighted means, (M, 3, 3) weighted covariances ``Σ w (p − μ)(p − μ)ᵀ / Σ w`` and
        the (M,) total weights. Rows with zero total weight get a zero mean and covariance.
    """
    pts = as_points(points, "points")
    idx = np.asarray(idx)
    w = np.where(idx >= 0, np.asarray(weights, dtype=np.float64), 0.0)
    total = w.sum(axis=1)
    # Normalised weights; a row with zero total weight keeps zeros, hence zero moments.
    w /= np.where(total > 0, total, 1.0)[:, None]
    mean = np.empty((len(idx), 3))
    cov = np.empty((len(idx), 3, 3))
    # Blocks of rows keep the (rows, k, 3) temporaries in cache: twice as fast as one pass.
    for start in range(0, len(idx), _BLOCK_ROWS):
        rows = slice(start, start + _BLOCK_ROWS)
        nb = pts[np.maximum(idx[rows], 0)]  # (B, k, 3); padding reads point 0 with weight 0
        wb = w[rows]
        mu = np.matmul(wb[:, None, :], nb)[:, 0]
        # Centre before the outer products: cumulant sums lose digits far from the origin.
        d = nb - mu[:, None, :]
        cov[rows] = np.matmul(np.swapaxes(d * wb[:, :, None], 1, 2), d)
        mean[rows] = mu
    return mean, cov, total


def local_covariances(
    points: ArrayLike, idx: NDArray[np.intp], mask: ArrayLike | None = None
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

    Returns
    -------
    (M, 3, 3) covariances, normalised by the neighbour count (zero for an empty neighbourhood).
    """
    idx = np.asarray(idx)
    use = idx >= 0 if mask is None else np.asarray(mask, dtype=bool) & (idx >= 0)
    _, cov, _ = weighted_moments(points, idx, use.astype(np.float64))
    return cov
