"""What the tracker registers against (docs/methods.md §5.4): prepared clouds and keyframes.

A *keyframe* is an accepted frame kept as a registration reference, with its pose and covariance;
model-based tracking has one fixed reference, the model. The policy (:func:`needs_keyframe`)
promotes the current frame when overlap, distance or rotation from the keyframe grow too large,
and also promotes a merely degraded frame once the keyframe is about to be lost from view: a
tracker must always keep a reference it can see.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from functools import cached_property

import numpy as np
from numpy.typing import NDArray

from spacepose.core import se3
from spacepose.core.cloud import PointCloud
from spacepose.core.degeneracy import CoarseSurface, Degeneracy
from spacepose.core.grid import VoxelIndex
from spacepose.core.health import pose_disagreement
from spacepose.core.normals import NormalsConfig, estimate_normals
from spacepose.core.part_influence import PartInfluence
from spacepose.core.registration import RegistrationResult
from spacepose.core.residual_structure import Structure
from spacepose.core.scale import rms_radius
from spacepose.core.tracker_config import KeyframeConfig

# A keyframe's registrations onto the keyframes before it: (their frame index, T_them_this, 6×6
# information), the pose-graph edges of a J-ICP window.
Edge = tuple[int, NDArray[np.float64], NDArray[np.float64]]


@dataclass(eq=False)
class PreparedCloud:
    """A preprocessed frame, its search index and what the registrations reuse.

    ``covariances`` (GICP) is filled once per frame; the normals of ``cloud``, the index and
    ``coarse`` (sparse cloud + FPFH) lazily, when the frame is a registration target or coarse
    registration needs it. ``raw`` holds the points ``cloud`` was downsampled from (cropped to
    the target), from which a keyframe's finer cloud is made
    (:meth:`~spacepose.core.frame_preparation.FramePreparer.keyframe_cloud`).
    """

    cloud: PointCloud
    covariances: NDArray[np.float64] | None = None
    coarse: tuple[PointCloud, NDArray[np.float64]] | None = None
    raw: PointCloud | None = None
    _tree: VoxelIndex | None = None

    @property
    def tree(self) -> VoxelIndex:
        """Search index of the points, built the first time the cloud is a registration target."""
        if self._tree is None:
            self._tree = VoxelIndex(self.cloud.points)
        return self._tree

    def with_normals(self, config: NormalsConfig, workers: int) -> PreparedCloud:
        """This cloud, its normals estimated (towards the sensor) if it has none yet."""
        if not self.cloud.has_normals:
            self.cloud = estimate_normals(self.cloud, config, workers=workers, tree=self.tree)
        return self

    # Cached: the points never change (``cloud`` is only replaced by itself with normals), and
    # the health check, the floor and the keyframe test ask for these several times per frame.
    @cached_property
    def centroid(self) -> NDArray[np.float64]:
        return self.cloud.points.mean(axis=0)

    @cached_property
    def radius(self) -> float:
        """RMS distance of the points from their centroid (m)."""
        return rms_radius(self.cloud.points)


@dataclass(eq=False)
class Keyframe:
    """A reference cloud and its pose.

    Attributes
    ----------
    index
        Frame index (-1 for the model).
    prepared
        The preprocessed cloud, in its own sensor frame (or the target frame for the model).
    dense
        The same frame downsampled finer and smoothed onto its surface, what frames are
        registered onto (None: ``prepared`` is; see
        :meth:`~spacepose.core.frame_preparation.FramePreparer.keyframe_cloud`).
    T_ref_target
        Pose of the reference frame: ``T_sensor_target`` at that frame (identity for the model).
    covariance
        (6, 6) covariance of ``T_ref_target`` (left perturbation).
    edges
        J-ICP: this keyframe's registrations onto the keyframes before it.
    drift
        1-σ (rad, m) of the drift the keyframe chain has built up to this keyframe, kept apart
        from ``covariance`` (see :func:`~spacepose.core.window_registration.chain_drift`).
    timestamp
        Time of the frame (s); NaN for the model.
    unobserved
        Whether the keyframe's pose rests on a registration that left a direction unobserved
        (its own frame's, or one along the chain of keyframes before it): the data could not
        see a slide there, and a frame registered onto it is never ``ok``.
    coarse
        Its surface as the degeneracy check samples it (made on the first frame judged
        against it; None before).
    """

    index: int
    prepared: PreparedCloud
    T_ref_target: NDArray[np.float64]
    covariance: NDArray[np.float64]
    edges: list[Edge] = field(default_factory=list)
    drift: tuple[float, float] = (0.0, 0.0)
    timestamp: float = float("nan")
    dense: PreparedCloud | None = None
    unobserved: bool = False
    coarse: CoarseSurface | None = None

    @property
    def registration_target(self) -> PreparedCloud:
        """The cloud frames are registered onto."""
        return self.prepared if self.dense is None else self.dense


@dataclass(frozen=True)
class FineEstimate:
    """Outcome of the fine registration of one frame (before the health check).

    Attributes
    ----------
    T_sensor_target, covariance
        The frame's pose and its full covariance (the reference's included).
    own_covariance
        The covariance of the frame's own registration alone, in the frame's sensor frame.
    result
        The registration onto the latest reference.
    reference
        That reference.
    surface_step
        (6,) point-to-plane Gauss-Newton step from the registered pose (reference frame).
    edges, window_poses
        J-ICP: the frame's pose-graph edges and the window keyframes' updated poses.
    bias, drift
        1-σ (rad, m) of the keyframe chain's drift up to this frame, and the (6, 6)
        covariance it adds to ``covariance`` (None: none).
    structure
        :func:`~spacepose.core.residual_structure.structure_of` the registration onto the
        latest reference (None: not measured).
    influence
        :func:`~spacepose.core.part_influence.part_influence` of that registration (None: not
        measured).
    degeneracy
        The directions the surfaces leave free, when they leave some (``covariance`` and
        ``own_covariance`` are widened along them); None otherwise.
    held
        The registration was ill-conditioned and the motion model's prediction, weighed as a
        prior, holds its weak directions (pose and covariances are the fused ones).
    """

    T_sensor_target: NDArray[np.float64]
    covariance: NDArray[np.float64]
    own_covariance: NDArray[np.float64]
    result: RegistrationResult
    reference: Keyframe
    surface_step: NDArray[np.float64]
    edges: tuple[Edge, ...] = ()
    window_poses: tuple[tuple[Keyframe, NDArray[np.float64], NDArray[np.float64]], ...] = ()
    bias: tuple[float, float] = (0.0, 0.0)
    drift: NDArray[np.float64] | None = None
    structure: Structure | None = None
    influence: PartInfluence | None = None
    degeneracy: Degeneracy | None = None
    held: bool = False

    def in_reference(self, point_k: NDArray[np.float64]) -> NDArray[np.float64]:
        """A frame-k point (3,) expressed in the reference frame (where the information is)."""
        return se3.transform_points(self.result.T_target_source, point_k[None])[0]


def moved_covariance(anchor: Keyframe, T_sensor_target: NDArray[np.float64]) -> NDArray[np.float64]:
    """The anchor keyframe's pose covariance carried into the frame of ``T_sensor_target``."""
    Ad = se3.adjoint(T_sensor_target @ se3.invert(anchor.T_ref_target))
    return Ad @ anchor.covariance @ Ad.T


def needs_keyframe(
    estimate: FineEstimate,
    prepared: PreparedCloud,
    config: KeyframeConfig,
    radius: float,
    degraded: bool,
) -> bool:
    """Whether the frame of ``estimate`` should become the new keyframe.

    Parameters
    ----------
    estimate, prepared
        The frame's fine registration and its cloud.
    config
        The promotion thresholds (translation in radii).
    radius
        The target's RMS radius (m).
    degraded
        The frame is degraded (not ok): it is promoted only when the keyframe is going stale
        (fitness below ``stale_fitness``).
    """
    fitness = estimate.result.fitness
    if degraded:
        return fitness < config.stale_fitness
    dt, dr = pose_disagreement(
        estimate.T_sensor_target, estimate.reference.T_ref_target, prepared.centroid
    )
    return (
        fitness < config.min_fitness
        or dt > config.max_translation * radius
        or dr > config.max_rotation_deg
        or not math.isfinite(dt)
    )
