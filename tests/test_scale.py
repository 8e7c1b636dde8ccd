"""Lengths from the data (core/scale.py) against closed forms."""

from __future__ import annotations

import numpy as np
import pytest

from spacepose.core.scale import (
    NOISE_VOXELS,
    derive_scale,
    point_spacing,
    range_noise,
    rms_radius,
    voxel_for,
)
from spacepose.errors import InputError


def _grid(n: int, step: float) -> np.ndarray:
    """A flat n × n square grid of pitch ``step`` in the z = 1 plane."""
    u, v = np.meshgrid(np.arange(n) * step, np.arange(n) * step)
    return np.c_[u.ravel(), v.ravel(), np.ones(n * n)]


def test_spacing_of_a_square_grid_is_its_pitch():
    assert point_spacing(_grid(40, 0.003)) == pytest.approx(0.003, rel=1e-9)
    # Sampled (2,000 of 10,000 query points): still every nearest neighbour is one pitch away.
    assert point_spacing(_grid(100, 0.05)) == pytest.approx(0.05, rel=1e-9)


def test_spacing_ignores_duplicates_when_most_points_are_doubled():
    pts = _grid(20, 0.01)
    assert point_spacing(np.r_[pts, pts]) == pytest.approx(0.01, rel=1e-9)
    with pytest.raises(InputError, match="same place"):
        point_spacing(np.zeros((10, 3)))
    with pytest.raises(InputError, match="at least two"):
        point_spacing(np.zeros((1, 3)))


def test_spacing_is_the_median_nearest_distance_of_scipys_tree():
    """Against scipy's balanced tree (each sampled point's nearest other point), on a target
    before a sparse far cluster, where a grid index is slow and a tree is not."""
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(4)
    near = rng.normal(0, 0.3, (6000, 3)) + np.array([0, 0, 2.0])
    far = rng.normal(0, 1e4, (500, 3)) + np.array([0, 0, 4e5])
    pts = np.r_[near, far]
    query = pts[np.sort(np.random.default_rng(0).choice(len(pts), 2000, replace=False))]
    expected = np.median(cKDTree(pts).query(query, k=2)[0][:, 1])
    assert point_spacing(pts) == expected


def test_voxel_keeps_about_the_requested_points():
    # A 0.3 m square sampled every 1 mm (90,000 points): for 2,500 points the voxel is
    # sqrt(0.09 / 2500) = 6 mm, and a 6 mm grid on the plane has 50 × 50 cells.
    pts = _grid(300, 0.001)
    v = voxel_for(point_spacing(pts), len(pts), 2500)
    assert v == pytest.approx(0.006, rel=1e-9)
    scale = derive_scale(pts, 2500)
    assert scale.voxel == pytest.approx(0.006, rel=1e-9)
    # The radius is that of the cell centroids: a uniform square of side a has RMS radius a/√6.
    assert scale.radius == pytest.approx(0.3 / np.sqrt(6), rel=0.02)
    # Never finer than the sampling itself.
    assert voxel_for(0.01, 100, 10_000) == 0.01


def test_scale_is_proportional_to_the_data():
    pts = _grid(120, 0.002) + np.random.default_rng(0).normal(0, 2e-4, (14400, 3))
    a, b = derive_scale(pts, 3000), derive_scale(10.0 * pts, 3000)
    assert b.spacing == pytest.approx(10 * a.spacing, rel=1e-9)
    assert b.voxel == pytest.approx(10 * a.voxel, rel=1e-9)
    assert b.radius == pytest.approx(10 * a.radius, rel=1e-6)
    assert rms_radius(pts) == pytest.approx(np.sqrt(((pts - pts.mean(0)) ** 2).sum(1).mean()))


