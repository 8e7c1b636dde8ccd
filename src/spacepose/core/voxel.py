"""Voxel grids: integer cell keys, a hash of the occupied cells, and the cells' centroids.

Compiled with numba: on a 18 000-point lab frame numpy spent about 0.5 ms on each axis-0
``min``/``max`` and as long on ``floor``/``astype``, and sorted every point's key to find the
occupied cells; here one pass computes the keys and one hashes them, and only the occupied cells
(a few thousand) are sorted. Downsampling (:func:`voxel_cells`, :func:`voxel_downsample`) takes
the cells' bounds from the points' bounds (``⌊x / h⌋`` is monotonic in x) and then one pass
keys, looks up and sums every point, point by point in index order: a raw 1280×720 frame
(900k points) never materialises its keys, and a table with one slot per cell of the box (when
the box has few cells, as at a coarse voxel) replaces the hash.
"""

from __future__ import annotations

from typing import NamedTuple

import numba
import numpy as np
from numpy.typing import ArrayLike, NDArray

from spacepose.core.cell_hash import find_cell, hash_bits, hash_slot
from spacepose.core.cloud import PointCloud, as_cloud, as_points
from spacepose.errors import InputError

# Largest key: three cell indices pack into one int64.
_MAX_KEY = 2.0**62
# The grid's default origin: the frame's (cells at multiples of the edge).
_ORIGIN = np.zeros(3)
# Cells whose blocks give the median of :func:`stray_voxels`.
_MEDIAN_SAMPLE = 512


class _Occupancy(NamedTuple):
    """The occupied cells of a grid in order of first appearance: (M,) keys, (M,) points in
    each, their hash ``table`` and ``bits`` (:mod:`spacepose.core.cell_hash`), (3,) cells along
    each axis, and (M,) the key order of the cells."""

    keys: NDArray[np.int64]
    counts: NDArray[np.float64]
    table: NDArray[np.int64]
    bits: int
    dims: NDArray[np.int64]
    by_key: NDArray[np.int64]


def cell_keys(
    points: NDArray[np.float64], cell_size: float, origin: NDArray[np.float64] | None = None
) -> tuple[NDArray[np.int64], NDArray[np.int64], NDArray[np.int64]]:
    """The cell ``c = ⌊(p − origin) / cell_size⌋`` of each point, packed into one integer key.

    Parameters
    ----------
    points
        (N, 3) finite points, N >= 1, any frame (m).
    cell_size
        Cell edge (m), > 0.
    origin
        (3,) grid origin; the frame's origin when None (cells aligned to multiples of the edge).

    Returns
    -------
    keys, dims, offset
        (N,) key ``(c_x' · dims_y + c_y') · dims_z + c_z'`` of the shifted cells ``c' = c −
        offset`` (all >= 0), the (3,) number of cells along each axis and the (3,) integer
        ``offset`` (the smallest cell).

    Raises
    ------
    InputError
        Points not finite (N, 3) with N >= 1, a cell size that is not a positive number, or a
        cloud spanning more cells than one int64 key can number (a cell size far too small).
    """
    pts = _finite_points(points)
    h = _cell_size(cell_size)
    o = np.zeros(3) if origin is None else np.asarray(origin, dtype=np.float64).reshape(3)
    # Compiled bounds: numpy's axis-0 min and max cost 0.5 ms each on a lab frame.
    low, high = _bounds(pts)
    _check_span(low - o, high - o, h)
    cells = np.empty(pts.shape, dtype=np.int64)
    low, high = _cells(pts, o, h, cells)
    return _pack(cells, low, high - low + 1), high - low + 1, low


def _cell_size(cell_size: object) -> float:
    """A cell edge as a positive finite float (m)."""
    # float() took "0.02" and True (a 1 m cell) without a word.
    if isinstance(cell_size, bool | str | bytes):
        raise InputError(f"cell size must be a number of metres, got {cell_size!r}")
    try:
        h = float(cell_size)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        raise InputError(f"cell size must be a number of metres, got {cell_size!r}") from None
    if not (np.isfinite(h) and h > 0):
        raise InputError(f"cell size must be a positive number of metres, got {cell_size}")
    return h


