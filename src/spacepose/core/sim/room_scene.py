"""A hand-held ToF camera in a furnished room: a run whose target is the whole scene.

Real ToF recordings are often of this kind (a camera carried through a room), and a tracker
built for a target before a wall must not take one piece of furniture for the target there
(docs/methods.md §5.7). The room is a closed box (``ROOM_M``: 6 × 5 × 2.8 m) seen from inside,
furnished with seven boxes standing on its floor at drawn places, sizes and headings, and a
pillar. The camera stays near the room's centre, 0.2 m above it, and looks around: its heading
swings as the sum of two sines whose rates peak near ``max_rate_deg_s`` together, its pitch
and roll sway by 12° and 5°, and its position drifts (two slow sines and a random walk of 3 mm
a frame). The truth is these closed-form motions; nothing of the estimator enters.
"""

from __future__ import annotations

import numpy as np
import trimesh
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from spacepose.core import se3
from spacepose.core.sim.sensors import SensorConfig, scan, sensor_config
from spacepose.errors import ConfigError

ROOM_M = (6.0, 5.0, 2.8)
# Camera axes (x right, y down, z ahead) in the room frame when its heading, pitch and roll are
# zero: looking along the room's +x, level.
_R_ROOM_CAMERA0 = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def kinect_nfov(**overrides: object) -> SensorConfig:
    """An Azure-Kinect-like ToF camera (narrow field of view: 640 × 576, 75° × 65°, 0.25–5.46 m)
    with the ``tof`` profile's noise, flying pixels and dropouts."""
    fields = dict(width=640, height=576, focal_px=504.0, min_range=0.25, max_range=5.46)
    return sensor_config("tof", **(fields | overrides))


def room_mesh(seed: int) -> trimesh.Trimesh:
    """The room (its inside faces) and its furniture, room frame (origin at the centre, z up)."""
    rng = np.random.default_rng(seed)
    width, depth, height = ROOM_M
    room = trimesh.creation.box(ROOM_M)
    room.invert()
    parts = [room]
    for _ in range(7):
        extent = rng.uniform([0.3, 0.3, 0.4], [1.4, 0.9, 1.6])
        box = trimesh.creation.box(extent)
        box.apply_transform(
            trimesh.transformations.rotation_matrix(rng.uniform(0, np.pi), [0, 0, 1])
        )
        box.apply_translation(
            [
                rng.uniform(-width / 2 + extent[0] / 2, width / 2 - extent[0] / 2),
                rng.uniform(-depth / 2 + extent[1] / 2, depth / 2 - extent[1] / 2),
                -height / 2 + extent[2] / 2,
            ]
        )
        parts.append(box)
    pillar = trimesh.creation.cylinder(0.15, height)
    pillar.apply_translation([1.0, -1.2, 0.0])
    parts.append(pillar)
    return trimesh.util.concatenate(parts)


def hand_held_poses(
    frames: int, fps: float, max_rate_deg_s: float, seed: int
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Timestamps (N,) s and the true ``T_sensor_room`` (N, 4, 4) of the module's camera."""
    rng = np.random.default_rng(seed)
    t = np.arange(frames) / fps
    rate = np.radians(max_rate_deg_s)
    phase = rng.uniform(0.0, 2.0 * np.pi, 6)
    heading = 0.6 * rate / 0.9 * np.sin(0.9 * t + phase[0])
    heading += 0.4 * rate / 2.3 * np.sin(2.3 * t + phase[1])
    pitch = np.radians(12.0) * np.sin(0.7 * t + phase[2]) - np.radians(10.0)
    roll = np.radians(5.0) * np.sin(1.3 * t + phase[3])
    position = np.stack(
        [
            0.4 * np.sin(0.3 * t + phase[4]),
            0.3 * np.sin(0.4 * t + phase[5]),
            0.2 + 0.05 * np.sin(1.1 * t),
        ],
        axis=1,
    )
    position += np.cumsum(rng.normal(0.0, 0.003, (frames, 3)), axis=0)
    R_room_camera = Rotation.from_euler("ZYX", np.stack([heading, pitch, roll], axis=1)).as_matrix()
    T = np.array(
        [
            se3.invert(se3.make_transform(R @ _R_ROOM_CAMERA0, p))
            for R, p in zip(R_room_camera, position, strict=True)
        ]
    )
    return t, T


def room_frames(
    frames: int = 60,
    fps: float = 8.6,
    max_rate_deg_s: float = 55.0,
    seed: int = 0,
    sensor: SensorConfig | None = None,
) -> tuple[list[NDArray[np.float64]], NDArray[np.float64], NDArray[np.float64]]:
    """The run: points (N_k, 3) of each frame (sensor frame, m), timestamps (N,) s and the true
    ``T_sensor_room`` (N, 4, 4). Frame k's noise is drawn from the seed ``[seed, k]``.

    Raises
    ------
    ConfigError
        No frames, a frame rate not above 0 or a negative turn rate.
    """
    if frames < 1 or not fps > 0 or not max_rate_deg_s >= 0:
        raise ConfigError(
            f"a room run needs frames >= 1, fps > 0 and max_rate_deg_s >= 0; got {frames}, "
            f"{fps} and {max_rate_deg_s}"
        )
    sensor = sensor or kinect_nfov()
    mesh = room_mesh(seed)
    timestamps, T_sensor_room = hand_held_poses(frames, fps, max_rate_deg_s, seed)
    clouds = []
    for k, T in enumerate(T_sensor_room):
        view = mesh.copy()
        view.apply_transform(T)
        clouds.append(scan(view, sensor, np.random.default_rng([seed, k])).points)
    return clouds, timestamps, T_sensor_room