def _tilted_plane_frame(sigma: float, seed: int, pixels: int = 160) -> np.ndarray:
    """A pinhole sensor's frame (focal 480 px) of a plane 2 m ahead tilted 25°, each range
    drawn with noise ``sigma`` along its ray: (pixels², 3) points in the sensor frame."""
    rng = np.random.default_rng(seed)
    c = (np.arange(pixels) - pixels / 2) / 480.0
    x, y = np.meshgrid(c, c)
    rays = np.c_[x.ravel(), y.ravel(), np.ones(x.size)]
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    normal = np.array([np.sin(np.radians(25.0)), 0.0, -np.cos(np.radians(25.0))])
    ranges = -2.0 * normal[2] / -(rays @ normal)
    return rays * (ranges + rng.normal(0.0, sigma, len(rays)))[:, None]


@pytest.mark.parametrize("sigma", [0.001, 0.01, 0.05])
def test_range_noise_recovers_the_noise_along_the_rays(sigma):
    # From 1 mm (below the 4 mm spacing) to 50 mm (12 spacings, where neighbourhoods in space
    # are thicker than wide): the median of a χ with 13 degrees of freedom is 0.974 σ.
    for seed in (0, 1):
        est = range_noise(_tilted_plane_frame(sigma, seed))
        assert 0.93 * sigma < est < 1.03 * sigma
    # 160,000 points: a seeded subset of 100,000 is indexed, neighbours a pixel or two apart.
    est = range_noise(_tilted_plane_frame(sigma, 2, pixels=400))
    assert 0.93 * sigma < est < 1.03 * sigma
    with pytest.raises(InputError, match="k >= 4"):
        range_noise(_tilted_plane_frame(sigma, 0), k=3)


def test_noise_grows_the_voxel_of_a_dense_frame_at_most_twice():
    quiet, loud, louder = (derive_scale(_tilted_plane_frame(s, 0), 3000) for s in (1e-3, 0.02, 0.1))
    # 25,600 points for 3,000: the spacing gives a voxel of about three spacings (12 mm at 1 mm
    # of noise, 18 mm at 20 mm, which 1.5 σ takes to 29 mm; 100 mm of noise: twice 30 mm).
    assert quiet.voxel == pytest.approx(voxel_for(quiet.spacing, quiet.points, 3000))
    assert loud.voxel == pytest.approx(NOISE_VOXELS * loud.noise, rel=1e-12)
    assert loud.voxel > 1.5 * voxel_for(loud.spacing, loud.points, 3000)
    assert louder.voxel == pytest.approx(2.0 * voxel_for(louder.spacing, louder.points, 3000))
    # A frame sparser than the target count keeps its spacing, however noisy.
    sparse = derive_scale(_tilted_plane_frame(0.01, 0, pixels=40), 3000)
    assert sparse.voxel == sparse.spacing
    assert derive_scale(_tilted_plane_frame(0.01, 0), 3000, voxel_size=0.005).voxel == 0.005


def test_a_configured_voxel_wider_than_the_frame_is_named(tmp_path, capsys) -> None:
    """A tracker config's voxel_size of 1000 m was reported as "4 points after preprocessing
    (< 100)" on every frame, the setting not named."""
    from spacepose.cli import main
    from spacepose.core.cloud import PointCloud

    grid = np.stack(np.meshgrid(np.linspace(-0.45, 0.45, 60), np.linspace(-0.3, 0.3, 40)), -1)
    points = np.c_[grid.reshape(-1, 2), np.full(2400, 1.2)]
    with pytest.raises(InputError, match=r"^f.ply: the configured voxel_size 1000 m is wider "
                       r"than the frame \(0\.9 m across\)$"):  # fmt: skip
        derive_scale(PointCloud(points, source="f.ply"), 3000, voxel_size=1000.0)
    assert derive_scale(points, 3000, voxel_size=0.01).voxel == 0.01
    frames = tmp_path / "frames"
    frames.mkdir()
    for k in range(2):
        np.save(frames / f"{k}.npy", points)
    (tmp_path / "cfg.yaml").write_text("voxel_size: 1000\n")
    args = ["track", str(frames), "--out", str(tmp_path / "e.tum"), "--config"]
    assert main([*args, str(tmp_path / "cfg.yaml")]) == 1
    err = capsys.readouterr().err
    assert "every frame was lost" in err and "configured voxel_size 1000 m is wider" in err, err