def _check_span(low: NDArray[np.float64], high: NDArray[np.float64], h: float) -> None:
    """Refuse cells of edge ``h`` that one int64 key cannot number over ``low..high`` (3,),
    checked in floating point before any cell index is cast: a cast that overflows is
    undefined (a voxel of 1e-20 m crashed the process)."""
    first, last = np.floor(low / h), np.floor(high / h)
    dims = last - first + 1.0
    if (
        not (np.all(np.abs(first) < _MAX_KEY) and np.all(np.abs(last) < _MAX_KEY))
        or float(np.prod(dims)) >= _MAX_KEY
    ):
        # Say how far the points reach: at 1e18 m one cell is already past numbering, and
        # "[1, 1, 1] cells are too many" would read as nonsense.
        reach = float(np.max(np.abs(np.r_[low, high])))
        grid = " x ".join(f"{d:.3g}" for d in dims)
        raise InputError(
            f"cells of {h:g} m are too many to number from the origin out to points reaching "
            f"|coordinate| {reach:.3g} m ({grid} cells here): use larger cells, or check the "
            "coordinates' units"
        )


def bounds(points: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """(3,) smallest and (3,) largest coordinates of the (N, 3) finite points, N >= 1."""
    return _bounds(_finite_points(points))


def _finite_points(points: NDArray[np.float64]) -> NDArray[np.float64]:
    # The kernels read points[0] and index cells from coordinates: an empty, misshaped or
    # non-finite array must stop here, not read out of bounds.
    return np.ascontiguousarray(as_points(points, "points"), dtype=np.float64)


def voxel_cells(
    points: NDArray[np.float64], voxel_size: float
) -> tuple[NDArray[np.float64], NDArray[np.intp]]:
    """Centroids of the occupied voxel cells and the cell of each point.

    Parameters
    ----------
    points
        (N, 3) points, any frame (m); cells are aligned to multiples of ``voxel_size``.
    voxel_size
        Cell edge (m).

    Returns
    -------
    centroids, cell
        (M, 3) mean point of each occupied cell, ordered by cell key; (N,) cell index of each
        point.
    """
    centroids, _, first_seen, by_key, _ = _cell_sums(_finite_points(points), voxel_size, None)
    rank = np.empty_like(by_key)
    rank[by_key] = np.arange(len(by_key))
    return centroids, rank[first_seen]


def _cell_sums(
    pts: NDArray[np.float64],
    voxel_size: float,
    sigma: NDArray[np.float64] | None,
    origin: NDArray[np.float64] = _ORIGIN,
) -> tuple[
    NDArray[np.float64], NDArray[np.float64], NDArray[np.int64], NDArray[np.int64], _Occupancy
]:
    """Centroids (M, 3) and mean σ (M,; empty without σ) of the occupied cells ordered by key,
    the (N,) cell of each point in order of first appearance, the (M,) key order of those and
    the cells' occupancy (by key).

    ``pts`` are finite and contiguous (at least one); the cells are aligned to ``origin`` (3,)
    plus multiples of the edge. Sums run point by point in index order: the same bits as a
    bincount per axis.
    """
    h = _cell_size(voxel_size)
    low, high = _bounds(pts)
    n = len(pts)
    low, high = low - origin, high - origin
    _check_span(low, high, h)
    first, last = np.floor(low / h).astype(np.int64), np.floor(high / h).astype(np.int64)
    dims = last - first + 1
    n_cells = float(np.prod(dims.astype(np.float64)))
    if n_cells <= 2 * n:
        # Few cells in the box: a slot per cell, one load per lookup.
        table, bits = np.full(int(n_cells), -1, dtype=np.int64), 0
    else:
        bits = hash_bits(n)
        table = np.full(1 << bits, -1, dtype=np.int64)
    cell = np.empty(n, dtype=np.int64)
    unique = np.empty(n, dtype=np.int64)
    no_sigma = sigma is None
    weights = np.empty(0) if no_sigma else np.ascontiguousarray(sigma, dtype=np.float64)
    sums = np.zeros((n, 4 if not no_sigma else 3))
    counts = np.zeros(n)
    m = _key_and_sum(pts, h, origin, first, dims, table, bits, weights, cell, unique, sums, counts)
    occupancy = _Occupancy(unique[:m], counts[:m], table, bits, dims, np.argsort(unique[:m]))
    # Rank the occupied cells by key: sorting M cells, not N points.
    by_key = occupancy.by_key
    sums, counts = sums[by_key], counts[by_key]
    mean_sigma = np.empty(0) if no_sigma else sums[:, 3] / counts
    return sums[:, :3] / counts[:, None], mean_sigma, cell, by_key, occupancy


@numba.njit(cache=True)
def _key_and_sum(points, h, origin, first, dims, table, bits, sigma, cell, unique, sums, counts):
    """Key every point (cell ``⌊(p − origin) / h⌋ − first`` packed with ``dims``), number the
    occupied cells in order of first appearance (``unique`` their keys, ``cell`` each point's)
    and add each point (and its σ, when ``sigma`` is not empty) to its cell's row of ``sums`` /
    ``counts``; return the number of cells. A point in the previous point's cell (a scan's
    neighbouring pixels) skips the lookup."""
    mask = (1 << bits) - 1
    count = 0
    previous, rank = -1, -1
    with_sigma = len(sigma) > 0
    for i in range(len(points)):
        cx = np.int64(np.floor((points[i, 0] - origin[0]) / h)) - first[0]
        cy = np.int64(np.floor((points[i, 1] - origin[1]) / h)) - first[1]
        cz = np.int64(np.floor((points[i, 2] - origin[2]) / h)) - first[2]
        key = (cx * dims[1] + cy) * dims[2] + cz
        if key != previous:
            s = key if bits == 0 else hash_slot(key, bits)
            while True:
                rank = table[s]
                if rank == -1:
                    table[s] = rank = count
                    unique[count] = key
                    count += 1
                    break
                if unique[rank] == key:
                    break
                s = (s + 1) & mask
            previous = key
        cell[i] = rank
        sums[rank, 0] += points[i, 0]
        sums[rank, 1] += points[i, 1]
        sums[rank, 2] += points[i, 2]
        if with_sigma:
            sums[rank, 3] += sigma[i]
        counts[rank] += 1.0
    return count


@numba.njit(cache=True)
def _bounds(points):
    """(3,) smallest and (3,) largest coordinates of the points (at least one)."""
    # One scalar per axis and side, not a loop over the axes: a third of the time.
    lx = hx = points[0, 0]
    ly = hy = points[0, 1]
    lz = hz = points[0, 2]
    for i in range(1, len(points)):
        x, y, z = points[i, 0], points[i, 1], points[i, 2]
        lx, hx = min(lx, x), max(hx, x)
        ly, hy = min(ly, y), max(hy, y)
        lz, hz = min(lz, z), max(hz, z)
    return np.array([lx, ly, lz]), np.array([hx, hy, hz])


@numba.njit(cache=True)
def _cells(points, origin, h, cells):
    """Fill ``cells`` (N, 3) with ⌊(p − origin) / h⌋; return the per-axis minimum and maximum."""
    low = np.full(3, np.iinfo(np.int64).max, dtype=np.int64)
    high = np.full(3, np.iinfo(np.int64).min, dtype=np.int64)
    for i in range(len(points)):
        for a in range(3):
            c = np.int64(np.floor((points[i, a] - origin[a]) / h))
            cells[i, a] = c
            low[a] = min(low[a], c)
            high[a] = max(high[a], c)
    return low, high


@numba.njit(cache=True)
def _pack(cells, low, dims):
    keys = np.empty(len(cells), dtype=np.int64)
    for i in range(len(cells)):
        keys[i] = ((cells[i, 0] - low[0]) * dims[1] + cells[i, 1] - low[1]) * dims[2] + (
            cells[i, 2] - low[2]
        )
    return keys


def voxel_downsample(
    cloud: PointCloud | ArrayLike,
    voxel_size: float,
    *,
    stray_share: float = 0.0,
    origin: ArrayLike | None = None,
) -> PointCloud:
    """Centroid of the points in each occupied voxel (edge ``voxel_size`` m), sorted by voxel.

    σ (if present) is averaged too; normals are dropped (recompute them on the sparse cloud).

    ``stray_share`` > 0 drops the voxels whose 3×3×3 block of voxels holds fewer points than
    that share of the median block: stray points, not a surface (:func:`stray_voxels`).

    ``origin`` (3,) m moves the grid: its cells are aligned to ``origin`` plus multiples of
    the edge (None: to the frame's origin). The same points on a grid moved by half a voxel
    sample the surface's edges otherwise, without copying a raw frame to shift it.

    Raises
    ------
    InputError
        A bad voxel size or a ``stray_share`` outside [0, 1).
    """
    cloud = as_cloud(cloud, "cloud")
    if isinstance(stray_share, bool) or not isinstance(stray_share, int | float | np.floating):
        raise InputError(f"stray_share must be a number, got {stray_share!r}", cloud.source)
    if not 0.0 <= stray_share < 1.0:
        # A share of 1 or more can drop every voxel; NaN would silently drop none.
        raise InputError(f"stray_share must lie in [0, 1), got {stray_share}", cloud.source)
    # A PointCloud's points are finite (N, 3) float64 already.
    pts = np.ascontiguousarray(cloud.points, dtype=np.float64)
    try:
        grid = _ORIGIN if origin is None else np.asarray(origin, dtype=np.float64).reshape(3)
    except (TypeError, ValueError):  # text, or not 3 numbers: numpy's ValueError
        grid = np.full(3, np.nan)
    if not np.all(np.isfinite(grid)):
        raise InputError(f"origin must be 3 finite numbers, got {origin!r}", cloud.source)
    centroids, sigma, _, _, occupancy = _cell_sums(pts, voxel_size, cloud.sigma, grid)
    if stray_share > 0.0:
        solid = np.flatnonzero(~stray_voxels(occupancy, stray_share))
        centroids, sigma = centroids[solid], sigma[solid] if len(sigma) else sigma
    return PointCloud(centroids, None, None if cloud.sigma is None else sigma, source=cloud.source)


def stray_voxels(occupancy: _Occupancy, share: float) -> NDArray[np.bool_]:
    """(M,) mask of the occupied voxels (by key) whose 3×3×3 block holds fewer points than
    ``share`` of the median block's.

    A surface sampled at spacing s puts about 9 (v / s)² points in the block around each of its
    voxels (v the edge), its noisy tails as many; a flying pixel (a return mixed between two
    depths) or a stray return has a block of its own: on raw lab frames at 640×480 and
    1280×720, every target voxel's block held at least a sixth of the median, 95 % of the
    flying pixels' a fortieth. The rule needs no length; with a voxel near the spacing (a
    sparse flash-LiDAR frame) the median block holds too few points to tell, and a share
    below one point of it drops nothing. The median is taken over at most 512 cells spread
    over the frame, and a block's count stops once it reaches the bound: a surface voxel
    looks at a few of its 27 cells.
    """
    o = occupancy
    m = len(o.keys)
    sample = np.arange(0, m, max(1, m // _MEDIAN_SAMPLE))
    full = _block_counts(o.keys, o.counts, o.table, o.bits, o.dims, sample, np.inf)
    bound = share * float(np.median(full))
    around = _block_counts(o.keys, o.counts, o.table, o.bits, o.dims, np.arange(m), bound)
    return (around < bound)[o.by_key]


@numba.njit(cache=True)
def _block_counts(keys, counts, table, bits, dims, cells, stop):
    """(len(cells),) points in the 3×3×3 cells around each of ``cells`` (ranks; itself
    included), each count cut short once it reaches ``stop``: ``keys`` and ``counts`` (M,) of
    the occupied cells, their hash ``table`` and ``bits`` (:mod:`spacepose.core.cell_hash`),
    ``dims`` (3,) cells along each axis."""
    out = np.empty(len(cells))
    for n in range(len(cells)):
        out[n] = _block_count(keys, counts, table, bits, dims, cells[n], stop)
    return out


@numba.njit(cache=True, inline="always")
def _block_count(keys, counts, table, bits, dims, i, stop):
    # Its own cell first: a dense cell stops there.
    total = counts[i]
    if total >= stop:
        return total
    plane = dims[1] * dims[2]
    cx, rest = keys[i] // plane, keys[i] % plane
    cy, cz = rest // dims[2], rest % dims[2]
    for x in range(max(cx - 1, 0), min(cx + 2, dims[0])):
        for y in range(max(cy - 1, 0), min(cy + 2, dims[1])):
            for z in range(max(cz - 1, 0), min(cz + 2, dims[2])):
                key = (x * dims[1] + y) * dims[2] + z
                if key == keys[i]:
                    continue
                rank = find_cell(table, keys, bits, key)
                if rank >= 0:
                    total += counts[rank]
                    if total >= stop:
                        return total
    return total


def evenly_thinned(cloud: PointCloud, most: int) -> PointCloud:
    """``cloud`` with at most ``most`` of its points: every k-th in its order (a grid's order
    spreads the thinning over the cloud), the cloud itself when it holds no more."""
    if len(cloud) <= most:
        return cloud
    return cloud.select(np.linspace(0, len(cloud) - 1, most).astype(np.intp))
