"""A parametric bootstrap of a tracker's pose errors (docs/methods.md §2.4).

A run has no truth to measure the tracker's errors against, but its own poses are close to it
(at 25 m the model-based tracker's are within 0.01–0.02°). Rendering the target's mesh at those
poses with the run's sensor gives frames whose truth is known and whose views are the run's;
tracking them against the same model gives errors of the kind the run's poses carry, and their
batch statistic (:mod:`spacepose.core.pose_noise`) the factor the covariance needs; their
constant part, in the sensor's frame and in the target's, is the bias the poses carry, which a
filter would take for the target's position and its centre of mass. What the simulator does
not model (a real sensor's biases, a mesh unlike the target) it cannot show.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from numpy.typing import ArrayLike

from spacepose.core.cloud import PointCloud
from spacepose.core.pose_noise import (
    BATCH_FRAMES,
    MIN_BATCHES,
    PoseNoiseScale,
    as_numbers,
    batch_ratios,
    gross_failures,
    pose_noise_scale,
    target_origin_whitened,
    translation_bias,
    whitened_errors,
)
from spacepose.core.sim.scenarios import OrbitConfig
from spacepose.core.sim.sensors import SensorConfig
from spacepose.core.sim.simulation import Simulation
from spacepose.core.sim.targets import Target
from spacepose.core.tracker import Tracker
from spacepose.core.tracker_config import TrackerConfig
from spacepose.errors import ConfigError, InputError


def bootstrap_pose_noise(
    target: Target,
    sensor: SensorConfig,
    timestamps: ArrayLike,
    T_sensor_target: ArrayLike,
    model: PointCloud,
    tracker: TrackerConfig | None = None,
    seed: int = 0,
    batch: int = BATCH_FRAMES,
    min_batches: int = MIN_BATCHES,
    start_covariance: ArrayLike | None = None,
    workers: int = 1,
) -> PoseNoiseScale:
    """Render ``target`` at the given poses with ``sensor``, track the renders against
    ``model`` and measure their constant translation errors in the sensor's and the target's
    frames (``bias``, :func:`~spacepose.core.pose_noise.translation_bias`) and the factor
    their covariance needs once those are taken off (:func:`pose_noise_scale`).

    Parameters
    ----------
    target
        The target's mesh in its model frame (the frame of ``model`` and of the poses).
    sensor
        The run's sensor (its noise model above all).
    timestamps
        (N,) seconds of the poses, increasing.
    T_sensor_target
        (N, 4, 4) poses to render at: a run's tracked poses, in order.
    model
        The tracker's reference, as the run's tracker has it.
    tracker
        The run's tracker config (default: the default tracker).
    seed
        Seed of the renders' noise.
    batch, min_batches
        Frames per batch and the batches needed (:func:`pose_noise_scale`).
    start_covariance
        (6, 6) covariance of the run tracker's first pose: the first render is then tracked
        from its own pose with it as a prior, so that the bootstrap starts right as the run
        did (a wrong coarse start is for the filter's restart to undo, not a noise to
        average); None: a coarse start, as a fresh tracker makes.
    workers
        Tracker threads.

    Raises
    ------
    InputError
        Poses, timestamps or the start covariance not numbers or of the wrong shapes, or fewer
        ``ok`` renders than ``min_batches`` batches.
    """
    t = as_numbers(timestamps, "timestamps")
    T = as_numbers(T_sensor_target, "poses")
    if t.ndim != 1 or T.shape != (len(t), 4, 4):
        raise InputError(f"timestamps of shape {t.shape} for poses of shape {T.shape}")
    start = None if start_covariance is None else as_numbers(start_covariance, "start covariance")
    if start is not None and start.shape != (6, 6):
        raise InputError(f"the start covariance must be (6, 6), got {start.shape}")
    sim = Simulation(
        name="bootstrap",
        config=OrbitConfig(frames=max(len(t), 1), seed=seed, sensor=sensor),
        target=target,
        timestamps=t,
        T_sensor_target=T,
    )
    run = Tracker(tracker or TrackerConfig(), model, workers)
    T_est = np.full_like(T, np.nan)
    C = np.full((len(t), 6, 6), np.nan)
    for k in range(len(t)):
        try:
            frame = sim.frame(k)
        except ConfigError:  # the pose puts nothing in view: no render, no error
            continue
        prior = None if start is None else (T[k], start)
        start = None
        result = run.track_frame(frame.cloud, frame.timestamp, prior)
        if result.status == "ok" and result.covariance is not None:
            T_est[k], C[k] = result.T_sensor_target, result.covariance
    # The constant biases over the frames the factor uses (gross failures and frames without
    # a covariance out): what the filter would take for the position and the centre of mass.
    whitened = whitened_errors(T_est, C, T)
    usable = T_est.copy()
    usable[gross_failures(whitened) | ~np.isfinite(whitened).all(axis=1)] = np.nan
    bias = translation_bias(usable, T, C, batch, min_batches)
    # The filter gets the poses with them taken off (FusionConfig.pose_bias_sensor and
    # pose_bias_body): the factor is what their errors need, not what the biases made them need.
    unbiased = bias.correct(T_est)
    noise = pose_noise_scale(whitened_errors(unbiased, C, T), batch, min_batches)
    # And a factor for the rotation and one for the translation, about the target's origin,
    # where the two are apart (FusionConfig.pose_sigma_scale_translation).
    about_target = target_origin_whitened(unbiased, C, T)
    about_target[gross_failures(whitened)] = np.nan
    ratios, _ = batch_ratios(about_target, batch, min_batches)
    return replace(noise, bias=bias, target_ratios=ratios)
