"""Inputs found by a twelfth hostile round: each read, tracked or refused as it should be."""

from __future__ import annotations

import numpy as np

from spacepose.cli import main
from spacepose.core.cloud import PointCloud
from spacepose.core.frame_preparation import FramePreparer
from spacepose.core.keyframes import PreparedCloud
from spacepose.core.relocalise import COARSE_POINTS, coarse_features
from spacepose.core.sim import simulate
from spacepose.core.sim.grid import grid_scenario
from spacepose.core.tracker import Tracker
from spacepose.core.tracker_config import TrackerConfig, stage_lengths
from spacepose.core.voxel import voxel_downsample

# -- A frame of depth noise: the coarse stage describes a bounded number of points ---------------


def test_the_coarse_stage_describes_a_volume_of_noise_at_a_bounded_number_of_points():
    """A depth map of noise fills a volume, not a surface: at the lab's coarse voxel its 300,000
    points were 292,000 cells, whose FPFH and feature matching took 4.3 s of a 6.3 s frame.
    The stage now describes at most ``COARSE_POINTS`` of them, spread over the whole volume."""
    lengths = stage_lengths(TrackerConfig(), voxel=0.006, radius=0.1)
    rng = np.random.default_rng(0)
    noise = PointCloud(rng.uniform([-0.5, -0.4, 0.5], [0.5, 0.4, 3.0], (300_000, 3)))
    sparse, features = coarse_features(PreparedCloud(noise), lengths, outward=False, workers=2)
    cells = voxel_downsample(noise, lengths.coarse_voxel)
    assert len(cells) > 20 * COARSE_POINTS
    assert len(sparse) == COARSE_POINTS and features.shape == (COARSE_POINTS, 33)
    # Spread: the kept cells span the volume's depth, not its first slab.
    np.testing.assert_allclose(
        np.ptp(sparse.points, axis=0), np.ptp(cells.points, axis=0), rtol=0.02
    )


def test_the_coarse_stage_keeps_every_cell_of_a_surface():
    """A surface at the coarse voxel is far below the bound: its cells are described as before."""
    lengths = stage_lengths(TrackerConfig(), voxel=0.006, radius=0.1)
    u, v = np.meshgrid(np.linspace(-0.2, 0.2, 200), np.linspace(-0.15, 0.15, 150))
    surface = PointCloud(np.column_stack([u.ravel(), v.ravel(), 1.2 + 0.1 * u.ravel() ** 2]))
    sparse, _ = coarse_features(PreparedCloud(surface), lengths, outward=False, workers=2)
    np.testing.assert_array_equal(
        sparse.points, voxel_downsample(surface, lengths.coarse_voxel).points
    )


# -- The lab's background removal at another range -----------------------------------------------


def test_a_lab_run_moved_behind_its_wall_is_refused_in_one_line(tmp_path, capsys):
    """``simulate lab --range 3 --background`` kept the wall at 2 m: every frame saw the wall
    alone, and the tracker was left to call a plane degenerate."""
    out = tmp_path / "run"
    args = ["simulate", "lab", "--range", "3", "--background", "--frames", "2", "--out", str(out)]
    assert main(args) == 1
    err = capsys.readouterr().err.strip()
    assert err.startswith("error: the wall at 2 m stands before or through the target (up to ")
    assert "\n" not in err and not out.exists()
    assert main([*args[:-2], "--grid", "--out", str(out)]) == 0  # the wall at 5/3 of the range


def test_background_removal_in_the_tracker_keeps_a_target_beyond_the_lab_range():
    """The tracker's background removal gated ranges at 1.8 m, the lab's: every frame of a
    target at 3 m was lost ("no point within the range gate 0.0..1.8 m")."""
    assert TrackerConfig().background.range_max is None
    sim = simulate(grid_scenario(range_m=3.0, clutter="wall-table", frames=1))
    frame = sim.frame(0)
    config = TrackerConfig(use_background_removal=True)
    result = Tracker(config, workers=2).track_frame(frame.cloud, frame.timestamp)
    assert result.status == "ok", result.reasons
    # What the frame kept is the target: within its reach of its centre (the wall is not).
    kept = FramePreparer(config, None, 2).prepare(frame.cloud, None).cloud.points
    reach = np.linalg.norm(sim.target.mesh.vertices, axis=1).max()
    centre = sim.T_sensor_target[0][:3, 3]
    assert len(kept) > 1000
    assert np.all(np.linalg.norm(kept - centre, axis=1) < reach)
