"""RANSAC plane extraction (methods.md §2.1, Yu et al. 2019 §2.1).

Hypotheses (planes through three sampled points) are scored in batches: a (B, chunk) matrix of
point-to-plane distances at a time, so no Python loop runs over points. The best plane is refitted
to its inliers by PCA (:func:`~spacepose.core.moments.fit_plane`). :func:`extract_planes` repeats
this on the points left over and, for a range sensor, finally gives every point to the plane
nearest along its ray (:func:`assign_along_rays`).

All coordinates are in the frame of the input cloud (usually the sensor frame), in metres. Each
plane's normal is oriented towards the origin of that frame (the sensor), so ``offset <= 0``.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import Field
from scipy.spatial import cKDTree

from spacepose.core import ransac
from spacepose.core.cloud import PointCloud, as_points
from spacepose.core.config import StageConfig, stage_config
from spacepose.core.moments import distribution, fit_plane, is_collinear, no_plane, on_a_line
from spacepose.core.plane_hypotheses import (
    best_hypothesis,
    fills_its_slab,
    one_face,
)
from spacepose.core.plane_support import cuts_a_curve, is_a_tail, largest_component
from spacepose.core.scale import plane_noise, plane_range_sigma
from spacepose.errors import DegenerateGeometryError, InputError, SpaceposeWarning


class PlaneConfig(StageConfig):
    """Settings of RANSAC plane extraction.

    Attributes
    ----------
    distance_threshold
        Plane thickness d (m): a point within d of the plane is an inlier.
    confidence
        Wanted probability p that at least one all-inlier sample is drawn.
    outlier_ratio
        Assumed outlier share ε used in the iteration bound
        ``k = log(1 − p) / log(1 − (1 − ε)³)``; ``None`` runs exactly ``max_iterations``.
    max_iterations
        Upper limit on the number of hypotheses per plane, at most 10⁷
        (:data:`~spacepose.core.ransac.MOST_ITERATIONS`).
    min_inliers
        A plane with fewer inliers ends :func:`extract_planes`.
    max_planes
        Largest number of planes :func:`extract_planes` returns.
    batch_size
        Hypotheses scored together in one distance matrix.
    cluster_radius
        When set (m), a plane keeps only the largest connected group of its inliers, points
        being connected when closer than this; the rest stay for later planes. A RANSAC slab is
        infinite, so without it a plane also collects strips of other parts that happen to lie
        in it (a panel and a band across the bus side). About 3 sample spacings works.
    range_threshold
        When set (m), the points the planes took are shared out again once every plane is found
        (:func:`assign_along_rays`): each goes to the plane whose surface its ray from the origin
        meets nearest its measured range, if that is within this distance, and every plane is
        refitted. For a range sensor about 3 σ_r. A fixed slab along the normal is the wrong
        test for range noise: it is ``σ_r |cos θ|`` thick on a face seen at incidence θ, so
        the slab is many σ thick on an oblique face, and the plane found first takes a strip
        of each neighbouring face along their shared edge (about 5 mm of centroid shift on
        the orbit run).
    seed
        Seed of the sampling RNG.
    """

    distance_threshold: float = Field(0.005, gt=0)
    confidence: float = Field(0.99, gt=0, lt=1)
    outlier_ratio: float | None = Field(0.5, ge=0, lt=1)
    # Bounded as feature RANSAC's (ransac.MOST_ITERATIONS): 10¹² ran without a word.
    max_iterations: int = Field(1000, ge=1, le=ransac.MOST_ITERATIONS)
    min_inliers: int = Field(50, ge=3)
    max_planes: int = Field(10, ge=1)
    batch_size: int = Field(64, ge=1, le=65536)
    cluster_radius: float | None = Field(None, gt=0)
    range_threshold: float | None = Field(None, gt=0)
    seed: int = Field(0, ge=0)


@dataclass(frozen=True, eq=False)
class Plane:
    """A plane found in a cloud.

    Attributes
    ----------
    normal
        (3,) unit normal, pointing towards the origin of the cloud's frame.
    offset
        Plane equation ``normal · x = offset`` (m).
    inliers
        Integer indices (K,) of the inlier points in the cloud given to the caller's function.
    centroid
        (3,) mean of the inliers.
    """

    normal: NDArray[np.float64]
    offset: float
    inliers: NDArray[np.intp]
    centroid: NDArray[np.float64]

    @property
    def n_inliers(self) -> int:
        return len(self.inliers)

    def distances(self, points: ArrayLike) -> NDArray[np.float64]:
        """Signed distances (N,) of points (N, 3) from the plane, positive on the normal's side."""
        return np.asarray(points, dtype=np.float64) @ self.normal - self.offset


