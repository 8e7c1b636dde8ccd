"""The tracker's fine registration of a frame and its health check (docs/methods.md §5.3, §5.5).

A frame is registered from an initial ``T_sensor_target`` onto the model (with a prediction, the
faces it turns to the sensor) or, model-free, onto the keyframe window
(:mod:`spacepose.core.window_registration`), after a wide first pass when the motion model has
been wrong by more than the fine gate; the estimate is then checked
(:func:`~spacepose.core.frame_check.check_frame`). Model-free, a support moving otherwise is
split off the target here (methods.md §5.8; the look itself is :mod:`spacepose.core.support`).

:class:`FineStage` holds the tracker's own objects, built with them once the first usable frame
has set every length: a tracker that adopts another's state (the whole scene's,
:mod:`spacepose.core.scene_follower`) adopts its fine stage with it.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray
from scipy.stats import chi2

from spacepose.core import se3, window_registration
from spacepose.core.basin_probe import (
    BETTER_BY,
    PROBE_ROUNDS,
    PROBE_VOXELS,
    probe_starts,
    truncated_cost,
)
from spacepose.core.cloud import PointCloud
from spacepose.core.degeneracy import CoarseSurface, surface_degeneracy
from spacepose.core.frame_check import (
    FAR_KEYFRAME,
    UNOBSERVED_CHAIN,
    CheckContext,
    check_frame,
    hardly_thinned,
    health_bounds,
)
from spacepose.core.frame_preparation import FramePreparer
from spacepose.core.frame_registration import FrameRegistrar
from spacepose.core.health import Status, normalised_condition
from spacepose.core.keyframe_window import KeyframeWindow
from spacepose.core.keyframes import FineEstimate, Keyframe, PreparedCloud
from spacepose.core.motion import MotionModel, Prediction
from spacepose.core.relocalise import Checked
from spacepose.core.support import SupportSeparation
from spacepose.core.tracker_config import TrackerConfig
from spacepose.errors import SpaceposeError

# A closure onto the first keyframe must agree with the chain's pose within the chain's own
# covariance (its drift included) at this probability (χ²₆), or it is not made.
_CLOSURE_PROBABILITY = 0.999
# A closure may leave off the first keyframe at most this many times the share of the frame
# the chain left off its keyframe, that share counted as at least the floor.
_CLOSURE_UNEXPLAINED = 2.0
_UNEXPLAINED_FLOOR = 0.1


@dataclass(frozen=True, eq=False)
class FineStage:
    """Fine registration of a frame, its health check, and a support split off.

    Frozen: it holds the tracker's own objects and never rebinds them (it changes the window
    and the frames' region in place), so it stays the state of the tracker that built it.

    Attributes
    ----------
    config
        The tracker's config (method, keyframe-graph weighting, health bounds).
    frames
        The tracker's frame preparation: the data's scale, the model's visible faces, the
        target's region (narrowed when a support is split off).
    registrar
        The tracker's registrar onto one reference.
    window
        The keyframe window (model-free: the references; restarted when a support is split off).
    motion
        The motion model: its observed error widens the health bounds.
    model, sensor_model
        The prepared model, and the model cloud :meth:`FramePreparer.visible_model` culls at
        every pose (:meth:`FramePreparer.sensor_model`); None, None model-free.
    support
        Model-free: the separation of a support moving otherwise; None against a model.
    """

    config: TrackerConfig
    frames: FramePreparer
    registrar: FrameRegistrar
    window: KeyframeWindow
    motion: MotionModel
    model: Keyframe | None
    sensor_model: PointCloud | None
    support: SupportSeparation | None

    @property
    def model_based(self) -> bool:
        return self.model is not None

    def reference(self) -> Keyframe:
        """The current registration reference: the model, or the latest keyframe."""
        return self.model if self.model is not None else self.window.latest

    def register(
        self,
        prepared: PreparedCloud,
        T_init: NDArray[np.float64],
        wide_gate: float,
        prediction: Prediction | None,
    ) -> Checked:
        """Fine registration from ``T_init`` (after a first pass at ``wide_gate`` m when that
        is well above the fine gate), then the health check against ``prediction``.

        With a prediction, a model is registered onto by the faces it turns to the sensor at
        ``T_init`` only (:meth:`FramePreparer.visible_model`), its residuals weighed by a
        redescending kernel: the frame holds returns the model lacks (flying pixels between
        parts, a one-sided panel seen from behind), which within the gate pull the pose. A pose
        without a prediction (a coarse pose, a twin) is tested against the whole model, whose
        hidden parts tell it wrong, without the kernel: from a coarse pose it settled on a
        wrong pose that fitted 0.46 of the points (orbit run, seed 2).
        """
        try:
            ref = self.reference()
            tracking_model = self.model is not None and prediction is not None
            if tracking_model:
                ref = self.frames.visible_model(self.sensor_model, T_init)
            elif not self.model_based:
                self.window.confirm(lambda kf: self._fitness_onto(prepared, kf, T_init, wide_gate))
                ref = self.reference()
            T_init = self.registrar.approach(prepared, ref, T_init, wide_gate)
            estimate = self._fine(prepared, ref, T_init, tracking_model)
            if self._probed(prediction):
                estimate = self._deepest_basin(prepared, ref, estimate, prediction)
            shifted = self.frames.shifted_source(prepared)
            if shifted is not None:
                estimate = window_registration.with_grid_spread(
                    self.registrar, shifted, estimate, tracking_model
                )
            estimate = self._free_directions(estimate, prepared)
            estimate = self._held_by_prediction(estimate, prepared, prediction)
        except SpaceposeError as exc:
            return None, "lost", (f"fine registration failed: {exc}",)
        return (estimate, *self.check(estimate, prepared, prediction))

    def _fitness_onto(
        self, prepared: PreparedCloud, kf: Keyframe, T_init: NDArray[np.float64], wide_gate: float
    ) -> float:
        """The frame's fitness registered onto ``kf`` from ``T_init`` (0 when it fails)."""
        try:
            T = self.registrar.approach(prepared, kf, T_init, wide_gate)
            return self.registrar.register(prepared, kf, T, measure=False).result.fitness
        except SpaceposeError:
            return 0.0

    def _fine(
        self,
        prepared: PreparedCloud,
        ref: Keyframe,
        T_init: NDArray[np.float64],
        robust: bool = False,
    ) -> FineEstimate:
        """Fine registration of the frame from the initial ``T_sensor_target`` onto ``ref``
        (model-free J-ICP and keyframe graph: onto the keyframe window it ends); ``robust``:
        a model's, weighed by a redescending kernel."""
        cfg = self.config
        if cfg.method not in ("jicp", "keyframe") or self.model_based:
            return window_registration.single(self.registrar, prepared, ref, T_init, robust)
        references = self.window.references()
        if cfg.method == "jicp":
            return window_registration.li_step(self.registrar, prepared, references, T_init)
        equal = cfg.keyframe_graph.weighting == "equal"
        return window_registration.joint(self.registrar, prepared, references, T_init, equal)

    def _probed(self, prediction: Prediction | None) -> bool:
        """Whether the frame's basin is probed (:meth:`_deepest_basin`): model-free, on frames
        the voxel grid hardly thins (:func:`~spacepose.core.frame_check.hardly_thinned`), until
        the motion model's error is known (:attr:`~spacepose.core.motion.MotionModel.settled`).
        A denser frame's voxels average many samples each, and its cost along a face is
        smooth. A prediction whose error has been measured on a frame or two confirms little: a
        registration that stays with it keeps that error small (the constant-velocity
        prediction of a motion that speeds up, followed one sample along a face a frame)."""
        settled = prediction is not None and prediction.velocity_known and self.motion.settled
        return not (self.model_based or settled) and hardly_thinned(self.frames.scale)

    def _deepest_basin(
        self,
        prepared: PreparedCloud,
        ref: Keyframe,
        estimate: FineEstimate,
        prediction: Prediction | None,
    ) -> FineEstimate:
        """Model-free, on a sparse frame no settled prediction confirms: the estimate, or the
        registration from a probe start
        (:func:`~spacepose.core.basin_probe.probe_starts`,
        :data:`~spacepose.core.basin_probe.PROBE_VOXELS` voxels away) that ends lower on the
        truncated cost by more than :data:`~spacepose.core.basin_probe.BETTER_BY` (a slide
        along a face into a neighbouring minimum; methods.md §5.5). The probes' own residual
        measurements are dropped.

        With no tested prediction (none, no velocity, or the motion model's error not yet
        measured) the cost is judged against the window's oldest keyframe: the latest may carry
        the slide itself. With one, a start must end lower against every keyframe of the
        window: a frame turned far from one keyframe can lower its cost there alone by pairing
        the points that keyframe lacks with other surfaces.
        """
        confirmed = prediction is not None and prediction.velocity_known and self.motion.tested
        cost = self._basin_cost(prepared, confirmed)
        best, best_cost = estimate, cost(estimate.T_sensor_target)
        measured = self.registrar.set_aside()
        step, centroid = PROBE_VOXELS * self.frames.scale.voxel, prepared.centroid
        try:
            for _ in range(PROBE_ROUNDS):
                around, bar = best, best_cost - BETTER_BY
                starts = probe_starts(around.T_sensor_target, around.covariance, centroid, step)
                for start in starts:
                    try:
                        probe = self._fine(prepared, ref, start)
                    except SpaceposeError:
                        continue
                    probe_cost = cost(probe.T_sensor_target)
                    if np.all(probe_cost < np.minimum(bar, best_cost)):
                        best, best_cost = probe, probe_cost
                if best is around:
                    break
        finally:
            # The frame's residual noise stays that of its first registration.
            self.registrar.put_back(measured)
        return best

    def _basin_cost(
        self, prepared: PreparedCloud, every_keyframe: bool
    ) -> Callable[[NDArray[np.float64]], NDArray[np.float64]]:
        """The frame's :func:`~spacepose.core.basin_probe.truncated_cost` at a
        ``T_sensor_target``, against each keyframe of the window (``every_keyframe``) or its
        oldest alone."""
        noise, workers = self.registrar.noise, self.registrar.workers
        # Noise-free frames measure σ = 0: the gate's third is the scale then.
        scales = (noise.gate, noise.sigma if noise.sigma else noise.gate / 3.0, workers)
        references = self.window.references()
        judges = [
            (judge.T_ref_target, self.registrar.as_target(judge.registration_target))
            for judge in (references if every_keyframe else references[:1])
        ]
        points = prepared.cloud.points

        def cost(T_sensor_target: NDArray[np.float64]) -> NDArray[np.float64]:
            T_target_sensor = se3.invert(T_sensor_target)
            return np.array(
                [
                    truncated_cost(target, points, T_ref_target @ T_target_sensor, *scales)
                    for T_ref_target, target in judges
                ]
            )

        return cost

    def _free_directions(self, estimate: FineEstimate, prepared: PreparedCloud) -> FineEstimate:
        """The estimate with its covariance widened along the directions the surfaces leave
        free (:func:`~spacepose.core.degeneracy.surface_degeneracy`, judged against the model or
        the estimate's keyframe at a coarse scale, where the normals' noise cannot pass for
        shape). A plate slid along itself fits a keyframe with a condition of about 500 at
        the fine voxel, under the ok bound; a sphere and a cylinder scored 559 and 752 with the
        former coarse check. All three are infinite now, while the grid's targets score at
        most 480 (lab mock-up, 99th percentile) and 7.2e3 (satellite_panels at 25 m, seed 0;
        methods.md §5.3)."""
        ref = self.model if self.model is not None else estimate.reference
        workers = self.registrar.workers
        if ref.coarse is None:
            target = ref.registration_target.cloud
            ref.coarse = CoarseSurface.of(target, ref.prepared.radius, workers)
        T_ref_k = estimate.result.T_target_source
        found = surface_degeneracy(
            prepared.cloud.points, ref.coarse, T_ref_k, prepared.radius, self.config.health, workers
        )
        if not found.degenerate:
            return estimate
        # Widened in the reference frame, carried into frame k's sensor frame as the
        # registration's own covariance is (window_registration.single).
        Ad = se3.adjoint(se3.invert(T_ref_k))
        wide = Ad @ found.widen(np.zeros((6, 6))) @ Ad.T
        return replace(
            estimate,
            covariance=estimate.covariance + wide,
            own_covariance=estimate.own_covariance + wide,
            degeneracy=found,
        )

    def _held_by_prediction(
        self, estimate: FineEstimate, prepared: PreparedCloud, prediction: Prediction | None
    ) -> FineEstimate:
        """The estimate fused with a constant-velocity ``prediction`` as a prior when its own
        registration is ill-conditioned (condition above the health's ok bound): along the
        directions the surfaces hardly see, the registration's pose is where noise and edges
        slid it, and the prediction is the better guess; along the others the registration's
        information dominates. Left perturbations in the sensor frame, the prediction's
        covariance taken ``model_error_sigmas`` wider (its error is measured on
        a few frames, and grows under acceleration: at 1σ the prior dragged accelerating runs
        at 25 m along the constant velocity, 195 -> 549 mm; methods.md §5.3)."""
        if prediction is None or not prediction.velocity_known:
            return estimate
        health, c = self.config.health, prepared.centroid
        info = estimate.result.information
        if normalised_condition(info, estimate.in_reference(c), prepared.radius) <= (
            health.ok_condition
        ):
            return estimate
        own = estimate.own_covariance
        # Covariance form (the Kalman gain): a prior given from outside may be singular (a
        # position known, an attitude not), which the information form cannot invert.
        spread = own + health.model_error_sigmas**2 * prediction.covariance
        gain = own @ np.linalg.pinv(spread, hermitian=True)
        fused_cov = own - gain @ own
        fused_cov = 0.5 * (fused_cov + fused_cov.T)
        towards = se3.log(prediction.T_sensor_target @ se3.invert(estimate.T_sensor_target))
        T = se3.exp(gain @ towards) @ estimate.T_sensor_target
        return replace(
            estimate,
            T_sensor_target=T,
            covariance=estimate.covariance - own + fused_cov,
            own_covariance=fused_cov,
            held=True,
        )

    def check(
        self, estimate: FineEstimate, prepared: PreparedCloud, prediction: Prediction | None
    ) -> tuple[Status, tuple[str, ...]]:
        """Status and reasons of a frame's fine estimate against ``prediction``."""
        return check_frame(estimate, prepared, prediction, self._context(), self.model_based)

    def _context(self) -> CheckContext:
        noise = self.registrar.noise.accepted_factor
        return CheckContext(self.config, self.frames.scale, self.motion, noise)

    def close_on_first(
        self, prepared: PreparedCloud, checked: Checked, prediction: Prediction | None
    ) -> Checked:
        """Model-free: a frame held back only because its keyframe chain passed through a view
        that left a direction unobserved (methods.md §5.4), registered onto the first keyframe,
        the one reference no slide has touched. When that registration passes every check of
        its own (its distance from the first keyframe aside) and agrees with the chain's pose
        within their summed covariances (the chain's drift included), it replaces the chain's
        and the window restarts at the first keyframe: the frame's keyframe, and the chain
        after it, rest on the first view again. Otherwise nothing changes.

        A tumbling target shows its first faces again; without this a chain once marked stayed
        marked (orbit run at 25 m, seed 1: no frame `ok` after frame 38 of 600).
        """
        estimate, _, reasons = checked
        first = None if self.support is None else self.support.first
        if estimate is None or first is None or reasons != (UNOBSERVED_CHAIN,):
            return checked
        if self.config.method != "keyframe" or estimate.reference is first:
            return checked
        # A closure that does not stand leaves the window, and the frame's residual noise and
        # design effect, as the chain's registration left them.
        saved, measured = self.window.snapshot(), self.registrar.set_aside()
        self.window.restart(first)
        closed = self.register(prepared, estimate.T_sensor_target, 0.0, prediction)
        # Far from the first keyframe is the usual case here: such a frame passed every check
        # of its own registration, and becomes the next keyframe (KeyframeWindow.update).
        own_checks = all(r.startswith(FAR_KEYFRAME) for r in closed[2])
        if (
            closed[1] != "lost"
            and own_checks
            and _explains_as_much(closed[0], estimate)
            and _agree(closed[0], estimate)
        ):
            return closed
        self.window.restore(saved)
        self.registrar.put_back(measured)
        return checked

    def split_off_support(
        self,
        prepared: PreparedCloud,
        checked: Checked,
        timestamp: float,
        reach: float,
        prediction: Prediction | None,
    ) -> tuple[PreparedCloud, Checked]:
        """Model-free: the frame's look for a support moving otherwise
        (:meth:`SupportSeparation.look`); once one is split off, the target's part of the frame
        registered onto the target's part of the first keyframe, from the split's pose and from
        ``prediction``'s (first pass at ``reach`` m), the end lower on the truncated cost by
        :data:`~spacepose.core.basin_probe.BETTER_BY` kept.

        The split's pose is the compromise's, moved by the target's fitted motion, and a
        target's registration from it keeps the compromise's error along a direction its faces
        hold weakly: a generated spacecraft 3 m before a wall and turntable, turning 10° a
        frame, stayed 64 mm along its long faces on its second frame (fitness 0.94, 0.02°),
        where from the prediction it ends 9 mm off; every later frame inherited the slide,
        ``ok`` at 8-11 σ."""
        if self.support is None:
            return prepared, checked
        bounds = health_bounds(self._context(), False)
        bound = (bounds.ok_structure, bounds.ok_shared_structure)
        look = self.support.look(prepared, checked, bound, timestamp, reach)
        if look.found is None:
            return prepared, look.checked
        prepared, T_init = look.found
        # The window's later keyframes hold the support and the compromise's error; the crop
        # follows the target alone.
        self.window.restart(self.support.first)
        self.frames.region = self.support.target_region(self.frames.region)
        split = self.register(prepared, T_init, 0.0, None)
        if prediction is None:
            return prepared, split
        measured = self.registrar.set_aside()
        fresh = self.register(prepared, prediction.T_sensor_target, reach, None)
        if split[0] is None or (fresh[0] is not None and self._deeper(prepared, fresh, split)):
            return prepared, fresh
        self.registrar.put_back(measured)
        return prepared, split

    def _deeper(self, prepared: PreparedCloud, a: Checked, b: Checked) -> bool:
        """Whether estimate ``a`` ends lower than ``b`` on the truncated cost against the
        window's oldest keyframe by more than :data:`~spacepose.core.basin_probe.BETTER_BY`."""
        cost = self._basin_cost(prepared, every_keyframe=False)
        return bool(cost(a[0].T_sensor_target)[0] < cost(b[0].T_sensor_target)[0] - BETTER_BY)


