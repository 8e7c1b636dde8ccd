"""Which points are the target (core/segmentation.py): synthetic scenes with a known answer."""

from __future__ import annotations

import numpy as np
import pytest

from spacepose.core.segmentation import crop_sphere, nearest_object, region_of


def _plate(center, size, normal_axis, step, rng):
    """Points every ``step`` m (jittered by 2 % of it) on an axis-aligned plate."""
    axes = [a for a in range(3) if a != normal_axis]
    u = np.arange(-size[0] / 2, size[0] / 2, step)
    v = np.arange(-size[1] / 2, size[1] / 2, step)
    U, V = np.meshgrid(u, v)
    pts = np.zeros((U.size, 3))
    pts[:, axes[0]], pts[:, axes[1]] = U.ravel(), V.ravel()
    pts += np.asarray(center) + rng.normal(0, 0.02 * step, pts.shape)
    return pts


@pytest.mark.parametrize("scale", [1.0, 20.0])
def test_nearest_object_keeps_the_target_and_its_parts_and_drops_the_wall(scale):
    rng = np.random.default_rng(0)
    s = 0.003 * scale
    bus = _plate(np.array([0.0, 0.0, 1.2]) * scale, (0.2 * scale, 0.16 * scale), 2, s, rng)
    # A wing 8 cm from the bus (its boom unseen), and a wall 0.8 m behind.
    wing = _plate(np.array([0.28, 0.0, 1.22]) * scale, (0.2 * scale, 0.1 * scale), 2, s, rng)
    wall = _plate(np.array([0.0, 0.0, 2.0]) * scale, (2.0 * scale, 1.5 * scale), 2, 2 * s, rng)
    stray = rng.uniform(-0.5, 0.5, (5, 3)) * scale + np.array([0, 0, 1.6]) * scale
    pts = np.r_[bus, wing, wall, stray]
    mask = nearest_object(pts, s)
    n_target = len(bus) + len(wing)
    assert mask[:n_target].all()
    assert not mask[n_target:].any()


def test_a_part_behind_the_nearest_piece_is_merged_but_the_wall_around_the_object_is_not():
    """A dish 4 cm in front of a wide bus (the nearest piece, its mount unseen) grows by the
    bus, which is larger and spans it in the view but is not wholly behind it; a wall within
    the grown object's reach that is wholly behind it and seen past it on every side is the
    background (the lab mock-up seen with a wall 0.8 of its range behind)."""
    rng = np.random.default_rng(2)
    s = 0.004
    dish = _plate([0.0, 0.0, 1.1], (0.1, 0.1), 2, s, rng)
    bus = _plate([0.0, 0.0, 1.14], (0.6, 0.3), 2, s, rng)
    wall = _plate([0.0, 0.0, 1.35], (2.0, 1.5), 2, 2 * s, rng)
    pts = np.r_[dish, bus, wall]
    mask = nearest_object(pts, s)
    n_target = len(dish) + len(bus)
    assert mask[:n_target].all()
    # The wall is 0.19 m behind the bus, within the grown object's 0.26 m reach: the gap rule
    # alone merges it (the previous rule did).
    assert not mask[n_target:].any()


def test_a_lone_target_is_kept_whole_and_a_far_cluster_is_not_merged():
    rng = np.random.default_rng(1)
    plate = _plate([0.0, 0.0, 25.0], (4.0, 2.0), 2, 0.1, rng)
    assert nearest_object(plate, 0.1).all()
    # A second object 3 m away (more than half the first one's size): not merged.
    other = _plate([6.0, 0.0, 26.0], (2.0, 2.0), 2, 0.1, rng)
    mask = nearest_object(np.r_[plate, other], 0.1)
    assert mask[: len(plate)].all() and not mask[len(plate) :].any()


def test_region_and_crop_closed_form():
    pts = np.array([[1.0, 0, 0], [-1.0, 0, 0], [0, 2.0, 0], [0, -2.0, 0]])
    region = region_of(pts)
    np.testing.assert_allclose(region.center, 0.0)
    assert region.radius == pytest.approx(2.0)
    assert crop_sphere(pts, [1.0, 0, 0], 1.0).tolist() == [0]