def _check_resolution(pts: NDArray[np.float64], threshold: float, source: str | None) -> None:
    """Refuse coordinates so large that float64 cannot resolve the inlier threshold there: a
    plane's distances would be rounding noise, and its refit found no inlier (a cloud scaled
    by 1e30 gave 0 planes and numpy's "Mean of empty slice")."""
    resolution = 16 * float(np.spacing(np.abs(pts).max()))
    if resolution > threshold:
        raise InputError(
            f"coordinates up to {np.abs(pts).max():.3g} m leave float64 a resolution of "
            f"{resolution:.3g} m there, coarser than the {threshold:g} m plane threshold: "
            "corrupt values, or another unit?",
            source,
        )


def _refit(points: NDArray[np.float64], inliers: NDArray[np.intp], config: PlaneConfig) -> Plane:
    """PCA refit of a hypothesis' inliers, the refitted plane's inliers, their largest group."""
    normal, offset = fit_plane(points[inliers])
    refit = np.flatnonzero(np.abs(points @ normal - offset) <= config.distance_threshold)
    if config.cluster_radius is not None:
        refit = refit[largest_component(points[refit], config.cluster_radius)]
    # Refit once more so normal, offset and centroid describe the reported inliers, unless
    # these alone are degenerate (a thin strip): then the first refit stands.
    if len(refit) >= 3 and not is_collinear(distribution(points[refit])[1]):
        normal, offset = fit_plane(points[refit])
    return Plane(normal, offset, refit, points[refit].mean(axis=0))


def ransac_plane(
    points: PointCloud | ArrayLike,
    config: PlaneConfig = PlaneConfig(),
    rng: np.random.Generator | None = None,
) -> Plane:
    """The plane with most inliers among RANSAC hypotheses, refitted to its inliers.

    Parameters
    ----------
    points
        (N, 3) points or a PointCloud, any frame (m).
    config
        Thresholds and iteration limits.
    rng
        Random generator; ``np.random.default_rng(config.seed)`` when omitted.

    Returns
    -------
    Plane whose ``inliers`` index ``points``.

    Raises
    ------
    InputError
        Fewer than 3 points, a wrong shape or non-finite values.
    DegenerateGeometryError
        All points collinear.
    """
    pts = as_points(points, min_points=3)
    _check_resolution(pts, config.distance_threshold, getattr(points, "source", None))
    if on_a_line(pts):
        raise no_plane(pts, getattr(points, "source", None))
    # About the points' mean: a plane's moments about an origin 1e11 m away cancel to rounding
    # noise, and every refit had no inlier (0 planes and numpy's "Mean of empty slice").
    origin = pts.mean(axis=0)
    pts = pts - origin
    rng = np.random.default_rng(config.seed) if rng is None else rng
    threshold = config.distance_threshold
    inliers = best_hypothesis(pts, config, rng, threshold)
    if fills_its_slab(pts, inliers, threshold):
        inliers = one_face(pts, inliers, config)
    plane = _refit(pts, inliers, config)
    normal, offset = plane.normal, plane.offset + float(plane.normal @ origin)
    if offset > 0:  # towards the cloud's origin (the sensor), as fit_plane faces it
        normal, offset = -normal, -offset
    return replace(plane, normal=normal, offset=offset, centroid=plane.centroid + origin)


