"""A frame cut to the target's clusters (methods.md §5.7).

After the first frame, a frame is cropped to the sphere around where the prediction puts the
target (:func:`spacepose.core.segmentation.crop_sphere`), widened by the largest motion allowed
while the velocity is unknown. A large target near a wall fills that sphere only in part: a
1.4 m spacecraft at 1.2 m, 0.8 m before a wall, took 11,000 of the wall's points into a crop of
17,500 on its second frame, which registered at a fitness of 0.37, and no frame after it came
within 1 % of the range. :func:`cut_to_target` keeps the frame's connected clusters that lie
where the prediction puts the target's reference, judged by their share of points near it
(:func:`spacepose.core.segmentation.clusters_near`); what touches the target (a turntable
under it) stays. The tracker cuts the frames cropped while the velocity is unknown
(:meth:`spacepose.core.frame_preparation.FramePreparer.cut`): what later crops hold beside
the target is for the split by motion of methods.md §5.8.

Frames: the frame's points are in its sensor frame; the reference keyframe's in its own,
``T_ref_target`` its pose; ``T_sensor_target`` (4, 4) is the frame's predicted pose.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from spacepose.core import se3
from spacepose.core.bodies import nearest_within
from spacepose.core.clutter_body import subset
from spacepose.core.correspondences import find_correspondences
from spacepose.core.keyframes import Keyframe, PreparedCloud
from spacepose.core.segmentation import clusters_near

# Cell edge of the clusters, in voxels: two voxel centroids of one surface lie within two
# voxels of each other, and so in the same or neighbouring cells.
CUT_CELL_VOXELS = 2.0


def cut_to_target(
    prepared: PreparedCloud,
    reference: Keyframe,
    T_sensor_target: NDArray[np.float64],
    reach: float,
    voxel: float,
    min_points: int,
    fitness: float,
    workers: int = -1,
) -> PreparedCloud:
    """The frame without the clusters that do not lie where the prediction puts the target.

    Parameters
    ----------
    prepared
        The frame, downsampled at ``voxel`` m (its raw points, when kept, are cut too: the
        keyframe's finer cloud and the grid moved half a voxel are made from them).
    reference
        The target's reference (the latest keyframe, or the model).
    T_sensor_target
        (4, 4) the frame's predicted pose.
    reach
        How far (m) a frame point of the target may lie from the reference where the
        prediction puts it: the prediction's reach and the fine gate.
    min_points
        Fewest points a frame needs (the tracker's ``health.min_points``): a cut that would
        leave fewer returns the frame whole.
    fitness
        The ``ok`` bound of a registration's fitness: a frame with at least this share of
        its points near the reference is returned whole. The rest could not take its fit
        below the bound, and a body beside the target the frame keeps is what the split by
        motion of methods.md §5.8 needs.
    """
    points = prepared.cloud.points
    T_ref_frame = reference.T_ref_target @ se3.invert(T_sensor_target)
    _, s, _, _ = nearest_within(reference.prepared, points, T_ref_frame, reach, workers)
    if len(s) >= fitness * len(points):
        return prepared  # the rest would not take the frame's fit below its bound
    near = np.zeros(len(points), dtype=bool)
    near[s] = True
    keep = clusters_near(points, CUT_CELL_VOXELS * voxel, near)
    kept = np.count_nonzero(keep)
    if kept == len(points) or kept < min_points:
        return prepared
    cut = subset(prepared, keep)
    if prepared.raw is not None:
        # A raw point is the target's when a kept voxel centroid lies within a voxel of it.
        on, _, _ = find_correspondences(cut.tree, prepared.raw.points, voxel, workers)
        cut.raw = prepared.raw.select(on)
    return cut
