"""Coarse re-initialisation of a tracked frame: FPFH + RANSAC at the tracker's scale
(docs/methods.md §5.6).

The sparse cloud is the frame at the coarse voxel (twice the tracker's), its normals use a radius
of two coarse voxels, FPFH five and RANSAC's gate one and a half: every length follows from the
frame's own scale, so the same settings re-initialise a 1 m mock-up and a 10 m satellite.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from spacepose.core import se3
from spacepose.core.cloud import PointCloud
from spacepose.core.fpfh import compute_fpfh
from spacepose.core.keyframes import Keyframe, PreparedCloud
from spacepose.core.normals import estimate_normals
from spacepose.core.ransac import feature_ransac
from spacepose.core.tracker_config import StageLengths
from spacepose.core.voxel import voxel_downsample
from spacepose.errors import SpaceposeError


def coarse_features(
    prepared: PreparedCloud, lengths: StageLengths, outward: bool, workers: int = -1
) -> tuple[PointCloud, NDArray[np.float64]]:
    """Sparse cloud (with normals) and (M, 33) FPFH descriptors of a prepared cloud, once.

    ``outward``: a model's normals point away from its centroid (as a sensor sees them; FPFH is
    sign-sensitive); a frame's point towards the sensor.
    """
    if prepared.coarse is None:
        sparse = voxel_downsample(prepared.cloud, lengths.coarse_voxel)
        if outward:
            centroid = sparse.points.mean(axis=0)
            sparse = estimate_normals(sparse, lengths.coarse_normals, centroid, workers)
            sparse = sparse.with_normals(-sparse.normals)
        else:
            sparse = estimate_normals(sparse, lengths.coarse_normals, workers=workers)
        prepared.coarse = (sparse, compute_fpfh(sparse, lengths.fpfh, workers=workers))
    return prepared.coarse


def coarse_pose(
    prepared: PreparedCloud,
    ref: Keyframe,
    lengths: StageLengths,
    ref_is_model: bool,
    workers: int = -1,
) -> NDArray[np.float64] | None:
    """Initial ``T_sensor_target`` (4, 4) of a frame by FPFH + RANSAC onto ``ref``, or None when
    RANSAC finds no consensus."""
    src, src_f = coarse_features(prepared, lengths, False, workers)
    tgt, tgt_f = coarse_features(ref.prepared, lengths, ref_is_model, workers)
    try:
        res = feature_ransac(src, tgt, src_f, tgt_f, lengths.ransac, workers=workers)
    except SpaceposeError:
        return None
    return se3.invert(res.T_target_source) @ ref.T_ref_target
