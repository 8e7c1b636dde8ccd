"""A support split off the object, followed by its own rigid motion (methods.md §5.8).

Once :func:`spacepose.core.bodies.split_trial` has set a support apart from the target, a
:class:`ClutterBody` holds the support's reference points and follows them frame by frame: it
predicts the support's pose at constant velocity from its last two poses, takes out of each
frame the points that lie nearer the support's surface there than the target's
(:meth:`ClutterBody.separate`), and registers those points from the prediction to keep the
pose and the prediction's error, which sets how far the separation reaches
(:meth:`ClutterBody.follow`, :meth:`ClutterBody.gate`). :func:`subset` keeps a prepared cloud's
points under a mask, for the target's reference as for the support's.

Frames: a *reference* is a keyframe's sensor frame; ``T_ref_frame`` (4, 4) maps the current
frame's sensor coordinates into it. Points are (N, 3) float64 in metres, times in seconds.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from spacepose.core import se3
from spacepose.core.bodies import nearest_within, plane_residuals
from spacepose.core.cloud import PointCloud
from spacepose.core.icp import ICPConfig, icp
from spacepose.core.keyframes import PreparedCloud
from spacepose.errors import InputError, SpaceposeError

# Points the support is followed with, at most: its pose needs the accuracy of the separation's
# reach (a few gates), not the target's.
FOLLOW_POINTS = 1000


class ClutterBody:
    """The support split off the object, followed with its own constant-velocity motion so
    that its points can be left out of every later frame.

    Parameters
    ----------
    ref
        The support's points of the reference (with normals), the reference's sensor frame.
    poses
        ``(time s, T_ref_frame (4, 4))`` of the support at one or two frames, oldest first:
        the reference's own (the identity) when its time is known, and the frame the split was
        found on.
    """

    def __init__(self, ref: PreparedCloud, poses: list[tuple[float, NDArray[np.float64]]]) -> None:
        self.ref = ref
        self._poses = [(t, T) for t, T in poses if np.isfinite(t)][-2:]
        if not self._poses:
            raise InputError("a followed support needs a pose at a finite time")
        # RMS error of the last prediction (m); None before the first follow.
        self.error: float | None = None

    def predict(self, timestamp: float) -> NDArray[np.float64]:
        """(4, 4) predicted ``T_ref_frame`` of the support at ``timestamp``."""
        t1, T1 = self._poses[-1]
        if len(self._poses) < 2:
            return T1
        t0, T0 = self._poses[-2]
        if t1 <= t0:
            return T1
        # Constant velocity in the frame's sensor coordinates: the last step, scaled in time.
        step = se3.log(se3.invert(T0) @ T1) * ((timestamp - t1) / (t1 - t0))
        return T1 @ se3.exp(step)

    def separate(
        self,
        points: NDArray[np.float64],
        timestamp: float,
        target_ref: PreparedCloud,
        T_ref_frame_target: NDArray[np.float64],
        gate: float,
        workers: int = -1,
    ) -> NDArray[np.bool_]:
        """(N,) True for the frame points that are not the support's: a point within ``gate``
        (m) of the support where its motion puts it, and nearer to it than to the target's
        reference (at ``T_ref_frame_target``), is the support's."""
        T_support = self.predict(timestamp)
        d_support = _gated_distance(self.ref, points, T_support, gate, workers)
        near = np.flatnonzero(np.isfinite(d_support))
        keep = np.ones(len(points), dtype=bool)
        if not len(near):  # the support is out of view (or left it)
            return keep
        # The target's distance only where the support is near (a search of a third of them).
        d_target = _gated_distance(target_ref, points[near], T_ref_frame_target, gate, workers)
        keep[near[d_support[near] < d_target]] = False
        return keep

    def follow(
        self, points: NDArray[np.float64], timestamp: float, gate: float, workers: int = -1
    ) -> bool:
        """Register the support's points of a frame from the prediction and record the pose
        and the prediction's error; False when they no longer register (the support has left
        the view)."""
        T_predicted = self.predict(timestamp)
        points = points[:: max(1, len(points) // FOLLOW_POINTS)]
        config = ICPConfig(
            method="point_to_plane", max_correspondence_distance=gate, robust_kernel="geman_mcclure"
        )
        try:
            result = icp(points, self.ref.cloud, T_predicted, config, workers, self.ref.tree)
        except SpaceposeError:
            return False
        # The prediction's error off the surface (a support seen by few faces slides along them
        # unseen, and that costs the separation nothing); a point beyond the gate counts it.
        off = np.minimum(plane_residuals(self.ref, points, T_predicted, gate, workers), gate)
        self.error = float(np.sqrt(np.mean(off**2)))
        self._poses = [*self._poses[-1:], (timestamp, result.T_target_source)]
        return True

    def gate(self, fallback: float, floor: float) -> float:
        """Reach (m) of the separation: three times the last prediction error (RMS distance
        of the support's points from its surface at the predicted pose), at least ``floor``;
        ``fallback`` before the support was first followed."""
        return fallback if self.error is None else max(floor, 3.0 * self.error)


def _gated_distance(
    ref: PreparedCloud,
    points: NDArray[np.float64],
    T_ref_frame: NDArray[np.float64],
    gate: float,
    workers: int,
) -> NDArray[np.float64]:
    """(N,) distance of each frame point to the nearest reference point within ``gate``; inf
    beyond."""
    _, s, _, d2 = nearest_within(ref, points, T_ref_frame, gate, workers)
    d = np.full(len(points), np.inf)
    d[s] = np.sqrt(d2)
    return d


def subset(prepared: PreparedCloud, keep: NDArray[np.bool_]) -> PreparedCloud:
    """The prepared cloud's points where ``keep``; GICP covariances follow, the index is
    rebuilt when next asked for."""
    index = np.flatnonzero(keep)
    cov = None if prepared.covariances is None else prepared.covariances[index]
    cloud: PointCloud = prepared.cloud.select(index)
    return PreparedCloud(cloud, cov)
