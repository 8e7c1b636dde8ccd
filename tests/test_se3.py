"""SE(3) helpers against scipy and closed-form identities."""

import numpy as np
import pytest
from scipy.linalg import expm, logm
from scipy.spatial.transform import Rotation

from spacepose.core import se3
from spacepose.errors import InputError


def _hat(xi: np.ndarray) -> np.ndarray:
    """4×4 Lie-algebra matrix of a twist (omega, v), for the scipy.linalg reference."""
    X = np.zeros((4, 4))
    X[:3, :3] = se3.skew(xi[:3])
    X[:3, 3] = xi[3:]
    return X


@pytest.mark.parametrize("seed", range(5))
def test_exp_log_match_matrix_exponential(seed: int) -> None:
    rng = np.random.default_rng(seed)
    # Angles below π: log returns the shortest rotation, so larger ones would not round-trip.
    xi = rng.uniform(-1.5, 1.5, size=6) * np.array([1.0, 1.0, 1.0, 2.0, 2.0, 2.0])
    T = se3.exp(xi)
    np.testing.assert_allclose(T, expm(_hat(xi)), atol=1e-12)
    np.testing.assert_allclose(se3.log(T), xi, atol=1e-10)
    np.testing.assert_allclose(_hat(se3.log(T)), np.real(logm(T)), atol=1e-8)


def test_exp_small_angle_branch_is_continuous() -> None:
    xi = np.array([1e-10, -2e-10, 3e-10, 0.1, 0.2, 0.3])
    np.testing.assert_allclose(se3.exp(xi), expm(_hat(xi)), atol=1e-15)
    np.testing.assert_allclose(se3.log(se3.exp(xi)), xi, atol=1e-15)


def test_invert_compose_transform_points() -> None:
    rng = np.random.default_rng(1)
    T_a_b = se3.make_transform(Rotation.random(random_state=2), rng.normal(size=3))
    T_b_c = se3.make_transform(Rotation.random(random_state=3), rng.normal(size=3))
    np.testing.assert_allclose(se3.invert(T_a_b), np.linalg.inv(T_a_b), atol=1e-12)
    np.testing.assert_allclose(se3.compose(T_a_b, T_b_c), T_a_b @ T_b_c, atol=1e-12)
    p_c = rng.normal(size=(10, 3))
    p_a = se3.transform_points(se3.compose(T_a_b, T_b_c), p_c)
    p_a_ref = (T_a_b @ T_b_c @ np.c_[p_c, np.ones(10)].T).T[:, :3]
    np.testing.assert_allclose(p_a, p_a_ref, atol=1e-12)
    stack = np.stack([T_a_b, T_b_c])
    np.testing.assert_allclose(se3.invert(stack), np.linalg.inv(stack), atol=1e-12)


def test_adjoint_moves_twists_between_frames() -> None:
    rng = np.random.default_rng(4)
    T = se3.make_transform(Rotation.random(random_state=5), rng.normal(size=3))
    xi = rng.normal(size=6) * 0.3
    np.testing.assert_allclose(
        se3.exp(se3.adjoint(T) @ xi), T @ se3.exp(xi) @ se3.invert(T), atol=1e-12
    )


def test_geodesic_mean_of_symmetric_perturbations_is_the_centre() -> None:
    rng = np.random.default_rng(6)
    centre = se3.make_transform(Rotation.random(random_state=7), rng.normal(size=3))
    deltas = rng.normal(size=(4, 6)) * 0.05
    stack = [se3.exp(d) @ centre for d in deltas] + [se3.exp(-d) @ centre for d in deltas]
    mean = se3.geodesic_mean(np.array(stack))
    # Symmetric perturbations of a point average back to it only to second order on SE(3).
    np.testing.assert_allclose(se3.log(mean @ se3.invert(centre)), 0.0, atol=1e-3)
    # Two transforms, equal weights: the midpoint of the geodesic between them.
    T1 = se3.exp(np.array([0.0, 0.0, 0.4, 1.0, 0.0, 0.0]))
    mid = se3.geodesic_mean(np.stack([np.eye(4), T1]))
    np.testing.assert_allclose(mid, se3.exp(0.5 * se3.log(T1)), atol=1e-10)
    # Weights pull the mean: weight 3:1 lands a quarter of the way from T1.
    quarter = se3.geodesic_mean(np.stack([np.eye(4), T1]), weights=[1.0, 3.0])
    np.testing.assert_allclose(quarter, se3.exp(0.75 * se3.log(T1)), atol=1e-10)


@pytest.mark.parametrize(
    "bad, match",
    [
        (np.eye(3), "4x4"),
        (np.full((4, 4), np.nan), "non-finite"),
        (np.diag([1.0, 1.0, -1.0, 1.0]), "proper rotation"),
        (np.diag([2.0, 1.0, 1.0, 1.0]), "proper rotation"),
        (np.vstack([np.eye(4)[:3], [0, 0, 1, 1]]), "last row"),
    ],
)
def test_as_transform_rejects_non_rigid(bad: np.ndarray, match: str) -> None:
    with pytest.raises(InputError, match=match):
        se3.as_transform(bad)


def test_geodesic_mean_rejects_bad_input() -> None:
    with pytest.raises(InputError):
        se3.geodesic_mean(np.zeros((0, 4, 4)))
    with pytest.raises(InputError):
        se3.geodesic_mean(np.stack([np.eye(4)] * 2), weights=[1.0, -1.0])
