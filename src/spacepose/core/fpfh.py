"""Fast Point Feature Histograms (methods.md §1.3; Rusu et al. 2009; Li §2.3.1).

The definition follows Open3D's ``compute_fpfh_feature`` number for number (bin edges, the swap
rule, the 1/d² weighting, the per-sub-histogram scaling to 100), so the two can be compared
directly. The radius search, the pair features and both histogram passes are compiled (numba)
kernels over the cells of a :class:`~spacepose.core.grid.VoxelIndex`:

* cells are about a third of the radius wide; the points of one cell share one candidate list,
  the points of the cells around it that can lie within the radius, copied once;
* a point's neighbours are the candidates strictly within the radius, in that fixed visiting
  order; past ``max_nn`` (the point included) the ``max_nn`` nearest are kept, ties by index, as
  a KD-tree's hybrid search returns them, and the point itself is dropped as Open3D drops it;
* the simplified histograms (SPFH) of a block of cells are taken as its neighbours are found,
  whose squared distances are kept (12 bytes per pair) for the weighted neighbour sum (FPFH).

Every row is summed in its own fixed order and blocks and chunks are fixed, so the result is the
same on any thread count.
"""

from __future__ import annotations

import numba
import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import Field, PositiveFloat

from spacepose.core.cloud import PointCloud, as_cloud
from spacepose.core.config import StageConfig, stage_config
from spacepose.core.grid import VoxelIndex
from spacepose.core.grid_knn import cell_candidates
from spacepose.core.threads import numba_threads
from spacepose.errors import InputError

N_BINS = 11
N_FEATURES = 3 * N_BINS
# Cells per radius: the candidate block of a cell then spans (2·3 + 1) cells of r/3, 2.3 r, about
# 1.7× the pairs inside the radius on a surface (cells of r/2: 2.5 r; of r: 3 r).
_CELLS_PER_RADIUS = 3
# Points per block of the search and SPFH pass: bounds the (block, max_nn) pair buffers.
_BLOCK_POINTS = 8192
# Rows per unit of parallel work in the weighted-sum pass.
_CHUNK_ROWS = 64


class FPFHConfig(StageConfig):
    """Neighbourhood of the descriptor (Open3D's hybrid search).

    Attributes
    ----------
    radius
        Search radius in metres; typically 5× the point spacing.
    max_nn
        Cap on the neighbours inside the radius, the point itself included (as in Open3D).
    """

    radius: PositiveFloat = 0.05
    # Bounded: the pair buffers grow with it (10^7 asked for 75 GiB).
    max_nn: int = Field(default=100, ge=2, le=10_000)


def pair_features(
    p1: NDArray[np.float64],
    n1: NDArray[np.float64],
    p2: NDArray[np.float64],
    n2: NDArray[np.float64],
) -> NDArray[np.float64]:
    """Darboux-frame features of point pairs, batched.

    Parameters
    ----------
    p1, n1, p2, n2
        (P, 3) positions and unit normals of the two points of each pair (broadcast: one
        point against P others takes (1, 3) arrays).

    Returns
    -------
    (P, 3) features ``(f1, f2, f3)``: f1 the angle in [−π, π], f2 and f3 cosines in [−1, 1].
    The pair is ordered so that the source normal makes the smaller angle with the line joining
    the points; a zero-length pair, or a normal parallel to that line, gives all zeros.

    When the two normals are equal to rounding (neighbours whose normals came from the same
    neighbour set), the swap, hence the sign of f3, is decided by the last bit of the dot
    products; they are summed in Eigen's order so that the choice matches Open3D's.
    """
    arrays = [
        np.ascontiguousarray(a, dtype=np.float64).reshape(-1, 3)
        for a in np.broadcast_arrays(p1, n1, p2, n2)
    ]
    out = np.empty((len(arrays[0]), 3))
    _pair_features_kernel(*arrays, out)
    return out


def feature_bins(features: NDArray[np.float64]) -> NDArray[np.intp]:
    """Histogram bins (P, 3) of pair features in 0..10: f1 over [−π, π], f2 and f3 over [−1, 1]."""
    f = np.ascontiguousarray(features, dtype=np.float64).reshape(-1, 3)
    out = np.empty(f.shape, dtype=np.intp)
    _bins_kernel(f, out)
    return out


