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
