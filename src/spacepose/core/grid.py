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
  (:func:`nearest_point`, also called from other modules' kernels); a query that moved less
  than its last search's margin keeps that answer unsearched (:func:`certified_nearest`).

Queries are independent, so the result is the same on any thread count. :class:`VoxelIndex`
answers ``query`` with the contract of ``cKDTree.query`` (missing neighbours: index ``n``,
distance ``inf``; the k axis dropped for ``k=1``) so either structure can back a search.
"""

from __future__ import annotations

import functools
import os
from collections.abc import Iterator
from contextlib import contextmanager

import numba
import numpy as np
from numpy.typing import ArrayLike, NDArray

from spacepose.core.cloud import as_points
from spacepose.core.voxel import bounds, cell_keys, find_cell, group_cells
from spacepose.errors import InputError

# Queries per unit of parallel work: enough to amortise scheduling, few enough to balance.
_CHUNK = 64
# Mean points per occupied cell the automatic cell size aims at: a k ≈ 15..30 ball then spans
# a few cells per axis and a correspondence gate one or two.
_TARGET_OCCUPANCY = 6.0
# Rings of cells a gated search visits one by one before falling back to the gate's box.
_MAX_RINGS = 6
# Largest number of cells per axis; three of them pack into one int64 key.
_MAX_CELLS_PER_AXIS = 1 << 20
# Bands of squared distance the self k-nearest search sorts its candidates into, over this
# multiple of the previous point's squared k-th distance (the rest: one more band): the bands
# below the k-th's are taken without comparisons, about two points each are sorted.
_BANDS = 32
_BAND_SPAN = 2.0
# Direct (dense) cell table while the box has at most this many cells per point (plus a floor):
# a scanned surface fills few of its box's cells, but a lookup then costs one load.
_DENSE_CELLS_PER_POINT = 16
_DENSE_CELLS_MIN = 1 << 16
# OpenMP before TBB: Open3D (the optional peer) bundles a TBB older than numba accepts, and the
# OpenMP layer, unlike the workqueue fallback, takes concurrent calls from several threads.
numba.config.THREADING_LAYER_PRIORITY = ["omp", "tbb", "workqueue"]
# Idle OpenMP threads sleep instead of spinning: after a short kernel a spinning thread takes a
# core from the work that follows (a lab tracking step interleaved with Open3D took 80 ms instead
# of 27 on two cores). Read when the OpenMP runtime starts; a user's own setting wins.
os.environ.setdefault("OMP_WAIT_POLICY", "PASSIVE")


@contextmanager
def numba_threads(workers: int) -> Iterator[None]:
    """Run the enclosed kernels on ``workers`` threads (-1: all cores), then restore the count."""
    available = numba.config.NUMBA_NUM_THREADS
    if workers == -1:
        count = available
    elif isinstance(workers, int | np.integer) and workers >= 1:
        count = min(int(workers), available)
    else:
        raise InputError(f"workers must be -1 (all cores) or a positive count, got {workers}")
    before = numba.get_num_threads()
    numba.set_num_threads(count)
    try:
        yield
    finally:
        numba.set_num_threads(before)


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
            _search(self.kernel_grid, np.ascontiguousarray(q, dtype=np.float64), k, bound, d2, idx)
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
            _self_knn(self.kernel_grid, k, _near_first(reach), reach, d2, idx, unsure)
        dist = np.sqrt(d2, out=d2)
        if unsure.any():
            rows = np.flatnonzero(unsure)
            # A few per cent of the rows: one thread, as waking a second costs more.
            d, i = self.query(self.data[rows], k=k, distance_upper_bound=bound, workers=1)
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
            _nearest(
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


@numba.njit(cache=True, inline="always")
def _cell_range(x: float, radius: float, origin: float, h: float, dim: int) -> tuple[int, int]:
    """First and last cell index along one axis overlapping ``[x − radius, x + radius]``.

    ``int`` truncates rather than floors: it differs only below zero, where the clamp makes the
    first index 0 either way and the last at worst admits cell 0 needlessly (never misses one).
    """
    return max(int((x - radius - origin) / h), 0), min(int((x + radius - origin) / h), dim - 1)


@numba.njit(cache=True, inline="always")
def _gap(x: float, cell: int, origin: float, h: float) -> float:
    """Distance along one axis from ``x`` to the cell's slab (0 inside it)."""
    low = origin + cell * h
    if x < low:
        return low - x
    if x > low + h:
        return x - low - h
    return 0.0


@numba.njit(cache=True, inline="always")
def _insert(order, j, d2, bd, bi):
    """Insert point ``j`` (sorted rank) at squared distance ``d2`` into the k-best buffer
    ``(bd, bi)`` (squared distances ascending, sorted ranks) if it belongs there. Ties compare
    the original index (cells are visited in no particular order); an empty slot holds the
    bound itself (or ``inf``), which admits only strictly nearer points."""
    k = len(bd)
    if d2 > bd[k - 1] or (d2 == bd[k - 1] and (bi[k - 1] < 0 or order[j] > order[bi[k - 1]])):
        return
    pos = k - 1
    while pos > 0 and (bd[pos - 1] > d2 or (bd[pos - 1] == d2 and order[bi[pos - 1]] > order[j])):
        bd[pos] = bd[pos - 1]
        bi[pos] = bi[pos - 1]
        pos -= 1
    bd[pos] = d2
    bi[pos] = j


@numba.njit(cache=True, inline="always")
def _collect(grid, q, radius, bd, bi):
    """Offer the points of the cells overlapping the box ``q ± radius`` to the k-best buffer
    ``(bd, bi)``: squared distances ascending and sorted ranks; empty slots hold the bound and -1.

    A cell entirely farther than the current k-th best is skipped before its hash lookup.
    """
    points, order, starts, cell_keys, table, bits, origin, h, dims, _ = grid
    k = len(bd)
    qx, qy, qz = q[0], q[1], q[2]
    x0, x1 = _cell_range(qx, radius, origin[0], h, dims[0])
    y0, y1 = _cell_range(qy, radius, origin[1], h, dims[1])
    z0, z1 = _cell_range(qz, radius, origin[2], h, dims[2])
    for cx in range(x0, x1 + 1):
        gx = _gap(qx, cx, origin[0], h) ** 2
        for cy in range(y0, y1 + 1):
            gxy = _gap(qy, cy, origin[1], h) ** 2 + gx
            row = (cx * dims[1] + cy) * dims[2]
            for cz in range(z0, z1 + 1):
                if _gap(qz, cz, origin[2], h) ** 2 + gxy > bd[k - 1]:
                    continue
                rank = find_cell(table, cell_keys, bits, row + cz)
                if rank < 0:
                    continue
                for j in range(starts[rank], starts[rank + 1]):
                    d2 = (points[j, 0] - qx) ** 2 + (points[j, 1] - qy) ** 2
                    _insert(order, j, d2 + (points[j, 2] - qz) ** 2, bd, bi)


@numba.njit(cache=True, parallel=True)
def _search(grid, queries, k, bound, d2, idx):
    """k nearest (strictly within ``bound``) of every query into ``d2`` and ``idx`` (original
    indices, -1 for none)."""
    order, h, dims = grid[1], grid[7], grid[8]
    origin = grid[6]
    n_queries = len(queries)
    half_diagonal = 0.5 * h * np.sqrt((dims[0] ** 2 + dims[1] ** 2 + dims[2] ** 2) * 1.0)
    cx = origin[0] + 0.5 * h * dims[0]
    cy = origin[1] + 0.5 * h * dims[1]
    cz = origin[2] + 0.5 * h * dims[2]
    for chunk in numba.prange((n_queries + _CHUNK - 1) // _CHUNK):
        bd = np.empty(k)
        bi = np.empty(k, dtype=np.int64)
        guess = h
        for i in range(chunk * _CHUNK, min(n_queries, (chunk + 1) * _CHUNK)):
            q = queries[i]
            bi[:] = -1
            if np.isfinite(bound):
                # Strictly inside the bound: start the buffer at it.
                bd[:] = bound * bound
                _collect(grid, q, bound, bd, bi)
            else:
                bd[:] = np.inf
                radius = guess
                # Beyond this radius the box holds every cell: nothing more to find.
                reach = np.sqrt((q[0] - cx) ** 2 + (q[1] - cy) ** 2 + (q[2] - cz) ** 2)
                reach += half_diagonal
                while True:
                    _collect(grid, q, radius, bd, bi)
                    if bi[k - 1] >= 0:
                        kth = np.sqrt(bd[k - 1])
                        if kth > radius:
                            # k candidates bound the k-th distance: one more pass is exact.
                            radius = kth * (1.0 + 1e-12)
                            bd[:] = np.inf
                            bi[:] = -1
                            _collect(grid, q, radius, bd, bi)
                        # Never zero (a duplicate point), or the doubling would never grow.
                        guess = max(1.25 * np.sqrt(bd[k - 1]), 0.5 * h)
                        break
                    if radius > reach:
                        break
                    radius *= 2.0
                    bd[:] = np.inf
                    bi[:] = -1
            for j in range(k):
                found = bi[j] >= 0
                idx[i, j] = order[bi[j]] if found else -1
                d2[i, j] = bd[j] if found else np.inf


@numba.njit(cache=True, inline="always")
def nearest_point(grid, rings, qx, qy, qz, gate, hint):
    """Compiled core of :meth:`VoxelIndex.nearest_within` for one query point, for other kernels
    to call: ``(original index, squared distance)`` of its nearest point strictly within
    ``gate`` (``(-1, gate²)`` when none). ``hint`` is a candidate's original index (-1: none).
    ``grid`` is a VoxelIndex's ``kernel_grid``, ``rings`` its :meth:`VoxelIndex.rings` for the
    gate.

    With a hint inside the gate, one pass over the box of the hint's distance (a cell or two
    after a small move). Without, the query's own cell, then the box of the distance found
    there (or of the gate) when the gate is within a cell; else the cells ring by ring, nearest
    first, until no further ring can hold anything nearer: a wide gate's box holds hundreds of
    cells.
    """
    best, found = _hinted(grid, qx, qy, qz, gate, hint)
    j, d2, _ = _gated_search(grid, rings, qx, qy, qz, gate, best, found, False)
    return j, d2


@numba.njit(cache=True, inline="always")
def certified_nearest(grid, rings, qx, qy, qz, gate, hint, anchor, bound):
    """:func:`nearest_point` for a query that moves a little between calls (ICP's source
    points), skipping the search while a certificate from an earlier one still holds.

    The certificate of a search at ``anchor`` is a lower bound ``b`` on the distance from there
    to every indexed point but the nearest found (the second nearest scanned, or the scanned
    block's border when nearer; with none, a ring search's skipped cells and rings): at a query
    ``δ`` from the anchor every other point is at least ``b − δ`` away, so the previous
    nearest ``hint`` is still the nearest when it is strictly within ``b − δ``. Without a
    nearest (none within the gate) ``b`` bounds every point, and there is still none while
    ``b − δ`` reaches the gate. The answer is :func:`nearest_point`'s to the bit (same
    distances, ties by index); a tie or a bound within rounding of the distance is searched
    again.

    Parameters
    ----------
    grid, rings, qx, qy, qz, gate, hint
        As for :func:`nearest_point` (``hint``: the previous call's answer for this query).
    anchor
        (3,) where this query's certificate was taken (read only when ``bound`` is not 0).
    bound
        The certificate: ``b > 0`` with a nearest (``hint``), ``−b < 0`` without one, 0 none.

    Returns
    -------
    (index, squared distance, certificate)
        As :func:`nearest_point`, and the certificate of a new search at this query (store it
        with the query as the new anchor) or NaN when the old one held
        (keep both).
    """
    best, found = _hinted(grid, qx, qy, qz, gate, hint)
    if bound != 0.0:
        dx, dy, dz = qx - anchor[0], qy - anchor[1], qz - anchor[2]
        delta = np.sqrt(dx * dx + dy * dy + dz * dz)
        if bound > 0.0 and found >= 0 and np.sqrt(best) + delta < bound:
            return hint, best, np.nan
        if bound < 0.0 and -bound - delta >= gate:
            return -1, best, np.nan
    return _gated_search(grid, rings, qx, qy, qz, gate, best, found, True)


@numba.njit(cache=True, inline="always")
def move_and_match(grid, rings, src, R, t, gate, hint, anchors, bounds, i, q):
    """Move source point ``i`` into ``q`` (3,) (``R p + t``) and find its nearest indexed point
    within the gate by :func:`certified_nearest` from ``hint[i]`` and its certificate
    (``anchors[i]``, ``bounds[i]``, renewed in place when it searched): ICP's and GICP's
    compiled passes. Returns ``(original index or -1, squared distance)``."""
    for a in range(3):
        q[a] = R[a, 0] * src[i, 0] + R[a, 1] * src[i, 1] + R[a, 2] * src[i, 2] + t[a]
    j, d2, bound = certified_nearest(
        grid, rings, q[0], q[1], q[2], gate, hint[i], anchors[i], bounds[i]
    )
    if not np.isnan(bound):
        bounds[i] = bound
        anchors[i, 0], anchors[i, 1], anchors[i, 2] = q[0], q[1], q[2]
    return j, d2


@numba.njit(cache=True, inline="always")
def _hinted(grid, qx, qy, qz, gate, hint):
    """(squared distance, sorted rank) of the hint when it lies strictly within the gate, else
    (gate², -1)."""
    points, rank = grid[0], grid[9]
    if hint >= 0:
        j = rank[hint]
        d2 = (points[j, 0] - qx) ** 2 + (points[j, 1] - qy) ** 2 + (points[j, 2] - qz) ** 2
        if d2 < gate * gate:
            return d2, j
    return gate * gate, -1


@numba.njit(cache=True, inline="always")
def _gated_search(grid, rings, qx, qy, qz, gate, best, found, certify):
    """The search of :func:`nearest_point` from ``(best, found)`` (:func:`_hinted`):
    ``(original index or -1, squared distance, certificate)``, the certificate as
    :func:`certified_nearest` returns it (``certify``: worth a wider ring search)."""
    points, order, starts, cell_keys, table, bits, origin, h, dims, _ = grid
    second, own = np.inf, -1
    if found < 0 and gate > h:
        # A gate wider than a cell and nothing to start from: ring by ring, nearest first.
        ox = int(np.floor((qx - origin[0]) / h))
        oy = int(np.floor((qy - origin[1]) / h))
        oz = int(np.floor((qz - origin[2]) / h))
        # Every cell from the first ring not visited on is at least its ring less one cell away;
        # a skipped cell at least its gap (squared: skipped). While nothing is within the gate,
        # the cells up to a cell beyond it are scanned too (none can hold a match): their
        # points bound how far the query may move and still have none (when the rings reach
        # that far: else the block search below takes over).
        reach, skipped = rings[-1, 3] + 1, np.inf
        wide = (gate + h) ** 2 if certify and rings[-1, 3] * h >= gate + h else best
        for o in range(len(rings)):
            limit = best if found >= 0 else wide
            # Ring r lies at least (r − 1) cells away; ">" keeps ties at the bound in play.
            if rings[o, 3] > 1 and ((rings[o, 3] - 1) * h) ** 2 > limit:
                reach = rings[o, 3]
                break
            cx, cy, cz = ox + rings[o, 0], oy + rings[o, 1], oz + rings[o, 2]
            if not (0 <= cx < dims[0] and 0 <= cy < dims[1] and 0 <= cz < dims[2]):
                continue
            gap2 = _gap(qx, cx, origin[0], h) ** 2 + _gap(qy, cy, origin[1], h) ** 2
            gap2 += _gap(qz, cz, origin[2], h) ** 2
            if gap2 > limit:
                skipped = min(skipped, gap2)
                continue
            cell = find_cell(table, cell_keys, bits, (cx * dims[1] + cy) * dims[2] + cz)
            if cell >= 0 and found >= 0:
                best, found = _nearest_in_cell(points, order, starts, cell, qx, qy, qz, best, found)
            elif cell >= 0:
                best, second, found = _two_nearest_in_cell(
                    points, order, starts, cell, qx, qy, qz, best, second, found
                )
        if best < ((reach - 1) * h) ** 2 and found >= 0:
            # A nearest found ring by ring has moved a query far: no certificate (0).
            return order[found], best, 0.0
        if best < ((reach - 1) * h) ** 2:
            return _certified(found, order, best, (reach - 1) * h, second, skipped, qx, qy, qz)
    elif found < 0:
        # The own cell first: its nearest (if any) shrinks the box of the others.
        ox = int(np.floor((qx - origin[0]) / h))
        oy = int(np.floor((qy - origin[1]) / h))
        oz = int(np.floor((qz - origin[2]) / h))
        if 0 <= ox < dims[0] and 0 <= oy < dims[1] and 0 <= oz < dims[2]:
            own = (ox * dims[1] + oy) * dims[2] + oz
            cell = find_cell(table, cell_keys, bits, own)
            if cell >= 0:
                best, second, found = _two_nearest_in_cell(
                    points, order, starts, cell, qx, qy, qz, best, second, found
                )
    # (1 + 1e-12): a tie at exactly the best distance must fall inside the box.
    radius = np.sqrt(best) * (1.0 + 1e-12)
    x0, x1 = _cell_range(qx, radius, origin[0], h, dims[0])
    y0, y1 = _cell_range(qy, radius, origin[1], h, dims[1])
    z0, z1 = _cell_range(qz, radius, origin[2], h, dims[2])
    for cx in range(x0, x1 + 1):
        for cy in range(y0, y1 + 1):
            row = (cx * dims[1] + cy) * dims[2]
            for cz in range(z0, z1 + 1):
                if row + cz == own:
                    continue
                cell = find_cell(table, cell_keys, bits, row + cz)
                if cell >= 0:
                    best, second, found = _two_nearest_in_cell(
                        points, order, starts, cell, qx, qy, qz, best, second, found
                    )
    # Every point outside the scanned block is beyond its nearest face (none past the grid).
    outside = np.inf
    if x0 > 0:
        outside = min(outside, qx - (origin[0] + x0 * h))
    if x1 < dims[0] - 1:
        outside = min(outside, origin[0] + (x1 + 1) * h - qx)
    if y0 > 0:
        outside = min(outside, qy - (origin[1] + y0 * h))
    if y1 < dims[1] - 1:
        outside = min(outside, origin[1] + (y1 + 1) * h - qy)
    if z0 > 0:
        outside = min(outside, qz - (origin[2] + z0 * h))
    if z1 < dims[2] - 1:
        outside = min(outside, origin[2] + (z1 + 1) * h - qz)
    return _certified(found, order, best, outside, second, np.inf, qx, qy, qz)


@numba.njit(cache=True, inline="always")
def _certified(found, order, best, outside, second, skipped, qx, qy, qz):
    """``(original index or -1, best, certificate)`` of a search that scanned every point
    nearer than ``outside`` but those in cells at least ``√skipped`` away, and whose second
    smallest squared distance offered (with the gate² it started from) was ``second``."""
    # Rounding of the distances (relative to the coordinates) must not fake a certificate.
    limit = min(np.sqrt(min(second, skipped)), outside)
    b = max(limit - 1e-12 * (1.0 + abs(qx) + abs(qy) + abs(qz)), 0.0)
    if found < 0:
        # Everything scanned is at the gate or beyond, and so is the block's border.
        return -1, best, -b
    return order[found], best, b


@numba.njit(cache=True, inline="always")
def _nearest_in_cell(points, order, starts, cell, qx, qy, qz, best, found):
    """(best squared distance, its sorted rank) after offering the points of ``cell``; ties go
    to the smaller original index, as everywhere in this module."""
    for j in range(starts[cell], starts[cell + 1]):
        d2 = (points[j, 0] - qx) ** 2 + (points[j, 1] - qy) ** 2 + (points[j, 2] - qz) ** 2
        if d2 < best or (d2 == best and found >= 0 and order[j] < order[found]):
            best, found = d2, j
    return best, found


@numba.njit(cache=True, inline="always")
def _two_nearest_in_cell(points, order, starts, cell, qx, qy, qz, best, second, found):
    """:func:`_nearest_in_cell` that also keeps the second smallest squared distance offered
    (``second``; the point ``found`` itself is skipped, as it is already counted)."""
    for j in range(starts[cell], starts[cell + 1]):
        if j == found:
            continue
        d2 = (points[j, 0] - qx) ** 2 + (points[j, 1] - qy) ** 2 + (points[j, 2] - qz) ** 2
        if d2 < best or (d2 == best and found >= 0 and order[j] < order[found]):
            second = best
            best, found = d2, j
        elif d2 < second:
            second = d2
    return best, second, found


@numba.njit(cache=True, parallel=True)
def _nearest(grid, rings, queries, hint, gate, idx, d2):
    """:func:`nearest_point` of every query into ``idx`` and ``d2`` (``inf`` for none)."""
    n_queries = len(queries)
    for chunk in numba.prange((n_queries + _CHUNK - 1) // _CHUNK):
        for i in range(chunk * _CHUNK, min(n_queries, (chunk + 1) * _CHUNK)):
            q = queries[i]
            idx[i], best = nearest_point(grid, rings, q[0], q[1], q[2], gate, hint[i])
            d2[i] = best if idx[i] >= 0 else np.inf


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


@numba.njit(cache=True, inline="always")
def cell_candidates(grid, offsets, c):
    """The points of the cells at ``offsets`` (K, 3) from sorted cell ``c``, in cell order.

    Returns ``c``'s cell coordinates and the candidates' sorted ranks and coordinates, one array
    per axis, copied once per cell: a query's distances to all of them then run as one
    vectorised loop (13 % faster than point by point).
    """
    points, _, starts, cell_keys, table, bits, _, _, dims, _ = grid
    key = cell_keys[c]
    cz = key % dims[2]
    cy = (key // dims[2]) % dims[1]
    cx = key // (dims[2] * dims[1])
    first = np.empty(len(offsets), dtype=np.int64)
    last = np.empty(len(offsets), dtype=np.int64)
    runs = total = 0
    for o in range(len(offsets)):
        x, y, z = cx + offsets[o, 0], cy + offsets[o, 1], cz + offsets[o, 2]
        if not (0 <= x < dims[0] and 0 <= y < dims[1] and 0 <= z < dims[2]):
            continue
        rank = find_cell(table, cell_keys, bits, (x * dims[1] + y) * dims[2] + z)
        if rank >= 0:
            first[runs] = starts[rank]
            last[runs] = starts[rank + 1]
            total += last[runs] - first[runs]
            runs += 1
    cand = np.empty(total, dtype=np.int64)
    cand_x, cand_y, cand_z = np.empty(total), np.empty(total), np.empty(total)
    m = 0
    for r in range(runs):
        for j in range(first[r], last[r]):
            cand[m] = j
            cand_x[m], cand_y[m], cand_z[m] = points[j, 0], points[j, 1], points[j, 2]
            m += 1
    return cx, cy, cz, cand, cand_x, cand_y, cand_z


@numba.njit(cache=True, parallel=True)
def _self_knn(grid, k, offsets, w, d2, idx, unsure):
    """k nearest of every indexed point among the cells at ``offsets`` (:func:`_near_first`,
    within ``w`` cells) from its own, a cell at a time; rows (original indices) whose k-th
    distance may reach beyond those cells are flagged in ``unsure`` instead.

    The candidates (about 200 for k = 30) are counted into bands of squared distance rather
    than offered one by one to a sorted buffer (whose shifts took about 70 % of the time): the
    bands below the k-th's are taken whole and the k-th's band gives its best. The answer is
    the buffer's to the bit: sorted by (squared distance, index)."""
    points, order, starts, cell_keys, _, _, origin, h, dims, _ = grid
    for c in numba.prange(len(cell_keys)):
        cx, cy, cz, cand, cand_x, cand_y, cand_z = cell_candidates(grid, offsets, c)
        total = len(cand)
        dd = np.empty(total)
        band = np.empty(total, dtype=np.int64)
        counts = np.empty(_BANDS + 1, dtype=np.int64)
        # The faces of the searched block, per axis and side: a face at the grid's border has
        # nothing beyond it.
        low_x = origin[0] + (cx - w) * h if cx - w > 0 else -np.inf
        high_x = origin[0] + (cx + w + 1) * h if cx + w + 1 < dims[0] else np.inf
        low_y = origin[1] + (cy - w) * h if cy - w > 0 else -np.inf
        high_y = origin[1] + (cy + w + 1) * h if cy + w + 1 < dims[1] else np.inf
        low_z = origin[2] + (cz - w) * h if cz - w > 0 else -np.inf
        high_z = origin[2] + (cz + w + 1) * h if cz + w + 1 < dims[2] else np.inf
        bd = np.empty(k)
        bi = np.empty(k, dtype=np.int64)
        # Squared k-th distance of the cell's previous point: the scale of the bands (per cell,
        # so the work does not depend on the thread that takes the cell).
        scale = h * h
        for i in range(starts[c], starts[c + 1]):
            qx, qy, qz = points[i, 0], points[i, 1], points[i, 2]
            # Bands of squared distance, monotone in it: a nearer band's points are all nearer.
            inv = _BANDS / (_BAND_SPAN * scale)
            counts[:] = 0
            for m in range(total):
                dd[m] = (cand_x[m] - qx) ** 2 + (cand_y[m] - qy) ** 2 + (cand_z[m] - qz) ** 2
                band[m] = int(min(dd[m] * inv, _BANDS))
                counts[band[m]] += 1
            row = order[i]
            if total < k:
                unsure[row] = True
                continue
            # The bands below the k-th's ("edge") are taken whole, each to its own run of the
            # buffer (a counting sort); the edge band's best fill the rest, in order.
            edge = below = 0
            while below + counts[edge] < k:
                below += counts[edge]
                edge += 1
            start = 0
            for b in range(edge):
                counts[b], start = start, start + counts[b]
            tail_d, tail_i = bd[below:], bi[below:]
            tail_d[:] = np.inf
            tail_i[:] = -1
            for m in range(total):
                if band[m] < edge:
                    bd[counts[band[m]]] = dd[m]
                    bi[counts[band[m]]] = cand[m]
                    counts[band[m]] += 1
                elif band[m] == edge:
                    _insert(order, cand[m], dd[m], tail_d, tail_i)
            reach = min(qx - low_x, high_x - qx, qy - low_y, high_y - qy, qz - low_z, high_z - qz)
            # Exact when every point not seen is strictly farther than the k-th (ties too).
            if bd[k - 1] >= reach * reach:
                unsure[row] = True
                continue
            if bd[k - 1] > 0:
                scale = bd[k - 1]
            # Within each band (a point or two): the order of (squared distance, index).
            for j in range(1, below):
                dj, rj = bd[j], bi[j]
                pos = j
                while pos > 0 and (
                    bd[pos - 1] > dj or (bd[pos - 1] == dj and order[bi[pos - 1]] > order[rj])
                ):
                    bd[pos], bi[pos] = bd[pos - 1], bi[pos - 1]
                    pos -= 1
                bd[pos], bi[pos] = dj, rj
            for j in range(k):
                d2[row, j] = bd[j]
                idx[row, j] = order[bi[j]]
