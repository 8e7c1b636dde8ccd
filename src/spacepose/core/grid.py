"""Voxel-hash neighbour index: exact k-nearest and gated nearest searches, compiled and threaded.

``scipy.spatial.cKDTree`` spends about 1.8 µs per k = 15 query on a 5000-point lab keyframe and
gains nothing from a second thread at that size; the tracker asks for such searches every frame
(keyframe normals, ICP correspondences), and a Python loop over queries cannot be vectorised in
numpy (every query visits a different, variable number of candidates). So the search is a numba
kernel over a hash of voxel cells:

* the points are grouped by cell; a direct table (or, for a sparse box, an open-addressing
  hash) maps a cell key to its run of points;
* a query visits the cells overlapping the box around its search ball and keeps the k best
  candidates ordered by (squared distance, index): ties are broken by index, so the answer does
  not depend on the visiting order;
* without an upper bound the ball radius starts at the previous query's k-th distance (queries
  arrive spatially sorted in practice) and grows until the k-th best lies inside it, which makes
  the answer exact: every point nearer than it sits in a visited cell;
* the k nearest of every indexed point (normals, covariances) are taken a cell at a time, the
  block of cells around it shared by all its points (:meth:`VoxelIndex.query_self`);
* the gated nearest point (ICP correspondences) starts at the point's previous match, or else
  at its own cell (a gate within a cell) or the cells ring by ring, nearest first
  (:func:`~spacepose.core.grid_nearest.nearest_point`, also called from other modules'
  kernels); a query that moved less than its last search's margin keeps that answer
  unsearched (:func:`~spacepose.core.grid_nearest.certified_nearest`).

Queries are independent, so the result is the same on any thread count. :class:`VoxelIndex`
answers ``query`` with the contract of ``cKDTree.query`` (missing neighbours: index ``n``,
distance ``inf``; the k axis dropped for ``k=1``) so either structure can back a search.

This module builds the index and checks the calls; the compiled searches are in
:mod:`spacepose.core.grid_knn` (k nearest) and :mod:`spacepose.core.grid_nearest` (gated
nearest), the thread count in :mod:`spacepose.core.threads`.
"""

from __future__ import annotations

import functools

import numpy as np
from numpy.typing import ArrayLike, NDArray

from spacepose.core.cell_hash import group_cells
from spacepose.core.cloud import as_points
from spacepose.core.grid_knn import knn_kernel, self_knn_kernel
from spacepose.core.grid_nearest import nearest_kernel
from spacepose.core.threads import numba_threads
from spacepose.core.voxel import bounds, cell_keys
from spacepose.errors import InputError

# Mean points per occupied cell the automatic cell size aims at: a k ≈ 15..30 ball then spans
# a few cells per axis and a correspondence gate one or two.
_TARGET_OCCUPANCY = 6.0
# Rings of cells a gated search visits one by one before falling back to the gate's box.
_MAX_RINGS = 6
# Largest number of cells per axis; three of them pack into one int64 key.
_MAX_CELLS_PER_AXIS = 1 << 20
# Direct (dense) cell table while the box has at most this many cells per point (plus a floor):
# a scanned surface fills few of its box's cells, but a lookup then costs one load.
_DENSE_CELLS_PER_POINT = 16
_DENSE_CELLS_MIN = 1 << 16
# Rows left unsure by the shared-cell search worth a second thread (each takes about 4 µs).
_PARALLEL_ROWS = 256


