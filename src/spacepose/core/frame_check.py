"""The health check of a tracked frame, in the tracker's context (docs/methods.md §5.3, §5.4).

:func:`~spacepose.core.health.assess_health` judges one registration against bounds. Here the
bounds follow the data's scale and the motion model's observed error (:func:`health_bounds`),
the first pass's gate follows that error too (:func:`wide_gate`), and a model-free frame
registered onto a keyframe far behind is held back (:func:`check_frame`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from spacepose.core.health import (
    CONDITION,
    HealthBounds,
    Status,
    assess_health,
    normalised_condition,
    pose_disagreement,
    step_size,
)
from spacepose.core.keyframes import FineEstimate, PreparedCloud
from spacepose.core.motion import MotionModel, Prediction
from spacepose.core.scale import DataScale
from spacepose.core.tracker_config import TrackerConfig

# Reason of a frame degraded only because its keyframe is far: it may become the new keyframe.
FAR_KEYFRAME = "keyframe"
# Reason of a model-free frame whose prediction comes from a motion model never yet tested.
UNTESTED_MODEL = "the motion model's error not yet observed to confirm the pose"
# Reason of a frame registered onto a keyframe whose chain left a direction unobserved, or
# passed through a coarse pose that fitted poorly and nothing confirmed.
UNOBSERVED_CHAIN = "keyframe chain through a view the data did not confirm"
# The reason of a frame whose ill-conditioned registration the prediction held (fine_stage).
HELD = "its weakly observed directions held by the motion model's prediction"


@dataclass(frozen=True)
class CheckContext:
    """What a frame is checked against: the tracker's config, the lengths derived from the
    first usable frame, the motion model (its observed error and last poses), and how many
    times the voxel gate the accepted frames' residual noise asks for
    (:attr:`~spacepose.core.residual_noise.ResidualNoise.accepted_factor`)."""

    config: TrackerConfig
    scale: DataScale
    motion: MotionModel
    noise_factor: float = 1.0


def health_bounds(context: CheckContext, model_based: bool) -> HealthBounds:
    """The health bounds at the data's scale, widened by the motion model's observed error
    and the measured residual noise."""
    return HealthBounds.from_scale(
        context.config.health,
        context.scale.voxel,
        context.scale.radius,
        context.motion.model_error(),
        model_based,
        context.noise_factor,
    )


# Least reach of the first pass on a frame the voxel grid hardly thins, in voxels. The fine
# gate is under a voxel (0.83 v, or three residual σ when wider). A voxel centroid of many
# samples moves with the surface by fractions of a sample, but on a frame whose voxel holds
# fewer than two samples (a flash LiDAR at 25 m: 82 mm voxels, the sensor's own spacing) a
# silhouette sample that moved by a sample or more finds no surface within the gate and pulls
# nothing: along face-on surfaces the registration goes no further than the prediction took
# it. Under an accelerating slide the constant-velocity prediction falls short, the
# registration with it, and the motion model's error, measured against those same poses, stays
# small (generated spacecraft at 25 m, methods.md §5.5: 70-210 mm short, 5-10 σ, frames 3-5).
WIDE_PASS_VOXELS = 2.0
# A voxel holds fewer than two samples when its edge is under this many point spacings.
THIN_VOXEL_SPACINGS = 2.0**0.5


def wide_gate(context: CheckContext, prediction: Prediction) -> float:
    """Reach (m) of the prediction: three model-error σ at the radius (KISS-ICP-like), at most
    the largest motion allowed while the velocity is unknown, which is the reach then; 0
    before the error is measured.

    At most: a prediction whose error reaches further than a frame may move knowing no velocity
    at all is no better than none. Frames the tracker followed onto the wrong surfaces give the
    motion model errors of a radius and more; a generated spacecraft at 1.2 m before a wall,
    turning 10° a frame (``random:6``, seed 0), reached 0.44 m on frame 7, its crop took in
    128,000 points of the scene, and its frames 7-11 took 79-558 s each (capped: 0.5-6.4 s)."""
    h, r = context.config.health, context.scale.radius
    if not prediction.velocity_known:
        return h.max_motion * r
    error = context.motion.model_error()
    if error is None:
        return 0.0
    return min(h.model_error_sigmas * (error[0] + r * error[1]), h.max_motion * r)


def first_pass_gate(context: CheckContext, prediction: Prediction) -> float:
    """Gate (m) of the fine registration's first pass: the prediction's reach
    (:func:`wide_gate`); at least :data:`WIDE_PASS_VOXELS` voxels on frames whose voxel holds
    fewer than two samples (:data:`THIN_VOXEL_SPACINGS`), once the motion model's error has
    been measured.

    Not before: the frame after a (re)start carries the first look for a support (methods.md
    §5.8), whose split starts from this registration; a wider pass there pulled the support
    into it (lab mock-up at 25 m before a wall and table, ×3, tumbling 5° a frame: the split
    kept the wrong body, and frames 5-11 followed it ``ok``, 11-23° off)."""
    reach, scale = wide_gate(context, prediction), context.scale
    if not hardly_thinned(scale) or (
        prediction.velocity_known and context.motion.model_error() is None
    ):
        return reach
    return max(reach, WIDE_PASS_VOXELS * scale.voxel)


def hardly_thinned(scale: DataScale) -> bool:
    """Whether the voxel grid hardly thins the frames: a voxel holds fewer than two samples
    (its edge under :data:`THIN_VOXEL_SPACINGS` point spacings; the flash LiDAR at 16-25 m,
    whose voxel is its own spacing). There a registration's cost along a face is a row of
    minima a sample apart (methods.md §5.5)."""
    return scale.voxel < THIN_VOXEL_SPACINGS * scale.spacing


def check_frame(
    estimate: FineEstimate,
    prepared: PreparedCloud,
    prediction: Prediction | None,
    context: CheckContext,
    model_based: bool,
) -> tuple[Status, tuple[str, ...]]:
    """Status and reasons of a frame's fine estimate (``prepared`` is the frame, ``prediction``
    the motion model's or a prior; None when there is none)."""
    c = prepared.centroid
    res = estimate.result
    c_ref = estimate.in_reference(c)
    disagreement = None
    if prediction is not None:
        disagreement = pose_disagreement(estimate.T_sensor_target, prediction.T_sensor_target, c)
    bounds = health_bounds(context, model_based)
    condition = normalised_condition(res.information, c_ref, prepared.radius)
    if estimate.held or estimate.degeneracy is not None:
        # Its weak directions are the prediction's, or widened as the surfaces leave them free
        # (a cylinder's turn about its axis: a rocket body seen from the side was lost frame
        # after frame at a condition of 1.9e4): degraded, not lost.
        condition = min(condition, bounds.lost_condition)
    status, reasons = assess_health(
        res.fitness,
        res.inlier_rmse,
        condition,
        estimate.own_covariance,
        c,
        disagreement,
        bounds,
        velocity_known=prediction is not None and prediction.velocity_known,
        surface_step=step_size(estimate.surface_step, c_ref),
        model_reference=model_based,
        structure=estimate.structure,
        influence=estimate.influence,
    )
    if estimate.held and status != "lost":
        reasons = (*reasons, HELD)
    free = estimate.degeneracy
    if free is not None and status != "lost":
        # The reason starts as the fine condition's does: the keyframe policy takes either
        # for a slide the data could not see.
        names = ", ".join(free.names()) or "every direction"
        reasons = (
            *reasons,
            f"{CONDITION} of the coarse surfaces {free.condition:.3g} > {free.bound:.3g}: "
            f"{names} unconstrained",
        )
        status = "degraded"
    scale = context.scale
    if scale.surfaceless and status != "lost":
        # Random points filling a volume register onto anything at a σ of their count: eight
        # frames of a uniform cube were ok 11-14 σ off.
        reasons = (
            *reasons,
            f"no surface: ranges along neighbouring rays spread {1e3 * scale.noise:.1f} mm, as "
            f"the whole first frame's {1e3 * (scale.range_spread or 0.0):.1f} mm",
        )
        status = "degraded"
    if status == "ok" and not model_based and estimate.reference.unobserved:
        return "degraded", (UNOBSERVED_CHAIN,)
    if status == "ok" and not model_based and not context.motion.tested:
        # The first velocity (of the run, or after a coarse restart) is one registered step
        # that nothing confirmed: a registration that stops short of the true motion (a turning
        # target on a table that only slides) stops short again by as much, and agrees with it.
        # Once the model has predicted a frame its error is measured and sets the bounds
        # (seed-0 robustness grid: the 3 false ok frames of the clean cells, and 18 of the 63
        # in all, were third frames).
        return "degraded", (UNTESTED_MODEL,)
    if status == "ok" and not model_based:
        # A keyframe far behind (none promoted for a while: the frames were degraded) is a
        # reference whose registration can lock onto a wrong but plausible overlap.
        kc, f = context.config.keyframe, context.config.health.max_reference_factor
        dt, dr = pose_disagreement(estimate.T_sensor_target, estimate.reference.T_ref_target, c)
        # Far beyond the promotion thresholds, or beyond the target's own last step when it
        # moves more than those in one frame (a 10°-a-frame tumble: every frame promoted).
        step_t, step_r = _last_step(context.motion, c)
        far_t = f * max(kc.max_translation * context.scale.radius, step_t)
        far_r = f * max(kc.max_rotation_deg, step_r)
        if dt > far_t or dr > far_r:
            status = "degraded"
            reasons = (f"{FAR_KEYFRAME} {1e3 * dt:.0f} mm / {dr:.1f} deg away",)
    return status, reasons


def _last_step(motion: MotionModel, point: NDArray[np.float64]) -> tuple[float, float]:
    """(displacement of ``point`` m, rotation deg) between the last two accepted poses."""
    history = motion.history
    if len(history) < 2:
        return 0.0, 0.0
    return pose_disagreement(history[-1][1], history[-2][1], point)
