"""Mirrored frames against a model (core/handedness.py)."""

from __future__ import annotations

import warnings

import numpy as np
import trimesh
from scipy.spatial.transform import Rotation

from spacepose.core import se3
from spacepose.core.cloud import PointCloud
from spacepose.core.handedness import mirror_cost_share, principal_reflections
from spacepose.errors import SpaceposeWarning


def test_principal_reflections_map_a_box_onto_itself():
    """A box's three principal planes are its planes of symmetry: each reflection maps its
    corners onto its corners, and each is a reflection (determinant −1, an involution)."""
    box = trimesh.creation.box(extents=(1.0, 0.6, 0.3))
    T = se3.make_transform(Rotation.from_rotvec((0.3, -0.5, 0.2)), (0.2, 0.1, -0.4))
    corners = se3.transform_points(T, box.vertices)
    dense = se3.transform_points(T, trimesh.sample.sample_surface(box, 4000, seed=0)[0])
    for S in principal_reflections(dense):
        assert np.isclose(np.linalg.det(S[:3, :3]), -1.0)
        np.testing.assert_allclose(S @ S, np.eye(4), atol=1e-12)
        moved = S[:3, :3] @ corners.T + S[:3, 3:4]
        gaps = np.linalg.norm(moved.T[:, None] - corners[None], axis=2).min(axis=1)
        assert gaps.max() < 0.02


def test_a_mirror_symmetric_target_cannot_tell_and_says_nothing():
    """A box seen from its sensor, 1 mm of noise: its mirror image fits as well, so the share
    is 1 (nothing to tell), mirrored or not."""
    rng = np.random.default_rng(0)
    mesh = trimesh.creation.box(extents=(1.0, 0.6, 0.3))
    points, face = trimesh.sample.sample_surface(mesh, 30_000, seed=1)
    model = PointCloud(points, mesh.face_normals[face])
    T = se3.make_transform(Rotation.from_rotvec((0.4, 0.5, 0.1)), (0.1, -0.1, 3.0))
    sensor = se3.invert(T)[:3, 3]
    seen = np.einsum("ij,ij->i", model.normals, sensor - model.points) > 0.0
    frame = se3.transform_points(T, model.points[seen][::10])
    frame += (
        frame / np.linalg.norm(frame, axis=1, keepdims=True) * rng.normal(0, 0.001, (len(frame), 1))
    )
    assert mirror_cost_share(frame, model, T, 0.006, 0.001) == 1.0


def _track(sim, mirror: bool) -> tuple[list, list[str]]:
    from spacepose.core.tracker import Tracker, TrackerConfig

    tracker = Tracker(TrackerConfig(), model=sim.model_cloud(), workers=1)
    flip = np.array([-1.0, 1.0, 1.0]) if mirror else np.ones(3)
    rows = []
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        for frame in sim.frames():
            result = tracker.track_frame(PointCloud(frame.cloud.points * flip), frame.timestamp)
            error = se3.log(result.T_sensor_target @ se3.invert(frame.T_sensor_target))
            rows.append((result.status, np.degrees(np.linalg.norm(error[:3])), result.reasons))
    said = [str(w.message) for w in caught if issubclass(w.category, SpaceposeWarning)]
    return rows, said


def test_the_lab_runs_mirror_image_is_not_ok_against_its_model():
    """The lab run's frames with x flipped (a left-handed frame), against its model: frames
    were `ok` 178-180° off at 5-35σ (the mock-up is close to symmetric under a reflection).
    Mirrored back, the first `ok` frame fits with 40 % of the cost: the run warns once and
    every frame is `degraded`. Unflipped, nothing is said and the frames stay `ok`."""
    from spacepose.core.sim import simulate
    from spacepose.core.sim.scenarios import LabConfig

    sim = simulate(LabConfig(frames=5, seed=0))
    mirrored, said = _track(sim, mirror=True)
    assert [s for s in said if "look mirrored" in s] == said[-1:] and said
    assert not [r for r in mirrored if r[0] == "ok"]
    assert max(angle for _, angle, _ in mirrored) > 150.0  # the poses are as they were
    right, said = _track(sim, mirror=False)
    assert not [s for s in said if "mirrored" in s]
    assert sum(status == "ok" for status, _, _ in right) >= 4
    assert max(angle for _, angle, _ in right) < 0.5


def test_no_returns_or_a_model_without_normals_is_refused_in_one_line():
    """An empty frame ended in numpy's "slice step cannot be zero": an InputError now, as is
    a model without the normals the point-to-plane fits need."""
    import pytest

    from spacepose.errors import InputError

    points = np.random.default_rng(1).normal(size=(100, 3))
    model = PointCloud(points, np.tile([0.0, 0.0, 1.0], (100, 1)))
    with pytest.raises(InputError, match="returns: need at least 1 point"):
        mirror_cost_share(np.zeros((0, 3)), model, np.eye(4), 0.01, 0.001)
    with pytest.raises(InputError, match="needs normals"):
        mirror_cost_share(points, PointCloud(points), np.eye(4), 0.01, 0.001)