def test_a_frame_of_many_small_pieces_keeps_the_nearest_one():
    # 100 blobs of 30 points, 1 m apart, none a 2 % share of the frame (was a raw ValueError).
    rng = np.random.default_rng(0)
    pts = np.concatenate([rng.normal(0, 0.01, (30, 3)) + np.array([x, 0, 2]) for x in range(100)])
    mask = nearest_object(pts, 0.004)
    # One whole blob, nothing of the others (the largest-by-cells among equals; here blob 36).
    kept = np.flatnonzero(mask)
    assert len(kept) == 30 and len(set(kept // 30)) == 1


def _view(center_z, half_width, half_height, step_rad, rng):
    """Points of a fronto-parallel plate at ``center_z`` m sampled as a camera does: one per
    ``step_rad`` of view angle, so the spacing grows with range (jittered by 2 % of it)."""
    u = np.arange(-half_width, half_width, step_rad * center_z)
    v = np.arange(-half_height, half_height, step_rad * center_z)
    U, V = np.meshgrid(u, v)
    pts = np.c_[U.ravel(), V.ravel(), np.full(U.size, center_z)]
    return pts + rng.normal(0, 0.02 * step_rad * center_z, pts.shape)


def test_a_small_target_before_a_far_wall_is_found_by_its_share_of_the_view():
    """A 0.6 m plate at 3 m before a wall at 5 m, sampled every 2 mrad: the plate holds 4 % of
    the points but, in cells sized by the wall's spacing, 1.5 % of the cells (the share rule by
    cells alone kept the wall)."""
    rng = np.random.default_rng(3)
    target = _view(3.0, 0.3, 0.3, 0.002, rng)
    wall = _view(5.0, 3.0, 2.0, 0.002, rng)
    pts = np.r_[target, wall]
    assert 0.03 < len(target) / len(pts) < 0.05
    mask = nearest_object(pts, 0.002 * 5.0)
    assert mask[: len(target)].all()
    assert not mask[len(target) :].any()


@pytest.mark.parametrize(("target", "range_m"), [("lab", 3.0), ("panels", 3.0), ("hubble", 1.2)])
def test_a_target_alone_before_a_wall_is_found_in_a_simulated_frame(target, range_m):
    """The simulator's first frame, the wall at 5/3 of the range, flying pixels trailing from
    the silhouette towards the wall: the target's own points (the renderer's labels) are kept,
    the wall is not, and the kept points' extent is the target's. Before the share of points,
    the wall was kept at 3 m; before flying pixels were left out of the clusters, Hubble's
    region at 1.2 m reached 0.89 m from its centre (its own points: 0.55 m) and took in the
    wall."""
    from spacepose.core.scale import point_spacing
    from spacepose.core.sim import grid_scenario, simulate
    from spacepose.tools.experiments.robustness_cells import mesh_path

    config = grid_scenario(target=mesh_path(target), range_m=range_m, clutter="wall", frames=1)
    frame = simulate(config).frame(0)
    pts = frame.cloud.points
    mask = nearest_object(pts, point_spacing(pts))
    assert (mask & frame.on_target).sum() >= 0.95 * frame.on_target.sum()
    assert (mask & ~frame.on_target).sum() <= 0.02 * mask.sum()
    own = pts[frame.on_target & ~frame.flying]
    extent = region_of(own).radius
    assert region_of(pts[mask]).radius < 1.05 * extent


def test_no_returns_at_the_sensor_are_never_the_object():
    """Drivers write a pixel with no return as a point at the origin: 5,107 of the 69,792
    points of the real LiDAR scan in data/real. Before, they passed the share of points and,
    nearest the sensor, were taken for the object (and the tracker lost every frame with
    "every point is at the same place")."""
    from pathlib import Path

    from spacepose.core.reach import returns
    from spacepose.core.scale import point_spacing
    from spacepose.tools.cloud_io import read_cloud

    rng = np.random.default_rng(3)
    target = _view(3.0, 0.3, 0.3, 0.002, rng)
    wall = _view(5.0, 3.0, 2.0, 0.002, rng)
    clean = np.r_[target, wall]
    zeros = np.zeros((len(clean) // 10, 3))
    mask = nearest_object(np.r_[clean, zeros], 0.002 * 5.0)
    np.testing.assert_array_equal(mask[: len(clean)], nearest_object(clean, 0.002 * 5.0))
    assert not mask[len(clean) :].any() and mask[: len(target)].all()
    scan = read_cloud(Path(__file__).resolve().parents[1] / "data/real/small_gicp/source.ply")
    at_sensor = ~returns(scan.points)
    assert at_sensor.sum() == 5107
    kept = nearest_object(scan.points, point_spacing(scan.points))
    assert kept.sum() > 1000 and not (kept & at_sensor).any()


def test_a_return_is_any_point_with_a_nonzero_coordinate():
    """Only (0, 0, 0), either sign of zero, is no return; a point on an axis is one. A
    non-finite point is an input error, not a missing return."""
    from spacepose.core.reach import returns
    from spacepose.errors import InputError

    pts = np.array(
        [[0.0, 0.0, 0.0], [-0.0, 0.0, -0.0], [0.0, 0.0, 1.5], [0.0, -2.0, 0.0], [1e-300, 0, 0]]
    )
    np.testing.assert_array_equal(returns(pts), [False, False, True, True, True])
    with pytest.raises(InputError, match="non-finite"):
        returns(np.array([[np.nan, 0.0, 0.0]]))


def earth_behind(near: np.ndarray, share: float, rng: np.random.Generator) -> np.ndarray:
    """Returns of an Earth 400-1,200 km away filling the lower ``share`` of a 60° × 45° view,
    around the directions ``near`` (N, 3) covers, as a renderer's depth gives them."""
    u, v = np.meshgrid(np.linspace(-0.58, 0.58, 160), np.linspace(-0.41, 0.41, 113))
    rays = np.c_[u.ravel(), v.ravel(), np.ones(u.size)]
    rays = rays[rays[:, 1] > 0.41 * (1.0 - 2.0 * share)]
    from scipy.spatial import cKDTree

    gap, _ = cKDTree(near[:, :2] / near[:, 2:]).query(rays[:, :2])
    rays = rays[gap > 0.015]
    return rays * (4e5 * (1.0 + 2.0 * rays[:, 1:2] / 0.41) + rng.normal(0, 0.5, (len(rays), 1)))


def test_returns_far_beyond_the_frame_are_out_of_reach_and_of_the_object():
    """A renderer's Earth 400 km behind a target 3 m away: a grid of the target's cells could
    not number cells out to it, and the nearest object ended in "cells ... too many to number"
    (every frame lost). The far returns are out of reach and never the object; the near ones
    split as without them. A room seen from 0.3 to 6 m keeps every return."""
    from spacepose.core.reach import within_reach

    rng = np.random.default_rng(5)
    target = _view(3.0, 0.3, 0.3, 0.002, rng)
    wall = _view(5.0, 1.0, 0.8, 0.002, rng)
    near = np.r_[target, wall]
    earth = earth_behind(near, 0.4, rng)
    pts = np.r_[near, earth]
    np.testing.assert_array_equal(within_reach(pts), np.arange(len(pts)) < len(near))
    mask = nearest_object(pts, 0.002 * 5.0)
    np.testing.assert_array_equal(mask[: len(near)], nearest_object(near, 0.002 * 5.0))
    assert mask[: len(target)].all() and not mask[len(target) :].any()
    room = np.r_[_view(0.3, 0.1, 0.1, 0.002, rng), _view(6.0, 3.0, 1.5, 0.002, rng)]
    assert within_reach(room, workers=2).all()


def test_reach_is_numpys_on_any_thread_count():
    """The compiled pass (returns, least and largest range) against numpy: no-returns at the
    sensor mixed in, a far cluster that needs the median, and a frame without any return."""
    from spacepose.core.reach import _FARTHEST_RANGES, returns, within_reach

    rng = np.random.default_rng(11)
    pts = np.r_[rng.normal([0, 0, 2.0], 0.3, (997, 3)), rng.normal([0, 0, 900.0], 5.0, (30, 3))]
    pts[rng.choice(len(pts), 150, replace=False)] = 0.0
    valid = np.any(pts != 0.0, axis=1)
    ranges = np.linalg.norm(pts, axis=1)
    expected = valid & (ranges <= _FARTHEST_RANGES * np.median(ranges[valid]))
    assert 0 < (valid & ~expected).sum() <= 30
    for workers in (1, 2, 3):
        np.testing.assert_array_equal(returns(pts, workers), valid)
        np.testing.assert_array_equal(within_reach(pts, workers), expected)
    near = pts[expected]
    assert within_reach(near, 2).all()
    assert not within_reach(np.zeros((5, 3)), 2).any()


def _view_grid(depth, width, height, pitch):
    """Points of a ``width`` × ``height`` pixel camera of angular ``pitch`` (rad) whose rays meet
    ``depth(x, y)`` (z, m, on each ray's direction (x, y, 1))."""
    u = (np.arange(width) - width / 2) * pitch
    v = (np.arange(height) - height / 2) * pitch
    X, Y = np.meshgrid(u, v)
    Z = depth(X, Y)
    return np.column_stack([X.ravel() * Z.ravel(), Y.ravel() * Z.ravel(), Z.ravel()])


@pytest.mark.parametrize("box_m", [2.0, 1.0])
def test_a_small_target_far_before_a_wall_that_fills_the_view_is_the_object(box_m):
    """A box at 20 m before a wall at 30 m that fills a 73° view: 0.8 % of the points (box
    2 m; 1 m: 0.2 %), below the share that makes a cluster real, and the wall was taken for
    the target (every frame then lost: a plane is degenerate)."""
    half = box_m / 2 / 20.0  # the box's half-width as a tangent

    def depth(x, y):
        return np.where((np.abs(x) < half) & (np.abs(y) < half), 20.0, 30.0)

    pts = _view_grid(depth, 320, 240, 0.004)
    box = pts[:, 2] < 25.0
    assert 100 <= box.sum() < 0.01 * len(pts)
    mask = nearest_object(pts, 0.12, min_points=100)
    np.testing.assert_array_equal(mask, box)


def test_a_cluster_before_a_wall_with_fewer_points_than_a_frame_needs_is_not_the_object():
    """Debris of 49 returns before the wall: too few to track, so the wall stays the object
    (the rule before backdrops), rather than a frame of 49 points."""

    def depth(x, y):
        return np.where((np.abs(x) < 0.016) & (np.abs(y) < 0.016), 20.0, 30.0)

    pts = _view_grid(depth, 320, 240, 0.004)
    debris = pts[:, 2] < 25.0
    assert debris.sum() == 49
    mask = nearest_object(pts, 0.12, min_points=100)
    assert not mask[debris].any() and mask[~debris].all()


def test_with_a_model_the_body_behind_a_dish_pointed_at_the_sensor_is_part_of_the_object():
    """A 0.36 m dish 0.7 m before a 1 m bus at 5 m, its boom unseen: by its own size the dish
    is the object and the bus, wholly behind it and around it in the view, its background.
    Given the model's radius (1.33 m), the bus fits with the dish in the model's diameter and
    joins it; a wall 3 m behind, spanning the view, does not."""
    rng = np.random.default_rng(4)
    s = 0.01
    dish = _plate([0.2, 0.1, 3.7], (0.36, 0.36), 2, s, rng)
    bus = _plate([0.0, 0.0, 4.4], (1.0, 1.0), 2, s, rng)
    wall = _plate([0.0, 0.0, 7.4], (4.0, 3.0), 2, 4 * s, rng)
    pts = np.r_[dish, bus, wall]
    alone = nearest_object(pts, s)
    assert alone[: len(dish)].all() and not alone[len(dish) :].any()
    mask = nearest_object(pts, s, model_radius=1.33)
    n_target = len(dish) + len(bus)
    assert mask[:n_target].all()
    assert not mask[n_target:].any()
    # A model half the size does not reach the bus.
    assert not nearest_object(pts, s, model_radius=0.5)[len(dish) : n_target].any()
