"""Background removal before registration: range gate, dominant planes, largest cluster.

A lab or orbit frame holds the target and whatever else the sensor sees: a wall, a floor, a
turntable, stray returns. Three steps, each optional, isolate the target:

1. a range gate on the distance from the sensor origin;
2. removal of the dominant large planes (walls, floor) found by RANSAC
   (:func:`spacepose.core.planes.extract_planes`); a plane is removed only if it holds at least
   ``min_plane_share`` of the gated points, so that the target's own faces, each a small share of
   the frame, are left alone;
3. the largest Euclidean cluster: connected components of the graph linking points closer than
   ``cluster_distance`` (``cKDTree.query_pairs`` + ``scipy.sparse.csgraph``).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray
from pydantic import Field, model_validator
from scipy.sparse import coo_matrix
from scipy.sparse.csgraph import connected_components
from scipy.spatial import cKDTree

from spacepose.core.cloud import PointCloud
from spacepose.core.config import StageConfig
from spacepose.core.planes import PlaneConfig, extract_planes
from spacepose.errors import InputError


class BackgroundConfig(StageConfig):
    """Parameters of :func:`remove_background`.

    Attributes
    ----------
    range_min, range_max
        Kept distances from the sensor origin (m).
    remove_planes
        Largest number of dominant planes removed (0: none).
    plane_distance
        Plane thickness (m): points within it of a removed plane go with it.
    min_plane_share
        Smallest share of the gated points a plane must hold to count as background.
    keep_largest_cluster
        Keep only the largest Euclidean cluster of what is left.
    cluster_distance
        Points closer than this (m) belong to one cluster; a few point spacings.
    seed
        Seed of the plane RANSAC.
    """

    range_min: float = Field(default=0.0, ge=0)
    range_max: float = Field(default=math.inf, gt=0)
    remove_planes: int = Field(default=2, ge=0)
    plane_distance: float = Field(default=0.01, gt=0)
    min_plane_share: float = Field(default=0.15, gt=0, le=1)
    keep_largest_cluster: bool = True
    cluster_distance: float = Field(default=0.02, gt=0)
    seed: int = 0

    @model_validator(mode="after")
    def _range_order(self) -> BackgroundConfig:
        if self.range_min >= self.range_max:
            raise ValueError(f"range_min {self.range_min} must be below range_max {self.range_max}")
        return self


def largest_cluster(points: NDArray[np.float64], distance: float) -> NDArray[np.bool_]:
    """Mask (N,) of the largest group of points connected by links shorter than ``distance``.

    Ties between equally large clusters go to the one holding the lowest point index.
    """
    pairs = cKDTree(points).query_pairs(distance, output_type="ndarray")
    n = len(points)
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(n, n))
    _, labels = connected_components(graph, directed=False)
    # argmax of the sizes returns the first label of the largest size: components are labelled
    # in order of their lowest point index, so the tie rule above holds.
    return labels == np.argmax(np.bincount(labels))


def remove_background(
    cloud: PointCloud, config: BackgroundConfig = BackgroundConfig()
) -> tuple[PointCloud, NDArray[np.bool_]]:
    """The target's points: range gate, dominant planes removed, largest cluster kept.

    Parameters
    ----------
    cloud
        Frame (N, 3) in the sensor frame (the range is the distance from its origin).
    config
        Gate, plane and cluster settings.

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
    mask = np.zeros(len(pts), dtype=bool)
    rng = np.linalg.norm(pts, axis=1)
    keep = np.flatnonzero((rng >= config.range_min) & (rng <= config.range_max))
    if len(keep) == 0:
        raise InputError(
            f"no point within the range gate {config.range_min}..{config.range_max} m "
            f"(ranges {rng.min():.3g}..{rng.max():.3g} m)",
            cloud.source,
        )
    if config.remove_planes > 0 and len(keep) >= 3:
        planes = extract_planes(
            pts[keep],
            PlaneConfig(
                distance_threshold=config.plane_distance,
                min_inliers=max(3, math.ceil(config.min_plane_share * len(keep))),
                max_planes=config.remove_planes,
                seed=config.seed,
            ),
        )
        on_plane = np.zeros(len(keep), dtype=bool)
        for plane in planes:
            on_plane[plane.inliers] = True
        keep = keep[~on_plane]
        if len(keep) == 0:
            raise InputError(
                f"every point lies on the {len(planes)} removed plane(s)", cloud.source
            )
    if config.keep_largest_cluster:
        keep = keep[largest_cluster(pts[keep], config.cluster_distance)]
    mask[keep] = True
    return cloud.select(mask), mask