def compute_fpfh(
    cloud: PointCloud | ArrayLike, config: FPFHConfig = FPFHConfig(), workers: int = -1
) -> NDArray[np.float64]:
    """FPFH descriptor of every point.

    Parameters
    ----------
    cloud
        Points (N, 3) with normals (N, 3); the normals' orientation matters (f1 and f3 are signed).
        An (N, 3) array is taken as a cloud without normals, which is refused with a clear
        :class:`~spacepose.errors.InputError` (estimate them with ``estimate_normals``, which
        takes the same array).
    config
        Hybrid neighbourhood (radius, max_nn).
    workers
        Threads (-1: all cores); the result does not depend on it.

    Returns
    -------
    (N, 33) descriptors: three 11-bin sub-histograms (f1, f2, f3). A point without neighbours
    gets a zero row.

    Notes
    -----
    Memory: the (N, 33) histograms, 12 bytes per (point, neighbour) pair and one block's
    (block, max_nn) pair buffers, whatever the cloud size.
    """
    config = stage_config(config, FPFHConfig)
    cloud = as_cloud(cloud, "cloud")
    if not cloud.has_normals:
        raise InputError(
            "FPFH needs a cloud with normals (run estimate_normals first)", cloud.source
        )
    index = VoxelIndex(cloud.points, cell_size=config.radius / _CELLS_PER_RADIUS)
    grid = index.kernel_grid
    order, starts = grid[1], grid[2]
    # Normals in the index's (cell-sorted) order, as its points are.
    normals = np.ascontiguousarray(cloud.normals[order])
    reach = int(np.ceil(config.radius / index.cell_size))
    offsets = _block_offsets(reach, config.radius / index.cell_size)
    n, n_cells, max_nn = index.n, len(starts) - 1, config.max_nn
    spfh = np.empty((n, N_FEATURES))
    counts = np.zeros(n + 1, dtype=np.int64)
    neighbours, distances = [], []
    with numba_threads(workers):
        first = 0
        while first < n_cells:
            # Whole cells, at least one, up to _BLOCK_POINTS points.
            last = max(
                int(np.searchsorted(starts, starts[first] + _BLOCK_POINTS, "right")) - 1, first + 1
            )
            rows = int(starts[last] - starts[first])
            nbr = np.empty((rows, max_nn), dtype=np.int32)
            d2 = np.empty((rows, max_nn))
            _search_spfh(
                grid,
                normals,
                offsets,
                config.radius,
                first,
                last,
                nbr,
                d2,
                counts[1 + starts[first] :],
                spfh,
            )
            taken = np.arange(max_nn) < counts[1 + starts[first] : 1 + starts[last], None]
            neighbours.append(nbr[taken])
            distances.append(d2[taken])
            first = last
        indptr = np.cumsum(counts)
        out = np.empty((n, N_FEATURES))
        _weighted_sum(
            spfh, indptr, np.concatenate(neighbours), np.concatenate(distances), order, out
        )
    return out


def _block_offsets(reach: int, radius_cells: float) -> NDArray[np.int64]:
    """(M, 3) cell offsets within ``reach`` cells whose cell can hold a point strictly within
    ``radius_cells`` (the radius in cell edges) of a point of the centre cell, nearest first."""
    side = 2 * reach + 1
    offsets = np.array(list(np.ndindex(side, side, side)), dtype=np.int64) - reach
    gap2 = (np.maximum(np.abs(offsets) - 1, 0) ** 2).sum(axis=1)
    offsets = offsets[gap2 < radius_cells**2]
    return offsets[np.argsort(np.abs(offsets).sum(axis=1), kind="stable")]


