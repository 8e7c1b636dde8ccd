"""A hand-held ToF camera in a furnished room: the default tracker against Open3D.

``room``: for each seed, a run of :mod:`spacepose.core.sim.room_scene` (an Azure-Kinect-like
camera carried through a room, 8.6 frames a second, turning at up to 55°/s) is tracked by the
default tracker, with no flag, and by Open3D's plain frame-to-frame point-to-plane ICP on 2 cm
voxels (the peer a user of such recordings reaches for first; skipped without Open3D). Both
report ``T_k0``, the room's pose in the camera relative to the first frame; the errors are
those of ``spacepose evaluate --rebase-first`` (ATE), and ours also counts its flags: an ``ok``
frame further than 5 σ from the truth on any axis is a false ``ok``.

Outputs ``room.json`` (per seed and method, and the mean ± std over seeds) and ``room.md``.
Quick mode: two seeds of 8 frames at a quarter of the camera's pixels.
"""

from __future__ import annotations

import importlib
import time
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from spacepose.core import se3
from spacepose.core.metrics import error_table
from spacepose.core.scene_follower import SCENE_NOTE
from spacepose.core.sim.room_scene import kinect_nfov, room_frames
from spacepose.core.track_result import TrackResult
from spacepose.core.tracker import Tracker
from spacepose.tools.experiments import ExperimentOptions, register
from spacepose.tools.experiments.robustness_scores import FALSE_OK_SIGMAS
from spacepose.tools.text_io import strict_json

SEEDS, FRAMES = 5, 60
QUICK_SEEDS, QUICK_FRAMES = 2, 8
QUICK_SENSOR = {"width": 160, "height": 144, "focal_px": 126.0}
# Open3D's voxel (m), its normals' radius and its ICP gate in voxels: the issue's peer setup.
OPEN3D_VOXEL = 0.02
OPEN3D_NORMAL_VOXELS = 3.0
OPEN3D_GATE_VOXELS = 3.0


def open3d_frame_to_frame(
    o3d: Any, clouds: list[NDArray[np.float64]], voxel: float = OPEN3D_VOXEL
) -> NDArray[np.float64]:
    """(N, 4, 4) ``T_k0`` from Open3D's point-to-plane ICP of each frame onto the previous one
    (voxel downsampling, hybrid-radius normals; the last step as the next start)."""

    def prepared(points: NDArray[np.float64]) -> Any:
        pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
        pc = pc.voxel_down_sample(voxel)
        search = o3d.geometry.KDTreeSearchParamHybrid(
            radius=OPEN3D_NORMAL_VOXELS * voxel, max_nn=30
        )
        pc.estimate_normals(search)
        return pc

    estimation = o3d.pipelines.registration.TransformationEstimationPointToPlane()
    poses = [np.eye(4)]
    previous, T_prev_cur = prepared(clouds[0]), np.eye(4)
    for points in clouds[1:]:
        current = prepared(points)
        result = o3d.pipelines.registration.registration_icp(
            current, previous, OPEN3D_GATE_VOXELS * voxel, T_prev_cur, estimation
        )
        T_prev_cur = np.asarray(result.transformation)
        poses.append(se3.invert(T_prev_cur) @ poses[-1])
        previous = current
    return np.array(poses)


def false_ok(results: list[TrackResult], T_true_k0: NDArray[np.float64]) -> int:
    """``ok`` frames (after the first) further than 5 σ from the truth on some axis."""
    count = 0
    for r, T in zip(results[1:], T_true_k0[1:], strict=True):
        if r.status == "ok":
            delta = np.abs(se3.log(r.T_sensor_target @ se3.invert(T)))
            count += bool(np.any(delta > FALSE_OK_SIGMAS * r.sigma))
    return count


def _errors(T_est: NDArray[np.float64], T_true: NDArray[np.float64]) -> dict[str, float]:
    table = error_table(T_est, T_true)
    return {
        "ate_mm": 1e3 * table.ate_translation_rmse,
        "ate_deg": table.ate_rotation_rmse,
    }