def _explains_as_much(closed: FineEstimate, chained: FineEstimate) -> bool:
    """Whether a closure leaves off the first keyframe at most :data:`_CLOSURE_UNEXPLAINED`
    times the share of the frame's points the chain's registration left off its own (that
    share taken as at least :data:`_UNEXPLAINED_FLOOR`). A first keyframe that shares too
    little of the view cannot decide the pose, and a closure started at the chain's pose then
    stops where the chain has slid: a cylinder bus slid 24° about its axis while seen side-on
    closed 82° from the first view at a fitness of 0.62 against the chain's 0.86, and two
    frames after it were ``ok`` at 20σ. The orbit run's closure 130° away: 0.61 against 0.67."""
    unexplained = max(1.0 - chained.result.fitness, _UNEXPLAINED_FLOOR)
    return 1.0 - closed.result.fitness <= _CLOSURE_UNEXPLAINED * unexplained


def _agree(closed: FineEstimate, chained: FineEstimate) -> bool:
    """Whether two estimates of one frame's pose agree within their summed covariances
    (left perturbations in the frame's sensor frame; χ²₆ at ``_CLOSURE_PROBABILITY``)."""
    xi = se3.log(chained.T_sensor_target @ se3.invert(closed.T_sensor_target))
    cov = closed.covariance + chained.covariance
    statistic = float(xi @ np.linalg.pinv(cov, hermitian=True) @ xi)
    return statistic <= chi2.ppf(_CLOSURE_PROBABILITY, 6)