@numba.njit(cache=True)
def _pair_feature(p1x, p1y, p1z, n1x, n1y, n1z, p2x, p2y, p2z, n2x, n2y, n2z):
    """``(f1, f2, f3)`` of one pair (:func:`pair_features`) from its twelve coordinates, with
    numpy's arithmetic step for step (dot products left to right, as Eigen sums them).
    Scalars, not row views: a view per pair costs more than the arithmetic."""
    d0, d1, d2 = p2x - p1x, p2y - p1y, p2z - p1z
    length = np.sqrt(d0 * d0 + d1 * d1 + d2 * d2)
    safe = length if length > 0 else 1.0
    a1 = (n1x * d0 + n1y * d1 + n1z * d2) / safe
    a2 = (n2x * d0 + n2y * d1 + n2z * d2) / safe
    # Open3D compares arccos|a1| > arccos|a2|; arccos is decreasing, and comparing |a1| < |a2|
    # directly is what its build does in effect: pairs whose normals are equal to the last bit
    # (same neighbour set) then resolve the same way, while a libm arccos can map two
    # neighbouring doubles to one value and flip the sign of f3.
    if abs(a1) < abs(a2):
        s0, s1, s2, t0, t1, t2 = n2x, n2y, n2z, n1x, n1y, n1z
        d0, d1, d2 = -d0, -d1, -d2
        f3 = -a2
    else:
        s0, s1, s2, t0, t1, t2 = n1x, n1y, n1z, n2x, n2y, n2z
        f3 = a1
    v0 = d1 * s2 - d2 * s1
    v1 = d2 * s0 - d0 * s2
    v2 = d0 * s1 - d1 * s0
    v_norm = np.sqrt(v0 * v0 + v1 * v1 + v2 * v2)
    if length == 0 or v_norm == 0:
        return 0.0, 0.0, 0.0
    v0, v1, v2 = v0 / v_norm, v1 / v_norm, v2 / v_norm
    w0 = s1 * v2 - s2 * v1
    w1 = s2 * v0 - s0 * v2
    w2 = s0 * v1 - s1 * v0
    f2 = v0 * t0 + v1 * t1 + v2 * t2
    f1 = np.arctan2(w0 * t0 + w1 * t1 + w2 * t2, s0 * t0 + s1 * t1 + s2 * t2)
    return f1, f2, f3


@numba.njit(cache=True)
def _bin(scaled):
    return min(max(int(np.floor(scaled)), 0), N_BINS - 1)


@numba.njit(cache=True)
def _feature_bins(f1, f2, f3):
    """Bins of one pair's features: f1 over [−π, π], f2 and f3 over [−1, 1]."""
    return (
        _bin(N_BINS * (f1 + np.pi) / (2.0 * np.pi)),
        N_BINS + _bin(N_BINS * (f2 + 1.0) * 0.5),
        2 * N_BINS + _bin(N_BINS * (f3 + 1.0) * 0.5),
    )


@numba.njit(cache=True)
def _pair_features_kernel(p1, n1, p2, n2, out):
    for i in range(len(p1)):
        out[i, 0], out[i, 1], out[i, 2] = _pair_feature(
            p1[i, 0],
            p1[i, 1],
            p1[i, 2],
            n1[i, 0],
            n1[i, 1],
            n1[i, 2],
            p2[i, 0],
            p2[i, 1],
            p2[i, 2],
            n2[i, 0],
            n2[i, 1],
            n2[i, 2],
        )


@numba.njit(cache=True)
def _bins_kernel(features, out):
    for i in range(len(features)):
        b1, b2, b3 = _feature_bins(features[i, 0], features[i, 1], features[i, 2])
        out[i, 0], out[i, 1], out[i, 2] = b1, b2 - N_BINS, b3 - 2 * N_BINS


