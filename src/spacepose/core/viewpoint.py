"""Is the cloud's origin the sensor? The model's faces a frame lies on tell (methods.md §5.3).

A range sensor sees a surface only from its front: every return of a frame lies on a face of
the target turned towards the sensor. The tracker takes the sensor to sit at the cloud's
origin, and against a model it registers onto the faces turned to the origin
(:meth:`~spacepose.core.frame_preparation.FramePreparer.visible_model`). A cloud written in
another frame (a world or vehicle frame, the sensor metres away) breaks that: the faces kept
are then the wrong ones, and a probe's frames with the sensor 3.9 m from the origin were `ok`
0.6° off at 11-44σ.

Registered against the model, a return within the gate of a face turned away from the origin,
with no face turned towards it near, is one the origin could not have seen. A pose wrong enough to
lay the frame on faces it cannot see shows the same.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.spatial import cKDTree

from spacepose.core import se3
from spacepose.core.cloud import PointCloud, as_points
from spacepose.core.health import Status
from spacepose.errors import InputError, SpaceposeWarning

# Returns tested a frame, at most (every k-th): a share of 0.1 is then known to ±0.013 (one
# binomial σ), and a 5,000-return frame costs 3 ms instead of 33.
SAMPLED_RETURNS = 500
# Model points searched about each return in each of the six normal directions.
_PER_DIRECTION = 2
# Share of a frame's returns on faces turned away above which the frame is degraded: twice
# the largest share of 66 simulated runs whose origin is the sensor (0.05: the lab mock-up's
# 5 mm wings under three times the noise at 0.5 m; at most 0.02 in the others); six of the
# probe's eight false `ok` frames had 0.15-0.19, and the run's verdict took the other two.
UNSEEN_BOUND = 0.1
# Frames beyond the bound after which the run's origin is taken not to be the sensor.
VERDICT_FRAMES = 2


@dataclass(frozen=True, eq=False)
class FacingTest:
    """A model's surface with outward normals, indexed once, to test frames against.

    Attributes
    ----------
    points, normals
        (M, 3) model points and their outward unit normals, target frame.
    trees
        One k-d tree per normal direction (the nearest of ±x, ±y, ±z), and the indices of
        its points: a part's opposite faces fall in different trees, so that a return on a
        thin part finds both.
    spacing
        The median distance (m) between neighbouring model points of one direction.
    """

    points: NDArray[np.float64]
    normals: NDArray[np.float64]
    trees: tuple[tuple[cKDTree, NDArray[np.intp]], ...]
    spacing: float

    @classmethod
    def of(cls, model: PointCloud) -> FacingTest:
        """The test against ``model``, whose normals point outwards.

        Raises
        ------
        InputError
            ``model`` has no normals (which faces turn away is read from them).
        """
        if model.normals is None:
            raise InputError(
                "the model needs outward normals to tell its faces' sides", model.source
            )
        points, normals = model.points, model.normals
        side = facing_bin(normals)
        members = [np.flatnonzero(side == b) for b in range(6)]
        trees = tuple((cKDTree(points[m]), m) for m in members if len(m))
        gaps = [t.query(t.data, k=2)[0][:, 1] for t, m in trees if len(m) > 1]
        spacing = float(np.median(np.concatenate(gaps))) if gaps else 0.0
        return cls(points, normals, trees, spacing)

    def unseen_share(
        self,
        points_sensor: NDArray[np.float64],
        T_sensor_target: NDArray[np.float64],
        gate: float,
        workers: int = 1,
    ) -> float:
        """Share of the returns ``points_sensor`` (N, 3), sensor frame, that lie on model faces
        turned away from the sensor at ``T_sensor_target`` (4, 4), among those near the model
        (0 when none is): a return within ``gate`` m of the plane of a face turned away, and
        farther than the reach (two gates and two model spacings) from the plane of any face
        turned towards the sensor or edge-on.

        Planes, not points, within the gate: a return on a thin part displaced by its noise
        towards the far face lies farther than the gate from the near face's samples when
        they are sparse, yet within the gate of its plane."""
        T_target_sensor = se3.invert(T_sensor_target)
        points_sensor = as_points(points_sensor, "returns")
        step = -(-len(points_sensor) // SAMPLED_RETURNS)
        q = se3.transform_points(T_target_sensor, points_sensor[::step])
        # Far enough to find a sample of the face a return lies on, however sparse the model.
        reach = 2.0 * (gate + self.spacing)
        candidates = []
        for tree, members in self.trees:
            k = min(_PER_DIRECTION, len(members))
            d, j = tree.query(q, k=k, distance_upper_bound=reach, workers=workers)
            d, j = d.reshape(len(q), k), j.reshape(len(q), k)
            near = np.isfinite(d)
            candidates.append(np.where(near, members[np.where(near, j, 0)], -1))
        j = np.hstack(candidates)
        counted = (j >= 0).any(axis=1)
        if not counted.any():
            return 0.0
        q, j = q[counted], j[counted]
        near, j = j >= 0, np.maximum(j, 0)
        points, normals = self.points[j], self.normals[j]
        # Turned away as visible_model culls: the sensor behind the face's plane.
        away = np.einsum("nkj,nkj->nk", normals, T_target_sensor[:3, 3] - points) < 0.0
        plane = np.abs(np.einsum("nkj,nkj->nk", normals, q[:, None, :] - points))
        seen_plane = np.where(near & ~away, plane, np.inf).min(axis=1)
        away_plane = np.where(near & away, plane, np.inf).min(axis=1)
        # A face turned to the origin within reach is a thin part's near face: a return pushed
        # through the part by a range error (a 6 mm wiggle on the lab's 5 mm wings: 27 % of
        # the returns) is the sensor's fault, not the origin's.
        return float(np.mean((away_plane <= gate) & (seen_plane > reach)))


def facing_bin(normals: NDArray[np.float64]) -> NDArray[np.intp]:
    """(N,) which of the six axis directions (±x, ±y, ±z) each normal is nearest: opposite
    faces always fall in different bins."""
    axis = np.argmax(np.abs(normals), axis=1)
    positive = normals[np.arange(len(normals)), axis] > 0.0
    return 2 * axis + positive


class OriginCheck:
    """The run's test of its origin against the model (model-based tracking only).

    A frame with more than :data:`UNSEEN_BOUND` of its returns on faces turned away from the
    origin is degraded. After :data:`VERDICT_FRAMES` such frames that passed every other check
    the origin is taken not to be the sensor: said once as a warning, and every later frame is
    degraded with it, because the faces the tracker registers onto are chosen from the origin
    and a frame whose own share is small may still have lost one the sensor sees.
    """

    def __init__(self, model: PointCloud, normals_estimated: bool = False) -> None:
        self.facing = FacingTest.of(model)
        self.beyond: list[str] = []
        self.verdict: str | None = None
        # A model given without normals has them estimated away from its centre, wrong on
        # the faces of a non-convex body: the verdict then names that first (a cloud of the
        # Hubble kit's samples, its frames in the sensor's frame, was told to give them so).
        self.normals_estimated = normals_estimated

    def assess(
        self,
        points_sensor: NDArray[np.float64],
        T_sensor_target: NDArray[np.float64],
        gate: float,
        health: tuple[Status, tuple[str, ...]],
        workers: int = 1,
    ) -> tuple[Status, tuple[str, ...]]:
        """``health`` of a frame (returns ``points_sensor`` (N, 3) at ``T_sensor_target``
        (4, 4), gate ``gate`` m), degraded when it or the run's earlier frames show that the
        origin cannot see them."""
        status, reasons = health
        if status == "lost":
            return health
        share = self.facing.unseen_share(points_sensor, T_sensor_target, gate, workers)
        if share > UNSEEN_BOUND:
            if status == "ok":
                # A pose the other checks trust: a wrong coarse pose lies on unseen faces too.
                self.beyond.append(f"{100 * share:.0f} %")
            reason = (
                f"{100 * share:.0f} % of the returns lie on model faces turned away from the "
                f"cloud's origin (> {100 * UNSEEN_BOUND:.0f} %)"
            )
            if len(self.beyond) == VERDICT_FRAMES and self.verdict is None:
                remedy = (
                    "the model has no normals of its own, and those estimated away from its "
                    "centre are wrong on a body that is not convex: give the mesh, or a cloud "
                    "with its outward normals; or the clouds are not in the sensor's frame"
                    if self.normals_estimated
                    else "give clouds in the sensor's frame, or check that the model's normals "
                    "point outwards"
                )
                self.verdict = (
                    f"the cloud's origin is not the sensor: {VERDICT_FRAMES} frames have "
                    f"{' and '.join(self.beyond)} of their returns on model faces turned away "
                    f"from it ({remedy})"
                )
                warnings.warn(SpaceposeWarning(self.verdict), stacklevel=3)
            return "degraded", (*reasons, reason)
        if self.verdict is not None:
            return "degraded", (*reasons, self.verdict)
        return health
