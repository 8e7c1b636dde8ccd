"""Tests of spacepose.core.dynamics: CW relative motion and torque-free attitude."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.linalg import expm
from scipy.spatial.transform import Rotation

from spacepose.core import dynamics
from spacepose.errors import InputError

N_500KM = 1.1068e-3  # rad/s, circular orbit at 500 km


def test_rk4_cw_matches_closed_form_over_600s() -> None:
    x0 = np.array([25.0, -0.3, 0.4, 0.01, 0.002, -0.005])
    x = x0.copy()
    for _ in range(600):
        x = dynamics.rk4_step(lambda s: dynamics.cw_derivative(s, N_500KM), x, 1.0)
    ref = dynamics.cw_closed_form(x0, N_500KM, 600.0)
    assert np.max(np.abs(x[:3] - ref[:3])) < 1e-6
    assert np.max(np.abs(x[3:] - ref[3:])) < 1e-9
    # The trajectory really moves (the comparison is not trivially between equal inputs).
    assert np.linalg.norm(ref[:3] - x0[:3]) > 1.0


def test_cw_stm_equals_matrix_exponential() -> None:
    A = dynamics.cw_matrix(N_500KM)
    for t in (1.0, 37.0, 2500.0):
        np.testing.assert_allclose(dynamics.cw_stm(N_500KM, t), expm(A * t), atol=1e-9)
    np.testing.assert_allclose(dynamics.cw_stm(0.0, 3.0), expm(dynamics.cw_matrix(0.0) * 3.0))


def test_cw_same_orbit_offset_is_an_equilibrium() -> None:
    # Chaser 25 m behind on the same circular orbit: ρ = (25, 0, 0) stays put.
    state = np.array([25.0, 0, 0, 0, 0, 0])
    np.testing.assert_allclose(dynamics.cw_closed_form(state, N_500KM, 5000.0), state, atol=1e-12)


def test_R_I_O_rotates_about_minus_y() -> None:
    n, t = N_500KM, 300.0
    R = dynamics.R_I_O(n, t)
    np.testing.assert_allclose(R @ [0, 1, 0], [0, 1, 0], atol=1e-15)
    # Flight direction x_O turns towards the Earth (+z_I at t=0 points to the Earth centre,
    # the new flight direction tilts towards the old nadir).
    np.testing.assert_allclose(R @ [1, 0, 0], [np.cos(n * t), 0, np.sin(n * t)], atol=1e-15)
    np.testing.assert_allclose(dynamics.R_I_O(n, 0.0), np.eye(3))


def test_torque_free_conserves_energy_and_momentum() -> None:
    inertia = np.array([1200.0, 1000.0, 800.0])
    w = np.deg2rad([1.0, -2.0, 1.5])
    q = Rotation.from_rotvec([0.3, -0.2, 0.5]).as_quat()
    R0 = Rotation.from_quat(q).as_matrix()
    H_I0 = R0 @ (inertia * w)
    E0 = 0.5 * np.sum(inertia * w**2)
    for _ in range(600):
        q, w = dynamics.propagate_attitude(q, w, inertia, 1.0, substeps=10)
    E = 0.5 * np.sum(inertia * w**2)
    H_I = Rotation.from_quat(q).as_matrix() @ (inertia * w)
    assert abs(E - E0) / E0 < 1e-9
    assert abs(np.linalg.norm(inertia * w) - np.linalg.norm(H_I0)) / np.linalg.norm(H_I0) < 1e-9
    # Inertial angular momentum is constant: checks the quaternion kinematics as well.
    assert np.linalg.norm(H_I - H_I0) / np.linalg.norm(H_I0) < 1e-9
    assert abs(np.linalg.norm(q) - 1.0) < 1e-12


def test_quat_derivative_matches_scipy_composition() -> None:
    q = Rotation.from_rotvec([0.4, 0.1, -0.7]).as_quat()
    w = np.array([0.05, -0.02, 0.03])
    h = 1e-6
    fd = ((Rotation.from_quat(q) * Rotation.from_rotvec(w * h)).as_quat() - q) / h
    np.testing.assert_allclose(dynamics.quat_derivative(q, w), fd, atol=1e-7)


def test_euler_derivative_is_scale_free_and_matches_ratios() -> None:
    inertia = np.array([1200.0, 1000.0, 800.0])
    w = np.array([0.1, -0.2, 0.3])
    k = dynamics.inertia_ratios(inertia)
    np.testing.assert_allclose(k, [200 / 1200, -400 / 1000, 200 / 800])
    expected = np.linalg.solve(np.diag(inertia), -np.cross(w, inertia * w))
    np.testing.assert_allclose(dynamics.euler_derivative(w, inertia), expected, rtol=1e-12)
    np.testing.assert_allclose(dynamics.euler_derivative(w, inertia / 800), expected, rtol=1e-12)


def test_bad_inputs_raise_input_error() -> None:
    with pytest.raises(InputError, match="state6"):
        dynamics.cw_derivative([1.0, 2.0], N_500KM)
    with pytest.raises(InputError, match="positive"):
        dynamics.inertia_ratios([1.0, -1.0, 2.0])
    with pytest.raises(InputError, match="non-finite"):
        dynamics.propagate_attitude([0, 0, 0, np.nan], [0, 0, 0], [1, 1, 1], 1.0)
    with pytest.raises(InputError, match="substeps"):
        dynamics.propagate_attitude([0, 0, 0, 1], [0, 0, 0], [1, 1, 1], 1.0, substeps=0)