class VoxelIndex:
    """Points hashed by voxel cell, searched like a ``cKDTree``.

    Parameters
    ----------
    points
        (N, 3) finite points, any frame (m); N >= 1.
    cell_size
        Cell edge (m); by default chosen so that occupied cells hold about ``occupancy`` points.
    occupancy
        Mean points per occupied cell the default cell size aims at (>= 1). Six suits gated
        nearest searches; :meth:`query_self` with a large k is faster on fuller cells
        (:func:`self_knn_occupancy`).

    Attributes
    ----------
    data
        (N, 3) the points, as given (read-only copy).
    n, m
        Number of points and dimension (3), as on a ``cKDTree``.
    cell_size
        Cell edge (m).
    kernel_grid
        The arrays and scalars the compiled searches take, as one tuple (for kernels in other
        modules that call :func:`nearest_point`).
    """

    def __init__(
        self,
        points: ArrayLike,
        cell_size: float | None = None,
        occupancy: float = _TARGET_OCCUPANCY,
    ) -> None:
        pts = as_points(points, "points")
        self.data = np.array(pts, dtype=np.float64)
        self.data.setflags(write=False)
        self.n, self.m = len(pts), 3
        low, high = bounds(self.data)
        if not occupancy >= 1:
            raise InputError(f"occupancy must be at least one point per cell, got {occupancy}")
        auto = cell_size is None
        h = _auto_cell_size(self.data, low, high, occupancy) if auto else float(cell_size)
        if not np.isfinite(h) or h <= 0:
            raise InputError(f"cell_size must be a positive number of metres, got {cell_size}")
        # Cells never exceed the key range: a cloud much wider than its cells gets larger cells.
        h = max(h, float((high - low).max()) / (_MAX_CELLS_PER_AXIS - 1))
        self.origin, self.cell_size = low, h
        # Anchored at the smallest corner, so the cells start at 0 on every axis.
        keys, self.dims, _ = cell_keys(self.data, h, low)
        cell, self._cell_keys, table, bits = group_cells(keys)
        # Points grouped by cell (cells in order of first appearance, points in index order).
        self._order = np.argsort(cell, kind="stable")
        self._rank = np.empty_like(self._order)
        self._rank[self._order] = np.arange(self.n)
        self._points = np.ascontiguousarray(self.data[self._order])
        counts = np.bincount(cell, minlength=len(self._cell_keys))
        self._starts = np.concatenate([[0], np.cumsum(counts)]).astype(np.int64)
        n_cells = int(np.prod(self.dims.astype(np.float64)))
        if n_cells <= _DENSE_CELLS_PER_POINT * self.n + _DENSE_CELLS_MIN:
            # A direct table over the whole box: a lookup is one load instead of a probe.
            table, bits = np.full(n_cells, -1, dtype=np.int64), 0
            table[self._cell_keys] = np.arange(len(self._cell_keys))
        # Everything a kernel needs, in the order _collect and nearest_point unpack it.
        self.kernel_grid = (
            self._points,
            self._order,
            self._starts,
            self._cell_keys,
            table,
            bits,
            self.origin,
            h,
            self.dims,
            self._rank,
        )

    def query(
        self,
        x: ArrayLike,
        k: int = 1,
        distance_upper_bound: float = np.inf,
        workers: int = 1,
    ) -> tuple[NDArray[np.float64], NDArray[np.intp]]:
        """The ``k`` nearest points of each query, as ``cKDTree.query`` returns them.

        Parameters
        ----------
        x
            (M, 3) query points, the frame of the indexed points.
        k
            Number of neighbours (>= 1).
        distance_upper_bound
            Only neighbours strictly nearer than this (m) are returned.
        workers
            Threads (-1: all cores); the result does not depend on it.

        Returns
        -------
        dist, idx
            (M, k) distances ascending and indices into ``data`` (ties by index); a missing
            neighbour has distance ``inf`` and index ``n``. For ``k=1`` both are (M,).
        """
        q = as_points(x, "queries")
        k = int(k)
        if k < 1:
            raise InputError(f"k must be >= 1, got {k}")
        bound = float(distance_upper_bound)
        if np.isnan(bound) or bound <= 0:
            raise InputError(f"distance_upper_bound must be positive, got {distance_upper_bound}")
        if k == 1 and np.isfinite(bound):
            # The gated nearest neighbour: the ring-by-ring search of nearest_within.
            nearest, d2_1 = self.nearest_within(q, bound, workers=workers)
            return np.sqrt(d2_1), np.where(nearest < 0, self.n, nearest)
        d2 = np.empty((len(q), k))
        idx = np.empty((len(q), k), dtype=np.int64)
        with numba_threads(workers):
            knn_kernel(
                self.kernel_grid, np.ascontiguousarray(q, dtype=np.float64), k, bound, d2, idx
            )
        missing = idx < 0
        idx[missing] = self.n
        dist = np.sqrt(d2, out=d2)
        if k == 1:
            return dist[:, 0], idx[:, 0]
        return dist, idx

    def query_self(
        self, k: int, workers: int = 1, distance_upper_bound: float = np.inf
    ) -> tuple[NDArray[np.float64], NDArray[np.intp]]:
        """The ``k`` nearest indexed points of every indexed point (itself included): the
        answer of ``query(data, k)``, about twice as fast.

        Queries are taken a cell at a time: the points of the cells around a cell (27, or more
        for a large k) are the candidates of all its points, visited nearest first, so the cell
        lookups are shared, and a point whose k-th distance stays within those cells needs
        nothing else (every point outside them is farther). The few others (sparse borders)
        are searched one by one, within ``distance_upper_bound`` when it is finite: an isolated
        point (a flying pixel far from any surface) otherwise scans every cell out to its k-th
        neighbour, and a thousand of them took a 1280×720 frame's 47k-point keyframe from
        22 ms to 130.

        Parameters
        ----------
        k
            Number of neighbours, 1 <= k <= n.
        workers
            Threads (-1: all cores); the result does not depend on it.
        distance_upper_bound
            Only neighbours strictly nearer than this (m) are returned, as :meth:`query`.

        Returns
        -------
        dist, idx
            (n, k) distances ascending and indices into ``data`` (ties by index); a missing
            neighbour has distance ``inf`` and index ``n``.
        """
        k = int(k)
        if not 1 <= k <= self.n:
            raise InputError(f"k must be in 1..{self.n} (number of points), got {k}")
        bound = float(distance_upper_bound)
        if np.isnan(bound) or bound <= 0:
            raise InputError(f"distance_upper_bound must be positive, got {distance_upper_bound}")
        # Zeros: the rows left unsure are filled below, not read before.
        d2 = np.zeros((self.n, k))
        idx = np.empty((self.n, k), dtype=np.int64)
        unsure = np.zeros(self.n, dtype=np.bool_)
        # Cells around each cell to take as candidates: enough that the k-th neighbour of a
        # typical point lies within them (a scanned surface holds about π r² / h² · occupancy
        # points within r). No margin: the stragglers cost less one by one than a wider block
        # for all (k = 15 on a lab keyframe: 3.7 ms with one cell around, 4.7 with two).
        occupancy = self.n / len(self._cell_keys)
        reach = int(np.ceil(np.sqrt(k / (np.pi * occupancy))))
        with numba_threads(workers):
            reach = max(reach, 1)
            self_knn_kernel(self.kernel_grid, k, _near_first(reach), reach, d2, idx, unsure)
        dist = np.sqrt(d2, out=d2)
        if unsure.any():
            rows = np.flatnonzero(unsure)
            # A few per cent of the rows: one thread unless there are many (waking a second
            # costs more than a few rows; 997 stray rows of a 1280×720 keyframe: 3.7 -> 1.9 ms).
            threads = workers if len(rows) >= _PARALLEL_ROWS else 1
            d, i = self.query(self.data[rows], k=k, distance_upper_bound=bound, workers=threads)
            dist[rows], idx[rows] = d.reshape(len(rows), k), i.reshape(len(rows), k)
        if np.isfinite(bound):
            far = dist >= bound
            dist[far], idx[far] = np.inf, self.n
        return dist, idx

    def rings(self, max_distance: float) -> NDArray[np.int64]:
        """(M, 4) cell offsets ``(dx, dy, dz, r)`` around a cell out to the ring ``r`` that
        covers ``max_distance`` and one ring more (at most :data:`_MAX_RINGS`), sorted by ring
        ``r`` (Chebyshev distance) and then nearest first: the visiting order of
        :func:`nearest_point`. The ring beyond gives a query with nothing within the gate a
        certificate a cell wide (:func:`certified_nearest`)."""
        return _rings(int(min(np.ceil(max_distance / self.cell_size) + 1, _MAX_RINGS)))

    def nearest_within(
        self,
        points: NDArray[np.float64],
        max_distance: float,
        hint: NDArray[np.int64] | None = None,
        workers: int = 1,
    ) -> tuple[NDArray[np.int64], NDArray[np.float64]]:
        """Nearest indexed point strictly within ``max_distance`` of each point.

        The correspondence search of ICP-like loops, with an optional warm start. A point's
        previous nearest (``hint``) bounds its search ball before any cell is visited; after a
        small move that ball is a few millimetres wide instead of the whole gate, so late
        iterations visit a cell or two per point. The answer does not depend on the hint.

        Parameters
        ----------
        points
            (N, 3) points in the index's frame.
        max_distance
            Gate (m), > 0.
        hint
            (N,) index into ``data`` of a candidate per point (-1: none), e.g. the previous
            call's answer.
        workers
            Threads (-1: all cores); the result does not depend on it.

        Returns
        -------
        idx, dist2
            (N,) index into ``data`` of each point's nearest (-1: none within the gate) and its
            squared distance (``inf`` when none).
        """
        points = as_points(points, "points")
        if not np.isfinite(max_distance) or max_distance <= 0:
            raise InputError(f"max_distance must be a positive number, got {max_distance}")
        if hint is None:
            hint = np.full(len(points), -1, dtype=np.int64)
        else:
            hint = np.asarray(hint)
            if hint.shape != (len(points),) or not np.issubdtype(hint.dtype, np.integer):
                raise InputError(f"hints must be ({len(points)},) integers, got {hint.shape}")
            # The kernel looks a hint up unchecked: out of range would read stray memory.
            if len(hint) and (hint.min() < -1 or hint.max() >= self.n):
                raise InputError(f"hints must lie in -1..{self.n - 1}")
        idx = np.empty(len(points), dtype=np.int64)
        d2 = np.empty(len(points))
        with numba_threads(workers):
            nearest_kernel(
                self.kernel_grid,
                self.rings(max_distance),
                np.ascontiguousarray(points, dtype=np.float64),
                np.asarray(hint, dtype=np.int64),
                float(max_distance),
                idx,
                d2,
            )
        return idx, d2