@numba.njit(cache=True, parallel=True)
def _search_spfh(grid, normals, offsets, radius, first, last, nbr, d2, counts, spfh):
    """Neighbours and SPFH of the points of cells ``first .. last − 1`` (sorted ranks).

    Fills, for the block's rows (rank − the block's first rank), ``nbr`` (rows, max_nn) with the
    neighbours' sorted ranks, ``d2`` with their squared distances, ``counts`` with how many, and
    ``spfh`` (rows by sorted rank) with each point's simplified histograms.
    """
    points, order, starts, _, _, _, _, _, _, _ = grid
    r2 = radius * radius
    base = starts[first]
    for c in numba.prange(first, last):
        _, _, _, cand, cand_x, cand_y, cand_z = cell_candidates(grid, offsets, c)
        total = len(cand)
        dd = np.empty(total)
        found = np.empty(total, dtype=np.int64)
        hist = np.empty(N_FEATURES)
        for i in range(starts[c], starts[c + 1]):
            qx, qy, qz = points[i, 0], points[i, 1], points[i, 2]
            mx, my, mz = normals[i, 0], normals[i, 1], normals[i, 2]
            for m in range(total):
                dd[m] = (cand_x[m] - qx) ** 2 + (cand_y[m] - qy) ** 2 + (cand_z[m] - qz) ** 2
            inside = 0
            for m in range(total):
                if dd[m] < r2:
                    found[inside] = m
                    inside += 1
            row = i - base
            count = _keep_neighbours(order, cand, dd, found[:inside], i, nbr[row], d2[row])
            counts[row] = count
            hist[:] = 0.0
            if count > 0:
                incr = 100.0 / count
                for t in range(count):
                    j = nbr[row, t]
                    f1, f2, f3 = _pair_feature(
                        qx,
                        qy,
                        qz,
                        mx,
                        my,
                        mz,
                        points[j, 0],
                        points[j, 1],
                        points[j, 2],
                        normals[j, 0],
                        normals[j, 1],
                        normals[j, 2],
                    )
                    b1, b2, b3 = _feature_bins(f1, f2, f3)
                    hist[b1] += incr
                    hist[b2] += incr
                    hist[b3] += incr
            spfh[i, :] = hist


@numba.njit(cache=True)
def _keep_neighbours(order, cand, dd, found, i, nbr_row, d2_row):
    """Write the neighbours of sorted rank ``i`` among the candidates ``found`` (positions in
    ``cand``/``dd``, all within the radius, ``i`` itself among them) into ``nbr_row`` and
    ``d2_row``, as Open3D's hybrid search and FPFH keep them; return their count.

    Within the cap, every candidate but ``i``, in visiting order. Over it, the ``max_nn``
    nearest by (distance, original index), nearest first, without ``i``, or without the
    nearest when duplicates pushed ``i`` out.
    """
    max_nn = len(nbr_row)
    if len(found) <= max_nn:
        count = 0
        for m in found:
            if cand[m] != i:
                nbr_row[count], d2_row[count] = cand[m], dd[m]
                count += 1
        return count
    # By original index, then stably by distance: ties go to the smaller index.
    by_index = found[np.argsort(order[cand[found]])]
    nearest = by_index[np.argsort(dd[by_index], kind="mergesort")[:max_nn]]
    skip = -1
    for t in range(max_nn):
        if cand[nearest[t]] == i:
            skip = t
    skip = max(skip, 0)
    count = 0
    for t in range(max_nn):
        if t != skip:
            nbr_row[count], d2_row[count] = cand[nearest[t]], dd[nearest[t]]
            count += 1
    return count


@numba.njit(cache=True, parallel=True)
def _weighted_sum(spfh, indptr, nbr, d2, order, out):
    """FPFH of every point (sorted rank r, written at row ``order[r]`` of ``out``): its SPFH
    plus its neighbours' SPFH weighted by 1/d² (coincident neighbours carry no weight, as in
    Open3D), each sub-histogram of that sum scaled to 100."""
    n = len(spfh)
    for chunk in numba.prange((n + _CHUNK_ROWS - 1) // _CHUNK_ROWS):
        acc = np.empty(N_FEATURES)
        for r in range(chunk * _CHUNK_ROWS, min(n, (chunk + 1) * _CHUNK_ROWS)):
            acc[:] = 0.0
            for p in range(indptr[r], indptr[r + 1]):
                if d2[p] > 0:
                    w = 1.0 / d2[p]
                    j = nbr[p]
                    for f in range(N_FEATURES):
                        acc[f] += w * spfh[j, f]
            row = order[r]
            for s in range(3):
                total = 0.0
                for f in range(s * N_BINS, (s + 1) * N_BINS):
                    total += acc[f]
                scale = 100.0 / total if total != 0 else 0.0
                for f in range(s * N_BINS, (s + 1) * N_BINS):
                    out[row, f] = acc[f] * scale + spfh[r, f]
