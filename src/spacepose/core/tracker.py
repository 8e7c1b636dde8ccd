"""Frame-by-frame pose tracking of a rigid target (Li et al. 2024 pipeline, METHODS §1).

Each frame goes through

1. preprocessing: optional background removal, mpp-MLS (or voxel downsampling), the per-point
   GICP covariances when GICP is the fine registration (normals only for frames that become
   keyframes, the registration targets);
2. coarse registration (FPFH + feature RANSAC) only when there is no prior pose or the track is
   lost;
3. fine registration (ICP, GICP, or J-ICP = registrations against a window of keyframes solved as
   a pose graph, METHODS §1.6) started from the constant-velocity prediction;
4. a health check (fitness, residual, conditioning, covariance size, agreement with the
   prediction, distance to the point-to-plane optimum and to the keyframe) that labels the
   frame ``ok``, ``degraded`` or ``lost``;
5. a state update: pose history for the prediction, keyframe promotion.

J-ICP here is a window of *keyframes* solved with :mod:`spacepose.core.posegraph`, not
:class:`spacepose.core.jicp.JointICP` (a window of consecutive frames): a tracker must be able to
reject a frame after registering it, and JointICP adds every frame to its window as it goes;
keyframes also bound the drift over a long run (METHODS §1.6). Its settings are ``jicp``
(:class:`~spacepose.core.jicp.JICPConfig`: window, pairwise registration, weighting).

Two modes. *Model-based*: a reference model cloud (target frame) is given and every pose is
``T_sensor_target`` directly. *Model-free* (METHODS §0): the first usable frame defines the target
frame, its pose is the identity and pose k is ``T_k0``; keyframes bound the drift.

Covariances are 6×6, twist order (omega, v), for a left perturbation of ``T_sensor_target``
(``T ← exp(δ) T``, δ in the sensor frame at frame k), so their square-rooted diagonal is directly
comparable with the per-axis errors of ``ΔT = T_est · T_gt⁻¹`` (METHODS §0).
"""

from __future__ import annotations

import time
from collections.abc import Iterable
from dataclasses import dataclass, field
from functools import cached_property
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import Field, PositiveFloat
from scipy.spatial.transform import Rotation

from spacepose.core import se3
from spacepose.core.background import BackgroundConfig, remove_background
from spacepose.core.cloud import PointCloud
from spacepose.core.config import StageConfig
from spacepose.core.fpfh import FPFHConfig, compute_fpfh
from spacepose.core.gicp import GICPConfig, compute_covariances, gicp
from spacepose.core.grid import VoxelIndex
from spacepose.core.icp import (
    Correspondences,
    ICPConfig,
    find_correspondences,
    icp_correspondences,
    point_to_plane_system,
)
from spacepose.core.jicp import JICPConfig
from spacepose.core.mls import MLSConfig, mpp_mls
from spacepose.core.normals import NormalsConfig, estimate_normals
from spacepose.core.posegraph import PoseGraphEdge, optimize_pose_graph
from spacepose.core.ransac import RansacConfig, feature_ransac
from spacepose.core.registration import RegistrationResult
from spacepose.core.trajectory import Trajectory
from spacepose.core.voxel import voxel_cells
from spacepose.errors import InputError, RegistrationError, SpaceposeError

Status = Literal["ok", "degraded", "lost"]
# Reason of a frame degraded only because its keyframe is far: it may become the new keyframe.
_FAR_KEYFRAME = "keyframe"
# Timed parts of a step; "other" is the health checks and state bookkeeping, so that the first
# four add up to "total".
STAGES: tuple[str, ...] = ("preprocess", "coarse", "fine", "other", "total")
# Largest pose-graph update (rad, m) at which J-ICP stops iterating. Its Gauss-Newton shrinks the
# update about 1000× per iteration on the lab run: after a 1e-6 step the poses are within ~1e-9
# of the optimum, and the default 1e-12 cost two more iterations (~1 ms per frame).
_POSE_GRAPH_TOLERANCE = 1e-6


# --------------------------------------------------------------------------------------------
# Configuration


class KeyframeConfig(StageConfig):
    """When a model-free tracker promotes the current frame to a keyframe.

    Attributes
    ----------
    min_fitness
        Promote when the fitness against the current keyframe falls below this (overlap drops).
    max_translation
        Promote when the target centroid moved more than this (m) since the keyframe.
    max_rotation_deg
        Promote when the target turned more than this (degrees) since the keyframe.
    """

    min_fitness: float = Field(0.85, ge=0, le=1)
    max_translation: PositiveFloat = 0.04
    max_rotation_deg: PositiveFloat = 4.0


class HealthConfig(StageConfig):
    """Thresholds of the per-frame health check: an ``ok`` bound and a ``lost`` bound each.

    A frame breaking any ``lost`` bound is lost (its pose is not used); one breaking only ``ok``
    bounds is degraded (used, flagged, never promoted to keyframe).

    Attributes
    ----------
    min_points
        Fewer points than this after preprocessing: lost.
    ok_fitness, lost_fitness
        Share of frame points with a reference point within the correspondence gate.
    ok_rmse, lost_rmse
        Inlier RMSE (m) of the fine registration.
    ok_condition, lost_condition
        Condition number of the registration information, expressed at the cloud centroid with
        the rotation block scaled by the cloud's RMS radius (so it is unit-free).
    ok_sigma_translation, ok_sigma_rotation_deg
        Largest 1-σ (m, degrees) of the frame's own registration (translation at the centroid).
    ok_prediction_translation, ok_prediction_rotation_deg
        Largest disagreement (centroid displacement m, rotation angle degrees) with the
        constant-velocity prediction; ``lost_prediction_factor`` times these is lost.
    max_reference_factor
        Model-free: a frame further from its keyframe than this many times the keyframe
        promotion thresholds is at best degraded (on the lab run, point-to-point ICP frames 35°
        from a stale keyframe registered 31 mm off while every other check passed).
    ok_step_translation, ok_step_rotation_deg
        Largest point-to-plane Gauss-Newton step from the registered pose (m at the centroid,
        degrees): a registration that stopped off the surface optimum is not ok (point-to-point
        ICP on voxel clouds locks onto the sampling grid while fitness, RMSE and a slowly
        adapting prediction all look fine); ``lost_prediction_factor`` times these is lost.
    max_motion_translation, max_motion_rotation_deg
        Largest inter-frame motion expected; the "ok" disagreement bound while the velocity is
        not yet known (one pose in the history: the prediction is the last pose).
    """

    min_points: int = Field(100, ge=3)
    ok_fitness: float = Field(0.6, ge=0, le=1)
    lost_fitness: float = Field(0.3, ge=0, le=1)
    ok_rmse: PositiveFloat = 0.004
    lost_rmse: PositiveFloat = 0.006
    ok_condition: PositiveFloat = 1e5
    lost_condition: PositiveFloat = 1e8
    ok_sigma_translation: PositiveFloat = 0.001
    ok_sigma_rotation_deg: PositiveFloat = 0.1
    ok_prediction_translation: PositiveFloat = 0.01
    ok_prediction_rotation_deg: PositiveFloat = 1.5
    lost_prediction_factor: float = Field(4.0, ge=1)
    max_reference_factor: float = Field(2.0, ge=1)
    ok_step_translation: PositiveFloat = 0.0005
    ok_step_rotation_deg: PositiveFloat = 0.1
    max_motion_translation: PositiveFloat = 0.03
    max_motion_rotation_deg: PositiveFloat = 3.0


