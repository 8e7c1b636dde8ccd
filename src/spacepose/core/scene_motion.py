"""Is the target the nearest object, or the whole scene? (docs/methods.md §5.7)

Target isolation (:mod:`spacepose.core.segmentation`) keeps the nearest object of the first
frame. Before a wall, a table or the Earth that is the target. But a camera moving through a
static scene (a hand-held ToF camera in a room) sees the rest of the scene move exactly as the
nearest object does: that object is one piece of furniture, which the camera soon turns away
from, while the surfaces that would hold the pose are cropped off; and a small object (a box) is
easily registered onto a wrong twin on the first fast step.

The data tell the two cases apart. While a run is undecided and the first frame's background
no longer stays where it was (:meth:`SceneTest.background_stays`: the sensor moves against it),
a second tracker follows the whole scene (``T_scene``) beside the one that follows the object
(``T_target``); both carry the first frame's points into the current frame. A point *lands*
under a pose when, so carried, it falls within a voxel of the current frame's surface. Between
two poses only the points they carry several voxels apart and into the view can tell, and a
point votes for a pose only when it lands under that one alone (a wall sliding in its own
plane lands both ways and votes for neither). Then

- the background lands under ``T_scene`` and not where it was (the scene moves in the sensor
  frame: the camera moves), and the object does not clearly move otherwise (it lands under
  ``T_scene``, or the poses agree on it, or it has left the view; its own tracker may have gone
  astray, as on a small box registered onto its wrong twin): the whole scene is the target;
- the object lands under ``T_target`` alone (it moves otherwise than the scene: a target
  before a static wall, or before a moving background), or the background lands where it was
  and not under ``T_scene``: the object is the target.

A side wins with at least 50 votes, 80 % of the votes and a quarter of the telling points: a
wall sliding in its own plane abstains, and a few points at its edges must not speak for it.
Everything is in the first frame's own voxels (of the object's points and of the rest, each
sized like the tracker's voxel), so no length is set by hand.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree

from spacepose.core import se3
from spacepose.core.cloud import as_points
from spacepose.core.scale import point_spacing, voxel_for
from spacepose.core.segmentation import solid
from spacepose.core.voxel import voxel_cells

Verdict = Literal["scene", "target", "undecided"]

# A point tells two poses apart when they carry it this many voxels apart: closer, both put it
# on the same surface to within the sampling.
_TELLING_VOXELS = 4.0
# Points whose spacing is measured (a seeded sample of a larger cloud).
_SPACING_POINTS = 100_000
# Fewest votes for a side, and the share of the votes it must hold.
_MIN_VOTES = 50
_CLEAR_SHARE = 0.8
# Share of the telling points the winning side must hold.
_QUORUM = 0.25
# Frame points searched for the background staying where it was, background points searched
# for, and the share of them that must stay.
_STAY_SAMPLE = 5_000
_STAY_BACKGROUND = 1_000
_STAY_SHARE = 0.5


@dataclass(frozen=True)
class Vote:
    """Points of the first frame landing under one of two poses alone.

    Attributes
    ----------
    telling
        Points the two poses carry more than four voxels apart, both into the view.
    first, second
        Of those, the points that land under the first pose alone, and under the second.
    """

    telling: int
    first: int
    second: int

    @property
    def winner(self) -> Literal["first", "second", "none"]:
        """The side with at least 50 votes, 80 % of the votes and a quarter of the telling
        points, if any (a wall sliding in its own plane abstains, and a few edge points must
        not speak for it)."""
        votes = self.first + self.second
        quorum = max(_MIN_VOTES, _QUORUM * self.telling)
        if self.first >= quorum and self.first >= _CLEAR_SHARE * votes:
            return "first"
        if self.second >= quorum and self.second >= _CLEAR_SHARE * votes:
            return "second"
        return "none"


class Landings:
    """Points of the first frame (target frame, m), downsampled at ``voxel`` (m)."""

    def __init__(self, points_target: ArrayLike, voxel: float) -> None:
        self.voxel = float(voxel)
        self.points_target, _ = voxel_cells(as_points(points_target), self.voxel)

    @classmethod
    def at_own_voxel(cls, points_target: ArrayLike, target_points: int) -> Landings:
        """At the voxel that leaves about ``target_points`` of them."""
        pts = as_points(points_target)
        return cls(pts, _voxel_for(pts, target_points))

    def vote(self, frame: Surface, T_first: ArrayLike, T_second: ArrayLike) -> Vote:
        """Which of two ``T_sensor_target`` (4, 4) carries these points onto ``frame`` (the
        current frame's surface at this voxel, :meth:`surface`)."""
        first = se3.transform_points(T_first, self.points_target)
        second = se3.transform_points(T_second, self.points_target)
        telling = np.linalg.norm(first - second, axis=1) > _TELLING_VOXELS * self.voxel
        # A point out of the view under either pose tells nothing (a target leaving the view).
        telling &= frame.sees(first) & frame.sees(second)
        if not telling.any():
            return Vote(0, 0, 0)
        on_first = frame.lands(first[telling], self.voxel)
        on_second = frame.lands(second[telling], self.voxel)
        only_first = int((on_first & ~on_second).sum())
        return Vote(int(telling.sum()), only_first, int((on_second & ~on_first).sum()))

    def surface(self, points_sensor: NDArray[np.float64]) -> Surface:
        """The current frame (N, 3), sensor frame, as voxel centroids at this voxel."""
        return Surface.of(points_sensor, self.voxel)


@dataclass(frozen=True)
class Surface:
    """A frame's voxel centroids, searchable, and the bounds of its view.

    Attributes
    ----------
    tree
        Search tree of the centroids (sensor frame, m).
    tan_bounds
        (4,) least and greatest x/z, then y/z of the frame's points: a pinhole sensor's
        view; None when some point is not in front of the sensor (a scanner's wide view).
    """

    tree: cKDTree
    tan_bounds: NDArray[np.float64] | None

    @classmethod
    def of(cls, points_sensor: NDArray[np.float64], voxel: float) -> Surface:
        centroids, _ = voxel_cells(points_sensor, voxel)
        bounds = None
        z = points_sensor[:, 2]
        if (z > 0).all():
            tx, ty = points_sensor[:, 0] / z, points_sensor[:, 1] / z
            bounds = np.array([tx.min(), tx.max(), ty.min(), ty.max()])
        return cls(cKDTree(centroids), bounds)

    def sees(self, points: NDArray[np.float64]) -> NDArray[np.bool_]:
        """(M,) whether each point (sensor frame) is within the view."""
        if self.tan_bounds is None:
            return np.ones(len(points), dtype=bool)
        z = points[:, 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            tx, ty = points[:, 0] / z, points[:, 1] / z
        lo_x, hi_x, lo_y, hi_y = self.tan_bounds
        return (z > 0) & (tx >= lo_x) & (tx <= hi_x) & (ty >= lo_y) & (ty <= hi_y)

    def lands(self, points: NDArray[np.float64], reach: float) -> NDArray[np.bool_]:
        """(M,) whether each point has a centroid within ``reach`` (m)."""
        distance, _ = self.tree.query(points, distance_upper_bound=reach)
        return np.isfinite(distance)


class SceneTest:
    """The decision of the module docstring for one run.

    Parameters
    ----------
    target, background
        The first frame's isolated object and everything else, each at its own voxel.
    """

    def __init__(self, target: Landings, background: Landings) -> None:
        self.target = target
        self.background = background

    @classmethod
    def of_first_frame(
        cls,
        points: ArrayLike,
        target_mask: ArrayLike,
        spacing: float,
        target_points: int,
        min_points: int,
    ) -> SceneTest | None:
        """The test for a first frame ``points`` (N, 3) of point spacing ``spacing`` (m) whose
        object is ``target_mask`` (N,); None when the rest holds fewer than ``min_points``
        points of a surface (lone flying pixels and stray returns are not a background to
        tell motion by: they trail the target's silhouette)."""
        pts = as_points(points)
        mask = np.asarray(target_mask, dtype=bool)
        rest = pts[~mask]
        rest = rest[solid(rest, spacing)] if len(rest) else rest
        if len(rest) < min_points:
            return None
        background = Landings.at_own_voxel(rest, target_points)
        if len(background.points_target) < min_points:
            return None
        return cls(Landings.at_own_voxel(pts[mask], target_points), background)

    def background_stays(self, points_sensor: NDArray[np.float64]) -> bool:
        """Whether most of the background (half of it or more) lands where it was in a frame
        ``points_sensor`` (N, 3): the sensor has not moved against it, and no scene tracker is
        needed yet. Samples are searched: about 5,000 of the frame's points (a few per background
        voxel) for about 1,000 of the background's (about 1.5 ms on a 1280×720 frame)."""
        if len(points_sensor) == 0:
            return False
        frame = points_sensor[:: max(1, len(points_sensor) // _STAY_SAMPLE)]
        background = self.background.points_target
        background = background[:: max(1, len(background) // _STAY_BACKGROUND)]
        landed = Surface(cKDTree(frame), None).lands(background, self.background.voxel)
        return bool(landed.mean() >= _STAY_SHARE)

    def decide(self, points_sensor: ArrayLike, T_target: ArrayLike, T_scene: ArrayLike) -> Verdict:
        """The verdict on a frame ``points_sensor`` (N, 3) given the object's tracked pose and
        the whole scene's (``T_sensor_target`` (4, 4) each, the first frame's sensor frame as
        the target frame)."""
        pts = as_points(points_sensor)
        if len(pts) == 0:
            return "undecided"
        # The object, where it is in view and the two poses part: which does it move with?
        obj = self.target.vote(self.target.surface(pts), T_target, T_scene).winner
        # The background: does it move in the sensor frame (as the scene's pose carries it)?
        background = self.background.vote(self.background.surface(pts), T_scene, np.eye(4))
        if background.winner == "first" and obj != "first":
            return "scene"
        if obj == "first" or background.winner == "second":
            return "target"
        return "undecided"


def _voxel_for(points: NDArray[np.float64], target_points: int) -> float:
    """The voxel (m) that leaves about ``target_points`` of a surface cloud: its area from its
    point spacing (:func:`~spacepose.core.scale.voxel_for`), measured on a seeded sample of at
    most 100,000 of its points, which covers the same area (a 1280×720 frame's whole tree took
    0.26 s)."""
    if len(points) > _SPACING_POINTS:
        pick = np.random.default_rng(0).choice(len(points), _SPACING_POINTS, replace=False)
        points = points[np.sort(pick)]
    return voxel_for(point_spacing(points), len(points), target_points)
