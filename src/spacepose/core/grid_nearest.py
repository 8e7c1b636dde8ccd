"""Compiled gated nearest-point searches over the cells of a
:class:`~spacepose.core.grid.VoxelIndex`: ICP's and GICP's correspondences.

For one query point ``(qx, qy, qz)`` and a gate (m), the nearest indexed point strictly within
the gate as ``(original index, squared distance)``, or ``(-1, gate²)`` when there is none; ties
go to the smaller original index. ``grid`` is the index's ``kernel_grid`` and ``rings`` its
(R, 4) ring table :meth:`~spacepose.core.grid.VoxelIndex.rings` for the gate.

* :func:`nearest_point`: the search, warm-started from a previous match (``hint``);
* :func:`certified_nearest`: the same answer to the bit for a query that moves a little between
  calls, skipping the search while the certificate of an earlier one still holds;
* :func:`move_and_match`: moves a source point by ``(R, t)`` first and keeps its certificate
  (anchor (3,), bound) up to date: ICP's and GICP's compiled passes;
* :func:`nearest_kernel`: :func:`nearest_point` of M queries into (M,) indices and squared
  distances, for :meth:`~spacepose.core.grid.VoxelIndex.nearest_within`.

The first three are ``inline="always"`` for other modules' kernels to call: after editing them,
clear the cached kernels that inline them (``make clean``).
"""

from __future__ import annotations

import numba
import numpy as np

from spacepose.core.cell_hash import find_cell
from spacepose.core.grid_knn import QUERY_CHUNK, cell_gap, cell_range


@numba.njit(cache=True, inline="always")
def nearest_point(grid, rings, qx, qy, qz, gate, hint):
    """Compiled core of :meth:`VoxelIndex.nearest_within` for one query point, for other kernels
    to call: ``(original index, squared distance)`` of its nearest point strictly within
    ``gate`` (``(-1, gate²)`` when none). ``hint`` is a candidate's original index (-1: none).
    ``grid`` is a VoxelIndex's ``kernel_grid``, ``rings`` its :meth:`VoxelIndex.rings` for the
    gate.

    With a hint inside the gate, one pass over the box of the hint's distance (a cell or two
    after a small move). Without, the query's own cell, then the box of the distance found
    there (or of the gate) when the gate is within two cells; else the cells ring by ring, nearest
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
    block's border when nearer; after a ring search, the nearest skipped cell or ring): at a query
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
    if found < 0 and gate > 2.0 * h:
        # A gate over two cells wide and nothing to start from: ring by ring, nearest first.
        # (Within two cells the box below is cheaper: a query without a match visits at most
        # 5³ cells there, against the 7³ of the rings out to the gate and a cell beyond.)
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
            gap2 = cell_gap(qx, cx, origin[0], h) ** 2 + cell_gap(qy, cy, origin[1], h) ** 2
            gap2 += cell_gap(qz, cz, origin[2], h) ** 2
            if gap2 > limit:
                skipped = min(skipped, gap2)
                continue
            cell = find_cell(table, cell_keys, bits, (cx * dims[1] + cy) * dims[2] + cz)
            if cell >= 0 and found >= 0 and not certify:
                best, found = _nearest_in_cell(points, order, starts, cell, qx, qy, qz, best, found)
            elif cell >= 0:
                # A certificate needs the second nearest of every cell visited.
                best, second, found = _two_nearest_in_cell(
                    points, order, starts, cell, qx, qy, qz, best, second, found
                )
        if best < ((reach - 1) * h) ** 2 and found >= 0 and not certify:
            return order[found], best, 0.0
        if best < ((reach - 1) * h) ** 2:
            # Every cell not visited lies beyond the ring before the last one reached.
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
    x0, x1 = cell_range(qx, radius, origin[0], h, dims[0])
    y0, y1 = cell_range(qy, radius, origin[1], h, dims[1])
    z0, z1 = cell_range(qz, radius, origin[2], h, dims[2])
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
def nearest_kernel(grid, rings, queries, hint, gate, idx, d2):
    """:func:`nearest_point` of every query into ``idx`` and ``d2`` (``inf`` for none)."""
    n_queries = len(queries)
    for chunk in numba.prange((n_queries + QUERY_CHUNK - 1) // QUERY_CHUNK):
        for i in range(chunk * QUERY_CHUNK, min(n_queries, (chunk + 1) * QUERY_CHUNK)):
            q = queries[i]
            idx[i], best = nearest_point(grid, rings, q[0], q[1], q[2], gate, hint[i])
            d2[i] = best if idx[i] >= 0 else np.inf
