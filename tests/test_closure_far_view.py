"""A model-free keyframe chain that slid about a cylinder's axis is not closed onto a first view
that shares too little of the frame (core.fine_stage.close_on_first)."""

from __future__ import annotations

import numpy as np
import trimesh
from scipy.spatial.transform import Rotation

from spacepose.core import se3
from spacepose.core.cloud import PointCloud
from spacepose.core.sim.sensors import SENSOR_PRESETS, scan
from spacepose.core.tracker import Tracker, TrackerConfig


def _cylinder_bus() -> trimesh.Trimesh:
    """A 1.2 m cylinder bus, 1.6 m long, with a 1.4 m dish on a 1.2 m boom off its side."""
    bus = trimesh.creation.cylinder(radius=0.6, height=1.6, sections=48)
    side = Rotation.from_rotvec([0.0, np.pi / 2, 0.0])
    boom = trimesh.creation.cylinder(radius=0.03, height=1.2, sections=12)
    boom.apply_transform(se3.make_transform(side, [1.2, 0.0, 0.5]))
    dish = trimesh.creation.cylinder(radius=0.7, height=0.04, sections=40)
    dish.apply_transform(se3.make_transform(side, [1.8, 0.0, 0.5]))
    mesh = trimesh.util.concatenate([bus, boom, dish])
    return mesh.apply_translation(-mesh.bounds.mean(axis=0))


def test_a_chain_slid_about_a_cylinders_axis_is_not_closed_onto_a_far_first_view():
    """8 m out, turning 8° a frame: seen side-on with the dish hidden, the chain slides 20-30°
    about the bus's axis while ``degraded`` (σ about 55°, within it). Before, a frame 80-130°
    from the first view was closed onto it at the slid pose, fitting 0.6 of the frame where
    the chain fitted 0.86, and 10 frames after it were ``ok`` beyond 5σ (seed 2; 10 on seed 3
    too). Such a closure is refused, and the chain stays marked."""
    mesh = _cylinder_bus()
    rng = np.random.default_rng(2)
    axis = np.array([0.7, 0.2, 0.6]) / np.linalg.norm([0.7, 0.2, 0.6])
    start = Rotation.from_rotvec([0.3, -0.4, 0.2])
    tracker = Tracker(TrackerConfig(), None, 1)
    T0, ok, beyond = None, 0, []
    for k in range(48):
        R = start * Rotation.from_rotvec(axis * np.radians(8.0) * k)
        T_sensor_target = se3.make_transform(R, [0.1, -0.05, 8.0])
        T0 = T_sensor_target if T0 is None else T0
        view = scan(mesh.copy().apply_transform(T_sensor_target), SENSOR_PRESETS["tof"], rng)
        result = tracker.track_frame(PointCloud(view.points), 0.1 * k)
        if result.status != "ok" or k == 0:
            continue
        ok += 1
        xi = se3.log(result.T_sensor_target @ se3.invert(T_sensor_target @ se3.invert(T0)))
        if np.any(np.abs(xi) > 5.0 * result.sigma):
            beyond.append(k)
    assert beyond == [] and ok >= 20
