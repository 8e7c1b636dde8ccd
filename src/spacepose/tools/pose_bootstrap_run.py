"""The registration poses' σ factor of a navigation run, by a parametric bootstrap (methods.md
§2.4).

A first pass tracks the run against its model; the run's mesh is rendered at the poses the
tracker called ``ok``, with the run's sensor, and tracked again
(:func:`~spacepose.core.pose_bootstrap.bootstrap_pose_noise`). The factor it measures replaces
``FusionConfig.pose_sigma_scale`` for the navigating pass. It needs the target's mesh and the
sensor's description, which a simulated run folder holds (model.obj, scenario.json); without
them, or without enough ``ok`` poses, the configured factor stays.
"""

from __future__ import annotations

import warnings
from collections.abc import Iterable
from pathlib import Path

import numpy as np

from spacepose.core.cloud import PointCloud
from spacepose.core.fused_navigation import FusionConfig
from spacepose.core.pose_bootstrap import bootstrap_pose_noise
from spacepose.core.pose_noise import BATCH_FRAMES, MIN_BATCHES, PoseNoiseScale
from spacepose.core.sim.mesh_files import load_mesh
from spacepose.core.sim.sensors import SensorConfig
from spacepose.core.sim.targets import Target
from spacepose.core.tracker import Tracker
from spacepose.errors import InputError, SpaceposeError, SpaceposeWarning

# Seed of the bootstrap's renders, apart from any run's (runs use small seeds).
BOOTSTRAP_SEED = 2**20 + 7


def bootstrapped_fusion(
    pairs: Iterable[tuple[float, PointCloud | None]],
    target: Target,
    sensor: SensorConfig,
    model: PointCloud,
    fusion: FusionConfig,
    workers: int = 1,
) -> tuple[FusionConfig, PoseNoiseScale | None]:
    """``fusion`` with ``pose_sigma_scale`` measured on the run (see the module docstring), and
    the measurement; ``fusion`` as it is and None when the run's ``ok`` poses, or its
    bootstrap's ``ok`` renders, fill fewer than :data:`~spacepose.core.pose_noise.MIN_BATCHES`
    batches.

    Parameters
    ----------
    pairs
        The run's (timestamp, cloud) frames, in order (a cloud of None: an unreadable frame).
    target
        The target's mesh in the model's frame.
    sensor
        The run's sensor.
    model
        The tracker's model (surface samples, model frame).
    fusion
        The navigation's settings (its tracker's config is the one bootstrapped).
    workers
        Tracker threads.
    """
    if not fusion.bootstrap_poses or fusion.measurements == "rectangles":
        return fusion, None
    tracker = Tracker(fusion.tracker, model, workers)
    times, poses, covariances = [], [], []
    for t, cloud in pairs:
        if cloud is None:
            continue
        result = tracker.track_frame(cloud, t)
        if result.status == "ok":
            times.append(t)
            poses.append(result.T_sensor_target)
            covariances.append(result.covariance)
    if len(poses) < MIN_BATCHES * BATCH_FRAMES:
        return fusion, None
    try:
        noise = bootstrap_pose_noise(
            target,
            sensor,
            times,
            np.array(poses),
            model,
            fusion.tracker,
            BOOTSTRAP_SEED,
            BATCH_FRAMES,
            MIN_BATCHES,
            covariances[0],
            workers,
        )
    except InputError:  # fewer ok renders than the batches need
        return fusion, None
    measured = {
        "pose_sigma_scale": noise.rotation_scale,
        "pose_sigma_scale_translation": noise.translation_scale,
        "pose_bias_sensor": tuple(noise.bias.sensor),
        "pose_bias_body": tuple(noise.bias.body),
    }
    return fusion.model_copy(update=measured), noise


def run_mesh_and_sensor(
    input_dir: str | Path, description: dict
) -> tuple[Target, SensorConfig] | None:
    """A simulated run folder's target mesh (model.obj, model frame) and sensor (its
    scenario's config), or None when the folder lacks either; one it cannot read is warned
    about (the navigation then keeps the configured factor, it does not fail)."""
    mesh = Path(input_dir) / "model.obj"
    sensor = (description.get("config") or {}).get("sensor")
    if not mesh.is_file() or not isinstance(sensor, dict):
        return None
    try:
        return load_mesh(mesh, center=False), SensorConfig(**sensor)
    except (SpaceposeError, ValueError) as exc:  # pydantic's errors are ValueErrors
        reason = str(exc).splitlines()[0]
        warnings.warn(
            SpaceposeWarning(f"the poses' σ factor is not measured on the run: {reason}", mesh),
            stacklevel=2,
        )
        return None