def slab_thickness(points: ArrayLike, sigma: float = 0.0) -> float:
    """The plane slab (m) for a frame: 3σ, σ given (> 0) or measured along the frame's rays
    (:func:`~spacepose.core.scale.plane_range_sigma`), or :class:`PlaneConfig`'s default when
    the frame shows no noise. A fixed 5 mm slab under a flash LiDAR's 1 cm noise cut each face
    of the orbit run in two parallel planes 1 cm apart, and named none of them.

    Warns
    -----
    SpaceposeWarning
        The noise measured is too large a share of the frame's size to be taken for noise
        alone, and the default slab would be thinner than it: the slab is then its 3σ all
        the same (a plate filling the view at 1 m under 1 cm of noise was cut by the default
        5 mm slab into three parallel planes 0.8° off)."""
    default = PlaneConfig.model_fields["distance_threshold"].default
    if sigma <= 0.0:
        sigma = plane_range_sigma(points) or 0.0
        measured = plane_noise(points) if sigma == 0.0 else 0.0
        if 3.0 * measured > default:
            problem = (
                f"the range noise reads {1e3 * measured:.1f} mm, a large share of the frame's "
                f"size: the plane slab is its 3σ, {3e3 * measured:.1f} mm (give the sensor's "
                "sigma if the frame holds more than noise)"
            )
            warnings.warn(SpaceposeWarning(problem, getattr(points, "source", None)), stacklevel=2)
            sigma = measured
    return 3.0 * sigma if sigma > 0.0 else default


def why_no_planes(
    cloud_or_points: PointCloud | ArrayLike, config: PlaneConfig = PlaneConfig()
) -> str:
    """Why :func:`extract_planes` found no plane in these points, in one line.

    Raises
    ------
    InputError
        As :func:`extract_planes`, for points it refuses.
    """
    config = stage_config(config, PlaneConfig)
    pts = as_points(cloud_or_points, min_points=3)
    if len(pts) < config.min_inliers:
        return f"{len(pts)} points, fewer than min_inliers {config.min_inliers}"
    try:
        best = ransac_plane(pts, config, np.random.default_rng(config.seed))
    except DegenerateGeometryError as exc:
        return str(exc)
    within = f"within {config.distance_threshold:g} m"
    if config.cluster_radius is not None:
        within += f" (its largest group, links under {config.cluster_radius:g} m)"
    if best.n_inliers < config.min_inliers:
        return (
            f"the best plane holds {best.n_inliers} points {within}, fewer than min_inliers "
            f"{config.min_inliers}"
        )
    return f"the best plane ({best.n_inliers} points {within}) cuts a curved surface, no face"


def range_residuals(
    points: ArrayLike, normals: ArrayLike, offsets: ArrayLike
) -> NDArray[np.float64]:
    """Distances (N, K), along each point's ray from the origin, from the point to K planes.

    A range sensor at the origin measures a point p on the ray ``p / |p|``; the ray meets the
    plane ``n · x = o`` where the range is ``o / (n · p/|p|)``. The difference from ``|p|`` is
    ``|n · p − o| / |n · p/|p||``: the normal distance over the cosine of the incidence, the
    quantity range noise σ_r scatters. A plane the ray grazes (or a point at the origin) gets
    a distance so large that no threshold accepts it.

    Parameters
    ----------
    points
        (N, 3) points in the frame of the sensor (origin at the sensor), m.
    normals
        (K, 3) unit normals.
    offsets
        (K,) plane offsets, ``normal · x = offset``.
    """
    p = np.asarray(points, dtype=np.float64)
    N = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    o = np.asarray(offsets, dtype=np.float64).reshape(-1)
    r = np.linalg.norm(p, axis=1)
    cos = np.abs(p @ N.T) / np.maximum(r, 1e-300)[:, None]
    return np.abs(p @ N.T - o) / np.maximum(cos, 1e-300)


