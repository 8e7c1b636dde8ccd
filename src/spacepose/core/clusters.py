"""Euclidean clusters of a point cloud: the groups linked by short distances, and the largest
group with the clusters near it (the target's cluster group of :mod:`spacepose.core.background`).

Points are (N, 3) in any one frame, distances in metres. Labels and ties follow the lowest point
index, so a result does not depend on the thread count.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from spacepose.errors import InputError


def cluster_labels(points: NDArray[np.float64], distance: float) -> NDArray[np.intp]:
    """Labels (N,) of the groups of points connected by links shorter than ``distance``.

    Labels are numbered in the order of each group's lowest point index.

    Raises
    ------
    InputError
        ``distance`` is not a positive, finite number of metres (0 or NaN left every point its
        own cluster, a negative or infinite one put them all in one), or the points are not a
        finite (N, 3) array.
    """
    _check_distance("distance", distance)
    points = np.asarray(points, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3:
        raise InputError(f"cluster_labels: points must have shape (N, 3), got {points.shape}")
    if not np.isfinite(points).all():
        raise InputError("cluster_labels: points have non-finite entries (NaN or inf)")
    distinct = _distinct_rows(points)
    if distinct is None:
        return _linked(points, distance)
    # Rows repeated exactly (a driver's (0, 0, 0) for every pixel without a return) are one
    # point: every pair of copies is a link, and 20,000 copies took 9.7 GB to list them.
    first, inverse = distinct
    labels = _linked(points[first], distance)[inverse]
    # Numbered again by each group's lowest point index, as without copies.
    lowest = np.full(labels.max() + 1, len(points))
    np.minimum.at(lowest, labels, np.arange(len(points)))
    rank = np.empty_like(lowest)
    rank[np.argsort(lowest)] = np.arange(len(lowest))
    return rank[labels]


def _linked(points: NDArray[np.float64], distance: float) -> NDArray[np.intp]:
    """Connected components (N,) of the links shorter than ``distance``."""
    n = len(points)
    pairs = cKDTree(points).query_pairs(distance, output_type="ndarray")
    graph = coo_matrix(
        (np.ones(len(pairs), dtype=np.int8), (pairs[:, 0], pairs[:, 1])), shape=(n, n)
    )
    return connected_components(graph, directed=False)[1]


def _distinct_rows(
    points: NDArray[np.float64],
) -> tuple[NDArray[np.intp], NDArray[np.intp]] | None:
    """(index of each distinct row, (N,) distinct row of each point) when some rows repeat
    exactly, else None. A hash of the rows' bits rules out repeats in one sort (about 25 ms for
    300,000 points, where ``np.unique`` over rows takes 450 ms)."""
    bits = np.ascontiguousarray(points, dtype=np.float64).view(np.int64)
    key = np.sort(bits[:, 0] ^ (bits[:, 1] * 1_000_003) ^ (bits[:, 2] * 998_244_353))
    if not (key[1:] == key[:-1]).any():
        return None
    _, first, inverse = np.unique(points, axis=0, return_index=True, return_inverse=True)
    return first, inverse.ravel()


def main_cluster_group(
    points: NDArray[np.float64],
    distance: float,
    merge_distance: float,
    min_share: float,
    workers: int = -1,
) -> NDArray[np.bool_]:
    """Mask (N,) of the largest Euclidean cluster and the clusters merged with it.

    Parameters
    ----------
    points
        (N, 3) points, any frame (m).
    distance
        Link length (m) of the clusters.
    merge_distance
        Clusters of at least ``min_share`` of the largest one's size whose closest points are
        within this (m) of each other are merged, transitively, starting from the largest.
    min_share
        Smallest cluster size, as a share of the largest, that can be merged.
    workers
        Threads for the nearest-neighbour queries.

    Returns
    -------
    NDArray
        The mask; empty for no points (argmax of no cluster sizes failed before).

    Notes
    -----
    Ties between equally large clusters go to the one holding the lowest point index.
    """
    _check_distance("merge_distance", merge_distance)
    if not 0.0 < min_share <= 1.0:
        raise InputError(f"min_share must be in (0, 1], got {min_share}")
    labels = cluster_labels(points, distance)
    if len(labels) == 0:
        return np.zeros(0, dtype=bool)
    sizes = np.bincount(labels)
    # argmax returns the first label of the largest size: labels follow the lowest point index.
    largest = int(np.argmax(sizes))
    big = np.flatnonzero(sizes >= min_share * sizes[largest])
    group = labels == largest
    if merge_distance <= distance:
        return group
    waiting = np.isin(labels, big) & ~group
    # Grow the group from the largest cluster: a cluster joins when one of its points is within
    # merge_distance of the clusters that joined last (those near earlier ones joined then).
    # Each round is one tree query over the waiting points; rounds = merge chain length.
    frontier = group
    while np.any(waiting):
        idx = np.flatnonzero(waiting)
        d, _ = cKDTree(points[frontier]).query(
            points[idx], distance_upper_bound=merge_distance, workers=workers
        )
        joining = np.isin(labels, labels[idx[np.isfinite(d)]]) & waiting
        if not np.any(joining):
            break
        group |= joining
        waiting &= ~joining
        frontier = joining
    return group


def _check_distance(name: str, value: float) -> None:
    """A link length must be a positive, finite number of metres."""
    try:
        ok = 0.0 < float(value) < np.inf
    except (TypeError, ValueError):
        ok = False
    if not ok:
        raise InputError(f"{name} must be a positive, finite number of metres, got {value!r}")
