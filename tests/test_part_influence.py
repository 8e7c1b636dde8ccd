"""The part influence of a registration (core/part_influence.py) against least squares solved
part by part with numpy, and on a second motion against white noise."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from spacepose.core import se3
from spacepose.core.part_influence import MIN_PART_PAIRS, part_influence
from spacepose.core.voxel import voxel_cells
from spacepose.errors import InputError


def _box_surface(rng: np.random.Generator, n: int, half: np.ndarray, centre: np.ndarray):
    """(n, 3) points spread over the three faces of a box a sensor at the origin sees, and
    their outward normals."""
    axes = rng.integers(0, 3, n)
    p = rng.uniform(-1.0, 1.0, (n, 3)) * half
    normals = np.zeros((n, 3))
    rows = np.arange(n)
    p[rows, axes] = -half[axes]  # the faces towards the origin (the box is at +z, +x, +y)
    normals[rows, axes] = -1.0
    return p + centre, normals


def _rows(points: np.ndarray, normals: np.ndarray) -> np.ndarray:
    return np.hstack([np.cross(points, normals), normals])


def _two_bodies(seed: int, turn_deg: float, sigma: float = 0.002):
    """A body and a smaller one below it; the second turned by ``turn_deg`` about its own
    centre between the two views. Returns points, normals, the residuals at the least-squares
    pose of all pairs (the compromise a registration settles on) and its covariance σ² H⁻¹."""
    rng = np.random.default_rng(seed)
    p1, n1 = _box_surface(rng, 6000, np.array([0.3, 0.2, 0.15]), np.array([0.1, 0.0, 1.5]))
    c2 = np.array([0.1, 0.45, 1.5])
    p2, n2 = _box_surface(rng, 3000, np.array([0.2, 0.15, 0.2]), c2)
    R = Rotation.from_euler("y", turn_deg, degrees=True).as_matrix()
    # The second body's pairs see its surface moved: a residual n·(R(p − c) + c − p).
    moved2 = (p2 - c2) @ R.T + c2
    points = np.vstack([p1, p2])
    normals = np.vstack([n1, n2])
    r = rng.normal(0.0, sigma, len(points))
    r[len(p1) :] += np.einsum("ij,ij->i", moved2 - p2, n2)
    J = _rows(points, normals)
    delta = np.linalg.lstsq(J, -r, rcond=None)[0]
    r_fit = r + J @ delta  # the residuals at the compromise pose
    H = J.T @ J
    return points, normals, r_fit, sigma**2 * np.linalg.inv(H)


def test_the_shift_is_least_squares_without_the_part() -> None:
    """For every part, the pose of the remaining pairs solved by numpy's lstsq, its shift from
    the pose of all pairs measured by the covariance: the largest is the function's."""
    points, normals, r, cov = _two_bodies(0, 0.3)
    size = 0.25
    _, part = voxel_cells(points, size)
    J = _rows(points, normals)
    full = np.linalg.lstsq(J, -r, rcond=None)[0]
    info = np.linalg.inv(cov)
    expected = []
    for p in np.unique(part):
        keep = part != p
        if (~keep).sum() < MIN_PART_PAIRS:
            continue
        d = np.linalg.lstsq(J[keep], -r[keep], rcond=None)[0] - full
        expected.append(d @ info @ d)
    found = part_influence(points, normals, r, cov, size)
    assert found is not None
    assert found.parts == len(expected)
    assert found.largest == pytest.approx(max(expected), rel=1e-6)


def test_a_second_motion_moves_the_pose_by_many_sigma() -> None:
    """White noise alone: no part moves the pose beyond its bound on any of 10 seeds (largest
    4.7 against 9). The second body turned by 0.5° about its centre: leaving one of its parts
    out moves the compromise by 22-50 squared σ, every seed beyond twice the bound."""
    rigid = [part_influence(*_two_bodies(s, 0.0), 0.25) for s in range(10)]
    turned = [part_influence(*_two_bodies(s, 0.5), 0.25) for s in range(10)]
    assert not any(r.excessive for r in rigid)
    assert max(r.largest for r in rigid) < 6.0
    assert min(t.largest / t.bound for t in turned) > 2.0


def test_a_part_with_half_the_information_has_a_higher_bound() -> None:
    """Parts of 10 m cut the two bodies into four large parts: noise alone moves the pose by
    up to 15 squared σ when one is left out, and the bound follows their leverage (25-161);
    the turned body still exceeds it on 9 of 10 seeds."""
    rigid = [part_influence(*_two_bodies(s, 0.0), 10.0) for s in range(10)]
    turned = [part_influence(*_two_bodies(s, 0.5), 10.0) for s in range(10)]
    assert max(r.largest for r in rigid) > 9.0 and not any(r.excessive for r in rigid)
    assert min(r.bound for r in rigid) > 20.0
    assert sum(t.excessive for t in turned) >= 9


def test_weights_take_a_pair_out() -> None:
    """A zero weight is the pair left out: the same influence as without it."""
    points, normals, r, cov = _two_bodies(1, 0.2)
    w = np.ones(len(points))
    w[::7] = 0.0
    keep = w > 0
    a = part_influence(points, normals, r, cov, 0.25, w)
    b = part_influence(points[keep], normals[keep], r[keep], cov, 0.25)
    assert a.largest == pytest.approx(b.largest, rel=1e-9)


def test_a_covariance_twice_as_wide_halves_the_influence() -> None:
    points, normals, r, cov = _two_bodies(2, 0.2)
    one = part_influence(points, normals, r, cov, 0.25).largest
    two = part_influence(points, normals, r, 2.0 * cov, 0.25).largest
    assert two == pytest.approx(one / 2.0, rel=1e-9)


def test_one_part_is_nothing_to_compare() -> None:
    points, normals, r, cov = _two_bodies(3, 0.0)
    inside = points + 10.0  # all in the one cell [0, 100) of each axis
    assert part_influence(inside, normals, r, cov, 100.0) is None
    assert part_influence(points[:0], normals[:0], r[:0], cov, 0.25) is None


def test_the_pose_frame_does_not_matter() -> None:
    """Points moved by a whole number of parts (the same parts) and the covariance moved with
    them: the same influence."""
    points, normals, r, cov = _two_bodies(4, 0.3)
    T = np.eye(4)
    T[:3, 3] = [0.5, -1.0, 2.0]
    Ad = se3.adjoint(T)
    a = part_influence(points, normals, r, cov, 0.25)
    b = part_influence(points + T[:3, 3], normals, r, Ad @ cov @ Ad.T, 0.25)
    assert b.largest == pytest.approx(a.largest, rel=1e-6)
    assert b.bound == pytest.approx(a.bound, rel=1e-6)


def test_bad_inputs_raise() -> None:
    points, normals, r, cov = _two_bodies(5, 0.0)
    with pytest.raises(InputError, match="residuals"):
        part_influence(points, normals, r[:3], cov, 0.25)
    with pytest.raises(InputError, match="positive"):
        part_influence(points, normals, r, cov, 0.0)
    bad = r.copy()
    bad[3] = np.nan
    with pytest.raises(InputError, match="finite"):
        part_influence(points, normals, bad, cov, 0.25)
    with pytest.raises(InputError, match="weights >= 0"):
        part_influence(points, normals, r, cov, 0.25, -np.ones(len(r)))
    with pytest.raises(InputError, match="covariance"):
        part_influence(points, normals, r, cov[:3, :3], 0.25)
