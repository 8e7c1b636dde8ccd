"""The default model-free tracker on a target whose range changes: receding and approaching.

Run from the repository's root: ``.venv/bin/python examples/range_change.py`` (about 2 minutes),
and ``.venv/bin/python examples/range_change.py far`` (about 5). satellite_panels (scaled to
1.57 m) is rendered by the ToF camera, turning about a random axis from a random attitude (per
seed), at 2 frames a second.

- The first table: 3° a frame, 20 frames, receding from 1.5 to 5 m before a wall at 7 m and from
  1.5 to 4 m alone, approaching from 8 to 1.5 m before a wall at 9.5 m and from 6 to 1.5 m
  alone; noise ×0 and ×1, seeds 1 and 2. Each row: the frames after the target frame that are
  ``ok``, those beyond 3σ and 5σ on some axis, and the median and largest error of the target
  frame's target centre (mm).
- ``far``: 2° a frame, 36 frames, alone, approaching from 9.8 m (the camera's range is 10 m) or
  from 8 m to 1.5 m; noise ×1 and ×3, seeds 1-3. Each row: the target frame, the ``ok`` frames
  and those beyond 3σ and 5σ, and the median rotation error of the run's second half (degrees).

The truth is re-based on the frame the tracker made its target frame (a later one when the first
was never confirmed, :attr:`~spacepose.core.tracker.Tracker.first_index`).
"""

from __future__ import annotations

import sys
import warnings
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import trimesh
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from spacepose.core import se3
from spacepose.core.cloud import PointCloud
from spacepose.core.sim.mesh_files import load_mesh
from spacepose.core.sim.sensors import SENSOR_PRESETS, scan
from spacepose.core.track_result import revise_results
from spacepose.core.tracker import Tracker, TrackerConfig

MESH = Path("data/models/satellite_panels.obj")
# The first table's runs: (start range, end range, wall range or None), metres.
NEAR_RUNS = [(1.5, 5.0, 7.0), (8.0, 1.5, 9.5), (1.5, 4.0, None), (6.0, 1.5, None)]


@dataclass(frozen=True)
class Run:
    """One run: ranges (m) from first to last frame, a wall's range (m) or None, the turn a
    frame (degrees), the number of frames and the target's offset from the optical axis (m)."""

    start_m: float
    end_m: float
    wall_m: float | None
    turn_deg: float
    frames: int
    offset: tuple[float, float]


@dataclass(frozen=True)
class Scored:
    """A run's frames after its target frame: index, ``ok``, largest |error| / σ, rotation error
    (degrees) and the error of the target frame's target centre (m)."""

    first: int
    frames: list[tuple[int, bool, float, float, float]]

    def ok(self, beyond: float | None = None) -> int:
        """``ok`` frames (those beyond ``beyond`` σ on some axis, when given)."""
        return sum(ok and (beyond is None or z > beyond) for _, ok, z, _, _ in self.frames)


def track_run(mesh: trimesh.Trimesh, run: Run, noise: float, seed: int) -> Scored:
    """Render, track and score one run."""
    rng = np.random.default_rng(seed)
    attitude = Rotation.from_rotvec(rng.normal(size=3))
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    sensor = SENSOR_PRESETS["tof"].model_copy(update={"noise_scale": noise})
    tracker = Tracker(TrackerConfig(), None, 1)
    truths: list[NDArray[np.float64]] = []
    results = []
    for k in range(run.frames):
        turned = attitude * Rotation.from_rotvec(axis * np.radians(run.turn_deg) * k)
        z = run.start_m + (run.end_m - run.start_m) * k / (run.frames - 1)
        truths.append(se3.make_transform(turned.as_matrix(), [*run.offset, z]))
        scene = mesh.copy().apply_transform(truths[-1])
        if run.wall_m is not None:
            backdrop = trimesh.creation.box([30.0, 30.0, 0.1])
            backdrop.apply_translation([0, 0, run.wall_m])
            scene = trimesh.util.concatenate([scene, backdrop])
        points = scan(scene, sensor, rng).points
        results.append(tracker.track_frame(PointCloud(points) if len(points) else None, 0.5 * k))
        revise_results(results, results[-1])
    first = tracker.first_index or 0
    centre = truths[first][:3, 3]
    frames = []
    for k in range(first + 1, run.frames):
        truth = truths[k] @ se3.invert(truths[first])
        T = results[k].T_sensor_target
        xi = se3.log(T @ se3.invert(truth))
        moved = se3.transform_points(T, centre[None])[0]
        error = float(np.linalg.norm(moved - se3.transform_points(truth, centre[None])[0]))
        z = float(np.max(np.abs(xi) / np.maximum(results[k].sigma, 1e-12)))
        ok = results[k].status == "ok"
        frames.append((k, ok, z, float(np.degrees(np.linalg.norm(xi[:3]))), error))
    return Scored(first, frames)


def near_table(mesh: trimesh.Trimesh) -> None:
    """The first table (module docstring)."""
    print("| range | clutter | noise | seed | ok | > 3σ | > 5σ | median mm | max mm |")
    print("|---|---|---|---|---|---|---|---|---|")
    for start_m, end_m, wall_m in NEAR_RUNS:
        for noise in (0.0, 1.0):
            for seed in (1, 2):
                run = Run(start_m, end_m, wall_m, 3.0, 20, (0.1, -0.05))
                s = track_run(mesh, run, noise, seed)
                # No frame after the target frame (found last, or never): nan, not max()'s
                # ValueError on an empty list.
                errors = [1e3 * e for *_, e in s.frames] or [float("nan")]
                where = "alone" if wall_m is None else f"wall at {wall_m} m"
                print(
                    f"| {start_m} → {end_m} m | {where} | ×{noise:g} | {seed} | {s.ok()} | "
                    f"{s.ok(3.0)} | {s.ok(5.0)} | {np.median(errors):.1f} | {max(errors):.1f} |",
                    flush=True,
                )


def far_table(mesh: trimesh.Trimesh) -> None:
    """The ``far`` table (module docstring)."""
    print("| range | noise | seed | target frame | ok | > 3σ | > 5σ | second half's median ° |")
    print("|---|---|---|---|---|---|---|---|")
    for start_m in (9.8, 8.0):
        for noise in (1.0, 3.0):
            for seed in (1, 2, 3):
                run = Run(start_m, 1.5, None, 2.0, 36, (0.05, -0.03))
                s = track_run(mesh, run, noise, seed)
                late = [deg for k, _, _, deg, _ in s.frames if k >= run.frames // 2] or [np.nan]
                print(
                    f"| {start_m} → 1.5 m | ×{noise:g} | {seed} | {s.first} | {s.ok()} | "
                    f"{s.ok(3.0)} | {s.ok(5.0)} | {np.median(late):.2f} |",
                    flush=True,
                )


def main() -> None:
    warnings.simplefilter("ignore")  # the mesh's inward-wound part, turned outwards
    mesh = load_mesh(MESH, scale=0.1).mesh
    if sys.argv[1:] == ["far"]:
        far_table(mesh)
    else:
        near_table(mesh)


if __name__ == "__main__":
    main()
