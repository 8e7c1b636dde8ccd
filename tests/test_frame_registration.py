"""The registrar's noise model off the white-noise sensor (core/frame_registration.py): frames
without noise, and noise a camera's filter shares between neighbouring pixels."""

from __future__ import annotations

import numpy as np

from spacepose.core import se3
from spacepose.core.sim import Simulation, grid_scenario, simulate
from spacepose.core.track_result import TrackResult
from spacepose.core.tracker import Tracker, TrackerConfig
from spacepose.tools.experiments.robustness_cells import mesh_path


def _tracked(sim: Simulation, config: TrackerConfig) -> list[TrackResult]:
    """Every frame of ``sim`` tracked by a fresh tracker; none lost, and every ``ok`` frame
    after the first within 3σ of the truth on every axis (left perturbation of
    ``T_sensor_target``, rotation first)."""
    tracker = Tracker(config, workers=2)
    results = []
    for k in range(len(sim)):
        frame = sim.frame(k)
        result = tracker.track_frame(frame.cloud, frame.timestamp)
        assert result.status != "lost"
        if result.status == "ok" and k > 0:
            T_true = sim.T_sensor_target[k] @ se3.invert(sim.T_sensor_target[0])
            error = se3.log(result.T_sensor_target @ se3.invert(T_true))
            assert np.all(np.abs(error) <= 3.0 * np.sqrt(np.diag(result.covariance)))
        results.append(result)
    return results


def _ok_after_the_first(results: list[TrackResult]) -> int:
    return sum(r.status == "ok" for r in results[1:])


def _structure_flags(results: list[TrackResult]) -> int:
    return sum(any(x.startswith("residual structure") for x in r.reasons) for r in results)


def test_noise_free_frames_are_ok_and_within_their_sigma():
    """A renderer's depth has no noise: the lab mock-up at 1.2 m, noise 0. Registering voxel
    centroids onto another view's surface then leaves residuals of the sampling alone, 0.002-0.02
    of the voxel, and over a σ that small every frame's residual structure read 20-80 ("part of
    the cloud fits another motion") and its covariance was widened by it: not one frame after
    the first was ``ok``. With the spread floored at the sampling's own (a twentieth of the
    voxel), the frames the motion model confirms are ``ok``, each within 3σ."""
    config = grid_scenario(target=mesh_path("lab"), range_m=1.2, noise_scale=0.0, frames=10)
    assert _ok_after_the_first(_tracked(simulate(config), TrackerConfig())) >= 5


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
    assert _structure_flags(_tracked(sim, TrackerConfig())) >= 8
    shared = _tracked(sim, TrackerConfig(health={"ok_shared_structure": 1.0}))
    assert _structure_flags(shared) == 0
    assert _ok_after_the_first(shared) >= 5
