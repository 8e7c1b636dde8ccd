"""The default model-free tracker on a target whose range changes: receding and approaching.

Run from the repository's root: ``.venv/bin/python examples/range_change.py``. satellite_panels
(scaled to 1.57 m) is rendered by the ToF camera, turning 3° a frame about a random axis from a
random attitude (per seed), 20 frames at 2 frames a second: receding from 1.5 to 5 m before a
wall at 7 m and from 1.5 to 4 m alone, approaching from 8 to 1.5 m before a wall at 9.5 m and
from 6 to 1.5 m alone; noise ×0 and ×1, seeds 1 and 2. Each row: the frames after the first
that are ``ok``, those beyond 3σ and 5σ on some axis, and the median and largest error of the
first frame's target centre (mm).
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import trimesh
from scipy.spatial.transform import Rotation

from spacepose.core import se3
from spacepose.core.cloud import PointCloud
from spacepose.core.sim.mesh_files import load_mesh
from spacepose.core.sim.sensors import SENSOR_PRESETS, scan
from spacepose.core.tracker import Tracker, TrackerConfig

MESH = Path("data/models/satellite_panels.obj")
# (start range, end range, wall range or None), metres.
RUNS = [(1.5, 5.0, 7.0), (8.0, 1.5, 9.5), (1.5, 4.0, None), (6.0, 1.5, None)]
FRAMES = 20


def track_run(mesh: trimesh.Trimesh, ranges: tuple, noise: float, seed: int) -> str:
    """One run's row."""
    z0, z1, wall = ranges
    rng = np.random.default_rng(seed)
    start = Rotation.from_rotvec(rng.normal(size=3))
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    sensor = SENSOR_PRESETS["tof"].model_copy(update={"noise_scale": noise})
    tracker = Tracker(TrackerConfig(), None, 1)
    T_first, ok, beyond3, beyond5, errors = None, 0, 0, 0, []
    for k in range(FRAMES):
        turned = start * Rotation.from_rotvec(axis * np.radians(3.0) * k)
        position = [0.1, -0.05, z0 + (z1 - z0) * k / (FRAMES - 1)]
        T_sensor_target = se3.make_transform(turned.as_matrix(), position)
        T_first = T_sensor_target if T_first is None else T_first
        scene = mesh.copy().apply_transform(T_sensor_target)
        if wall is not None:
            backdrop = trimesh.creation.box([30.0, 30.0, 0.1])
            scene = trimesh.util.concatenate([scene, backdrop.apply_translation([0, 0, wall])])
        result = tracker.track_frame(PointCloud(scan(scene, sensor, rng).points), 0.5 * k)
        if k == 0:
            continue
        truth = T_sensor_target @ se3.invert(T_first)
        xi = se3.log(result.T_sensor_target @ se3.invert(truth))
        centre = T_first[:3, 3]
        moved = se3.transform_points(result.T_sensor_target, centre[None])[0]
        errors.append(np.linalg.norm(moved - se3.transform_points(truth, centre[None])[0]))
        if result.status == "ok":
            z = np.max(np.abs(xi) / np.maximum(result.sigma, 1e-12))
            ok, beyond3, beyond5 = ok + 1, beyond3 + (z > 3), beyond5 + (z > 5)
    where = "alone" if wall is None else f"wall at {wall} m"
    return (
        f"| {z0} → {z1} m | {where} | ×{noise:g} | {seed} | {ok} | {beyond3} | {beyond5} | "
        f"{1e3 * np.median(errors):.1f} | {1e3 * np.max(errors):.1f} |"
    )


def main() -> None:
    warnings.simplefilter("ignore")  # the mesh's inward-wound part, turned outwards
    mesh = load_mesh(MESH, scale=0.1).mesh
    print("| range | clutter | noise | seed | ok | > 3σ | > 5σ | median mm | max mm |")
    print("|---|---|---|---|---|---|---|---|---|")
    for ranges in RUNS:
        for noise in (0.0, 1.0):
            for seed in (1, 2):
                print(track_run(mesh, ranges, noise, seed), flush=True)


if __name__ == "__main__":
    main()
