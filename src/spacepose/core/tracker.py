"""Frame-by-frame pose tracking of a rigid target (Li et al. 2024 pipeline, docs/methods.md §1, §5).

Each frame goes through

1. the motion model's prediction (constant velocity, with its observed error);
2. preprocessing: optional background removal, mpp-MLS or voxel downsampling at the voxel the
   first frame's spacing gives (:mod:`spacepose.core.scale`);
3. fine registration from the prediction (point-to-point or point-to-plane ICP, GICP, Li's
   J-ICP, or our keyframe graph), after a wide first pass when the motion model has been wrong
   by more than the fine gate;
4. a health check that labels the frame ``ok``, ``degraded`` or ``lost``
   (:mod:`spacepose.core.health`);
5. coarse re-initialisation (FPFH + RANSAC at the derived scale) when the frame is lost, and,
   against a model, when it fits the model poorly; a coarse pose's twins (the model half a turn
   about a principal axis) are registered too, and a twin the data cannot rule out is carried
   along with the frames flagged ambiguous (:mod:`spacepose.core.relocalise`);
6. a state update: the motion model and the keyframe window
   (:mod:`spacepose.core.keyframe_window`; a keyframe's finer cloud,
   :meth:`~spacepose.core.frame_preparation.FramePreparer.keyframe_cloud`).

Two modes. *Model-based*: a reference model cloud (target frame) is given and every pose is
``T_sensor_target`` directly. *Model-free*: the first usable frame defines the target frame, its
pose is the identity and pose k is ``T_k0``; keyframes bound the drift.

Covariances are 6×6, twist order (omega, v), for a left perturbation of ``T_sensor_target``
(``T ← exp(δ) T``, δ in the sensor frame at frame k), so their square-rooted diagonal is directly
comparable with the per-axis errors of ``ΔT = T_est · T_gt⁻¹``.
"""

from __future__ import annotations

import dataclasses
import time
import warnings
from collections.abc import Iterable

import numpy as np
from numpy.typing import ArrayLike, NDArray

from spacepose.core.cloud import PointCloud
from spacepose.core.frame_check import first_pass_gate, health_bounds, wide_gate
from spacepose.core.keyframes import PreparedCloud
from spacepose.core.motion import Prediction, next_timestamp
from spacepose.core.relocalise import Checked
from spacepose.core.scale import model_size_ratio
from spacepose.core.scene_follower import SCENE_NOTE
from spacepose.core.track_result import (
    STAGES,
    TrackResult,
    elapsed_ms,
    revise_results,
    with_time,
)
from spacepose.core.track_sequence import track_sequence as track_sequence
from spacepose.core.tracker_config import TrackerConfig as TrackerConfig
from spacepose.core.tracker_state import TrackerState
from spacepose.errors import InputError, SpaceposeError, SpaceposeWarning