def run_seed(seed: int, frames: int, quick: bool, workers: int) -> dict[str, Any]:
    """One room run tracked by ours (and Open3D when installed)."""
    sensor = kinect_nfov(**(QUICK_SENSOR if quick else {}))
    clouds, stamps, T_sensor_room = room_frames(frames=frames, seed=seed, sensor=sensor)
    T_true_k0 = T_sensor_room @ se3.invert(T_sensor_room[0])
    tic = time.perf_counter()
    results = Tracker(workers=workers).track(zip(clouds, stamps, strict=True))
    seconds = time.perf_counter() - tic
    statuses = [r.status for r in results]
    switched = [r.index for r in results if SCENE_NOTE in r.reasons]
    ours = _errors(np.array([r.T_sensor_target for r in results]), T_true_k0) | {
        "ok": statuses.count("ok"),
        "degraded": statuses.count("degraded"),
        "lost": statuses.count("lost"),
        "false_ok": false_ok(results, T_true_k0),
        "whole_scene_from": switched[0] if switched else -1,
        "ms_per_frame": 1e3 * seconds / frames,
    }
    row: dict[str, Any] = {"seed": seed, "frames": frames, "ours": ours}
    try:
        o3d = importlib.import_module("open3d")
    except ImportError:
        return row
    tic = time.perf_counter()
    T_open3d = open3d_frame_to_frame(o3d, clouds)
    ms = 1e3 * (time.perf_counter() - tic) / frames
    row["open3d"] = _errors(T_open3d, T_true_k0) | {"ms_per_frame": ms}
    return row


def summary(rows: list[dict[str, Any]]) -> dict[str, dict[str, list[float]]]:
    """Mean and std over seeds of every number of each method."""
    out: dict[str, dict[str, list[float]]] = {}
    for method in ("ours", "open3d"):
        found = [r[method] for r in rows if method in r]
        if found:
            out[method] = {
                key: [
                    float(np.mean([f[key] for f in found])),
                    float(np.std([f[key] for f in found])),
                ]
                for key in found[0]
            }
    return out


def _markdown(rows: list[dict[str, Any]], means: dict[str, dict[str, list[float]]]) -> str:
    lines = [
        "| seed | ours ATE mm | ours ATE ° | ok / degraded / lost | false ok | whole scene from "
        "| ms a frame | Open3D ATE mm | Open3D ATE ° |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for r in rows:
        o, p = r["ours"], r.get("open3d")
        peer = f"{p['ate_mm']:.1f} | {p['ate_deg']:.2f}" if p else "– | –"
        lines.append(
            f"| {r['seed']} | {o['ate_mm']:.1f} | {o['ate_deg']:.2f} | {o['ok']} / "
            f"{o['degraded']} / {o['lost']} | {o['false_ok']} | {o['whole_scene_from']} | "
            f"{o['ms_per_frame']:.0f} | {peer} |"
        )
    for method, m in means.items():
        lines.append(
            f"\n{method}: ATE {m['ate_mm'][0]:.1f} ± {m['ate_mm'][1]:.1f} mm, "
            f"{m['ate_deg'][0]:.2f} ± {m['ate_deg'][1]:.2f}° (mean ± std over seeds)"
        )
    return "\n".join(lines) + "\n"


@register("room", uses=("seeds", "frames"))
def room_experiment(out: Path, options: ExperimentOptions) -> dict[str, Any]:
    """The experiment of the module docstring; ``seeds`` and ``frames`` as given."""
    seeds = options.seeds or (QUICK_SEEDS if options.quick else SEEDS)
    frames = options.frames or (QUICK_FRAMES if options.quick else FRAMES)
    rows = [
        run_seed(seed, frames, options.quick, options.workers)
        for seed in range(options.seed, options.seed + seeds)
    ]
    table = {"rows": rows, "mean_std": summary(rows)}
    (out / "room.json").write_text(strict_json(table, indent=2) + "\n")
    (out / "room.md").write_text(_markdown(rows, table["mean_std"]))
    return table
