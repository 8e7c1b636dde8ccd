"""The model's half turns and the test between a pose and its twin, on closed-form clouds."""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from spacepose.core import se3
from spacepose.core.grid import VoxelIndex
from spacepose.core.twins import compare_fits, principal_turns


def _box_surface(rng: np.random.Generator, sides: np.ndarray, n: int) -> np.ndarray:
    """(n, 3) points uniform on the faces of an axis-aligned box centred at the origin."""
    p = rng.uniform(-0.5, 0.5, (n, 3)) * sides
    axis = rng.integers(0, 3, n)
    p[np.arange(n), axis] = np.sign(rng.uniform(-1, 1, n)) * sides[axis] / 2
    return p


def test_principal_turns_are_the_half_turns_about_the_axes_through_the_centroid():
    rng = np.random.default_rng(0)
    sides = np.array([2.4, 1.8, 1.0])
    R = Rotation.from_euler("xyz", [20, -35, 50], degrees=True).as_matrix()
    centre = np.array([0.3, -1.2, 4.0])
    points = _box_surface(rng, sides, 20000) @ R.T + centre
    turns = principal_turns(points)
    assert len(turns) == 3
    # Eigenvalues ascending: the shortest side's axis first.
    for T, axis in zip(turns, (R[:, 2], R[:, 1], R[:, 0]), strict=True):
        assert np.allclose(T @ T, np.eye(4), atol=1e-12)
        assert np.allclose(T[:3, :3] @ axis, axis, atol=2e-2)
        assert np.isclose(np.trace(T[:3, :3]), -1.0)
        # The box maps onto itself, its centroid stays.
        c = points.mean(axis=0)
        assert np.allclose(se3.transform_points(T, c[None])[0], c)
        d, _ = cKDTree(points).query(se3.transform_points(T, points))
        assert np.quantile(d, 0.99) < 0.05


def test_a_box_square_about_an_axis_has_its_quarter_turns_as_twins_too():
    """A 1 x 1 x 1.6 box maps onto itself a quarter turn about its long axis: both quarter
    turns join the three half turns; a 1 x 1.3 x 1.6 box (variances 1.3 apart) has none."""
    rng = np.random.default_rng(1)
    R = Rotation.from_euler("xyz", [-15, 40, 10], degrees=True).as_matrix()
    centre = np.array([0.5, 0.2, 6.0])
    square = _box_surface(rng, np.array([1.0, 1.0, 1.6]), 20000) @ R.T + centre
    turns = principal_turns(square)
    assert len(turns) == 5
    quarters = [T for T in turns if np.isclose(np.trace(T[:3, :3]), 1.0, atol=1e-9)]
    assert len(quarters) == 2
    for T in quarters:
        assert np.allclose(T[:3, :3] @ R[:, 2], R[:, 2], atol=2e-2) or np.allclose(
            T[:3, :3] @ R[:, 2], -R[:, 2], atol=2e-2
        )
        assert abs(R[:, 2] @ Rotation.from_matrix(T[:3, :3]).as_rotvec()) > 0.99 * np.pi / 2
        d, _ = cKDTree(square).query(se3.transform_points(T, square))
        assert np.quantile(d, 0.99) < 0.05
    assert np.allclose(quarters[0] @ quarters[1], np.eye(4), atol=1e-12)
    oblong = _box_surface(rng, np.array([1.0, 1.3, 1.6]), 20000)
    assert len(principal_turns(oblong)) == 3


def test_compare_fits_decides_on_an_appendage_and_not_on_a_symmetric_box():
    rng = np.random.default_rng(1)
    sides = np.array([2.4, 1.8, 1.4])

    def antenna(n: int) -> np.ndarray:
        # Off the symmetry: the twin puts it 1 m from any model point.
        return rng.uniform([-0.1, -1.6, 0.3], [0.1, -1.2, 0.7], (n, 3))

    turn = se3.make_transform(np.diag([-1.0, 1.0, -1.0]), np.zeros(3))  # half turn about y
    T = se3.make_transform(Rotation.from_rotvec([0.2, -0.4, 0.1]).as_matrix(), [0.5, 0.2, 25.0])
    # The model densely sampled, the frame sampled apart (3,000 box points).
    cases = (
        (_box_surface(rng, sides, 40000), _box_surface(rng, sides, 3000), None),
        (
            np.vstack([_box_surface(rng, sides, 40000), antenna(1000)]),
            np.vstack([_box_surface(rng, sides, 3000), antenna(40)]),
            0,
        ),
    )
    for model, body, expected in cases:
        frame = se3.transform_points(T, body)
        test = compare_fits(VoxelIndex(model), frame, T, T @ turn, gate=0.08)
        assert test.winner == expected
        if expected is None:
            # Box points land on the box again: next to none tell the poses apart.
            assert test.only_first + test.only_second <= 3
        else:
            assert test.only_first >= 40 and test.only_second <= 3
            # The twin first: the same test, the other winner.
            swapped = compare_fits(VoxelIndex(model), frame, T @ turn, T, gate=0.08)
            assert swapped.winner == 1 and swapped.statistic == test.statistic