def assign_along_rays(
    points: PointCloud | ArrayLike,
    planes: list[Plane],
    max_residual: float,
    min_inliers: int = 3,
) -> list[Plane]:
    """Share the planes' inliers out again by their distance along the ray, then refit.

    Every point some plane holds goes to the plane with the smallest :func:`range_residuals`,
    if that is at most ``max_residual``; else to none. Near the edge two faces share, the
    residual grows with the distance from the edge on both sides, so each point returns to
    its own face, where a normal-distance slab leaves it with whichever plane was found first.

    Parameters
    ----------
    points
        (N, 3) points (or a PointCloud) in the sensor frame, the cloud the inliers index (m).
    planes
        Planes of that cloud with disjoint inliers, e.g. from :func:`extract_planes`.
    max_residual
        Largest distance along the ray (m) at which a point may join a plane (about 3 σ_r).
    min_inliers
        A plane left with fewer points (or fewer than 3) is dropped and the points are shared
        among the others.

    Returns
    -------
    The remaining planes in their input order, each with its new inliers (sorted) and refitted
    by PCA (the old normal stands if the new inliers alone are collinear).
    """
    pts = as_points(points, min_points=3)
    if max_residual <= 0:
        raise InputError(f"max_residual must be positive, got {max_residual}")
    need = max(min_inliers, 3)  # a plane needs three points
    kept = [p for p in planes if p.n_inliers > 0]
    held = np.unique(np.concatenate([p.inliers for p in kept])) if kept else np.arange(0)
    while kept:
        normals = np.array([p.normal for p in kept])
        offsets = np.array([p.offset for p in kept])
        res = range_residuals(pts[held], normals, offsets)
        best = np.argmin(res, axis=1)
        best[res[np.arange(len(held)), best] > max_residual] = -1
        counts = np.bincount(best + 1, minlength=len(kept) + 1)[1:]
        if np.all(counts >= need):
            break
        # Drop the weakest plane only, so the others still compete for its points.
        kept.pop(int(np.argmin(counts)))
    out = []
    for k, plane in enumerate(kept):
        idx = held[best == k]
        normal, offset = plane.normal, plane.offset
        if not is_collinear(distribution(pts[idx])[1]):
            normal, offset = fit_plane(pts[idx])
        out.append(Plane(normal, offset, idx, pts[idx].mean(axis=0)))
    return out


def extract_planes(
    cloud_or_points: PointCloud | ArrayLike, config: PlaneConfig = PlaneConfig()
) -> list[Plane]:
    """Planes found one after the other, each on the points the previous ones left.

    Parameters
    ----------
    cloud_or_points
        (N, 3) points or a PointCloud (m).
    config
        RANSAC settings; ``min_inliers`` and ``max_planes`` end the loop. With
        ``range_threshold`` set, the points of all the planes are then shared out again along
        their rays (:func:`assign_along_rays`); the cloud's frame must be the sensor's.

    Returns
    -------
    Planes in the order found (most inliers first, as a rule); their ``inliers`` index the
    ORIGINAL cloud and are disjoint.

    Raises
    ------
    InputError
        Fewer than 3 points, a wrong shape or non-finite values.
    DegenerateGeometryError
        All points collinear.
    """
    config = stage_config(config, PlaneConfig)
    pts = as_points(cloud_or_points, min_points=3)
    _check_resolution(pts, config.distance_threshold, getattr(cloud_or_points, "source", None))
    if on_a_line(pts):
        raise no_plane(pts, getattr(cloud_or_points, "source", None))
    rng = np.random.default_rng(config.seed)
    remaining = np.arange(len(pts))
    planes: list[Plane] = []
    tree, slabs = cKDTree(pts), 0
    while len(planes) < config.max_planes and len(remaining) >= config.min_inliers:
        subset = pts[remaining]
        if planes and on_a_line(subset):
            break  # the leftover points are a line: nothing planar remains
        plane = ransac_plane(subset, config, rng)
        if plane.n_inliers < config.min_inliers:
            break
        inliers = remaining[plane.inliers]
        remaining = np.delete(remaining, plane.inliers)
        found = [(p.normal, p.offset, p.inliers) for p in planes]
        if cuts_a_curve(pts, tree, inliers, plane.normal) or is_a_tail(
            pts, tree, inliers, plane.normal, found, config.distance_threshold
        ):
            # A slab through a curved surface, or a face's noise beyond its slab: no face.
            slabs += 1
            if slabs >= config.max_planes:
                break
            continue
        planes.append(Plane(plane.normal, plane.offset, inliers, plane.centroid))
    if config.range_threshold is not None and planes:
        planes = assign_along_rays(pts, planes, config.range_threshold, config.min_inliers)
    return planes
