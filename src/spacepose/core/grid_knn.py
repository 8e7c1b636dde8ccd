"""Compiled k-nearest searches over the cells of a :class:`~spacepose.core.grid.VoxelIndex`.

Every kernel takes the index's ``kernel_grid``: the points grouped by cell (N, 3), their
original indices in that order (N,), each cell's first row (C + 1,), the cells' keys (C,), the
key table and its hash bits, the grid's corner (3,) and cell edge (m), its cells per axis (3,),
and each original point's row (N,).

* :func:`knn_kernel`: the k nearest of M queries, strictly within a bound or (without one) exact,
  the ball growing from the previous query's k-th distance, into (M, k) squared distances
  ascending and original indices (-1: none);
* :func:`self_knn_kernel`: the k nearest of every indexed point into (N, k) rows, a cell at a time
  over the block of cells around it, flagging in an (N,) mask the rows whose k-th neighbour may
  lie beyond that block (searched again one by one by
  :meth:`~spacepose.core.grid.VoxelIndex.query`);
* :func:`cell_candidates`: the points of a block of cells around one, for other modules'
  per-cell kernels (FPFH);
* :func:`cell_range`, :func:`cell_gap`: the cells a box overlaps and a cell's distance along one
  axis, shared with :mod:`spacepose.core.grid_nearest`.

Ties are broken by original index, so the answer depends neither on the order the cells are
visited in nor on the thread count (:func:`~spacepose.core.threads.numba_threads`).
"""

from __future__ import annotations

import numba
import numpy as np

from spacepose.core.cell_hash import find_cell

# Queries per unit of parallel work: enough to amortise scheduling, few enough to balance.
QUERY_CHUNK = 64
# Bands of squared distance the self k-nearest search sorts its candidates into, over this
# multiple of the previous point's squared k-th distance (the rest: one more band): the bands
# below the k-th's are taken without comparisons, about two points each are sorted.
_BANDS = 32
_BAND_SPAN = 2.0


@numba.njit(cache=True, inline="always")
def cell_range(x: float, radius: float, origin: float, h: float, dim: int) -> tuple[int, int]:
    """First and last cell index along one axis overlapping ``[x − radius, x + radius]``.

    ``int`` truncates rather than floors: it differs only below zero, where the clamp makes the
    first index 0 either way and the last at worst admits cell 0 needlessly (never misses one).
    """
    return max(int((x - radius - origin) / h), 0), min(int((x + radius - origin) / h), dim - 1)


@numba.njit(cache=True, inline="always")
def cell_gap(x: float, cell: int, origin: float, h: float) -> float:
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
    x0, x1 = cell_range(qx, radius, origin[0], h, dims[0])
    y0, y1 = cell_range(qy, radius, origin[1], h, dims[1])
    z0, z1 = cell_range(qz, radius, origin[2], h, dims[2])
    for cx in range(x0, x1 + 1):
        gx = cell_gap(qx, cx, origin[0], h) ** 2
        for cy in range(y0, y1 + 1):
            gxy = cell_gap(qy, cy, origin[1], h) ** 2 + gx
            row = (cx * dims[1] + cy) * dims[2]
            for cz in range(z0, z1 + 1):
                if cell_gap(qz, cz, origin[2], h) ** 2 + gxy > bd[k - 1]:
                    continue
                rank = find_cell(table, cell_keys, bits, row + cz)
                if rank < 0:
                    continue
                for j in range(starts[rank], starts[rank + 1]):
                    d2 = (points[j, 0] - qx) ** 2 + (points[j, 1] - qy) ** 2
                    _insert(order, j, d2 + (points[j, 2] - qz) ** 2, bd, bi)


@numba.njit(cache=True, parallel=True)
def knn_kernel(grid, queries, k, bound, d2, idx):
    """k nearest (strictly within ``bound``) of every query into ``d2`` and ``idx`` (original
    indices, -1 for none)."""
    order, h, dims = grid[1], grid[7], grid[8]
    origin = grid[6]
    n_queries = len(queries)
    half_diagonal = 0.5 * h * np.sqrt((dims[0] ** 2 + dims[1] ** 2 + dims[2] ** 2) * 1.0)
    cx = origin[0] + 0.5 * h * dims[0]
    cy = origin[1] + 0.5 * h * dims[1]
    cz = origin[2] + 0.5 * h * dims[2]
    for chunk in numba.prange((n_queries + QUERY_CHUNK - 1) // QUERY_CHUNK):
        bd = np.empty(k)
        bi = np.empty(k, dtype=np.int64)
        guess = h
        for i in range(chunk * QUERY_CHUNK, min(n_queries, (chunk + 1) * QUERY_CHUNK)):
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
def self_knn_kernel(grid, k, offsets, w, d2, idx, unsure):
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
