"""Scoring target poses on the model (spacepose.core.lost_in_space)."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy.spatial.transform import Rotation

from spacepose.core import se3
from spacepose.core.cloud import PointCloud
from spacepose.core.lost_in_space import (
    FrameEvidence,
    LostInSpaceConfig,
    ModelSurface,
    equally_good,
    explained_share,
    refine_on_model,
    visible_samples,
)
from spacepose.core.sim import sensor_config
from spacepose.core.sim.sensors import scan
from spacepose.core.sim.targets import Target, sample_surface
from spacepose.errors import InputError

SENSOR = sensor_config("flash-lidar")
SIGMA = 0.01  # the flash LiDAR's range σ, m
T_SENSOR_MODEL = se3.make_transform(
    Rotation.from_euler("zyx", [30.0, 40.0, -25.0], degrees=True).as_matrix(), [0.2, -0.1, 25.0]
)
HALF_TURN_Y = se3.make_transform(Rotation.from_euler("y", 180, degrees=True).as_matrix(), [0, 0, 0])


def _target(appendage: bool) -> Target:
    """A 2.4 x 1.8 x 1.4 m box, with or without a 0.6 m cube off its +x+z edge."""
    parts = [trimesh.creation.box((2.4, 1.8, 1.4))]
    if appendage:
        parts.append(trimesh.creation.box((0.6, 0.6, 0.6)).apply_translation((1.5, 0.3, 0.5)))
    return Target("test", trimesh.util.concatenate(parts), (), tuple(parts))


def _frame_and_model(appendage: bool) -> tuple[FrameEvidence, ModelSurface]:
    target = _target(appendage)
    mesh = target.mesh.copy().apply_transform(T_SENSOR_MODEL)
    points = scan(mesh, SENSOR, np.random.default_rng(3)).points
    model = ModelSurface.from_cloud(sample_surface(target, 20000, seed=1))
    return FrameEvidence.build(points, [], SIGMA), model


@pytest.fixture(scope="module")
def asymmetric():
    return _frame_and_model(appendage=True)


def test_the_true_pose_explains_the_frame_and_its_half_turn_does_not(asymmetric) -> None:
    frame, model = asymmetric
    config = LostInSpaceConfig(fov_deg=(30.0, 30.0))
    true = explained_share(T_SENSOR_MODEL, frame, model, config)
    turned = explained_share(T_SENSOR_MODEL @ HALF_TURN_Y, frame, model, config)
    # Measured: 1.000 and 0.926 (the cube is where the turned model has none, and the
    # turned model shows its cube where the frame has none).
    assert true > 0.98
    assert turned < true - 0.05
    assert list(equally_good([turned, true], config.ambiguity_margin)) == [1]


def test_a_symmetric_box_explains_its_half_turn_as_well() -> None:
    frame, model = _frame_and_model(appendage=False)
    true = explained_share(T_SENSOR_MODEL, frame, model)
    turned = explained_share(T_SENSOR_MODEL @ HALF_TURN_Y, frame, model)
    assert true > 0.98 and abs(true - turned) < 0.005  # measured: both 1.000
    assert sorted(equally_good([true, turned], 0.008)) == [0, 1]


def test_refinement_recovers_a_coarse_pose(asymmetric) -> None:
    frame, model = asymmetric
    off = se3.make_transform(
        Rotation.from_rotvec(np.deg2rad([1.5, -1.0, 2.0])).as_matrix(), [0.05, -0.04, 0.03]
    )
    coarse = off @ T_SENSOR_MODEL
    refined = refine_on_model(coarse, frame, model)
    angle = np.rad2deg(Rotation.from_matrix(refined[:3, :3] @ T_SENSOR_MODEL[:3, :3].T).magnitude())
    assert angle < 0.2 and np.linalg.norm(refined[:3, 3] - T_SENSOR_MODEL[:3, 3]) < 0.01
    assert explained_share(refined, frame, model) > explained_share(coarse, frame, model)
    no_icp = LostInSpaceConfig(refine_iterations=0)
    np.testing.assert_array_equal(refine_on_model(coarse, frame, model, no_icp), coarse)


def test_visible_samples_face_the_sensor_and_are_not_hidden(asymmetric) -> None:
    frame, model = asymmetric
    seen = visible_samples(T_SENSOR_MODEL, frame, model)
    R, t = T_SENSOR_MODEL[:3, :3], T_SENSOR_MODEL[:3, 3]
    q = model.points @ R.T + t
    cos = -np.einsum("ij,ij->i", model.normals @ R.T, q) / np.linalg.norm(q, axis=1)
    facing = cos > np.cos(np.deg2rad(75.0))  # max_incidence_deg
    assert not np.any(seen & ~facing)
    # The cube hides part of the box's facing surface, nothing else is hidden (measured: 0.962
    # of the facing samples seen).
    assert 0.9 < seen.sum() / facing.sum() < 1.0
    # Every seen sample has a measured point within the inlier radius (1.5 spacings + 3σ).
    radius = 1.5 * frame.spacing + 3 * SIGMA
    assert np.mean(np.isfinite(frame.tree.query(q[seen], distance_upper_bound=radius)[0])) > 0.99


def test_equally_good_orders_by_score() -> None:
    assert list(equally_good([0.90, 0.995, 0.99, 0.5], 0.01)) == [1, 2]
    assert list(equally_good([0.7, 0.7], 0.001)) == [0, 1]
    assert list(equally_good([], 0.1)) == []


def test_bad_inputs_raise() -> None:
    with pytest.raises(InputError, match="normals"):
        ModelSurface.from_cloud(PointCloud(np.zeros((1, 3))))
    # Bare points get normals turned away from their centroid (a sphere's are radial).
    sphere = np.random.default_rng(0).normal(size=(2000, 3))
    sphere /= np.linalg.norm(sphere, axis=1, keepdims=True)
    surface = ModelSurface.from_cloud(PointCloud(sphere))
    assert np.einsum("ij,ij->i", surface.normals, sphere).min() > 0.9
    with pytest.raises(InputError, match="at least 2 points"):
        FrameEvidence.build(np.zeros((1, 3)), [], 0.01)
