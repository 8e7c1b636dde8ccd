"""Cramér–Rao bound: degenerate plane, hand-derived Fisher matrix, numeric Jacobian, Monte Carlo."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from spacepose.core import se3
from spacepose.core.crlb import crlb, fisher_point_to_plane, range_sigma_along_normal
from spacepose.errors import InputError


def _box_corner(n_side: int) -> tuple[np.ndarray, np.ndarray]:
    """Grid points on the three faces x=1, y=1, z=1 of the unit cube [0, 1]³ (seen from a
    sensor beyond the corner (1, 1, 1)), with outward normals."""
    u, v = np.meshgrid(*(np.linspace(0.1, 0.9, n_side),) * 2)
    u, v, one = u.ravel(), v.ravel(), np.ones(u.size)
    points = np.vstack(
        [np.column_stack([one, u, v]), np.column_stack([u, one, v]), np.column_stack([u, v, one])]
    )
    normals = np.repeat(np.eye(3), u.size, axis=0)
    return points, normals


def test_single_plane_is_degenerate_with_the_right_null_space(rng: np.random.Generator) -> None:
    # A tilted plane that does not pass through the origin.
    R = Rotation.from_rotvec([0.3, -0.5, 0.2]).as_matrix()
    local = np.column_stack([rng.uniform(-1, 1, (200, 2)), np.zeros(200)])
    points = local @ R.T + np.array([0.5, -1.0, 4.0])
    normals = np.tile(R[:, 2], (200, 1))
    bound = crlb(points, normals, 0.01)
    assert bound.rank == 3
    assert bound.degenerate
    assert bound.null_directions.shape == (6, 3)
    # Expected unobservable twists: rotation about the normal, translations within the plane.
    expected = np.zeros((6, 3))
    expected[:3, 0] = R[:, 2]
    expected[3:, 1] = R[:, 0]
    expected[3:, 2] = R[:, 1]
    P_got = bound.null_directions @ bound.null_directions.T
    np.testing.assert_allclose(P_got, expected @ expected.T, atol=1e-9)
    # Every rotation axis and every translation axis touches the null space of a tilted plane.
    assert np.all(np.isinf(bound.std))
    # The observable part: the displacement of the centroid c along the normal, twist
    # a = (c × n, n), is the mean of N residuals, so its variance is σ²/N.
    c = points.mean(axis=0)
    a = np.concatenate([np.cross(c, R[:, 2]), R[:, 2]])
    assert a @ bound.covariance @ a == pytest.approx(0.01**2 / 200, rel=1e-9)


def test_axis_aligned_plane_reports_finite_std_on_observable_axes() -> None:
    u, v = np.meshgrid(np.linspace(-1, 1, 5), np.linspace(-1, 1, 5))
    points = np.column_stack([u.ravel(), v.ravel(), np.full(25, 3.0)])
    bound = crlb(points, np.tile([0.0, 0, 1], (25, 1)), 1.0)
    # Hand-derived: h = (y, −x, 0, 0, 0, 1), so J = diag(Σy², Σx², 0, 0, 0, N).
    sum_sq = 5 * np.sum(np.linspace(-1, 1, 5) ** 2)
    np.testing.assert_allclose(bound.information, np.diag([sum_sq, sum_sq, 0, 0, 0, 25]))
    np.testing.assert_allclose(
        bound.std, [1 / np.sqrt(sum_sq), 1 / np.sqrt(sum_sq), np.inf, np.inf, np.inf, 0.2]
    )


def test_box_corner_matches_hand_derived_fisher() -> None:
    points, normals = _box_corner(3)
    # Hand-derived h = (p × n, n) per face:
    #   x = 1, n = e_x, p = (1, u, v): p × e_x = (0, v, −u)
    #   y = 1, n = e_y, p = (u, 1, v): p × e_y = (−v, 0, u)
    #   z = 1, n = e_z, p = (u, v, 1): p × e_z = (v, −u, 0)
    n = len(points) // 3
    fx, fy, fz = points[:n], points[n : 2 * n], points[2 * n :]
    H = np.vstack(
        [
            np.column_stack(
                [0 * fx[:, 1], fx[:, 2], -fx[:, 1], np.ones(n), 0 * fx[:, 0], 0 * fx[:, 0]]
            ),
            np.column_stack(
                [-fy[:, 2], 0 * fy[:, 0], fy[:, 0], 0 * fy[:, 0], np.ones(n), 0 * fy[:, 0]]
            ),
            np.column_stack(
                [fz[:, 1], -fz[:, 0], 0 * fz[:, 0], 0 * fz[:, 0], 0 * fz[:, 0], np.ones(n)]
            ),
        ]
    )
    sigma = np.linspace(0.5, 2.0, len(points))  # unequal σ exercises the weighting
    expected = H.T @ (H / sigma[:, None] ** 2)
    np.testing.assert_allclose(fisher_point_to_plane(points, normals, sigma), expected, rtol=1e-14)
    bound = crlb(points, normals, 1.0)
    assert bound.rank == 6
    assert not bound.degenerate
    assert bound.null_directions.shape == (6, 0)
    np.testing.assert_allclose(bound.covariance, np.linalg.inv(H.T @ H), rtol=1e-10, atol=1e-14)
    twice = crlb(points, normals, 1.0, frame_to_frame=True)
    np.testing.assert_allclose(twice.covariance, 2 * bound.covariance, rtol=1e-12)
    np.testing.assert_allclose(twice.std, np.sqrt(2) * bound.std, rtol=1e-12)


def _residuals(delta: np.ndarray, points: np.ndarray, normals: np.ndarray, d: np.ndarray):
    """Point-to-plane residuals after moving the (M, N, 3) points by exp(delta) on the left.

    ``nᵀ(R p + t) = (Rᵀ n)ᵀ p + nᵀ t``: moving the N normals is cheaper than the M·N points.
    """
    T = se3.exp(delta)
    return np.einsum("mnk,nk->mn", points, normals @ T[:3, :3]) + normals @ T[:3, 3] - d


def _numeric_jacobian(points: np.ndarray, normals: np.ndarray, d: np.ndarray) -> np.ndarray:
    """(M, N, 6) central differences of the residuals w.r.t. the left twist, via se3.exp only."""
    eps = 1e-6
    cols = []
    for k in range(6):
        step = np.zeros(6)
        step[k] = eps
        cols.append(
            (_residuals(step, points, normals, d) - _residuals(-step, points, normals, d))
            / (2 * eps)
        )
    return np.stack(cols, axis=-1)


def test_fisher_matches_numeric_jacobian_of_se3_exp() -> None:
    # Checks the convention (rotation first, left perturbation about the origin) independently.
    points, normals = _box_corner(3)
    points = points + np.array([0.3, -0.2, 2.0])
    d = np.einsum("nk,nk->n", points, normals)
    sigma = np.linspace(0.5, 2.0, len(points))
    Jn = _numeric_jacobian(points[None], normals, d)[0]
    np.testing.assert_allclose(
        fisher_point_to_plane(points, normals, sigma),
        Jn.T @ (Jn / sigma[:, None] ** 2),
        rtol=1e-7,
        atol=1e-7,
    )


def test_monte_carlo_covariance_matches_bound() -> None:
    # ToF-like noise along the rays from a sensor beyond the corner, σ_r = 2 mm.
    points, normals = _box_corner(6)
    sensor = np.array([3.0, 2.5, 3.5])
    rays = points - sensor
    sigma_r = 0.002
    sigma_n = range_sigma_along_normal(sigma_r, rays, normals)
    bound = crlb(points, normals, sigma_n)
    rng = np.random.default_rng(7)
    draws = 4000
    unit_rays = rays / np.linalg.norm(rays, axis=1, keepdims=True)
    noisy = points + rng.normal(scale=sigma_r, size=(draws, len(points), 1)) * unit_rays
    d = np.einsum("nk,nk->n", points, normals)
    # One Gauss-Newton step from the truth with the Jacobian differentiated numerically at the
    # measured points: an estimator built without crlb's formula.
    J = _numeric_jacobian(noisy, normals, d)
    r = _residuals(np.zeros(6), noisy, normals, d)
    W = 1.0 / sigma_n**2
    JW = J * W[:, None]
    A = np.swapaxes(JW, 1, 2) @ J
    b = np.einsum("mni,mn->mi", JW, r)
    estimates = -np.linalg.solve(A, b[..., None])[..., 0]
    empirical_std = estimates.std(axis=0)
    np.testing.assert_allclose(empirical_std, bound.std, rtol=0.10)
    # Sampling error of a std over 4000 draws is ~1.1 %; the match is much tighter than 10 %.
    assert np.max(np.abs(empirical_std / bound.std - 1)) < 0.05


def test_range_sigma_along_normal() -> None:
    rays = np.array([[0.0, 0, 5], [0, 3, 3], [1, 0, 0]])
    normals = np.array([[0.0, 0, -1], [0, 0, 1], [0, 0, 1]])
    np.testing.assert_allclose(
        range_sigma_along_normal(0.01, rays, normals), [0.01, 0.01 / np.sqrt(2), 0.0], atol=1e-17
    )


def test_bad_input() -> None:
    pts = np.zeros((3, 3))
    nrm = np.tile([0.0, 0, 1], (3, 1))
    with pytest.raises(InputError, match=r"points must have shape \(N, 3\)"):
        fisher_point_to_plane(np.zeros((3, 2)), nrm, 1.0)
    with pytest.raises(InputError, match="3 points for 2 normals"):
        fisher_point_to_plane(pts, nrm[:2], 1.0)
    with pytest.raises(InputError, match="sigma must be finite and > 0"):
        fisher_point_to_plane(pts, nrm, [1.0, 0.0, 1.0])
    with pytest.raises(InputError, match=r"sigma must be a scalar or have shape \(3,\)"):
        fisher_point_to_plane(pts, nrm, [1.0, 1.0])
    with pytest.raises(InputError, match="normals have non-finite"):
        crlb(pts, np.full((3, 3), np.nan), 1.0)
    with pytest.raises(InputError, match="non-zero vectors"):
        range_sigma_along_normal(0.01, np.zeros((3, 3)), nrm)
    with pytest.raises(InputError, match="2 rays for 3 normals"):
        range_sigma_along_normal(0.01, np.ones((2, 3)), nrm)