class TrackerConfig(StageConfig):
    """Every parameter of the tracker; defaults suit the lab scenario (ToF at about 1.2 m).

    Attributes
    ----------
    method
        Fine registration: ``"icp"`` (with ``icp``), ``"gicp"`` (with ``gicp``) or ``"jicp"``:
        the frame registered to the last ``jicp.window − 1`` keyframes and the window solved as
        a pose graph (``jicp.registration``, ``jicp.icp`` / ``jicp.gicp``, ``jicp.weighting``).
        The default window is 4 (three keyframes): on the lab run it lowered every per-axis
        mean error against a window of 3 except pitch (0.0088° → 0.0105°).
        The correspondence gates are 5 mm: after the constant-velocity prediction the residual
        misalignment is well below that, and a wider gate lets silhouette points pair with the
        wrong surface (10 mm doubled the yaw error on the lab run).
        J-ICP pairs stop after 10 iterations: started from the prediction (or the latest pair)
        97 % converge within 5 on the lab run, while the rare pair that oscillates between two
        sets of correspondences ran to the limit of 30 (about 20 ms more for its frame); the
        cap left every mean error of the run unchanged or lower.
    use_background_removal
        Remove the wall / floor / turntable around the target first (``background``; the
        default range gate of 1.8 m suits the lab scene, whose wall stands at 2 m: without it
        the wall and table outnumber the target and the largest cluster is the wrong one).
    use_mls
        mpp-MLS (denoise + downsample + normals) instead of voxel downsampling + PCA normals.
        Off by default: on the lab run (ToF, 58 frames) it made J-ICP less accurate (mean roll
        error 0.092° against 0.024° with voxels, window 3) at about 5× the preprocessing time.
    voxel_size
        Voxel edge (m) of the downsampling when mpp-MLS is off.
    coarse_voxel_size
        Voxel edge (m) of the sparser cloud behind FPFH + RANSAC; ``coarse_normals``, ``fpfh``
        and ``ransac`` are sized for it (radius 2×, 5×, gate 1.5×). Without the mutual filter
        RANSAC found the lab pose from the model on 7 of 7 test frames, in about half the time.
    covariance_scale
        Factor on every registration covariance from the information matrix (1: as computed).
    floor_translation, floor_rotation_deg
        1-σ added to every registration, isotropically about the target centroid (m, deg):
        the error the information matrix cannot see because it is not noise but systematic
        (voxel sampling of two different views, normal estimation near edges). On the lab run
        the depth (z) error of the chain grew about linearly and sat at 2.2 σ (rms) without it;
        with 0.05 mm / 0.002° every axis is within 3 σ on more than 95 % of the frames.
    """

    method: Literal["icp", "gicp", "jicp"] = "jicp"
    use_background_removal: bool = False
    use_mls: bool = False
    voxel_size: PositiveFloat = 0.006
    coarse_voxel_size: PositiveFloat = 0.012
    covariance_scale: PositiveFloat = 1.0
    floor_translation: float = Field(5e-5, ge=0)
    floor_rotation_deg: float = Field(0.002, ge=0)
    background: BackgroundConfig = BackgroundConfig(range_max=1.8)
    mls: MLSConfig = MLSConfig()
    normals: NormalsConfig = NormalsConfig(k=15)
    coarse_normals: NormalsConfig = NormalsConfig(k=30, radius=0.024)
    fpfh: FPFHConfig = FPFHConfig(radius=0.06, max_nn=100)
    ransac: RansacConfig = RansacConfig(max_correspondence_distance=0.018, mutual_filter=False)
    icp: ICPConfig = ICPConfig(max_correspondence_distance=0.005, method="point_to_plane")
    gicp: GICPConfig = GICPConfig(max_correspondence_distance=0.005)
    jicp: JICPConfig = JICPConfig(
        window=4,
        icp=ICPConfig(
            max_correspondence_distance=0.005, method="point_to_plane", max_iterations=10
        ),
        gicp=GICPConfig(max_correspondence_distance=0.005),
    )
    keyframe: KeyframeConfig = KeyframeConfig()
    health: HealthConfig = HealthConfig()


# --------------------------------------------------------------------------------------------
# Results and state


