"""Principal axes from tracked attitudes (core/principal_axes.py) against an independently
integrated torque-free rotation (sim.orbit_truth) seen in a frame turned away from the axes."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from spacepose.core.dynamics import inertia_ratios
from spacepose.core.principal_axes import principal_axes
from spacepose.core.sim.orbit_truth import torque_free_attitude
from spacepose.errors import InputError

INERTIA = (1200.0, 1000.0, 800.0)


def _tracked(noise_deg: float, seed: int = 0):
    """600 s at 1 Hz of the orbit run's tumble, as attitudes of a frame F = B turned by R_B_F,
    each with ``noise_deg`` of seeded attitude noise; returns t, R_I_F, R_F_B."""
    t = np.arange(600.0)
    R_I_B0 = Rotation.from_euler("ZYX", (30.0, -20.0, 45.0), degrees=True).as_matrix()
    q, _ = torque_free_attitude(R_I_B0, np.radians([1.0, -2.0, 1.5]), INERTIA, t)
    R_B_F = Rotation.from_euler("xyz", (40.0, -70.0, 15.0), degrees=True)
    noise = Rotation.from_rotvec(
        np.radians(noise_deg) * np.random.default_rng(seed).standard_normal((len(t), 3))
    )
    R_I_F = (Rotation.from_quat(q) * R_B_F * noise).as_matrix()
    return t, R_I_F, R_B_F.inv().as_matrix()


def _axis_error_deg(R_F_B: np.ndarray, truth: np.ndarray) -> float:
    """Largest angle between estimated and true axes, each up to its sign."""
    cos = np.abs(np.sum(R_F_B * truth, axis=0))
    return float(np.degrees(np.arccos(np.clip(cos, -1, 1))).max())


def test_exact_attitudes_give_the_axes_and_ratios():
    t, R_I_F, R_F_B = _tracked(0.0)
    # A one-frame baseline: the central difference's error (second order in ω dt) is small.
    est = principal_axes(t, R_I_F, baseline=1)
    assert _axis_error_deg(est.R_F_B, R_F_B) < 0.01
    np.testing.assert_allclose(est.k, inertia_ratios(INERTIA), atol=2e-4)
    np.testing.assert_allclose(est.moments, np.array(INERTIA) / sum(INERTIA), atol=1e-4)
    assert est.residual < 1e-3
    assert np.linalg.det(est.R_F_B) > 0


def test_noisy_attitudes_like_the_tracker_at_25_m():
    """0.15° per frame (the model-based tracker's RMS on the orbit run, white here)."""
    t, R_I_F, R_F_B = _tracked(0.15)
    est = principal_axes(t, R_I_F, baseline=10)
    assert _axis_error_deg(est.R_F_B, R_F_B) < 1.0
    np.testing.assert_allclose(est.k, inertia_ratios(INERTIA), rtol=0.05)


def test_bad_input():
    with pytest.raises(InputError):
        principal_axes(np.arange(3.0), np.tile(np.eye(3), (3, 1, 1)))
    with pytest.raises(InputError):
        principal_axes(np.zeros(10), np.tile(np.eye(3), (10, 1, 1)))
