"""The tracker on surfaces that leave its pose partly free (never ``ok``, σ widened there), and
on a model it cannot use."""

from __future__ import annotations

import numpy as np

from spacepose.core.degeneracy import CoarseSurface, surface_degeneracy
from spacepose.core.health import covariance_at
from spacepose.core.sim import LabConfig, simulate
from spacepose.core.tracker import Tracker, TrackerConfig

COARSE = "condition of the coarse surfaces"


def plate_frame(rng: np.random.Generator) -> np.ndarray:
    """A static 1 m square plate 1.5 m ahead, face-on, sampled anew (20,000 points) with 2 mm
    of range noise: nothing on it tells a slide along it or a turn about its normal."""
    uv = rng.uniform(-0.5, 0.5, size=(20_000, 2))
    return np.c_[uv, 1.5 + rng.normal(0.0, 0.002, len(uv))]


def test_a_plate_is_never_ok_and_its_free_directions_get_its_size_as_sigma() -> None:
    """Before the coarse check every frame after the second was ``ok`` with 0.5-3.6 mm of σ
    along the plate while the pose wandered 7 mm along it (the fine condition, 530, was
    under its ok bound 1e3: the normals' noise passed for shape). Now each frame is degraded
    by a condition of about 3.6e7, and the slide and the turn get the plate's size as σ; the
    depth stays as tight and as right as before."""
    rng = np.random.default_rng(0)
    tracker = Tracker(TrackerConfig(), workers=1)
    results = [tracker.track_frame(plate_frame(rng), 0.1 * k) for k in range(8)]
    centre = np.array([0.0, 0.0, 1.5])
    for r in results[1:]:
        assert r.status == "degraded", (r.index, r.status, r.reasons)
        coarse = [x for x in r.reasons if x.startswith(COARSE)]
        assert len(coarse) == 1, r.reasons
        assert "rotation about [0.00 0.00 1.00]" in coarse[0], coarse
        assert coarse[0].count("translation along") == 2, coarse
        sigma = np.sqrt(np.diag(covariance_at(r.covariance, centre)))
        assert np.all(sigma[3:5] > 0.3) and np.degrees(sigma[2]) > 50, sigma
        # What the plate does fix: its depth and tilts, to the registration's own σ.
        assert sigma[5] < 1e-3 and np.all(np.degrees(sigma[:2]) < 0.1), sigma
        # The plate never moved: its centre's depth error, within 3σ (measured 0.84-1.01σ).
        err_z = (r.T_sensor_target @ np.r_[centre, 1.0])[2] - centre[2]
        assert abs(err_z) < 3 * sigma[5], (err_z, sigma[5])


def test_the_lab_target_is_not_flagged() -> None:
    """The lab mock-up on its slide scores 60-100 at the coarse voxel (the bound is 1e4): no
    frame of a short default run is held back by it."""
    sim = simulate(LabConfig(frames=6, seed=0))
    tracker = Tracker(TrackerConfig(), workers=1)
    for k in range(len(sim)):
        frame = sim.frame(k)
        r = tracker.track_frame(frame.cloud, frame.timestamp)
        assert not any(x.startswith(COARSE) for x in r.reasons), (k, r.reasons)
    assert r.status == "ok"


def test_a_coarse_surface_made_once_judges_as_the_one_call_does() -> None:
    """A tracker makes a keyframe's coarse surface once and judges every frame against it:
    the same bits as :func:`surface_degeneracy` from the points."""
    rng = np.random.default_rng(3)
    source, target = plate_frame(rng), plate_frame(rng)
    T = np.eye(4)
    T[:3, 3] = [0.004, -0.002, 0.001]
    radius = 0.41
    once = CoarseSurface.of(target, radius, workers=1)
    a = surface_degeneracy(source, target, T, radius, workers=1)
    b = surface_degeneracy(source, once, T, radius, workers=1)
    assert a.condition == b.condition and np.array_equal(a.free, b.free)
    assert a.degenerate and a.free.shape[1] == 3


def test_a_model_in_absurd_units_is_named_in_the_reason() -> None:
    """A model read with coordinates near 1e20 m lost every frame with a reason about the
    frame's cells; the reason now names the model and says it is the model's."""
    from spacepose.core.cloud import PointCloud

    rng = np.random.default_rng(0)
    model = PointCloud(plate_frame(rng)[:2000] * 1e20, source="huge.ply")
    result = Tracker(TrackerConfig(), model=model, workers=1).track_frame(plate_frame(rng), 0.0)
    assert result.status == "lost"
    assert "huge.ply: the model at the frame's voxel: cells of" in result.reasons[0], result.reasons


def test_a_first_frame_on_a_line_is_lost_and_the_next_one_starts_the_run() -> None:
    """A first frame whose points all lie on one line has no normals: the tracker raised out
    of track_frame (after normal estimation began refusing such clouds), and before that it
    derived its lengths from the line. It is lost with its reason; the next frame starts the
    run with the lengths it would have had first."""
    sim = simulate(LabConfig(frames=4, seed=0))
    line = np.c_[np.linspace(-0.3, 0.3, 2000), np.zeros(2000), np.full(2000, 1.5)]
    tracker = Tracker(TrackerConfig(), workers=1)
    first = tracker.track_frame(line, -0.1)
    assert first.status == "lost" and "lie on a line" in first.reasons[0], first.reasons
    statuses = [
        tracker.track_frame(sim.frame(k).cloud, sim.frame(k).timestamp).status for k in range(4)
    ]
    assert statuses == ["ok", "degraded", "ok", "ok"], statuses
    fresh = Tracker(TrackerConfig(), workers=1)
    fresh.track_frame(sim.frame(0).cloud, sim.frame(0).timestamp)
    assert tracker.scale.voxel == fresh.scale.voxel


def test_a_frame_on_a_line_mid_run_is_lost_and_the_run_goes_on() -> None:
    """Model-free and against the model: a frame whose points lie on one line fails fine
    registration and then its coarse features (no normals on a line), which raised out of
    track_frame. It is lost with both reasons; the frames after it are tracked."""
    sim = simulate(LabConfig(frames=5, seed=0))
    line = np.c_[np.linspace(-0.3, 0.3, 2000), np.zeros(2000), np.full(2000, 1.2)]
    for model in (None, sim.model_cloud()):
        tracker = Tracker(TrackerConfig(), model=model, workers=1)
        results = [
            tracker.track_frame(line if k == 2 else sim.frame(k).cloud, sim.frame(k).timestamp)
            for k in range(5)
        ]
        assert results[2].status == "lost", results[2].reasons
        assert results[2].reasons[-1] == "coarse registration found no consensus"
        assert [r.status for r in results[3:]] == ["ok", "ok"], [r.reasons for r in results]
