"""A frame that repeats the one before it (core/repeated_frame.py): a stale buffer is no
measurement while the target moves, and a target standing still may repeat itself."""

from __future__ import annotations

import numpy as np
import pytest

from spacepose.core.cloud import PointCloud
from spacepose.core.metrics import pose_errors
from spacepose.core.repeated_frame import RepeatWatch
from spacepose.core.sim.scenarios import LabConfig, simulate_lab
from spacepose.core.tracker import Tracker

FRAMES = 9


@pytest.fixture(scope="module")
def lab():
    sim = simulate_lab(LabConfig(frames=FRAMES, seed=4))
    return sim, [sim.frame(k).cloud for k in range(FRAMES)]


def test_repeat_watch_tells_equal_points_from_new_ones(rng):
    watch = RepeatWatch()
    frame = rng.normal(size=(5000, 3))
    assert not watch.repeats(frame)
    assert watch.repeats(PointCloud(frame.copy()))  # the same points, another container
    frame += rng.normal(scale=1e-6, size=frame.shape)  # refilled in place by a driver
    assert not watch.repeats(frame)
    assert not watch.repeats(frame[:-1])
    assert not watch.repeats(None)
    assert not watch.repeats(frame[:-1])  # after a frame without data nothing is repeated


def test_a_stale_frame_of_a_moving_target_is_lost_at_the_prediction(lab):
    # The driver hands out frame 5's buffer again as frame 6: registered, it held frame 5's
    # pose, one step (~10 mm, ~1°) behind, and was flagged ok.
    sim, clouds = lab
    clouds = list(clouds)
    clouds[6] = PointCloud(clouds[5].points.copy())
    tracker = Tracker(workers=1)
    results = [tracker.track_frame(c, t) for c, t in zip(clouds, sim.timestamps, strict=True)]
    stale = results[6]
    assert stale.status == "lost"
    assert any("repeated (stale) frame" in r for r in stale.reasons)
    poses = np.stack([r.T_sensor_target for r in results])
    truth = sim.T_sensor_target @ np.linalg.inv(sim.T_sensor_target[0])
    dt, dr = pose_errors(poses, truth)
    # The prediction stands in for it, and the frames after it track on.
    assert np.linalg.norm(dt[6]) < 3e-3 and np.degrees(np.linalg.norm(dr[6])) < 0.3
    assert all(r.status != "lost" for r in results[7:])
    assert np.abs(dt[7:]).max() < 3e-3


def test_a_target_standing_still_may_repeat_itself(lab):
    # A noise-free render of a still target gives the same points every frame: a measurement
    # of no motion, not a stale one.
    _, clouds = lab
    tracker = Tracker(workers=1)
    results = [tracker.track_frame(PointCloud(clouds[0].points.copy()), float(t)) for t in range(5)]
    assert all(r.status != "lost" for r in results)
    assert not any("repeated" in r for res in results for r in res.reasons)
    # Within the keyframe's sampling of the same points (a finer voxel than the frame's).
    dt, dr = pose_errors(
        np.stack([r.T_sensor_target for r in results]), np.tile(np.eye(4), (5, 1, 1))
    )
    assert np.abs(dt).max() < 1e-3 and np.degrees(np.abs(dr).max()) < 0.05
