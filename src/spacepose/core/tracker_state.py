"""The tracker's state and how a frame's outcome updates it: the motion model, the keyframe
window, a model-free run's first frame, and the stages built on the lengths of the first usable
frame (docs/methods.md §5). :class:`~spacepose.core.tracker.Tracker` runs the algorithm on it.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from numpy.typing import ArrayLike, NDArray

from spacepose.core.cloud import PointCloud
from spacepose.core.fine_stage import FineStage
from spacepose.core.frame_check import CheckContext, health_bounds
from spacepose.core.frame_preparation import FramePreparer, checked_model
from spacepose.core.frame_registration import FrameRegistrar
from spacepose.core.handedness import HandednessCheck
from spacepose.core.health import UNCONFIRMED, Status, pose_disagreement
from spacepose.core.keyframe_window import KeyframeWindow
from spacepose.core.keyframes import FineEstimate, Keyframe, PreparedCloud
from spacepose.core.motion import MotionModel, Prediction
from spacepose.core.pose_covariance import CLUSTER_VOXELS
from spacepose.core.range_bias import range_bias_effect
from spacepose.core.relocalise import Relocaliser, coarse_pose
from spacepose.core.repeated_frame import RepeatWatch, stale_reason
from spacepose.core.scale import DataScale
from spacepose.core.scene_follower import SceneFollower
from spacepose.core.spare_anchor import SpareAnchor
from spacepose.core.support import SupportSeparation
from spacepose.core.threads import thread_count
from spacepose.core.track_result import (
    TrackResult,
    accepted_result,
    close_times,
    first_result,
    lost_result,
)
from spacepose.core.tracker_config import StageLengths, TrackerConfig
from spacepose.core.viewpoint import OriginCheck
from spacepose.errors import ConfigError


class TrackerState:
    """What a :class:`~spacepose.core.tracker.Tracker` keeps from frame to frame (its
    parameters are the tracker's), and the updates of it after each frame."""

    def __init__(
        self,
        config: TrackerConfig | dict = TrackerConfig(),
        model: PointCloud | ArrayLike | None = None,
        workers: int = -1,
    ) -> None:
        if not isinstance(config, TrackerConfig):
            # A mapping of fields (as a config file holds) is validated; anything else is not a
            # config.
            if not isinstance(config, dict):
                raise ConfigError(f"config must be a TrackerConfig, got {type(config).__name__}")
            config = TrackerConfig.model_validate(config)
        self.config = config
        thread_count(workers)  # refused now, not on the first frame's first kernel
        self.workers = workers
        self._index = 0
        self._last_timestamp = -np.inf
        self._motion = MotionModel()
        self._lost_streak = 0
        self._window = KeyframeWindow(config)
        self._registrar: FrameRegistrar | None = None
        self._t_start = 0.0
        self._model_input = (
            None if model is None else checked_model(model, config.health.min_points)
        )
        self._model_cloud = self._model_input
        # The model's size over the first frame's (model_size_ratio): NaN until one is seen.
        self.model_size_ratio = float("nan")
        self._model: Keyframe | None = None
        self._relocaliser: Relocaliser | None = None
        # Against a model: whether the cloud's origin sees the faces a frame lies on, and
        # whether the frames are a mirror image.
        self._origin: OriginCheck | None = None
        self._handedness: HandednessCheck | None = None
        self._frames = FramePreparer(config, self._model_cloud, workers)
        # Model-free: a support moving otherwise, split off the object (core.support).
        self._support: SupportSeparation | None = None
        # Fine registration and its check (core.fine_stage), built with the registrar on this
        # tracker's objects: _follow_scene's adoption of another's state takes its stage too.
        self._fine: FineStage | None = None
        # Model-free with target isolation, while undecided: the whole scene tracked beside the
        # nearest object (core.scene_motion).
        self._scene: SceneFollower | None = None
        if model is None and config.isolate_target:
            self._scene = SceneFollower(config, workers)
        # Model-free: the first frame's result, and a spare tracker while no later frame has
        # confirmed it (core.spare_anchor).
        self._first: TrackResult | None = None
        self._first_centroid = np.zeros(3)
        # A frame with the last one's points (core.repeated_frame), and where the target's
        # points were centred in the last accepted frame (sensor frame).
        self._repeats = RepeatWatch()
        self._last_centroid: NDArray[np.float64] | None = None
        self._spare = None if model is not None else SpareAnchor(config, workers)

    @property
    def model_based(self) -> bool:
        return self._model_cloud is not None

    @property
    def support_found_at(self) -> float | None:
        """Time (s) of the frame on which a support (moving otherwise, or standing still) was
        last split off the target (model-free, methods.md §5.8); None while there is none."""
        return None if self._support is None else self._support.found_at

    @property
    def scale(self) -> DataScale | None:
        """The lengths derived from the first usable frame (None before it)."""
        return self._frames.scale

    @property
    def first_index(self) -> int | None:
        """Model-free: the frame whose sensor frame is the target frame (None before it, and
        against a model)."""
        return None if self._first is None else self._first.index

    @property
    def lengths(self) -> StageLengths | None:
        """Every stage's lengths, set from :attr:`scale` (None before the first usable frame)."""
        return self._frames.lengths

    def fits(self, result: TrackResult) -> bool:
        """Whether ``result`` was accepted with its registration's fitness and RMSE within
        their ok bounds (:mod:`spacepose.core.health`), the RMSE's at the voxel: the residual
        noise that widens it is measured on this tracker's own frames, and frames registered
        onto a garbage first frame would excuse themselves. A run whose first frame holds no
        surface never fits."""
        scale = self._frames.scale
        if result.status == "lost" or scale is None or scale.surfaceless:
            return False
        bounds = health_bounds(replace(self._context(), noise_factor=1.0), self.model_based)
        return result.fitness >= bounds.ok_fitness and result.rmse <= bounds.ok_rmse

    def jumped(self, result: TrackResult) -> bool:
        """Whether ``result`` is a pose no prediction confirmed that moves the first frame's
        target farther than it can move in the frames between (the largest motion a frame of
        the health check): a coarse jump onto a glitched first frame (moved 1 km), which later
        fits confirm instead of the first frame."""
        if self._first is None or result.status == "lost" or UNCONFIRMED not in result.reasons:
            return False
        bounds = health_bounds(self._context(), self.model_based)
        frames = max(1, result.index - self._first.index)
        moved, turned = pose_disagreement(result.T_sensor_target, np.eye(4), self._first_centroid)
        return (
            moved > frames * bounds.max_motion_translation
            or turned > frames * bounds.max_motion_rotation_deg
        )

    def continue_at(self, index: int) -> None:
        """Number the next frame ``index``: the frames before it went to another tracker (a
        run's whole-scene tracker starts late, :mod:`spacepose.core.scene_follower`).

        Raises
        ------
        ConfigError
            ``index`` not an integer, or below the next frame's number: frame numbers only
            grow.
        """
        if isinstance(index, bool) or not isinstance(index, int | np.integer):
            raise ConfigError(f"a frame number must be an integer, got {index!r}")
        if index < self._index:
            raise ConfigError(f"frame numbers only grow: {index} after {self._index - 1}")
        self._index = index

    def _build_stages(self) -> None:
        """The registration stages, once the first usable frame has set every length."""
        cfg, workers = self.config, self.workers
        lengths, ok_influence = self._frames.lengths, cfg.health.ok_influence
        registrar = FrameRegistrar(cfg.method, lengths, cfg.covariance_scale, workers, ok_influence)
        if self.model_based:
            # Before the registrar is kept: a model too sparse at this frame's voxel loses the
            # frame, and the next frame tries again instead of finding half-built stages.
            self._model = self._frames.prepare_model(self._model_cloud)
            # Its normals tell the faces a pose turns to the sensor (visible_model).
            self._model_cloud = self._frames.sensor_model(self._model_cloud)
            self._origin = OriginCheck(self._model_cloud, not self._model_input.has_normals)
            self._handedness = HandednessCheck(self._model_cloud, self._coarse_onto_model)
        self._registrar = registrar
        if not self.model_based:
            health, stale = cfg.health, cfg.keyframe.stale_fitness
            self._support = SupportSeparation(
                registrar, health.min_points, workers, stale, health.ok_condition
            )
        model, window, motion = self._model, self._window, self._motion
        fine = FineStage(
            cfg, self._frames, registrar, window, motion, model, self._model_cloud, self._support
        )
        self._fine = fine
        ok_fitness = health_bounds(self._context(), self.model_based).ok_fitness
        self._relocaliser = Relocaliser(
            registrar, fine.reference, model, fine.register, fine.check, ok_fitness, workers
        )

    def _coarse_onto_model(self, cloud: PointCloud) -> NDArray[np.float64] | None:
        """The coarse ``T_sensor_target`` (4, 4) of ``cloud`` (sensor frame) onto the model, or
        None (:func:`~spacepose.core.relocalise.coarse_pose`)."""
        prepared = PreparedCloud(cloud)
        return coarse_pose(prepared, self._model, self._frames.lengths, True, self.workers)

    def _context(self) -> CheckContext:
        noise = 1.0 if self._registrar is None else self._registrar.noise.accepted_factor
        return CheckContext(self.config, self._frames.scale, self._motion, noise)

    def _start(
        self, index: int, timestamp: float, prepared: PreparedCloud, times: dict[str, float]
    ) -> TrackResult:
        """Model-free: the first usable frame defines the target frame (pose identity)."""
        T, cov = np.eye(4), np.zeros((6, 6))
        first = Keyframe(index, prepared, T, cov, timestamp=timestamp, dense=self._dense(prepared))
        self._first_centroid = prepared.centroid
        self._window.restart(first)
        self._support.first = first
        self._motion.accept(timestamp, T, cov, None, restart=True)
        close_times(times, self._t_start)
        self._first = first_result(index, timestamp, times)
        return self._first

    def _dense(self, prepared: PreparedCloud) -> PreparedCloud | None:
        """A new keyframe's finer registration target (:meth:`FramePreparer.keyframe_cloud`;
        None: the frame's own cloud is), with normals now: it is the next frame's target,
        whose step should not pay for them."""
        dense = self._frames.keyframe_cloud(self._registrar.as_target(prepared))
        prepared.raw = None  # the raw points are not kept with the keyframe
        return dense

    def _lost(
        self,
        index: int,
        timestamp: float,
        prediction: Prediction | None,
        reasons: tuple[str, ...],
        times: dict[str, float],
        coarse: bool = False,
    ) -> TrackResult:
        self._lost_streak += 1
        if self._registrar is not None:
            self._registrar.noise.discard()
        if not self._motion.history:
            self._forget_lengths()
        close_times(times, self._t_start)
        return lost_result(index, timestamp, prediction, reasons, times, coarse)

    def _stale(self, cloud: object, prediction: Prediction | None) -> str | None:
        """Why a frame that repeats the last one's points is no measurement: the motion model
        predicts the target to move by more than a registration resolves (the step from its
        optimum a health check allows; None otherwise, or when it is no repeat;
        core.repeated_frame)."""
        repeats = self._repeats.repeats(cloud)
        if not repeats or prediction is None or self._frames.scale is None:
            return None
        if not self._motion.history or self._last_centroid is None:
            return None
        T_last = self._motion.history[-1][1]
        moved, turned = pose_disagreement(prediction.T_sensor_target, T_last, self._last_centroid)
        bounds = health_bounds(self._context(), self.model_based)
        if moved <= bounds.ok_step_translation and turned <= bounds.ok_step_rotation_deg:
            # A target standing still, rendered without noise, repeats itself (its poses
            # then differ by the keyframe's sampling: 0.1 mm / 0.02° on the lab run).
            return None
        return stale_reason(moved, turned)

    def _forget_lengths(self) -> None:
        """No pose accepted yet: the lengths a lost frame derived, and the stages built on
        them, are dropped, so that the next frame derives its own (a first frame of noise set
        a voxel at which the model kept 24 points, and every later frame was lost)."""
        self._frames = FramePreparer(self.config, self._model_input, self.workers)
        self._model_cloud = self._model_input
        self._registrar = self._model = self._relocaliser = self._fine = self._support = None
        self._origin = self._handedness = None

    def _accept(
        self,
        index: int,
        timestamp: float,
        prepared: PreparedCloud,
        estimate: FineEstimate,
        prediction: Prediction | None,
        health: tuple[Status, tuple[str, ...]],
        coarse: bool,
        times: dict[str, float],
    ) -> TrackResult:
        self._lost_streak = 0
        self._registrar.noise.commit()
        T, cov = estimate.T_sensor_target, estimate.covariance
        error = None
        # Only a constant-velocity prediction has a model error (the last pose alone has none).
        if prediction is not None and prediction.velocity_known and not coarse:
            dt, dr = pose_disagreement(T, prediction.T_sensor_target, prepared.centroid)
            error = (dt, np.radians(dr))
        self._motion.accept(timestamp, T, cov, error, restart=coarse)
        self._last_centroid = prepared.centroid
        promoted = False
        if not self.model_based:
            radius = self._frames.scale.radius
            promoted = self._window.update(
                index, timestamp, prepared, estimate, health, radius, self._dense
            )
        close_times(times, self._t_start)
        result = accepted_result(
            index, timestamp, estimate, prepared, health, times, coarse, promoted
        )
        if self.model_based and self.config.range_bias > 0:
            # Reported only: the health check weighs the registration's own σ, and the motion
            # model the poses' scatter, which one range error shared by every frame does not
            # widen.
            sigma = self.config.range_bias * self._frames.scale.noise
            gate = self._registrar.noise.gate
            points = prepared.cloud.points
            cell = CLUSTER_VOXELS * self._frames.scale.voxel
            effect = range_bias_effect(
                points, self._model.prepared, T, gate, sigma, cell, self.workers
            )
            result = replace(result, covariance=effect.covariance(result.covariance))
        return result
