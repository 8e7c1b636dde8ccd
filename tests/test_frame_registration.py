"""The registrar's noise model on frames without noise (core/frame_registration.py)."""

from __future__ import annotations

import numpy as np

from spacepose.core import se3
from spacepose.core.sim import grid_scenario, simulate
from spacepose.core.tracker import Tracker, TrackerConfig
from spacepose.tools.experiments.robustness_cells import mesh_path


def test_noise_free_frames_are_ok_and_within_their_sigma():
    """A renderer's depth has no noise: the lab mock-up at 1.2 m, noise 0. Registering voxel
    centroids onto another view's surface then leaves residuals of the sampling alone, 0.002-0.02
    of the voxel, and over a σ that small every frame's residual structure read 20-80 ("part of
    the cloud fits another motion") and its covariance was widened by it: not one frame after
    the first was ``ok``. With the spread floored at the sampling's own (a twentieth of the
    voxel), the frames the motion model confirms are ``ok``, each within 3σ of the truth on every
    axis (left perturbation of ``T_sensor_target``, rotation first)."""
    config = grid_scenario(target=mesh_path("lab"), range_m=1.2, noise_scale=0.0, frames=10)
    sim = simulate(config)
    tracker = Tracker(TrackerConfig(), workers=2)
    ok = 0
    for k in range(len(sim)):
        frame = sim.frame(k)
        result = tracker.track_frame(frame.cloud, frame.timestamp)
        assert result.status != "lost"
        if result.status != "ok" or k == 0:
            continue
        ok += 1
        T_true = sim.T_sensor_target[k] @ se3.invert(sim.T_sensor_target[0])
        error = se3.log(result.T_sensor_target @ se3.invert(T_true))
        assert np.all(np.abs(error) <= 3.0 * np.sqrt(np.diag(result.covariance)))
    assert ok >= 5


def test_a_camera_that_filters_its_depth_is_no_second_motion_with_the_shared_bound():
    """Range noise shared between pixels over a Gaussian of 2 pixels (a ToF camera's spatial
    filter), the lab mock-up at 1.2 m: each cell's residual mean strays 4-11 times white
    noise's, and by default most frames are `degraded` ("part of the cloud fits another
    motion"). Neighbouring cells do not share those offsets, as a second motion's parts do:
    with ``health.ok_shared_structure`` set (off by default, methods.md §5.3) that reason is
    gone, and the frames a confirmation can call `ok` are, each within 3σ (the covariance
    still carries the structure's design effect)."""
    config = grid_scenario(target=mesh_path("lab"), range_m=1.2, frames=12)
    config = config.model_copy(
        update={"sensor": config.sensor.model_copy(update={"noise_correlation_px": 2.0})}
    )
    sim = simulate(config)
    frames = [sim.frame(k) for k in range(len(sim))]
    default = Tracker(TrackerConfig(), workers=2)
    flagged = 0
    for frame in frames:
        result = default.track_frame(frame.cloud, frame.timestamp)
        flagged += any(r.startswith("residual structure") for r in result.reasons)
    assert flagged >= 8
    tracker = Tracker(TrackerConfig(health={"ok_shared_structure": 1.0}), workers=2)
    ok = 0
    for k, frame in enumerate(frames):
        result = tracker.track_frame(frame.cloud, frame.timestamp)
        assert result.status != "lost"
        assert not any(r.startswith("residual structure") for r in result.reasons)
        if result.status != "ok" or k == 0:
            continue
        ok += 1
        T_true = sim.T_sensor_target[k] @ se3.invert(sim.T_sensor_target[0])
        error = se3.log(result.T_sensor_target @ se3.invert(T_true))
        assert np.all(np.abs(error) <= 3.0 * np.sqrt(np.diag(result.covariance)))
    assert ok >= 5