class Tracker(TrackerState):
    """Stateful tracker: feed frames in time order with :meth:`track_frame`.

    Parameters
    ----------
    config
        The tracker's knobs; every length is derived from the first usable frame.
    model
        Reference model cloud or (N, 3) array in the target frame (model-based mode; normals
        estimated if missing, pointing away from the model centroid); None for model-free.
    workers
        Threads for the neighbour searches (results do not depend on it).

    Attributes
    ----------
    model_size_ratio
        Against a model: the model's RMS radius over the first frame's returns' (NaN until a
        frame with returns came; model-free, NaN). Five or more is warned of as another unit.
    """

    def track_frame(
        self,
        cloud: PointCloud | ArrayLike | None,
        timestamp: float,
        prior: tuple[ArrayLike, ArrayLike] | None = None,
    ) -> TrackResult:
        """Track one frame.

        Parameters
        ----------
        cloud
            Points (N, 3) in the sensor frame (a PointCloud or array); None or an empty array
            for a frame without data (reported as lost).
        timestamp
            Seconds; frames must come in time order.
        prior
            Optional ``(T_sensor_target (4, 4), covariance (6, 6))`` predicted outside the
            tracker (a navigation filter): it replaces the motion model's prediction as the
            start of registration and the reference of the health check.

        Returns
        -------
        TrackResult
            Always one per call: a frame that cannot be tracked is reported ``lost`` with the
            predicted pose, never dropped.
        """
        result = self._track_frame(cloud, timestamp, prior)
        if self._scene is not None:
            result = self._follow_scene(cloud, timestamp, prior, result)
        if self._spare is not None:
            result = self._follow_spare(cloud, timestamp, result)
        return result

    def _track_frame(
        self,
        cloud: PointCloud | ArrayLike | None,
        timestamp: float,
        prior: tuple[ArrayLike, ArrayLike] | None,
    ) -> TrackResult:
        timestamp = next_timestamp(timestamp, self._last_timestamp)
        if prior is not None and not (isinstance(prior, tuple | list) and len(prior) == 2):
            raise InputError("prior must be a pair (T_sensor_target (4, 4), covariance (6, 6))")
        if self._model_cloud is not None and np.isnan(self.model_size_ratio):
            self._check_model_size(cloud)
        prediction = self._predict(timestamp) if prior is None else Prediction.given(*prior)
        # Only a frame taken moves the clock on: a call refused above leaves its time free.
        self._last_timestamp = timestamp
        self._t_start = time.perf_counter()
        index = self._index
        self._index += 1
        times = dict.fromkeys(STAGES, 0.0)
        stale = self._stale(cloud, prediction)
        if stale is not None:
            return self._lost(index, timestamp, prediction, (stale,), times)

        tic = time.perf_counter()
        try:
            prepared = self._preprocess(cloud, prediction)
        except SpaceposeError as exc:
            prepared = self._whole_frame(cloud, prediction)
            if prepared is None:
                times["preprocess"] = elapsed_ms(tic)
                return self._lost(index, timestamp, prediction, (f"unusable frame: {exc}",), times)
        times["preprocess"] = elapsed_ms(tic)
        if not self.model_based and not self._window:
            try:
                return self._start(index, timestamp, prepared, times)
            except SpaceposeError as exc:  # no keyframe from it (all on a line): the next may
                return self._lost(index, timestamp, prediction, (f"unusable frame: {exc}",), times)

        checked: Checked = (None, "lost", ("no prior pose",))
        if prediction is not None:
            tic = time.perf_counter()
            T, reach = prediction.T_sensor_target, wide_gate(self._context(), prediction)
            prepared = self._frames.cut(prepared, self._fine.reference(), prediction, reach)
            if self._support is not None:
                prepared = self._support.remove(
                    prepared, self._fine.reference(), T, timestamp, reach
                )
            first_pass = first_pass_gate(self._context(), prediction)
            checked = self._fine.register(prepared, T, first_pass, prediction)
            prepared, checked = self._fine.split_off_support(
                prepared, checked, timestamp, reach, prediction
            )
            checked = self._fine.close_on_first(prepared, checked, prediction)
            times["fine"] += elapsed_ms(tic)
        relocaliser = self._relocaliser
        coarse = checked[1] == "lost"
        if coarse:
            checked = relocaliser.reinitialise(prepared, prediction, checked, times)
        elif relocaliser.retry_due(checked, health_bounds(self._context(), self.model_based)):
            # Against a model, a frame that leaves much of itself off the model's surface sits
            # in a wrong but stable optimum (a twin turned half a turn, a slide along a wing):
            # a coarse pose is tried, and kept only when it fits.
            retried = relocaliser.reinitialise(prepared, prediction, checked, times)
            coarse, checked = retried is not checked, retried
        if not coarse and relocaliser.twin is not None and checked[0] is not None:
            tic = time.perf_counter()
            checked, coarse = relocaliser.settle_twin(prepared, checked)
            times["fine"] += elapsed_ms(tic)
        estimate, status, reasons = checked
        if status == "lost" or estimate is None:
            return self._lost(index, timestamp, prediction, reasons, times, coarse)
        health = (status, reasons)
        if self._origin is not None:
            noise, points, T = (
                self._registrar.noise,
                prepared.cloud.points,
                estimate.T_sensor_target,
            )
            health = self._origin.assess(points, T, noise.gate, health, self.workers)
            # Noise-free frames measure σ = 0: the gate's third is the scale then.
            sigma = noise.sigma or noise.gate / 3.0
            health = self._handedness.assess(points, T, noise.gate, sigma, health, self.workers)
        return self._accept(index, timestamp, prepared, estimate, prediction, health, coarse, times)

    def track(
        self, frames: Iterable[tuple[PointCloud | ArrayLike | None, float]]
    ) -> list[TrackResult]:
        """Track a sequence of ``(cloud, timestamp)`` pairs; one result per frame, a result a
        later frame revised (:attr:`TrackResult.revises`) replaced."""
        results: list[TrackResult] = []
        for cloud, t in frames:
            results.append(self.track_frame(cloud, t))
            revise_results(results, results[-1])
        return results

    def coarse_pose(self, cloud: PointCloud | ArrayLike) -> NDArray[np.float64] | None:
        """Coarse ``T_sensor_target`` of a frame alone (preprocessing + FPFH + RANSAC against
        the model or the current keyframe), leaving the tracking state untouched.

        Returns None when RANSAC finds no consensus.

        Raises
        ------
        InputError
            No reference yet (model-free before the first frame) or an unusable frame.
        """
        if not self.model_based and not self._window:
            raise InputError("coarse registration needs a model or a first tracked frame")
        prepared = self._preprocess(cloud)
        return self._relocaliser.coarse(prepared)

    def _check_model_size(self, cloud: PointCloud | ArrayLike | None) -> None:
        """Measure :attr:`model_size_ratio` on the first frame with returns, and warn when the
        model is five times the frame's size or more: a model in centimetres lost every frame
        ("RANSAC found no consensus") without a hint. A frame that cannot be read is left to
        the frame's own check."""
        try:
            self.model_size_ratio = model_size_ratio(self._model_cloud.points, cloud)
        except (InputError, TypeError, ValueError):
            return
        if self.model_size_ratio >= 5.0:
            problem = (
                f"the model is {self.model_size_ratio:.3g} times the size of the first frame "
                "(RMS radius): in another unit than the frames (centimetres read as metres are "
                "100 times)?"
            )
            warnings.warn(SpaceposeWarning(problem, self._model_cloud.source), stacklevel=4)

    def _predict(self, timestamp: float) -> Prediction | None:
        fallback = None
        if self._frames.scale is not None:
            r = self._frames.scale.radius
            fallback = (self.config.health.max_motion * r, self.config.health.max_motion)
        return self._motion.predict(timestamp, self._lost_streak, fallback or (0.0, 0.0))

    def _preprocess(
        self, cloud: PointCloud | ArrayLike | None, prediction: Prediction | None = None
    ) -> PreparedCloud:
        slack = 0.0
        if prediction is not None and self._frames.scale is not None:
            # The prediction's own uncertainty at the object's edge (3 σ), or the wide gate's
            # reach while the motion model has no error to show yet.
            slack = wide_gate(self._context(), prediction)
        T = None if prediction is None else prediction.T_sensor_target
        prepared = self._frames.prepare(cloud, T, slack)
        if self._registrar is None:
            self._build_stages()
        return prepared

    def _whole_frame(
        self, cloud: PointCloud | ArrayLike | None, prediction: Prediction | None
    ) -> PreparedCloud | None:
        """Against a model, a frame with nothing usable where the prediction puts the target,
        prepared whole (its nearest object), or None: the model says which pose the object
        has wherever it is (the coarse registration finds it), and a prediction gone wrong
        (a first frame 1 km off, its pose accepted unconfirmed) otherwise cropped every later
        frame to where the target is not. Model-free, the nearest object elsewhere may be
        another one, and nothing tells it from the target."""
        if not self.model_based or prediction is None or self._frames.scale is None:
            return None
        try:
            return self._preprocess(cloud)
        except SpaceposeError:
            return None

    def _follow_scene(
        self,
        cloud: PointCloud | ArrayLike | None,
        timestamp: float,
        prior: tuple[ArrayLike, ArrayLike] | None,
        result: TrackResult,
    ) -> TrackResult:
        """Model-free, while undecided: the whole scene followed beside the nearest object
        (:mod:`spacepose.core.scene_follower`). When the object moves with the scene, the
        scene's tracker, which has followed every frame, carries on as this one."""
        verdict, scene = self._scene.follow((cloud, timestamp, prior), result, self._frames)
        if verdict == "undecided":
            return result
        whole, self._scene = self._scene.scene, None
        self._frames.scene_test = self._frames.last_frame = None
        if verdict == "target":
            return result
        vars(self).update(vars(whole))
        return dataclasses.replace(scene, reasons=(*scene.reasons, SCENE_NOTE))

    def _follow_spare(
        self, cloud: PointCloud | ArrayLike | None, timestamp: float, result: TrackResult
    ) -> TrackResult:
        """Model-free, until a frame after the first is accepted (core.spare_anchor). The
        frame's time counts both trackers'."""
        tic = time.perf_counter()
        fits, jumped = self.fits(result), self.jumped(result)
        needed, adopted = self._spare.follow((cloud, timestamp), result, self._first, fits, jumped)
        if adopted is None:
            self._spare = self._spare if needed else None
            return with_time(result, elapsed_ms(tic))
        spare, spare_result = adopted
        vars(self).update(vars(spare))  # its spare is None: a spare keeps none
        return with_time(spare_result, result.time_ms.get("total", 0.0))