def self_knn_occupancy(k: int) -> float:
    """Cell occupancy for a :meth:`VoxelIndex.query_self` of ``k`` neighbours: a third of k
    (at least the default), so that a point's k nearest lie within the 27 cells around its own
    and the search shares 27 cell lookups per cell instead of 125. On the bench's lab frame
    (18k points, k = 30, occupancy 6 -> 11): 26 -> 21.6 ms, the same answer."""
    return max(k / 3.0, _TARGET_OCCUPANCY)


def _auto_cell_size(
    points: NDArray[np.float64],
    low: NDArray[np.float64],
    high: NDArray[np.float64],
    target: float = _TARGET_OCCUPANCY,
) -> float:
    """A cell edge (m) giving about ``target`` points per occupied cell.

    One trial count at the spacing a surface of this extent would have, then a surface-like
    (area) rescaling: clouds here are scanned surfaces.
    """
    diagonal = float(np.linalg.norm(high - low))
    if diagonal == 0.0:
        return 1.0
    trial = max(diagonal / np.sqrt(len(points)), diagonal / (_MAX_CELLS_PER_AXIS - 1))
    keys, _, _ = cell_keys(points, trial, low)
    occupancy = len(points) / len(group_cells(keys)[1])
    return trial * float(np.sqrt(target / occupancy))


@functools.cache
def _rings(reach: int) -> NDArray[np.int64]:
    offsets = _near_first(max(reach, 1))
    ring = np.abs(offsets).max(axis=1)
    out = np.column_stack([offsets, ring])[np.argsort(ring, kind="stable")]
    out.setflags(write=False)
    return out


@functools.cache
def _near_first(reach: int) -> NDArray[np.int64]:
    """The (2r + 1)³ cell offsets within ``reach`` cells, nearest first (own cell, faces,
    edges, ...): a k-best buffer then fills with near points and rejects most of the rest at
    the first comparison."""
    side = 2 * reach + 1
    offsets = np.array(list(np.ndindex(side, side, side)), dtype=np.int64) - reach
    return offsets[np.argsort(np.abs(offsets).sum(axis=1), kind="stable")]