@dataclass(frozen=True)
class TrackResult:
    """What the tracker reports for one frame.

    Attributes
    ----------
    index
        Frame number (0-based, counting every frame given, lost ones included).
    timestamp
        Seconds.
    T_sensor_target
        (4, 4) pose; model-free: ``T_k0``. For a lost frame, the constant-velocity prediction.
    covariance
        (6, 6) covariance of ``T_sensor_target``, twist (omega, v), left perturbation in the
        sensor frame; model-free it includes the keyframe chain.
    status
        ``ok``, ``degraded`` or ``lost``.
    reasons
        Why the frame is not ``ok`` (empty when it is).
    fitness, rmse, iterations, condition_number
        Of the fine registration (NaN / 0 when there was none).
    time_ms
        Wall time per stage (``preprocess``, ``coarse``, ``fine``, ``other``: health checks and
        bookkeeping; ``total`` is their sum).
    reference_index
        Frame index of the keyframe the frame was registered to (-1: the model or none).
    coarse
        Whether coarse registration ran for this frame.
    keyframe
        Whether the frame became a keyframe.
    """

    index: int
    timestamp: float
    T_sensor_target: NDArray[np.float64]
    covariance: NDArray[np.float64]
    status: Status
    reasons: tuple[str, ...] = ()
    fitness: float = float("nan")
    rmse: float = float("nan")
    iterations: int = 0
    condition_number: float = float("nan")
    time_ms: dict[str, float] = field(default_factory=dict)
    reference_index: int = -1
    coarse: bool = False
    keyframe: bool = False

    @property
    def sigma(self) -> NDArray[np.float64]:
        """(6,) 1-σ of (rx, ry, rz) in rad and (tx, ty, tz) in m."""
        return np.sqrt(np.clip(np.diag(self.covariance), 0.0, None))


@dataclass(eq=False)
class PreparedCloud:
    """A preprocessed frame, its search index and what the registrations reuse.

    ``covariances`` (GICP) is filled once per frame; the normals of ``cloud``, the index and
    ``coarse`` (sparse cloud + FPFH) lazily, when the frame is a registration target or coarse
    registration needs it.
    """

    cloud: PointCloud
    covariances: NDArray[np.float64] | None = None
    coarse: tuple[PointCloud, NDArray[np.float64]] | None = None
    _tree: VoxelIndex | None = None

    @property
    def tree(self) -> VoxelIndex:
        """Search index of the points, built the first time the cloud is a registration target."""
        if self._tree is None:
            self._tree = VoxelIndex(self.cloud.points)
        return self._tree

    # Cached: the points never change (``cloud`` is only replaced by itself with normals), and
    # the health check, the floor and the keyframe test ask for these several times per frame.
    @cached_property
    def centroid(self) -> NDArray[np.float64]:
        return self.cloud.points.mean(axis=0)

    @cached_property
    def radius(self) -> float:
        """RMS distance of the points from their centroid (m)."""
        return float(np.sqrt(((self.cloud.points - self.centroid) ** 2).sum(axis=1).mean()))


@dataclass(eq=False)
class Keyframe:
    """A reference cloud and its pose.

    Attributes
    ----------
    index
        Frame index (-1 for the model).
    prepared
        The preprocessed cloud, in its own sensor frame (or the target frame for the model).
    T_ref_target
        Pose of the reference frame: ``T_sensor_target`` at that frame (identity for the model).
    covariance
        (6, 6) covariance of ``T_ref_target`` (left perturbation).
    edges
        J-ICP: this keyframe's registrations onto the keyframes before it, as
        ``(their frame index, T_them_this, 6×6 information)``: the pose-graph edges of a window.
    """

    index: int
    prepared: PreparedCloud
    T_ref_target: NDArray[np.float64]
    covariance: NDArray[np.float64]
    edges: list[tuple[int, NDArray[np.float64], NDArray[np.float64]]] = field(default_factory=list)


@dataclass(frozen=True)
class FineEstimate:
    """Outcome of the fine registration of one frame (before the health check)."""

    T_sensor_target: NDArray[np.float64]
    covariance: NDArray[np.float64]
    own_covariance: NDArray[np.float64]
    result: RegistrationResult
    reference: Keyframe
    surface_step: NDArray[np.float64]
    edges: tuple[tuple[int, NDArray[np.float64], NDArray[np.float64]], ...] = ()
    window_poses: tuple[tuple[Keyframe, NDArray[np.float64], NDArray[np.float64]], ...] = ()


# --------------------------------------------------------------------------------------------
# Primitives


def voxel_downsample(cloud: PointCloud, voxel_size: float) -> PointCloud:
    """Centroid of the points in each occupied voxel (edge ``voxel_size`` m), sorted by voxel.

    σ (if present) is averaged too; normals are dropped (recompute them on the sparse cloud).
    """
    centroids, cell = voxel_cells(cloud.points, voxel_size)
    sigma = None
    if cloud.sigma is not None:
        counts = np.bincount(cell, minlength=len(centroids))
        sigma = np.bincount(cell, weights=cloud.sigma, minlength=len(centroids)) / counts
    return PointCloud(centroids, None, sigma, source=cloud.source)


def predict_pose(
    history: list[tuple[float, NDArray[np.float64]]], timestamp: float
) -> NDArray[np.float64] | None:
    """Constant-velocity prediction of ``T_sensor_target`` at ``timestamp``.

    Parameters
    ----------
    history
        Up to the last two accepted ``(timestamp, T_sensor_target)``, oldest first.

    Returns
    -------
    The last pose moved on by the last inter-frame motion ``T_b T_a⁻¹`` scaled to the elapsed
    time (on the Lie algebra); the last pose itself with one entry; None with none.
    """
    if not history:
        return None
    t_b, T_b = history[-1]
    if len(history) < 2:
        return T_b.copy()
    t_a, T_a = history[-2]
    dt = t_b - t_a
    # Equal or missing timestamps: assume one frame period per frame.
    scale = (timestamp - t_b) / dt if dt > 0 else 1.0
    return rigid(se3.exp(scale * se3.log(T_b @ se3.invert(T_a))) @ T_b)


def rigid(T: NDArray[np.float64]) -> NDArray[np.float64]:
    """``T`` with its rotation block projected back onto SO(3).

    Long chains of products (keyframe poses, predictions, registrations started from them) let
    rounding errors grow; without this the rotation drifts measurably off orthonormal.
    """
    return se3.make_transform(Rotation.from_matrix(T[:3, :3]), T[:3, 3])


def covariance_at(covariance: NDArray[np.float64], point: ArrayLike) -> NDArray[np.float64]:
    """Covariance of a left perturbation re-expressed about ``point`` (3,) instead of the origin.

    The rotation part is unchanged; the translation part becomes the displacement of ``point``,
    so a rotation about a far origin no longer shows up as a large translation.
    """
    # The point moves by v + ω × c = v − skew(c) ω under a left perturbation (ω, v).
    J = np.eye(6)
    J[3:, :3] = -se3.skew(np.asarray(point, dtype=np.float64))
    return J @ covariance @ J.T


