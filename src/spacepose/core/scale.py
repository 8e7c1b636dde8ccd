"""Lengths from the data: the scale every tracker length is a multiple of (docs/methods.md §5.1).

A tracker tuned in metres works at one range with one sensor. Here the only length read from a
frame is its *point spacing* ``s`` (median nearest-neighbour distance of the raw points) and,
with the number of points N, the visible area ``A ≈ N s²`` it implies. The voxel edge is then

    v = max(s, sqrt(A / n_target))

so that a frame keeps about ``n_target`` points after downsampling whatever its range or
resolution (the time per frame stays bounded), but never a voxel finer than the sensor's own
sampling. Gates, health bounds, keyframe thresholds and the σ floor are multiples of ``v`` or of
the target's RMS radius ``R`` (:class:`spacepose.core.tracker_config.TrackerConfig`). On the lab
run at 1.2 m (s = 2.46 mm, N = 18,277) this gives v = 6.07 mm; at 2 m 6.1 mm, at 0.6 m 5.6 mm;
on the orbit run's flash-LiDAR frames at 25 m (s = 105 mm, N = 1,025), v = s.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree

from spacepose.core.cloud import as_points
from spacepose.errors import InputError

# Query points of the spacing estimate: the median of 2,000 nearest-neighbour distances is
# within about 2 % of the full median (its standard error is ~1.25 σ/√n of a narrow spread).
_SPACING_SAMPLES = 2000


@dataclass(frozen=True)
class DataScale:
    """The lengths a tracker derives from its first frame.

    Attributes
    ----------
    spacing
        Median nearest-neighbour distance of the raw points (m).
    points
        Number of raw points the scale was measured on.
    voxel
        Voxel edge of the downsampling (m).
    radius
        RMS distance of the downsampled points from their centroid (m): the target's size.
    """

    spacing: float
    points: int
    voxel: float
    radius: float

    def to_dict(self) -> dict[str, float]:
        return {
            "spacing_m": self.spacing,
            "points": self.points,
            "voxel_m": self.voxel,
            "radius_m": self.radius,
        }


def point_spacing(points: ArrayLike, samples: int = _SPACING_SAMPLES, seed: int = 0) -> float:
    """Median distance (m) from a point to its nearest neighbour.

    Parameters
    ----------
    points
        (N, 3) points, N ≥ 2.
    samples
        Query points drawn (seeded, without replacement) when N is larger; each is searched
        against all N points, so the estimate is unbiased.
    seed
        Seed of that draw.

    Raises
    ------
    InputError
        Fewer than two points, or every point at one place.
    """
    pts = as_points(points)
    if len(pts) < 2:
        raise InputError(f"{len(pts)} point(s): a spacing needs at least two")
    query = pts
    if len(pts) > samples:
        pick = np.random.default_rng(seed).choice(len(pts), samples, replace=False)
        query = pts[np.sort(pick)]
    tree = cKDTree(pts)
    d, _ = tree.query(query, k=2)
    spacing = float(np.median(d[:, 1]))
    if not spacing > 0:
        # Over half the points repeated (a sensor writing each return twice): the distance to
        # the nearest *other* place, among the 8 nearest.
        d, _ = tree.query(query, k=min(8, len(pts)))
        nonzero = np.where(d > 0, d, np.inf).min(axis=1)
        nonzero = nonzero[np.isfinite(nonzero)]
        if not len(nonzero):
            raise InputError("every point is at the same place: no spacing")
        spacing = float(np.median(nonzero))
    return spacing


def voxel_for(spacing: float, n_points: int, target_points: int) -> float:
    """Voxel edge (m) that leaves about ``target_points`` of a surface sampled at ``spacing``."""
    area = n_points * spacing**2
    return max(spacing, math.sqrt(area / target_points))


def rms_radius(points: NDArray[np.float64]) -> float:
    """RMS distance (m) of (N, 3) points from their centroid."""
    centred = points - points.mean(axis=0)
    return float(np.sqrt((centred**2).sum(axis=1).mean()))


def derive_scale(
    points: ArrayLike, target_points: int, voxel_size: float | None = None
) -> DataScale:
    """The scale of a frame: its spacing, the voxel edge and (after downsampling) its radius.

    Parameters
    ----------
    points
        (N, 3) raw points of the frame (sensor frame, m).
    target_points
        Points a frame should keep after downsampling (``n_target`` above).
    voxel_size
        A voxel edge (m) to use instead of the derived one.
    """
    from spacepose.core.voxel import voxel_cells

    pts = as_points(points)
    spacing = point_spacing(pts)
    voxel = voxel_size if voxel_size is not None else voxel_for(spacing, len(pts), target_points)
    centroids, _ = voxel_cells(pts, voxel)
    return DataScale(spacing, len(pts), voxel, rms_radius(centroids))
