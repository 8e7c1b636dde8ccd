"""How well rigid transforms align two clouds: the scores of feature RANSAC (methods.md §1.4).

:func:`coverage_counts` is the coverage score of H hypotheses ``T_target_source`` (H, 4, 4): how
many of m points (m, 3) of the source frame each maps within the gate ε (m) of the target cloud,
in one neighbour search of all H × m moved points. :func:`squared_residuals` gives the (H, K)
squared distances (m²) between the mapped source points and the target points of K
correspondences, from which a hypothesis' inliers are counted. Both move the points in one
compiled kernel, without (H, m, 3) temporaries. :func:`evaluate_alignment` scores the final
transform as every registration does: fitness, inlier RMSE (m), point-to-point information
(6, 6; 1/m²) and the number of matches, from the nearest target point within ε of every mapped
source point. None of the numbers depends on the number of threads.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numba
import numpy as np
from numpy.typing import NDArray

from spacepose.core import se3
from spacepose.core.cloud import PointCloud
from spacepose.core.correspondences import find_correspondences
from spacepose.core.grid import VoxelIndex
from spacepose.core.icp_systems import point_to_point_information
from spacepose.core.neighbors import SearchIndex
from spacepose.core.registration import RegistrationResult
from spacepose.errors import InputError

if TYPE_CHECKING:
    from spacepose.core.ransac import RansacConfig

# Fewest query points for which coverage_counts searches with the caller's threads.
_THREADED_QUERY = 20_000


def coverage_counts(
    T_target_source: NDArray[np.float64],
    source_points: NDArray[np.float64],
    target_tree: SearchIndex,
    max_distance: float,
    workers: int = -1,
) -> NDArray[np.intp]:
    """How many source points each transform maps within ``max_distance`` of the target cloud.

    Parameters
    ----------
    T_target_source
        (H, 4, 4) hypotheses mapping the source frame into the target frame.
    source_points
        (m, 3) points in the source frame (usually a fixed subsample).
    target_tree
        Search index (VoxelIndex, ``cKDTree``) of the target cloud, target frame.
    max_distance
        Gate (m); a point counts when its nearest target point is strictly closer.
    workers
        Threads for the single query of all H × m moved points.

    Returns
    -------
    (H,) counts in ``0..m``.

    Raises
    ------
    InputError
        Transforms not shaped (H, 4, 4) or points not (m, 3).
    """
    if T_target_source.ndim != 3 or T_target_source.shape[1:] != (4, 4):
        raise InputError(f"coverage_counts needs (H, 4, 4) transforms, got {T_target_source.shape}")
    if source_points.ndim != 2 or source_points.shape[1] != 3:
        raise InputError(f"coverage_counts needs (m, 3) points, got {source_points.shape}")
    moved = np.empty((len(T_target_source), len(source_points), 3))
    _transform_batch(
        np.ascontiguousarray(T_target_source, dtype=np.float64),
        np.ascontiguousarray(source_points, dtype=np.float64),
        np.empty((0, 3)),
        moved,
        np.empty((0, 0)),
    )
    moved = moved.reshape(-1, 3)
    # Most batches leave a handful of hypotheses, and starting threads then costs more than the
    # search (the counts do not depend on it).
    threads = workers if len(moved) >= _THREADED_QUERY else 1
    dist, _ = target_tree.query(moved, k=1, distance_upper_bound=max_distance, workers=threads)
    return np.count_nonzero((dist < max_distance).reshape(len(T_target_source), -1), axis=1)


def evaluate_alignment(
    source: PointCloud,
    target: PointCloud,
    T_target_source: NDArray[np.float64],
    config: RansacConfig,
    iterations: int,
    converged: bool,
    workers: int = -1,
) -> RegistrationResult:
    """Fitness, RMSE and information of ``T_target_source`` from nearest target points within ε."""
    moved = se3.transform_points(T_target_source, source.points)
    s, _, d2 = find_correspondences(
        VoxelIndex(target.points), moved, config.max_correspondence_distance, workers
    )
    return RegistrationResult(
        T_target_source=T_target_source,
        fitness=len(s) / len(source),
        inlier_rmse=float(np.sqrt(d2.mean())) if len(s) else 0.0,
        iterations=iterations,
        converged=converged,
        information=point_to_point_information(moved[s]),
        n_correspondences=len(s),
    )


def squared_residuals(
    T_target_source: NDArray[np.float64], src_c: NDArray[np.float64], tgt_c: NDArray[np.float64]
) -> NDArray[np.float64]:
    """(H, K) squared distances between mapped source and target points of K pairs."""
    r2 = np.empty((len(T_target_source), len(src_c)))
    _transform_batch(np.ascontiguousarray(T_target_source), src_c, tgt_c, np.empty((0, 0, 3)), r2)
    return r2


@numba.njit(cache=True)
def _transform_batch(T, points, targets, moved, r2):
    """Every (H, 4, 4) ``T`` applied to every (m, 3) point: into ``moved`` (H, m, 3), or, when
    ``targets`` (m, 3) is not empty, the squared distance to the matching target into ``r2``
    (H, m). One thread, no (H, m, 3) temporaries: numpy's einsum and axis-2 sum took three
    quarters of a RANSAC batch."""
    residuals = len(targets) > 0
    for h in range(len(T)):
        for m in range(len(points)):
            x, y, z = points[m, 0], points[m, 1], points[m, 2]
            mx = T[h, 0, 0] * x + T[h, 0, 1] * y + T[h, 0, 2] * z + T[h, 0, 3]
            my = T[h, 1, 0] * x + T[h, 1, 1] * y + T[h, 1, 2] * z + T[h, 1, 3]
            mz = T[h, 2, 0] * x + T[h, 2, 1] * y + T[h, 2, 2] * z + T[h, 2, 3]
            if residuals:
                dx, dy, dz = mx - targets[m, 0], my - targets[m, 1], mz - targets[m, 2]
                r2[h, m] = dx * dx + dy * dy + dz * dz
            else:
                moved[h, m, 0], moved[h, m, 1], moved[h, m, 2] = mx, my, mz
