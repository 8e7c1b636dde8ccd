"""Background removal before registration: range gate, large planes, the target's cluster group.

A lab frame holds the target and whatever else the sensor sees: a wall, a turntable and its
plinth, stray and flying pixels. Three steps, each optional, isolate the target:

1. a range gate on the distance from the sensor origin;
2. removal of large background planes. Planes are searched by RANSAC
   (:func:`spacepose.core.planes.ransac_plane`) on a voxel grid of the frame, so that a plane's
   weight is its visible area, not its point count (a wall at 2 m would otherwise outweigh
   everything by density). A plane's *patch* is the connected set of cells on it whose local
   normal agrees with the plane's; a patch counts as background when its width (the smallest
   distance between two parallel lines enclosing it) reaches ``min_plane_extent``. Judging by
   size rather than by share of the points keeps the target's own panels (the coplanar wings of
   a lone target can hold over half the points) and catches a turntable top seen at grazing
   incidence (few points, but half a metre wide). Every point within ``plane_distance`` of a
   background patch goes, and with ``cut_behind_planes`` so does every point beyond it (on the
   side away from the sensor) inside the patch's outline: a large plane facing the sensor bounds
   the target's side of the scene, so what lies behind it (the plinth under a turntable top,
   the noise behind a wall) is background;
3. the target's cluster group (:mod:`spacepose.core.clusters`): Euclidean clusters (links
   shorter than ``cluster_distance``) of at least ``min_cluster_share`` of the largest are
   merged with the largest when closer than ``merge_distance``. Thin parts (booms, masts) are
   lost to flying pixels and dropouts, so the target falls apart at a few centimetres; the
   merge distance bridges those gaps while isolated sparse debris (flying-pixel curtains)
   stays out.

Frames: everything is in the frame of the input cloud, the sensor frame, metres.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from pydantic import Field, field_validator, model_validator
from scipy.spatial import ConvexHull, QhullError

from spacepose.core.cloud import PointCloud
from spacepose.core.clusters import main_cluster_group
from spacepose.core.config import StageConfig
from spacepose.core.moments import fit_plane
from spacepose.core.neighbors import hybrid
from spacepose.core.normals import neighbourhood_normals
from spacepose.core.plane_support import largest_component
from spacepose.core.planes import PlaneConfig, ransac_plane
from spacepose.core.voxel import voxel_cells
from spacepose.errors import DegenerateGeometryError, InputError

# RANSAC outlier share assumed in the plane search: once the wall is gone, a turntable top is
# ~15 % of the cells left, so the iteration bound must assume a large outlier share.
_PLANE_OUTLIER_RATIO = 0.8
# Largest number of cells the plane hypotheses are scored on.
_RANSAC_CELLS = 20000
# Neighbours of a voxel cell used for its local normal (cells within 3 voxel edges).
_NORMAL_NEIGHBOURS = 16
_NORMAL_RADIUS_VOXELS = 3.0


class BackgroundConfig(StageConfig):
    """Parameters of :func:`remove_background`.

    Attributes
    ----------
    range_min, range_max
        Kept distances from the sensor origin (m); ``range_max`` None: no upper limit.
    remove_planes
        Largest number of background planes removed (0: no plane step).
    plane_candidates
        Largest number of planes examined; planes too small to be background (the target's own
        panels) count here but are kept.
    plane_distance
        Plane thickness (m): points within it (or within 3 σ of their own noise, when the cloud
        carries σ) of a background patch go with it.
    min_plane_share
        Smallest share of the frame's occupied voxel cells a plane patch must cover to be
        examined; the search stops at the first smaller one.
    min_plane_extent
        A patch whose width (m) reaches this is background. Set it above the width of the
        target's largest face (the lab mock-up: 0.12 m wings, 0.20 m bus) and below that of the
        smallest background plane (the lab turntable top: 0.5 m). A large target needs more
        (the orbit satellite's wing is 2 m wide), or ``remove_planes = 0``.
    normal_angle_deg
        A cell belongs to a plane's patch when its local normal is within this angle of the
        plane's; stops a patch from running along other surfaces that cross the plane.
    voxel_size
        Edge (m) of the voxel grid the planes are searched on; about 4 point spacings.
    outline_margin
        Growth (m) of a patch's outline before points are tested against it: the outline joins
        cell centroids, which stop short of the plane's physical edge, and a turntable's rim
        hangs just outside its top.
    cut_behind_planes
        Also remove what lies beyond a background patch inside its outline.
    keep_largest_cluster
        Keep only the cluster group around the largest Euclidean cluster.
    cluster_distance
        Points closer than this (m) belong to one cluster; a few point spacings.
    merge_distance
        Clusters closer than this (m) to the group are merged into it; above the largest gap
        inside the target (the lab mock-up's far wing, its boom hidden behind the bus, was
        measured up to 8.4 cm from the bus), below the target's distance to the background
        left after the planes.
    min_cluster_share
        Clusters smaller than this share of the largest are debris and never merged.
    seed
        Seed of the plane RANSAC.
    """

    range_min: float = Field(default=0.0, ge=0)
    range_max: float | None = Field(default=None, gt=0)
    remove_planes: int = Field(default=4, ge=0)
    plane_candidates: int = Field(default=12, ge=1)
    plane_distance: float = Field(default=0.01, gt=0)
    min_plane_share: float = Field(default=0.002, gt=0, le=1)
    min_plane_extent: float = Field(default=0.3, gt=0)
    normal_angle_deg: float = Field(default=25.0, gt=0, lt=90)
    voxel_size: float = Field(default=0.01, gt=0)
    outline_margin: float = Field(default=0.03, ge=0)
    cut_behind_planes: bool = True
    keep_largest_cluster: bool = True
    cluster_distance: float = Field(default=0.02, gt=0)
    merge_distance: float = Field(default=0.12, gt=0)
    min_cluster_share: float = Field(default=0.01, gt=0, le=1)
    seed: int = Field(default=0, ge=0)

    @field_validator("range_max", mode="before")
    @classmethod
    def _unbounded(cls, value: object) -> object:
        # Configs written before None meant "no limit" hold inf (JSON: Infinity) here.
        return None if isinstance(value, float) and value == math.inf else value

    @model_validator(mode="after")
    def _range_order(self) -> BackgroundConfig:
        if self.range_max is not None and self.range_min >= self.range_max:
            raise ValueError(f"range_min {self.range_min} must be below range_max {self.range_max}")
        return self


@dataclass(frozen=True, eq=False)
class BackgroundPlane:
    """A background plane patch: its plane and its outline, sensor frame.

    Attributes
    ----------
    normal
        (3,) unit normal, pointing towards the sensor (the frame origin).
    offset
        Plane equation ``normal · x = offset`` (m).
    origin
        (3,) a point of the patch, the origin of the in-plane coordinates.
    axes
        (2, 3) orthonormal in-plane axes: along the patch's length, and across it in the
        direction of its smallest width.
    outline
        (F, 3) half-planes ``a·u + b·v + c <= 0`` of the convex hull of the patch in the
        in-plane coordinates ``(u, v) = axes · (x − origin)``; (a, b) is a unit vector.
    extent
        (2,) length and smallest width (m) of the patch along ``axes``; the width is the
        smallest distance between two parallel lines enclosing the patch.
    n_cells
        Number of voxel cells of the patch.
    """

    normal: NDArray[np.float64]
    offset: float
    origin: NDArray[np.float64]
    axes: NDArray[np.float64]
    outline: NDArray[np.float64]
    extent: NDArray[np.float64]
    n_cells: int

    def covers(
        self,
        points: NDArray[np.float64],
        distance: float | NDArray[np.float64],
        margin: float,
        behind: bool,
    ) -> NDArray[np.bool_]:
        """Mask (N,) of points (N, 3) on the patch or, with ``behind``, beyond it (away from the
        sensor), whose projection falls inside the outline grown by ``margin`` (m).

        ``distance`` is the patch's half-thickness (m), one value or one per point (N,).
        """
        signed = points @ self.normal - self.offset
        near = signed <= distance if behind else np.abs(signed) <= distance
        idx = np.flatnonzero(near)
        uv = (points[idx] - self.origin) @ self.axes.T
        inside = np.all(uv @ self.outline[:, :2].T + self.outline[:, 2] <= margin, axis=1)
        mask = np.zeros(len(points), dtype=bool)
        mask[idx[inside]] = True
        return mask


def cell_normals(
    centroids: NDArray[np.float64], voxel_size: float, workers: int = -1
) -> NDArray[np.float64]:
    """Unoriented unit normals (M, 3) of voxel cells from the covariance of nearby cells.

    A cell with fewer than 3 neighbours within ``3 · voxel_size`` gets a zero vector, which
    agrees with no plane.
    """
    k = min(_NORMAL_NEIGHBOURS, len(centroids))
    idx, _ = hybrid(centroids, centroids, _NORMAL_RADIUS_VOXELS * voxel_size, k, workers=workers)
    normals = neighbourhood_normals(centroids, idx, workers)
    normals[(idx >= 0).sum(axis=1) < 3] = 0.0
    return normals


def background_planes(
    centroids: NDArray[np.float64],
    normals: NDArray[np.float64],
    config: BackgroundConfig = BackgroundConfig(),
) -> list[BackgroundPlane]:
    """The large plane patches among voxel cells, largest search first.

    Parameters
    ----------
    centroids
        (M, 3) cell centroids (:func:`voxel_cells`), sensor frame.
    normals
        (M, 3) cell normals (:func:`cell_normals`), any sign.
    config
        ``plane_candidates`` planes at most are examined and ``remove_planes`` at most returned.

    Returns
    -------
    Background patches (width >= ``min_plane_extent``) in the order found.
    """
    min_cells = max(3, math.ceil(config.min_plane_share * len(centroids)))
    ransac = PlaneConfig(
        distance_threshold=config.plane_distance,
        outlier_ratio=_PLANE_OUTLIER_RATIO,
        min_inliers=3,
        seed=config.seed,
    )
    rng = np.random.default_rng(config.seed)
    cos_tol = math.cos(math.radians(config.normal_angle_deg))
    remaining = np.arange(len(centroids))
    found: list[BackgroundPlane] = []
    for _ in range(config.plane_candidates):
        if len(found) >= config.remove_planes or len(remaining) < min_cells:
            break
        pts = centroids[remaining]
        # Hypotheses are scored on a seeded sample of the cells: the shares of the planes, all
        # that RANSAC needs, survive sampling, and a wall's 80k cells cost no more than 20k.
        sample = pts
        if len(pts) > _RANSAC_CELLS:
            sample = pts[np.sort(rng.choice(len(pts), _RANSAC_CELLS, replace=False))]
        try:
            plane = ransac_plane(sample, ransac, rng)
        except DegenerateGeometryError:
            break  # what is left is a line or a point: no plane at all
        on = np.abs(pts @ plane.normal - plane.offset) <= config.plane_distance
        on &= np.abs(normals[remaining] @ plane.normal) >= cos_tol
        members = np.flatnonzero(on)
        if len(members) < min_cells:
            break
        patch = members[largest_component(pts[members], _NORMAL_RADIUS_VOXELS * config.voxel_size)]
        # Every agreeing cell of the slab leaves the search, not only the patch: the next
        # RANSAC would otherwise find the same slab again.
        remaining = np.delete(remaining, members)
        if len(patch) < min_cells:
            continue
        try:
            # Refit to the patch alone: the slab also held cells of other surfaces crossing it.
            normal, offset = fit_plane(pts[patch])
        except DegenerateGeometryError:
            continue  # the patch is a line of cells
        candidate = _patch(pts[patch], normal, offset)
        if candidate is not None and candidate.extent[1] >= config.min_plane_extent:
            found.append(candidate)
            # A noisy plane fills several layers of cells; the layers beside this patch would
            # otherwise come back as planes of their own. Only the slab over the outline goes:
            # what lies behind it may be the next plane (the turntable top above the plinth).
            layers = candidate.covers(
                centroids[remaining], config.plane_distance + config.voxel_size, 0.0, False
            )
            remaining = remaining[~layers]
    return found


def _patch(
    cells: NDArray[np.float64], normal: NDArray[np.float64], offset: float
) -> BackgroundPlane | None:
    """The patch of cells (K, 3) on a plane; None when they do not span an area."""
    origin = cells.mean(axis=0)
    centred = cells - origin
    # Any orthonormal in-plane basis will do for the hull: take two principal directions.
    projected = centred - np.outer(centred @ normal, normal)
    _, vectors = np.linalg.eigh(projected.T @ projected)
    basis = vectors[:, [2, 1]].T
    try:
        hull = ConvexHull(centred @ basis.T)
    except QhullError:
        return None  # collinear cells: a strip with no area
    corners = hull.points[hull.vertices]
    # Width = the smallest caliper width, attained across one of the hull's edges (rotating
    # calipers); principal axes would not do, a square's are arbitrary and see its diagonal.
    edge_normals = hull.equations[:, :2]
    widths = np.ptp(corners @ edge_normals.T, axis=0)
    across = edge_normals[np.argmin(widths)]
    R = np.array([[-across[1], across[0]], across])  # rows: along the length, across
    extent = np.ptp(corners @ R.T, axis=0)
    # Same half-planes in the rotated in-plane coordinates (u, v) = R (u0, v0).
    outline = np.column_stack([edge_normals @ R.T, hull.equations[:, 2]])
    return BackgroundPlane(normal, offset, origin, R @ basis, outline, extent, len(cells))


def remove_background(
    cloud: PointCloud, config: BackgroundConfig = BackgroundConfig(), workers: int = -1
) -> tuple[PointCloud, NDArray[np.bool_]]:
    """The target's points: range gate, large background planes removed, cluster group kept.

    Parameters
    ----------
    cloud
        Frame (N, 3) in the sensor frame (the range is the distance from its origin).
    config
        Gate, plane and cluster settings.
    workers
        Threads for the neighbour searches; the result does not depend on it.

    Returns
    -------
    target, mask
        The kept points (normals and σ follow) and the (N,) boolean mask of them in ``cloud``.

    Raises
    ------
    InputError
        When no point survives a step (the message names the step).
    """
    pts = cloud.points
    rng = np.linalg.norm(pts, axis=1)
    range_max = math.inf if config.range_max is None else config.range_max
    keep = np.flatnonzero((rng >= config.range_min) & (rng <= range_max))
    if len(keep) == 0:
        raise InputError(
            f"no point within the range gate {config.range_min}..{range_max} m "
            f"(ranges {rng.min():.3g}..{rng.max():.3g} m)",
            cloud.source,
        )
    if config.remove_planes > 0:
        keep = _without_planes(cloud, keep, config, workers)
    if config.keep_largest_cluster:
        in_group = main_cluster_group(
            pts[keep],
            config.cluster_distance,
            config.merge_distance,
            config.min_cluster_share,
            workers,
        )
        keep = keep[in_group]
    mask = np.zeros(len(pts), dtype=bool)
    mask[keep] = True
    return cloud.select(mask), mask


def _without_planes(
    cloud: PointCloud, keep: NDArray[np.intp], config: BackgroundConfig, workers: int
) -> NDArray[np.intp]:
    """``keep`` minus the points on or behind the background planes found among them."""
    gated = cloud.points[keep]
    centroids, _ = voxel_cells(gated, config.voxel_size)
    if len(centroids) < 3:
        return keep
    planes = background_planes(
        centroids, cell_normals(centroids, config.voxel_size, workers), config
    )
    if not planes:
        return keep
    # A point goes with a plane within 3 σ of its own noise, when the cloud carries σ, so that
    # a noisier sensor does not leave a fringe of the wall behind.
    distance: float | NDArray[np.float64] = config.plane_distance
    if cloud.sigma is not None:
        distance = np.maximum(config.plane_distance, 3.0 * cloud.sigma[keep])
    drop = np.zeros(len(keep), dtype=bool)
    for plane in planes:
        drop |= plane.covers(gated, distance, config.outline_margin, config.cut_behind_planes)
    if np.all(drop):
        raise InputError(
            f"every point lies on or behind the {len(planes)} background plane(s) removed",
            cloud.source,
        )
    return keep[~drop]
