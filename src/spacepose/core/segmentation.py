"""Which points are the target (docs/methods.md §5.7): the nearest object, then a crop around it.

A sensor aimed at a target also sees what lies behind or around it: a wall, a table, a docking
fixture. A model-free tracker that registers the whole frame tracks whatever dominates it (the
static wall, at identity), and every check then says ``ok``. Two scale-free steps keep the
target alone:

1. on the first frame, :func:`nearest_object`: the frame's points grouped into connected
   clusters (grid cells of four point spacings holding a few points, linked to their 26
   neighbours; a flying pixel alone in its cell links nothing, and joins the object only on
   its rim); the object is the cluster nearest the sensor (smallest median range) among those
   holding a real share of the frame's points or cells, grown by every cluster whose gap to
   it is below 3/4 of its size (a wing on a boom the sensor does not see) unless it is the
   background: wholly behind the object and seen past it on every side (the wall behind a big
   object, the Earth behind a satellite); everything else (the wall behind, debris, stray
   pixels) is background;
2. on every later frame, :func:`crop_sphere`: the points within the object's bounding sphere,
   carried by the predicted pose and widened by the motion model's error (by the largest
   motion allowed while the velocity is unknown: then, when a body lies in the sphere beside
   the target, a wall behind a large one, :func:`clusters_near` keeps the clusters where the
   prediction puts the target, :func:`spacepose.core.target_cut.cut_to_target`).

Both steps use only the point spacing and the object's own size, so they work unchanged from a
mock-up at 1 m to a satellite at 25 m. A background *touching* the target (a turntable under
it) stays in the object: that needs a model or the motion to separate.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from spacepose.core.cloud import PointCloud, as_points
from spacepose.core.reach import within_reach
from spacepose.core.se3 import whole_number
from spacepose.core.threads import numba_threads
from spacepose.core.voxel import voxel_cells
from spacepose.errors import InputError

# Rows per chunk of the compiled crop's passes (a chunk's count and indices are one thread's).
_CROP_CHUNK = 65536
# Cell edge of the clustering, in point spacings: coarse enough to be cheap on a cluttered VGA
# frame (~40k cells), fine enough that a 5-spacing gap separates two objects.
_CELL_SPACINGS = 4.0
# Fewest points of a cell that is surface, not flying pixels.
_MIN_CELL_POINTS = 3
# A cluster holding less than this share of the frame's points and of its cells (of the
# object's cells, for a part of it) is debris or flying pixels.
_MIN_SHARE = 0.02
# A later frame's cluster is the target's when its share of points near the predicted target
# is at least this part of the best cluster's (clusters_near).
_NEAR_SHARE = 0.5
# A cluster whose gap to the object is below this share of the object's radius is part of it
# (the lab mock-up's far wing hangs 8.4 cm from its 0.13 m bus, its boom unseen).
_MERGE_RADII = 0.75


@dataclass(frozen=True)
class TargetRegion:
    """Where the target is in the frame it was found in.

    Attributes
    ----------
    center
        (3,) centroid of the object's points (sensor frame of that frame, m).
    radius
        Largest distance of an object point from ``center`` (m).
    kept
        Share of the frame's points that belong to the object.
    """

    center: NDArray[np.float64]
    radius: float
    kept: float


def nearest_object(
    points: ArrayLike, spacing: float, min_points: int = 1, model_radius: float | None = None
) -> NDArray[np.bool_]:
    """(N,) mask of the points of the nearest object of a frame (see the module docstring);
    points at the sensor's origin or far beyond the frame's surfaces (:func:`within_reach`) are
    never in it.

    Parameters
    ----------
    points
        (N, 3) points in the sensor frame (m), the sensor at the origin.
    spacing
        Median point spacing (m), :func:`spacepose.core.scale.point_spacing`.
    min_points
        Fewest points of an object found before a backdrop (a tracked frame's least).
    model_radius
        Radius (m) of the target model's bounding sphere, when there is a model: the object
        then also takes every cluster that lies wholly within the model's reach of it
        (:func:`_within_model`), the body behind an antenna pointed at the sensor, which the
        growth by the object's own size leaves behind as its background.
    """
    pts = as_points(points)
    min_points = whole_number(min_points, "min_points")
    valid = within_reach(pts)
    if not valid.all():
        mask = np.zeros(len(pts), dtype=bool)
        if valid.any():
            mask[valid] = nearest_object(pts[valid], spacing, min_points, model_radius)
        return mask
    cell = _CELL_SPACINGS * spacing
    all_centroids, all_of_point = voxel_cells(pts, cell)
    # A cell's centroid lies inside it: its floor is the cell's index.
    all_cells = np.floor(all_centroids / cell).astype(np.int64)
    # Cells of a surface hold a dozen points; a lone return in a cell is a flying pixel, whose
    # trails from the silhouette to what lies behind would link the two: the clusters are of
    # the solid cells, and the sparse ones join the object only beside it (its rim).
    solid = np.bincount(all_of_point) >= _MIN_CELL_POINTS
    if not solid.any():
        solid[:] = True
    index = np.cumsum(solid) - 1
    of_point = np.where(solid[all_of_point], index[all_of_point], -1)
    centroids, cells = all_centroids[solid], all_cells[solid]
    labels = _cluster_labels(cells)
    n_labels = int(labels.max()) + 1
    counts = np.bincount(labels, minlength=n_labels)
    # A real object fills a share of the view (its points: a camera samples solid angle) or of
    # the scene's surface (its cells): a target at 3 m before a wall at 5 m holds 6 % of the
    # points but 1 % of the cells, which the wall's coarser spacing sizes. The largest cluster
    # always counts: a frame of many small equal pieces has one still.
    points = np.bincount(labels[of_point[of_point >= 0]], minlength=n_labels)
    real = (counts >= _MIN_SHARE * len(cells)) | (points >= _MIN_SHARE * len(pts))
    real[np.argmax(counts)] = True
    ranges = np.linalg.norm(centroids, axis=1)
    # Directions in the view (horizontal and vertical angle from the optical axis +z).
    view = np.arctan2(centroids[:, :2], centroids[:, 2:3])
    chosen = _nearest(np.flatnonzero(real), ranges, labels)
    if (centroids[:, 2] > 0.0).all():  # a camera's view, with borders
        chosen = _before_backdrop(chosen, view, ranges, labels, points, cell, min_points)
    keep = labels == chosen
    nearest = np.full(n_labels, np.inf)
    np.minimum.at(nearest, labels, ranges)
    # Grow the object by the clusters close beside it (parts joined by what the sensor does
    # not see), each merge widening the reach with the object's size.
    while True:
        own = centroids[keep]
        radius = float(np.linalg.norm(own - own.mean(axis=0), axis=1).max()) + cell
        reach = _MERGE_RADII * radius
        # A part need only be a real share of the object, not of a frame full of wall; and it
        # is not the background: around the object in the view and wholly behind it (a wall
        # behind a big object is near it, but the object hides a hole in it). Behind its far
        # side less the flying pixels dense enough to fill a cell (2 % of its cells at most).
        behind = nearest > np.quantile(ranges[keep], 1.0 - _MIN_SHARE)
        background = behind & _surrounds(view, labels, n_labels, keep)
        part = (counts >= _MIN_SHARE * len(own)) & ~background
        near = part & (_gaps(own, centroids, labels, n_labels, reach) <= reach)
        grown = keep | near[labels]
        if grown.sum() == keep.sum():
            if model_radius is not None:
                fits = _within_model(centroids, keep, labels, n_labels, model_radius, cell)
                keep |= fits & (counts >= _MIN_SHARE * keep.sum())[labels]
            kept = np.zeros(len(all_cells), dtype=bool)
            kept[solid] = keep
            kept[~solid] = _beside(all_cells[~solid], cells[keep])
            return kept[all_of_point]
        keep = grown


def clusters_near(points: ArrayLike, cell: float, near: ArrayLike) -> NDArray[np.bool_]:
    """(N,) mask of the points of the connected clusters (grid cells of edge ``cell`` m,
    linked to their 26 neighbours) that are the target's on a later frame: those whose share
    of ``near`` points (N,) is at least :data:`_NEAR_SHARE` of the largest share of any
    cluster. All points when none or every one is near.

    ``near`` marks the points close to where the prediction puts the target's reference
    (:func:`spacepose.core.target_cut.cut_to_target`). A face that turns into view lies in
    the target's cluster with the faces seen before; a wall the crop took in behind a large
    target is a cluster of its own, with only its few points in front near the target.
    """
    pts = as_points(points)
    near = np.asarray(near)
    if near.shape != (len(pts),) or near.dtype != bool:
        # A float mask would read NaN as near.
        raise InputError(f"near must be ({len(pts)},) booleans, got {near.dtype} {near.shape}")
    if near.all() or not near.any():
        return np.ones(len(pts), dtype=bool)
    centroids, of_point = voxel_cells(pts, cell)
    labels = _cluster_labels(np.floor(centroids / cell).astype(np.int64))[of_point]
    share = np.bincount(labels, weights=near) / np.bincount(labels)
    return (share >= _NEAR_SHARE * share.max())[labels]


def solid(points: ArrayLike, spacing: float) -> NDArray[np.bool_]:
    """(N,) mask of the points in solid cells (see :func:`nearest_object`: cells of four point
    spacings holding at least 3 points): a surface's, not lone flying pixels or stray returns."""
    pts = as_points(points)
    _, of_point = voxel_cells(pts, _CELL_SPACINGS * spacing)
    return (np.bincount(of_point) >= _MIN_CELL_POINTS)[of_point]


def region_of(points: ArrayLike) -> TargetRegion:
    """The bounding sphere of (N, 3) object points; ``kept`` is set by the caller (1 here)."""
    pts = as_points(points)
    center = pts.mean(axis=0)
    return TargetRegion(center, float(np.linalg.norm(pts - center, axis=1).max()), 1.0)


def crop_sphere(
    points: PointCloud | ArrayLike, center: ArrayLike, radius: float, workers: int = 1
) -> NDArray[np.intp]:
    """(M,) indices, ascending, of the returns (points not at the sensor's origin, :func:`returns`)
    within ``radius`` (m) of ``center`` (3,): squared distance ``(dx² + dy²) + dz²`` at most
    ``radius²``.

    One compiled pass over fixed chunks of rows, on ``workers`` threads (-1: all cores), each
    chunk listing its kept rows in order: a raw 1280×720 frame (900k points, 21 MB, fresh from
    the sensor) is read once, where testing the returns, then cropping, then listing the kept
    points read it three times. The indices do not depend on the thread count.

    Raises
    ------
    InputError
        Bad points (:func:`~spacepose.core.cloud.as_points`; a cloud was checked when made), a
        centre that is not 3 finite numbers, or a radius that is not a finite length >= 0 (a
        negative one, squared, would crop as its opposite).
    """
    pts = np.ascontiguousarray(as_points(points))
    try:
        c = np.asarray(center, dtype=np.float64).reshape(3)
        r = float(radius)
    except (TypeError, ValueError):
        raise InputError(
            f"a crop needs a (3,) centre and a radius, got {center!r}, {radius!r}"
        ) from None
    if not (np.isfinite(c).all() and np.isfinite(r) and r >= 0.0):
        raise InputError(f"a crop needs a finite centre and radius >= 0, got {c.tolist()}, {r}")
    chunks = max(1, -(-len(pts) // _CROP_CHUNK))
    counts = np.empty(chunks, dtype=np.int64)
    # Each chunk writes its kept rows from its own first row on: np.empty's pages are touched
    # only where a chunk writes, a few hundred kilobytes of a 900k-point frame's 7 MB.
    slots = np.empty(len(pts), dtype=np.intp)
    with numba_threads(workers):
        _within(pts, c, r**2, slots, counts)
    starts = np.arange(chunks) * _CROP_CHUNK
    return np.concatenate([slots[a : a + m] for a, m in zip(starts, counts, strict=True)])


@numba.njit(cache=True, parallel=True)
def _within(points, center, radius2, slots, counts):
    """Chunk j (rows ``j · _CROP_CHUNK`` on) writes, in order, the indices of its returns
    within ``radius2`` (squared, m²) of ``center`` into ``slots`` from its first row, and
    their number into ``counts[j]``."""
    n = len(points)
    for j in numba.prange(len(counts)):
        first = j * _CROP_CHUNK
        at = first
        for i in range(first, min(n, first + _CROP_CHUNK)):
            x, y, z = points[i, 0], points[i, 1], points[i, 2]
            if x == 0.0 and y == 0.0 and z == 0.0:
                continue  # no return (returns)
            dx, dy, dz = x - center[0], y - center[1], z - center[2]
            if dx * dx + dy * dy + dz * dz <= radius2:
                slots[at] = i
                at += 1
        counts[j] = at - first


def _cluster_labels(cells: NDArray[np.int64]) -> NDArray[np.intp]:
    """Connected components of occupied grid cells (M, 3), linked to their 26 neighbours."""
    low = cells.min(axis=0) - 1
    span = cells.max(axis=0) - low + 2
    key = _keys(cells, low, span)
    order = np.argsort(key)
    sorted_keys = key[order]
    rows, cols = [], []
    # Half of the 26-neighbourhood: each link found once.
    for d in np.argwhere(np.ones((3, 3, 3))) - 1:
        step = (d[0] * span[1] + d[1]) * span[2] + d[2]
        if step <= 0:
            continue
        pos = np.searchsorted(sorted_keys, key + step)
        found = (pos < len(key)) & (sorted_keys[np.minimum(pos, len(key) - 1)] == key + step)
        rows.append(np.flatnonzero(found))
        cols.append(order[pos[found]])
    r, c = np.concatenate(rows), np.concatenate(cols)
    n = len(cells)
    graph = coo_matrix((np.ones(len(r)), (r, c)), shape=(n, n))
    _, labels = connected_components(graph, directed=False)
    return labels


def _beside(cells: NDArray[np.int64], of: NDArray[np.int64]) -> NDArray[np.bool_]:
    """(M,) True for the grid cells (M, 3) that are one of the cells ``of`` (K, 3) or among
    their 26 neighbours."""
    if len(cells) == 0 or len(of) == 0:
        return np.zeros(len(cells), dtype=bool)
    low = np.minimum(cells.min(axis=0), of.min(axis=0)) - 1
    span = np.maximum(cells.max(axis=0), of.max(axis=0)) - low + 2
    occupied = np.unique(_keys(of, low, span))
    near = np.zeros(len(cells), dtype=bool)
    for d in np.argwhere(np.ones((3, 3, 3))) - 1:
        near |= np.isin(_keys(cells + d, low, span), occupied)
    return near


def _keys(
    cells: NDArray[np.int64], low: NDArray[np.int64], span: NDArray[np.int64]
) -> NDArray[np.int64]:
    """One integer per grid cell (M, 3) of a box from ``low`` spanning ``span`` cells a side
    (the box holds a cell's neighbours too, so neighbours' keys never collide)."""
    c = cells - low
    return (c[:, 0] * span[1] + c[:, 1]) * span[2] + c[:, 2]


def _nearest(
    clusters: NDArray[np.intp], ranges: NDArray[np.float64], labels: NDArray[np.intp]
) -> int:
    """The one of ``clusters`` whose cells have the smallest median range."""
    median_range = [np.median(ranges[labels == c]) for c in clusters]
    return int(clusters[int(np.argmin(median_range))])


def _before_backdrop(
    chosen: int,
    view: NDArray[np.float64],
    ranges: NDArray[np.float64],
    labels: NDArray[np.intp],
    points: NDArray[np.intp],
    cell: float,
    min_points: int,
) -> int:
    """``chosen``, unless it is a backdrop and a cluster lies before it: then the nearest such.

    A backdrop reaches the border of the view on all four sides (within two cells at its
    nearest range), as a wall behind the target does. The shares that make a cluster real are
    then of what is not backdrop: a 2 m box at 20 m before a wall at 30 m fills 0.3 % of a
    640×480 view and 0.3 % of its cells, and the wall was tracked (the surface degenerate on
    every frame). A cluster before it needs ``min_points`` points, as a tracked frame does,
    and must lie wholly before the backdrop.
    """
    n_labels = len(points)
    lo, hi = _extents(view, labels, n_labels)
    tol = 2.0 * cell / ranges[labels == chosen].min()
    edge_lo, edge_hi = view.min(axis=0) + tol, view.max(axis=0) - tol
    backdrop = np.all((lo <= edge_lo) & (hi >= edge_hi), axis=1)
    if not backdrop[chosen] or backdrop.all():
        return chosen
    counts = np.bincount(labels, minlength=n_labels)
    rest_cells, rest_points = counts[~backdrop].sum(), points[~backdrop].sum()
    share = (counts >= _MIN_SHARE * rest_cells) | (points >= _MIN_SHARE * rest_points)
    before = np.flatnonzero(~backdrop & share & (points >= min_points))
    if not len(before):
        return chosen
    nearest = _nearest(before, ranges, labels)
    # Seen against the backdrop: wholly before it (beyond its far side less the flying pixels
    # dense enough to fill a cell, as a background is in the growth below). A room's shell,
    # whose floor runs under the furniture to the camera, is no backdrop to a chair.
    far_side = np.quantile(ranges[labels == nearest], 1.0 - _MIN_SHARE)
    return nearest if ranges[labels == chosen].min() > far_side else chosen


def _surrounds(
    view: NDArray[np.float64], labels: NDArray[np.intp], n_labels: int, keep: NDArray[np.bool_]
) -> NDArray[np.bool_]:
    """(n_labels,) True for the clusters whose extent in the view (angles (M, 2)) holds the
    object's (cells ``keep``) on both axes: what lies around the object, seen past it."""
    lo, hi = _extents(view, labels, n_labels)
    own = view[keep]
    return np.all((lo <= own.min(axis=0)) & (hi >= own.max(axis=0)), axis=1)


def _extents(
    view: NDArray[np.float64], labels: NDArray[np.intp], n_labels: int
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """(n_labels, 2) smallest and largest view angles of each cluster's cells."""
    lo = np.full((n_labels, 2), np.inf)
    hi = np.full((n_labels, 2), -np.inf)
    np.minimum.at(lo, labels, view)
    np.maximum.at(hi, labels, view)
    return lo, hi


def _within_model(
    centroids: NDArray[np.float64],
    keep: NDArray[np.bool_],
    labels: NDArray[np.intp],
    n_labels: int,
    model_radius: float,
    cell: float,
) -> NDArray[np.bool_]:
    """(M,) True for the cells (centroids (M, 3)) of the clusters that fit with the object
    (cells ``keep``) in the model's diameter: every cell of theirs within ``2 model_radius``
    (plus a cell) of the object's farthest cell, bounded by its distance from the object's
    centroid plus the object's radius. A wall or a table reaching beyond the target's size
    does not fit; the body behind a near appendage does. (The caller keeps those holding a
    real share of the object's cells: specks of flying pixels behind the silhouette fit too.)"""
    own = centroids[keep]
    center = own.mean(axis=0)
    reach = 2.0 * model_radius + cell - float(np.linalg.norm(own - center, axis=1).max())
    farthest = np.zeros(n_labels)
    np.maximum.at(farthest, labels, np.linalg.norm(centroids - center, axis=1))
    return (farthest <= reach)[labels]


def _gaps(
    own: NDArray[np.float64],
    centroids: NDArray[np.float64],
    labels: NDArray[np.intp],
    n_labels: int,
    reach: float,
) -> NDArray[np.float64]:
    """(n_labels,) smallest distance from each cluster's cells to the object's cells (inf
    beyond ``reach``: only whether a cluster is that close matters)."""
    d, _ = cKDTree(own).query(centroids, distance_upper_bound=reach)
    gaps = np.full(n_labels, np.inf)
    np.minimum.at(gaps, labels, d)
    return gaps
