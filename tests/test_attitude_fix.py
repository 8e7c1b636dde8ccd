"""Lost-in-space pose hypotheses from the rectangles of one frame (spacepose.core.attitude_fix)."""

from __future__ import annotations

import numpy as np
from scipy.spatial.transform import Rotation

from spacepose.core import se3
from spacepose.core.attitude_fix import (
    PoseHypothesis,
    attitude_hypotheses,
    explained_rectangles,
)
from spacepose.core.rectangle_measurement import measure_rectangle
from spacepose.core.rectangles import CatalogueEntry, candidates
from spacepose.core.sim.targets import box_rectangles

BOX = (2.4, 1.8, 1.4)  # the orbit bus, m
CATALOGUE = [
    CatalogueEntry.model_validate(r.to_dict()) for r in box_rectangles("bus", BOX, np.eye(4))
]
# The target 25 m ahead, turned so that its +x, −y and +z faces look at the sensor.
T_SENSOR_MODEL = se3.make_transform(
    Rotation.from_euler("zyx", [200.0, 35.0, -30.0], degrees=True).as_matrix(), [0.3, -0.2, 25.0]
)


def _face(name: str, T: np.ndarray = T_SENSOR_MODEL, step: float = 0.05) -> np.ndarray:
    """A regular grid of points on a catalogue face, sensor frame (m)."""
    e = next(e for e in CATALOGUE if e.name == name)
    u = np.arange(-e.a / 2 + step / 2, e.a / 2, step)
    v = np.arange(-e.b / 2 + step / 2, e.b / 2, step)
    U, V = (g.ravel() for g in np.meshgrid(u, v))
    local = e.centre + U[:, None] * e.rotation[:, 0] + V[:, None] * e.rotation[:, 1]
    return se3.transform_points(T, local)


def _visible_faces() -> list[str]:
    """Faces whose outward normal points at the sensor under T_SENSOR_MODEL."""
    R, t = T_SENSOR_MODEL[:3, :3], T_SENSOR_MODEL[:3, 3]
    return [e.name for e in CATALOGUE if (R @ e.rotation[:, 2]) @ (R @ e.centre + t) < 0]


def _rects(names):
    out = []
    for name in names:
        m = measure_rectangle(_face(name))
        out.append((m, candidates(m, CATALOGUE)))
    return out


def _angle_deg(T: np.ndarray, U: np.ndarray) -> float:
    return float(np.rad2deg(Rotation.from_matrix(T[:3, :3] @ U[:3, :3].T).magnitude()))


def test_a_box_seen_on_two_faces_leaves_its_four_symmetric_poses() -> None:
    names = _visible_faces()[:2]
    rects = _rects(names)
    assert all(len(c) == 2 for _, c in rects)  # each face has its opposite twin
    hypotheses = attitude_hypotheses(rects)
    # 2 rectangles x 2 faces x 2 sign choices, merged: the box's 4 symmetric poses (the
    # identity and the half turns about its axes), every one explaining both rectangles.
    assert len(hypotheses) == 4
    assert all(isinstance(h, PoseHypothesis) and len(h.assignment) == 2 for h in hypotheses)
    angles = sorted(_angle_deg(h.T_sensor_model, T_SENSOR_MODEL) for h in hypotheses)
    assert angles[0] < 1e-6 and all(abs(a - 180.0) < 1e-6 for a in angles[1:])
    true = min(hypotheses, key=lambda h: _angle_deg(h.T_sensor_model, T_SENSOR_MODEL))
    np.testing.assert_allclose(true.T_sensor_model[:3, 3], T_SENSOR_MODEL[:3, 3], atol=1e-9)
    assert sorted(name for _, name in true.assignment) == sorted(names)
    # A half turn about a seen face's normal keeps that face (turned about its centre) and puts
    # the other's opposite twin in its place; about the third axis both faces are swapped.
    swapped = sorted(len(set(name for _, name in h.assignment) - set(names)) for h in hypotheses)
    assert swapped == [0, 1, 1, 2]


def test_one_face_alone_gives_its_two_faces_times_two_turns() -> None:
    rects = _rects(_visible_faces()[:1])
    hypotheses = attitude_hypotheses(rects)
    assert len(hypotheses) == 4
    assert min(_angle_deg(h.T_sensor_model, T_SENSOR_MODEL) for h in hypotheses) < 1e-6


def test_explained_rectangles_needs_the_face_at_its_predicted_place() -> None:
    names = _visible_faces()
    rects = _rects(names)
    found = explained_rectangles(T_SENSOR_MODEL, rects)
    assert [(i, e.name) for i, e in found] == list(enumerate(names))
    # Moved by more than half of every face's long side: nothing is explained.
    moved = T_SENSOR_MODEL.copy()
    moved[:3, 3] += [1.5, 0.0, 0.0]
    assert explained_rectangles(moved, rects) == []
    # Turned by 90° about the sensor's boresight: the normals no longer agree.
    turned = se3.make_transform(Rotation.from_euler("x", 90, degrees=True).as_matrix(), np.zeros(3))
    assert explained_rectangles(turned @ T_SENSOR_MODEL, rects) == []


def test_rectangles_without_candidates_are_ignored() -> None:
    m = measure_rectangle(_face(_visible_faces()[0]))
    assert attitude_hypotheses([(m, [])]) == []
