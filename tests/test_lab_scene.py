"""Tests of the lab scene (motion profiles, target size, clutter) and of the grid scenarios."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from spacepose.core import se3
from spacepose.core.sim import LabConfig, sensor_config, simulate_lab
from spacepose.core.sim.grid import MOTIONS, grid_scenario, motion_fields
from spacepose.core.sim.lab_scene import lab_poses
from spacepose.errors import ConfigError

MODELS = Path(__file__).resolve().parents[1] / "data" / "models"
SMALL_TOF = sensor_config("tof", width=320, height=240, focal_px=241.8)


def _steps(T: np.ndarray) -> Rotation:
    """The frame-to-frame rotations ``R_{k+1} R_kᵀ`` (sensor frame) of poses (N, 4, 4)."""
    return Rotation.from_matrix(T[1:, :3, :3] @ np.transpose(T[:-1, :3, :3], (0, 2, 1)))


@pytest.mark.parametrize("rate_deg", [2.0, 5.0, 10.0])
def test_tumbling_turns_the_requested_angle_every_frame_about_a_moving_axis(rate_deg) -> None:
    config = LabConfig(**motion_fields(f"tumbling-{rate_deg:g}"))
    _, T = lab_poses(config)
    steps = _steps(T)
    assert np.allclose(np.degrees(steps.magnitude()), rate_deg, atol=1e-9)
    axes = steps.as_rotvec() / steps.magnitude()[:, None]
    # The axis precesses: consecutive axes differ by the same small angle, and over the run
    # the axis sweeps a cone of tens of degrees about the fixed angular momentum.
    turn = np.degrees(np.arccos(np.clip(np.einsum("ij,ij->i", axes[1:], axes[:-1]), -1, 1)))
    assert turn.min() > 0.05 * rate_deg and np.ptp(turn) < 1e-6
    spread = np.degrees(np.arccos(np.clip(axes @ axes[0], -1, 1)))
    assert spread.max() > 8.0
    # Torque-free axisymmetric motion: every step axis keeps one angle to one fixed direction
    # (the axis of the cone the step axes sweep), found here as their circle's normal.
    centred = axes - axes.mean(axis=0)
    cone_axis = np.linalg.svd(centred)[2][2]
    assert np.ptp(axes @ cone_axis) < 1e-9
    # The slide still moves in constant steps, and the target origin stays on its path.
    assert np.allclose(np.diff(T[:, 0, 3]), config.step_m, atol=1e-15)
    assert np.allclose(T[:, 1:3, 3], [0.0, config.range_m])


def test_accelerating_ramps_both_rates_over_the_same_span() -> None:
    n = 30
    _, T = lab_poses(LabConfig(motion="accelerating", frames=n))
    _, T_const = lab_poses(LabConfig(frames=n))
    dx = np.diff(T[:, 0, 3])
    # Steps grow linearly from step/(N − 1) to step·(2N − 3)/(N − 1); same extremes as constant.
    assert np.allclose(dx, 0.010 * (2 * np.arange(n - 1) + 1) / (n - 1), atol=1e-15)
    assert np.allclose(T[[0, -1], :3, 3], T_const[[0, -1], :3, 3], atol=1e-15)
    angles = np.degrees(_steps(T).magnitude())
    assert np.allclose(angles, 1.0 * (2 * np.arange(n - 1) + 1) / (n - 1), atol=1e-9)
    assert np.allclose(_steps(T).as_rotvec()[:, [0, 2]], 0.0, atol=1e-15)  # still the vertical


def test_grid_default_cell_is_the_lab_run() -> None:
    config = grid_scenario(frames=2)
    assert (config.range_m, config.step_m, config.wall_distance_m) == (1.2, 0.01, 2.0)
    assert config.target_size_m == 0.89 and config.sensor == LabConfig().sensor
    grid, lab = simulate_lab(config).frame(1), simulate_lab(LabConfig(frames=2)).frame(1)
    assert np.array_equal(grid.cloud.points, lab.cloud.points)
    assert MOTIONS == ("constant", "accelerating", "tumbling-2", "tumbling-5", "tumbling-10")


@pytest.mark.parametrize(
    ("range_m", "sensor", "size"), [(0.5, "tof", 0.89 * 0.5 / 1.2), (3.0, "tof", 2.225)]
)
def test_grid_scales_the_scene_with_the_range(range_m, sensor, size) -> None:
    config = grid_scenario(range_m=range_m, clutter="wall-table", frames=3)
    assert config.sensor.model == sensor and config.target_size_m == pytest.approx(size)
    assert config.wall_distance_m == pytest.approx(2.0 * range_m / 1.2)
    assert config.step_m == pytest.approx(0.01 * size / 0.89)
    sim = simulate_lab(config.model_copy(update={"sensor": SMALL_TOF}))
    assert np.max(sim.target.mesh.extents) == pytest.approx(size, rel=1e-12)
    # The mock-up covers the same pixels at every range: its image scales with nothing.
    frame = sim.frame(1)
    lab = simulate_lab(LabConfig(frames=3, sensor=SMALL_TOF, background=True)).frame(1)
    assert frame.on_target.sum() == pytest.approx(lab.on_target.sum(), rel=0.02)
    far = grid_scenario(range_m=25.0, frames=2)
    assert far.sensor.model == "flash-lidar"
    # The same share of the flash LiDAR's 30° view as of the ToF's (half-width 320 / 483.6).
    expected = 0.89 * 25.0 / 1.2 * np.tan(np.radians(15.0)) / (320.0 / 483.6)
    assert far.target_size_m == pytest.approx(expected, rel=1e-9)


@pytest.mark.parametrize("name", ["hubble_model_kit.obj", "satellite_panels.obj"])
def test_mesh_targets_are_sized_and_turned_broadside(name) -> None:
    config = grid_scenario(target=str(MODELS / name), frames=2, motion="tumbling-10")
    sim = simulate_lab(config.model_copy(update={"sensor": SMALL_TOF}))
    extents = sim.target.mesh.extents
    assert extents[0] == pytest.approx(0.89, rel=1e-12) and extents[0] >= extents[1] >= extents[2]
    assert sim.frame(1).on_target.sum() > 1000


def test_tumbling_target_never_enters_the_turntable() -> None:
    config = grid_scenario(motion="tumbling-10", clutter="wall-table", frames=36)
    sim = simulate_lab(config)
    table, poses = sim.background[1]
    # The disc and the plinth: every table vertex off the post's axis (the post is 1 cm thick).
    off_post = np.linalg.norm(table.vertices[:, [0, 2]], axis=1) > 0.02
    for k in range(0, 36, 5):
        target = se3.transform_points(sim.T_sensor_target[k], sim.target.mesh.vertices)
        table_now = se3.transform_points(poses[k], table.vertices[off_post])
        assert target[:, 1].max() < table_now[:, 1].min()  # y is down: the table is below


def test_grid_errors_are_one_line() -> None:
    with pytest.raises(ConfigError, match="unknown motion 'wobble'"):
        grid_scenario(motion="wobble")
    with pytest.raises(ConfigError, match="unknown clutter 'forest'"):
        grid_scenario(clutter="forest")
    with pytest.raises(ConfigError, match="unknown sensor 'sonar'"):
        grid_scenario(sensor="sonar")
    with pytest.raises(ConfigError, match=r"motion .tumbling-120.: D must lie in \(0, 90\]"):
        grid_scenario(motion="tumbling-120")
    with pytest.raises(ConfigError, match="range"):
        grid_scenario(range_m=-1.0)


def test_the_wall_alone_leaves_out_the_turntable() -> None:
    """``clutter="wall"``: the target floats before the wall; every return off the target
    is the wall's, at its distance (the wall-and-table scene has nearer ones: the table)."""
    wall = simulate_lab(
        grid_scenario(clutter="wall", frames=1).model_copy(update={"sensor": SMALL_TOF})
    )
    table = simulate_lab(
        grid_scenario(clutter="wall-table", frames=1).model_copy(update={"sensor": SMALL_TOF})
    )
    assert len(wall.background) == 1 and len(table.background) == 2
    assert wall.albedo == table.albedo[:2]
    off = wall.frame(0)
    behind = off.cloud.points[~off.on_target & ~off.flying, 2]
    assert len(behind) > 1000 and behind.min() > 2.0 - 0.03  # the wall at 2 m, noise ~3 mm
    near = table.frame(0)
    assert near.cloud.points[~near.on_target & ~near.flying, 2].min() < 1.6
