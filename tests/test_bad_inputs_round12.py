"""Inputs found by a twelfth hostile round: each read, tracked or refused as it should be."""

from __future__ import annotations

import numpy as np

from spacepose.core.cloud import PointCloud
from spacepose.core.keyframes import PreparedCloud
from spacepose.core.relocalise import COARSE_POINTS, coarse_features
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