def normalised_condition(
    information: NDArray[np.float64], centroid: ArrayLike, radius: float
) -> float:
    """Condition number of an information matrix made unit-free (see :class:`HealthConfig`)."""
    # Information about the centroid: Λ_c = Jᵀ Λ J with J the inverse of the covariance_at map.
    J = np.eye(6)
    J[3:, :3] = se3.skew(np.asarray(centroid, dtype=np.float64))
    S = np.diag([radius] * 3 + [1.0] * 3)
    info = S.T @ J.T @ information @ J @ S
    ev = np.linalg.eigvalsh(0.5 * (info + info.T))
    return float(ev[-1] / ev[0]) if ev[0] > 0 else float("inf")


def pose_disagreement(
    T_a: NDArray[np.float64], T_b: NDArray[np.float64], point: ArrayLike
) -> tuple[float, float]:
    """(displacement of ``point`` in m, rotation angle in degrees) between two poses of it."""
    D = T_a @ se3.invert(T_b)
    p = np.asarray(point, dtype=np.float64)
    moved = se3.transform_points(D, p[None])[0]
    cos = np.clip((np.trace(D[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)
    return float(np.linalg.norm(moved - p)), float(np.degrees(np.arccos(cos)))


def assess_health(
    fitness: float,
    rmse: float,
    condition: float,
    own_covariance: NDArray[np.float64],
    centroid: NDArray[np.float64],
    disagreement: tuple[float, float] | None,
    config: HealthConfig,
    velocity_known: bool = True,
    surface_step: tuple[float, float] = (0.0, 0.0),
) -> tuple[Status, tuple[str, ...]]:
    """Status and reasons of one registered frame.

    ``disagreement`` is :func:`pose_disagreement` against the prediction, or None when there is
    no prediction to check against (then the frame is at best degraded: unconfirmed);
    ``velocity_known`` False means the prediction is only the last pose. ``surface_step`` is
    the (displacement at the centroid m, rotation deg) of the point-to-plane step from the
    registered pose (:func:`plane_covariance`).
    """
    lost: list[str] = []
    weak: list[str] = []
    if fitness < config.lost_fitness:
        lost.append(f"fitness {fitness:.2f} < {config.lost_fitness}")
    elif fitness < config.ok_fitness:
        weak.append(f"fitness {fitness:.2f} < {config.ok_fitness}")
    if rmse > config.lost_rmse:
        lost.append(f"rmse {1e3 * rmse:.2f} mm > {1e3 * config.lost_rmse} mm")
    elif rmse > config.ok_rmse:
        weak.append(f"rmse {1e3 * rmse:.2f} mm > {1e3 * config.ok_rmse} mm")
    if not condition <= config.lost_condition:
        lost.append(f"condition {condition:.3g} > {config.lost_condition:.3g}")
    elif condition > config.ok_condition:
        weak.append(f"condition {condition:.3g} > {config.ok_condition:.3g}")
    cov_c = covariance_at(own_covariance, centroid)
    sig_t = float(np.sqrt(max(np.linalg.eigvalsh(cov_c[3:, 3:])[-1], 0.0)))
    sig_r = float(np.degrees(np.sqrt(max(np.linalg.eigvalsh(cov_c[:3, :3])[-1], 0.0))))
    if sig_t > config.ok_sigma_translation or sig_r > config.ok_sigma_rotation_deg:
        weak.append(f"registration sigma {1e3 * sig_t:.2f} mm / {sig_r:.3f} deg too large")
    st, sr = surface_step
    f = config.lost_prediction_factor
    msg = f"{1e3 * st:.2f} mm / {sr:.3f} deg off the surface optimum"
    if st > f * config.ok_step_translation or sr > f * config.ok_step_rotation_deg:
        lost.append(msg)
    elif st > config.ok_step_translation or sr > config.ok_step_rotation_deg:
        weak.append(msg)
    if disagreement is None:
        weak.append("no prediction to confirm the pose")
    else:
        dt, dr = disagreement
        ok_t, ok_r = config.ok_prediction_translation, config.ok_prediction_rotation_deg
        if not velocity_known:
            ok_t, ok_r = config.max_motion_translation, config.max_motion_rotation_deg
        msg = f"off the prediction by {1e3 * dt:.1f} mm / {dr:.2f} deg"
        if dt > f * ok_t or dr > f * ok_r:
            lost.append(msg)
        elif dt > ok_t or dr > ok_r:
            weak.append(msg)
    if lost:
        return "lost", tuple(lost + weak)
    return ("degraded" if weak else "ok"), tuple(weak)


# --------------------------------------------------------------------------------------------
# The tracker


class Tracker:
    """Stateful tracker: feed frames in time order with :meth:`track_frame`.

    Parameters
    ----------
    config
        Every stage's parameters.
    model
        Reference model cloud in the target frame (model-based mode; normals estimated if
        missing, pointing away from the model centroid); None for model-free tracking.
    workers
        Threads for the neighbour searches (results do not depend on it).
    """

    def __init__(
        self,
        config: TrackerConfig = TrackerConfig(),
        model: PointCloud | None = None,
        workers: int = -1,
    ) -> None:
        self.config = config
        self.workers = workers
        self._index = 0
        self._last_timestamp = -np.inf
        self._history: list[tuple[float, NDArray[np.float64], NDArray[np.float64]]] = []
        self._lost_streak = 0
        self._keyframes: list[Keyframe] = []
        self._model = None if model is None else self._prepare_model(model)

    @property
    def model_based(self) -> bool:
        return self._model is not None

    # -- the algorithm -----------------------------------------------------------------------

    def track_frame(self, cloud: PointCloud | ArrayLike | None, timestamp: float) -> TrackResult:
        """Track one frame.

        Parameters
        ----------
        cloud
            Points (N, 3) in the sensor frame (a PointCloud or array); None or an empty array
            for a frame without data (reported as lost).
        timestamp
            Seconds; frames must come in time order.

        Returns
        -------
        TrackResult
            Always one per call: a frame that cannot be tracked is reported ``lost`` with the
            predicted pose, never dropped.
        """
        timestamp = float(timestamp)
        if not np.isfinite(timestamp) or timestamp < self._last_timestamp:
            raise InputError(
                f"frame timestamps must be finite and non-decreasing, got {timestamp} after "
                f"{self._last_timestamp}"
            )
        self._last_timestamp = timestamp
        t_start = time.perf_counter()
        index = self._index
        self._index += 1
        times = dict.fromkeys(STAGES, 0.0)
        prediction = self._prediction(timestamp)

        tic = time.perf_counter()
        try:
            prepared = self._preprocess(cloud)
        except SpaceposeError as exc:
            times["preprocess"] = _ms(tic)
            return self._lost(
                index, timestamp, prediction, (f"unusable frame: {exc}",), times, t_start
            )
        times["preprocess"] = _ms(tic)

        if not self.model_based and not self._keyframes:
            return self._start(index, timestamp, prepared, times, t_start)

        estimate, status, reasons = None, "lost", ("no prior pose",)
        if prediction is not None:
            tic = time.perf_counter()
            estimate, status, reasons = self._fine_and_check(prepared, prediction[0], True)
            times["fine"] += _ms(tic)
        coarse = status == "lost" and (prediction is None or self._lost_streak > 0)
        if coarse:
            # No prior, or the track was already lost: re-initialise by coarse registration.
            estimate, status, reasons = self._reinitialise(
                prepared, prediction, (estimate, status, reasons), times
            )
        if status == "lost" or estimate is None:
            return self._lost(index, timestamp, prediction, reasons, times, t_start, coarse)
        return self._accept(
            index, timestamp, prepared, estimate, status, reasons, coarse, times, t_start
        )

    def _reinitialise(
        self,
        prepared: PreparedCloud,
        prediction: tuple[NDArray[np.float64], NDArray[np.float64]] | None,
        failed: tuple[FineEstimate | None, Status, tuple[str, ...]],
        times: dict[str, float],
    ) -> tuple[FineEstimate | None, Status, tuple[str, ...]]:
        """Coarse registration, then fine registration from it; ``failed`` if that fails too."""
        tic = time.perf_counter()
        init = self._coarse(prepared)
        times["coarse"] = _ms(tic)
        if init is None:
            return (*failed[:2], (*failed[2], "coarse registration found no consensus"))
        tic = time.perf_counter()
        estimate, status, reasons = self._fine_and_check(prepared, init, False)
        times["fine"] += _ms(tic)
        if prediction is not None and estimate is not None:
            # A stale prediction confirms the re-initialised pose when it agrees; when it does
            # not, the pose stands unconfirmed (degraded), not rejected.
            confirmed = self._check(estimate, prepared, prediction[0])
            if confirmed[0] != "lost":
                status, reasons = confirmed
        if status == "lost" and failed[0] is not None:
            return failed
        return estimate, status, reasons

    def coarse_pose(self, cloud: PointCloud | ArrayLike) -> NDArray[np.float64] | None:
        """Coarse ``T_sensor_target`` of a frame alone (preprocessing + FPFH + RANSAC against
        the model or the current keyframe), leaving the tracker's state untouched.

        Returns None when RANSAC finds no consensus.

        Raises
        ------
        InputError
            No reference yet (model-free before the first frame) or an unusable frame.
        """
        if self._model is None and not self._keyframes:
            raise InputError("coarse registration needs a model or a first tracked frame")
        return self._coarse(self._preprocess(cloud))

    def track(
        self, frames: Iterable[tuple[PointCloud | ArrayLike | None, float]]
    ) -> list[TrackResult]:
        """Track a sequence of ``(cloud, timestamp)`` pairs; one result per frame."""
        return [self.track_frame(cloud, t) for cloud, t in frames]

    # -- stages ------------------------------------------------------------------------------

    def _preprocess(self, cloud: PointCloud | ArrayLike | None) -> PreparedCloud:
        cfg = self.config
        if cloud is None:
            raise InputError("no points")
        pc = cloud if isinstance(cloud, PointCloud) else PointCloud(np.asarray(cloud))
        if cfg.use_background_removal:
            pc, _ = remove_background(pc, cfg.background)
        if cfg.use_mls:
            pc = mpp_mls(pc, cfg.mls, workers=self.workers)
        else:
            pc = voxel_downsample(pc, cfg.voxel_size)
        if len(pc) < cfg.health.min_points:
            raise InputError(
                f"{len(pc)} points after preprocessing (< {cfg.health.min_points})", pc.source
            )
        return self._prepared(pc)

    def _as_target(self, prepared: PreparedCloud) -> PreparedCloud:
        """The prepared cloud with normals, estimated the first time it is a registration
        target (a keyframe): most frames never are, and sources need none."""
        if not prepared.cloud.has_normals:
            prepared.cloud = estimate_normals(
                prepared.cloud, self.config.normals, workers=self.workers, tree=prepared.tree
            )
        return prepared

    def _pairwise(self) -> tuple[str, ICPConfig, GICPConfig]:
        """The pairwise registration the method uses, and its ICP and GICP configs."""
        cfg = self.config
        if cfg.method == "jicp":
            return cfg.jicp.registration, cfg.jicp.icp, cfg.jicp.gicp
        return cfg.method, cfg.icp, cfg.gicp

    def _prepared(self, pc: PointCloud) -> PreparedCloud:
        kind, _, gicp_cfg = self._pairwise()
        covariances = None
        if kind == "gicp":
            # Once per frame: reused whenever the frame is a source or a keyframe target.
            covariances = compute_covariances(
                pc.points, min(gicp_cfg.k_covariance, len(pc)), gicp_cfg.epsilon, self.workers
            )
        return PreparedCloud(pc, covariances)

    def _prepare_model(self, model: PointCloud) -> Keyframe:
        pc = model
        if not self.config.use_mls:
            pc = voxel_downsample(pc, self.config.voxel_size)
        if len(pc) < self.config.health.min_points:
            raise InputError(
                f"model has {len(pc)} points (< {self.config.health.min_points})", model.source
            )
        if not pc.has_normals:
            # Outward normals for a closed model: point them away from its centroid.
            centroid = pc.points.mean(axis=0)
            inward = estimate_normals(
                pc, self.config.normals, viewpoint=centroid, workers=self.workers
            )
            pc = inward.with_normals(-inward.normals)
        return Keyframe(-1, self._prepared(pc), np.eye(4), np.zeros((6, 6)))

    def _coarse_features(self, prepared: PreparedCloud) -> tuple[PointCloud, NDArray[np.float64]]:
        """Sparse cloud and FPFH descriptors of a prepared cloud, computed once."""
        if prepared.coarse is None:
            cfg = self.config
            sparse = voxel_downsample(prepared.cloud, cfg.coarse_voxel_size)
            if self._model is not None and prepared is self._model.prepared:
                # FPFH is sign-sensitive: model normals point outwards, as a sensor sees them.
                centroid = sparse.points.mean(axis=0)
                sparse = estimate_normals(sparse, cfg.coarse_normals, centroid, self.workers)
                sparse = sparse.with_normals(-sparse.normals)
            else:
                sparse = estimate_normals(sparse, cfg.coarse_normals, workers=self.workers)
            prepared.coarse = (sparse, compute_fpfh(sparse, cfg.fpfh, workers=self.workers))
        return prepared.coarse

    def _coarse(self, prepared: PreparedCloud) -> NDArray[np.float64] | None:
        """Initial ``T_sensor_target`` by FPFH + RANSAC against the reference, or None."""
        ref = self._reference()
        src, src_f = self._coarse_features(prepared)
        tgt, tgt_f = self._coarse_features(ref.prepared)
        try:
            res = feature_ransac(src, tgt, src_f, tgt_f, self.config.ransac, workers=self.workers)
        except SpaceposeError:
            return None
        return se3.invert(res.T_target_source) @ ref.T_ref_target

    def _fine_and_check(
        self, prepared: PreparedCloud, T_init: NDArray[np.float64], check_prediction: bool
    ) -> tuple[FineEstimate | None, Status, tuple[str, ...]]:
        try:
            estimate = self._fine(prepared, T_init)
        except SpaceposeError as exc:
            return None, "lost", (f"fine registration failed: {exc}",)
        status, reasons = self._check(estimate, prepared, T_init if check_prediction else None)
        return estimate, status, reasons

    def _check(
        self,
        estimate: FineEstimate,
        prepared: PreparedCloud,
        T_predicted: NDArray[np.float64] | None,
    ) -> tuple[Status, tuple[str, ...]]:
        c = prepared.centroid
        res = estimate.result
        disagreement = None
        if T_predicted is not None:
            disagreement = pose_disagreement(estimate.T_sensor_target, T_predicted, c)
        status, reasons = assess_health(
            res.fitness,
            res.inlier_rmse,
            normalised_condition(res.information, _in_reference(estimate, c), prepared.radius),
            estimate.own_covariance,
            c,
            disagreement,
            self.config.health,
            velocity_known=len(self._history) >= 2,
            surface_step=_step_size(estimate.surface_step, _in_reference(estimate, c)),
        )
        if status == "ok" and not self.model_based:
            # A keyframe far behind (none promoted for a while: the frames were degraded) is a
            # reference whose registration can lock onto a wrong but plausible overlap.
            kc, f = self.config.keyframe, self.config.health.max_reference_factor
            dt, dr = pose_disagreement(estimate.T_sensor_target, estimate.reference.T_ref_target, c)
            if dt > f * kc.max_translation or dr > f * kc.max_rotation_deg:
                status = "degraded"
                reasons = (f"{_FAR_KEYFRAME} {1e3 * dt:.0f} mm / {dr:.1f} deg away",)
        return status, reasons

    def _fine(self, prepared: PreparedCloud, T_init: NDArray[np.float64]) -> FineEstimate:
        """Fine registration of the frame from the initial ``T_sensor_target``."""
        if self.config.method != "jicp" or self.model_based:
            ref = self._reference()
            res, cov_ref_k, step = self._register(prepared, ref, T_init)
            T_ref_k = res.T_target_source
            T_k_ref = se3.invert(T_ref_k)
            Ad = se3.adjoint(T_k_ref)
            own = Ad @ cov_ref_k @ Ad.T
            cov = Ad @ (cov_ref_k + ref.covariance) @ Ad.T
            return FineEstimate(rigid(T_k_ref @ ref.T_ref_target), cov, own, res, ref, step)
        return self._fine_joint(prepared, T_init)

    def _fine_joint(self, prepared: PreparedCloud, T_init: NDArray[np.float64]) -> FineEstimate:
        """J-ICP: register the frame to each keyframe of the window, solve the pose graph.

        Nodes are the window's keyframes (the oldest fixed, METHODS §1.6) and the new frame;
        edges are the stored keyframe-to-keyframe registrations and the new frame's
        registrations to every keyframe, each weighted by its information. With a window of 3
        and equal weights this is Li's Eq. 9 averaged on SE(3).
        """
        cfg = self.config
        equal = cfg.jicp.weighting == "equal"
        window = self._keyframes[-(cfg.jicp.window - 1) :]
        node = {kf.index: n for n, kf in enumerate(window)}
        k = len(window)
        graph_edges: list[PoseGraphEdge] = []
        new_edges = []
        for kf in window:
            for ref_index, T_j_i, info in kf.edges:
                if ref_index in node:
                    graph_edges.append(PoseGraphEdge(node[kf.index], node[ref_index], T_j_i, info))
        # The latest keyframe must register (its failure fails the frame); an older one out of
        # reach is no reason to.
        latest = self._register(prepared, window[-1], T_init)
        pairs = [(window[-1], latest)]
        # The latest registration is a better start for the older pairs than the prediction.
        T_start = se3.invert(latest[0].T_target_source) @ window[-1].T_ref_target
        # ...and for the new node of the pose graph (now and then one iteration fewer).
        poses = [kf.T_ref_target for kf in window] + [T_start]
        for kf in window[:-1]:
            try:
                pairs.append((kf, self._register(prepared, kf, T_start)))
            except SpaceposeError:
                continue
        for kf, (res, cov, _) in pairs:
            info = np.eye(6) if equal else np.linalg.pinv(cov, hermitian=True)
            graph_edges.append(PoseGraphEdge(k, node[kf.index], res.T_target_source, info))
            new_edges.append((kf.index, res.T_target_source, info))
        # Gauge: the oldest keyframe keeps its pose; its covariance is added to the result.
        graph = optimize_pose_graph(
            np.array(poses), graph_edges, fixed=(0,), tolerance=_POSE_GRAPH_TOLERANCE
        )
        oldest = window[0]
        T_k0 = rigid(graph.poses[k])
        cov = graph.covariances[k] + _moved(oldest, T_k0)
        res, cov_ref_k, step = latest
        Ad_own = se3.adjoint(se3.invert(res.T_target_source))
        own = Ad_own @ cov_ref_k @ Ad_own.T
        updated = tuple(
            (kf, rigid(graph.poses[n]), graph.covariances[n] + _moved(oldest, graph.poses[n]))
            for n, kf in enumerate(window)
            if n > 0
        )
        return FineEstimate(T_k0, cov, own, res, window[-1], step, tuple(new_edges), updated)

    def _register(
        self,
        prepared: PreparedCloud,
        ref: Keyframe,
        T_init_sensor_target: NDArray[np.float64],
    ) -> tuple[RegistrationResult, NDArray[np.float64], NDArray[np.float64]]:
        """Register the frame (source) onto a reference.

        Returns the result, the covariance of ``T_ref_k`` and the point-to-plane step from it
        (both left perturbations in the reference frame; see :func:`plane_covariance`).
        """
        kind, icp_cfg, gicp_cfg = self._pairwise()
        init_T_ref_k = ref.T_ref_target @ se3.invert(T_init_sensor_target)
        tgt = self._as_target(ref.prepared)
        if kind == "gicp":
            res = gicp(
                prepared.cloud,
                tgt.cloud,
                init_T_ref_k,
                gicp_cfg,
                workers=self.workers,
                source_covariances=prepared.covariances,
                target_covariances=tgt.covariances,
                target_tree=tgt.tree,
            )
            matches = None
        else:
            # ICP hands back its final correspondences (and point-to-plane sums): the covariance
            # need not search or sum again.
            res, matches = icp_correspondences(
                prepared.cloud,
                tgt.cloud,
                init_T_ref_k,
                icp_cfg,
                workers=self.workers,
                target_tree=tgt.tree,
            )
        gate = (gicp_cfg if kind == "gicp" else icp_cfg).max_correspondence_distance
        cov, step = plane_covariance(
            res.T_target_source, prepared.cloud, tgt, gate, self.workers, matches
        )
        return res, self.config.covariance_scale * cov + self._floor(prepared, res), step

    def _floor(self, prepared: PreparedCloud, res: RegistrationResult) -> NDArray[np.float64]:
        """Systematic-error floor (see :class:`TrackerConfig`) in the reference frame."""
        cfg = self.config
        floor_c = np.diag(
            [np.radians(cfg.floor_rotation_deg) ** 2] * 3 + [cfg.floor_translation**2] * 3
        )
        # A twist about the centroid c is (ω, v + skew(c) ω) about the origin.
        M = np.eye(6)
        M[3:, :3] = se3.skew(_in_reference_point(res, prepared.centroid))
        return M @ floor_c @ M.T

    # -- state -------------------------------------------------------------------------------

    def _reference(self) -> Keyframe:
        return self._model if self._model is not None else self._keyframes[-1]

    def _prediction(
        self, timestamp: float
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]] | None:
        T = predict_pose([(t, T) for t, T, _ in self._history[-2:]], timestamp)
        if T is None:
            return None
        h = self.config.health
        # Uncertainty of a prediction: the last covariance plus the motion disagreement the
        # health check tolerates as "ok" per frame (about the origin; a deliberately loose
        # bound), growing with the number of frames since the last accepted pose.
        q = np.array(
            [np.radians(h.ok_prediction_rotation_deg)] * 3 + [h.ok_prediction_translation] * 3
        )
        return T, self._history[-1][2] + (1 + self._lost_streak) ** 2 * np.diag(q**2)

    def _start(
        self,
        index: int,
        timestamp: float,
        prepared: PreparedCloud,
        times: dict[str, float],
        t_start: float,
    ) -> TrackResult:
        """Model-free: the first usable frame defines the target frame (pose identity)."""
        T, cov = np.eye(4), np.zeros((6, 6))
        self._keyframes.append(Keyframe(index, prepared, T, cov))
        self._history.append((timestamp, T, cov))
        _close_times(times, t_start)
        return TrackResult(
            index,
            timestamp,
            T,
            cov,
            "ok",
            time_ms=times,
            reference_index=index,
            keyframe=True,
            fitness=1.0,
            rmse=0.0,
        )

    def _lost(
        self,
        index: int,
        timestamp: float,
        prediction: tuple[NDArray[np.float64], NDArray[np.float64]] | None,
        reasons: tuple[str, ...],
        times: dict[str, float],
        t_start: float,
        coarse: bool = False,
    ) -> TrackResult:
        self._lost_streak += 1
        if prediction is None:
            # Nothing known: an identity pose with infinite uncertainty, flagged lost.
            T, cov = np.eye(4), np.diag(np.full(6, np.inf))
        else:
            T, cov = prediction
        _close_times(times, t_start)
        return TrackResult(index, timestamp, T, cov, "lost", reasons, time_ms=times, coarse=coarse)

    def _accept(
        self,
        index: int,
        timestamp: float,
        prepared: PreparedCloud,
        estimate: FineEstimate,
        status: Status,
        reasons: tuple[str, ...],
        coarse: bool,
        times: dict[str, float],
        t_start: float,
    ) -> TrackResult:
        self._lost_streak = 0
        T, cov = estimate.T_sensor_target, estimate.covariance
        # After a re-initialisation the old velocity is meaningless: restart the history.
        self._history = [*([] if coarse else self._history[-1:]), (timestamp, T, cov)]
        promoted = False
        # A frame degraded only by the distance to its keyframe passed every check of its own
        # registration: promoting it is how the tracker gets back to ok after a re-initialisation.
        far_only = bool(reasons) and all(r.startswith(_FAR_KEYFRAME) for r in reasons)
        if not self.model_based and (status == "ok" or far_only):
            for kf, T_kf, cov_kf in estimate.window_poses:
                kf.T_ref_target, kf.covariance = T_kf, cov_kf
            if self._needs_keyframe(estimate, prepared):
                kf = Keyframe(index, prepared, T, cov, list(estimate.edges))
                self._keyframes = [*self._keyframes[-self.config.jicp.window :], kf]
                promoted = True
        res = estimate.result
        c = prepared.centroid
        _close_times(times, t_start)
        return TrackResult(
            index,
            timestamp,
            T,
            cov,
            status,
            reasons,
            fitness=res.fitness,
            rmse=res.inlier_rmse,
            iterations=res.iterations,
            condition_number=normalised_condition(
                res.information, _in_reference(estimate, c), prepared.radius
            ),
            time_ms=times,
            reference_index=estimate.reference.index,
            coarse=coarse,
            keyframe=promoted,
        )

    def _needs_keyframe(self, estimate: FineEstimate, prepared: PreparedCloud) -> bool:
        kc = self.config.keyframe
        ref = estimate.reference
        dt, dr = pose_disagreement(estimate.T_sensor_target, ref.T_ref_target, prepared.centroid)
        return (
            estimate.result.fitness < kc.min_fitness
            or dt > kc.max_translation
            or dr > kc.max_rotation_deg
        )


def plane_covariance(
    T_target_source: NDArray[np.float64],
    source: PointCloud,
    target: PreparedCloud,
    max_distance: float,
    workers: int = -1,
    correspondences: Correspondences | None = None,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Covariance of a registration from its point-to-plane residuals at the solution.

    ``σ² (Σ h hᵀ)⁻¹`` with ``h = (p × n, n)`` over the final correspondences (target normals)
    and ``σ²`` the variance of the normal distances: the same noise model whichever method
    produced ``T_target_source``, so ICP, GICP and J-ICP report comparable uncertainties.
    (The Euclidean RMSE would add the tangential offsets between two different samplings;
    GICP's own information, built on plane-regularised covariances, understated the error:
    only 77 % of the lab frames within 3 σ.)

    ``correspondences`` are the matches at ``T_target_source`` when the registration already
    has them (:func:`icp_correspondences`; its point-to-plane sums are used as they are, being
    these very sums); otherwise they are searched within ``max_distance``.

    Returns
    -------
    covariance
        (6, 6) covariance of ``T_target_source``, left perturbation in the target frame.
    step
        (6,) the Gauss-Newton point-to-plane step from ``T_target_source`` (same frame): about
        zero when the transform sits at the surface optimum, large when a registration stopped
        elsewhere (e.g. point-to-point ICP locked onto the voxel grid of two samplings).

    Raises
    ------
    RegistrationError
        Fewer than 7 correspondences within ``max_distance``.
    """
    if correspondences is not None and correspondences.system is not None:
        n_matches = len(correspondences.src_idx)
        H, g, sse = correspondences.system
    else:
        moved = se3.transform_points(T_target_source, source.points)
        if correspondences is None:
            s, t, _ = find_correspondences(target.tree, moved, max_distance, workers)
        else:
            s, t = correspondences.src_idx, correspondences.tgt_idx
        n_matches = len(s)
        # One thread: a few thousand rows are summed faster than a second thread wakes up.
        H, g, sse = point_to_plane_system(moved[s], target.cloud.points[t], target.cloud.normals[t])
    if n_matches < 7:
        raise RegistrationError(f"{n_matches} correspondences are too few for a covariance")
    sigma2 = sse / (n_matches - 6)
    H_inv = np.linalg.pinv(H, hermitian=True)
    return sigma2 * H_inv, -H_inv @ g


def _in_reference(estimate: FineEstimate, point_k: NDArray[np.float64]) -> NDArray[np.float64]:
    """A frame-k point expressed in the reference frame, where the information is expressed."""
    return _in_reference_point(estimate.result, point_k)


def _in_reference_point(
    result: RegistrationResult, point_k: NDArray[np.float64]
) -> NDArray[np.float64]:
    return se3.transform_points(result.T_target_source, point_k[None])[0]


def _step_size(step: NDArray[np.float64], point: NDArray[np.float64]) -> tuple[float, float]:
    """(displacement of ``point`` in m, rotation in degrees) of a small twist ``step``."""
    omega, v = step[:3], step[3:]
    return float(np.linalg.norm(v + np.cross(omega, point))), float(
        np.degrees(np.linalg.norm(omega))
    )


def _moved(anchor: Keyframe, T_sensor_target: NDArray[np.float64]) -> NDArray[np.float64]:
    """The anchor keyframe's pose covariance carried into the frame of ``T_sensor_target``."""
    Ad = se3.adjoint(T_sensor_target @ se3.invert(anchor.T_ref_target))
    return Ad @ anchor.covariance @ Ad.T


def _ms(tic: float) -> float:
    return 1e3 * (time.perf_counter() - tic)


def _close_times(times: dict[str, float], t_start: float) -> None:
    """Set ``total`` and ``other`` (the time no named stage took) of a step's timings (ms)."""
    times["total"] = _ms(t_start)
    named = sum(times.get(s, 0.0) for s in ("preprocess", "coarse", "fine"))
    times["other"] = max(times["total"] - named, 0.0)


# --------------------------------------------------------------------------------------------
# One call


@dataclass(frozen=True)
class TrackingOutput:
    """A tracked sequence: the trajectory (one pose per frame) and the per-frame results."""

    trajectory: Trajectory
    results: list[TrackResult]


def track_sequence(
    clouds: Iterable[PointCloud | ArrayLike | None],
    timestamps: ArrayLike,
    config: TrackerConfig = TrackerConfig(),
    model: PointCloud | None = None,
    workers: int = -1,
) -> TrackingOutput:
    """Track every frame of a sequence with a fresh :class:`Tracker`.

    Parameters
    ----------
    clouds
        One cloud per frame (sensor frame); None / empty for frames without data.
    timestamps
        (N,) seconds, one per cloud.
    config, model, workers
        As for :class:`Tracker`.
    """
    stamps = np.asarray(timestamps, dtype=np.float64).reshape(-1)
    clouds = list(clouds)
    if not clouds or len(clouds) != len(stamps):
        raise InputError(f"{len(clouds)} clouds for {len(stamps)} timestamps; need one each (>0)")
    results = Tracker(config, model, workers).track(zip(clouds, stamps, strict=True))
    poses = np.array([r.T_sensor_target for r in results])
    return TrackingOutput(Trajectory(stamps, poses), results)
