"""What the tracker reports: a :class:`TrackResult` per frame, a :class:`TrackingOutput` per run."""

from __future__ import annotations

import dataclasses
import time
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from spacepose.core.health import Status, normalised_condition
from spacepose.core.keyframes import FineEstimate, PreparedCloud
from spacepose.core.motion import Prediction
from spacepose.core.trajectory import Trajectory

# Timed parts of a step; "other" is the health checks and state bookkeeping, so that the first
# four add up to "total".
STAGES: tuple[str, ...] = ("preprocess", "coarse", "fine", "other", "total")


def elapsed_ms(tic: float) -> float:
    """Milliseconds since ``tic`` (a :func:`time.perf_counter` reading)."""
    return 1e3 * (time.perf_counter() - tic)


def close_times(times: dict[str, float], t_start: float) -> None:
    """Set ``total`` and ``other`` (the time no named stage took) of a step's timings (ms)."""
    times["total"] = elapsed_ms(t_start)
    named = sum(times.get(s, 0.0) for s in ("preprocess", "coarse", "fine"))
    times["other"] = max(times["total"] - named, 0.0)


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
        (4, 4) pose; model-free: ``T_k0``. For a lost frame, the motion model's prediction.
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
        Wall time per stage (see ``STAGES``).
    reference_index
        Frame index of the keyframe the frame was registered to (-1: the model or none).
    coarse
        Whether coarse registration ran for this frame.
    keyframe
        Whether the frame became a keyframe.
    structure
        Residual structure of the registration onto its latest reference
        (:func:`~spacepose.core.residual_structure.residual_structure`: 1 for white residuals;
        model-free, above ``health.ok_structure`` the frame is degraded); NaN where it was not
        measured (against a model, a first or a lost frame).
    revises
        Results that replace those reported for earlier frames (their ``index``): model-free,
        when a first frame no later frame confirmed gives way to a later one as the target
        frame (:mod:`spacepose.core.spare_anchor`); empty otherwise.
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
    structure: float = float("nan")
    revises: tuple[TrackResult, ...] = ()

    @property
    def sigma(self) -> NDArray[np.float64]:
        """(6,) 1-σ of (rx, ry, rz) in rad and (tx, ty, tz) in m."""
        return np.sqrt(np.clip(np.diag(self.covariance), 0.0, None))


@dataclass(frozen=True)
class TrackingOutput:
    """A tracked sequence: the trajectory (one pose per frame) and the per-frame results."""

    trajectory: Trajectory
    results: list[TrackResult]


def with_time(result: TrackResult, ms: float) -> TrackResult:
    """``result`` with ``ms`` more of other work in its step (``other`` and ``total``)."""
    times = dict(result.time_ms)
    for stage in ("other", "total"):
        times[stage] = times.get(stage, 0.0) + ms
    return dataclasses.replace(result, time_ms=times)


def revise_results(results: list[TrackResult], latest: TrackResult) -> None:
    """Replace in ``results`` those of the frames ``latest`` revises (matched by index)."""
    where = {r.index: k for k, r in enumerate(results)} if latest.revises else {}
    for revised in latest.revises:
        if revised.index in where:
            results[where[revised.index]] = revised


def lost_result(
    index: int,
    timestamp: float,
    prediction: Prediction | None,
    reasons: tuple[str, ...],
    times: dict[str, float],
    coarse: bool = False,
) -> TrackResult:
    """A lost frame's result: the predicted pose and covariance, or, with nothing known, the
    identity with infinite uncertainty."""
    if prediction is None:
        T, cov = np.eye(4), np.diag(np.full(6, np.inf))
    else:
        T, cov = prediction.T_sensor_target, prediction.covariance
    return TrackResult(index, timestamp, T, cov, "lost", reasons, time_ms=times, coarse=coarse)


def accepted_result(
    index: int,
    timestamp: float,
    estimate: FineEstimate,
    prepared: PreparedCloud,
    health: tuple[Status, tuple[str, ...]],
    times: dict[str, float],
    coarse: bool,
    keyframe: bool,
) -> TrackResult:
    """An accepted frame's result (``ok`` or ``degraded``): its fine estimate, the fit of its
    registration and its health."""
    res = estimate.result
    return TrackResult(
        index,
        timestamp,
        estimate.T_sensor_target,
        estimate.covariance,
        *health,
        fitness=res.fitness,
        rmse=res.inlier_rmse,
        iterations=res.iterations,
        condition_number=normalised_condition(
            res.information, estimate.in_reference(prepared.centroid), prepared.radius
        ),
        time_ms=times,
        reference_index=estimate.reference.index,
        coarse=coarse,
        keyframe=keyframe,
        structure=float("nan") if estimate.structure is None else estimate.structure.within,
    )


def first_result(index: int, timestamp: float, times: dict[str, float]) -> TrackResult:
    """Model-free, the first usable frame's result: it defines the target frame (pose identity,
    no uncertainty) and is the first keyframe."""
    return TrackResult(
        index,
        timestamp,
        np.eye(4),
        np.zeros((6, 6)),
        "ok",
        time_ms=times,
        reference_index=index,
        keyframe=True,
        fitness=1.0,
        rmse=0.0,
    )
