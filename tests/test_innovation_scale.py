"""Innovation-based noise scale against closed-form AR(1) and covariance-matching cases."""

import numpy as np
import pytest

from spacepose.core.innovation_scale import InnovationScale


def _ar1(rho: float, var: float, n: int, seed: int) -> np.ndarray:
    """(n, 3) stationary AR(1) rows with lag-one correlation rho and variance var."""
    rng = np.random.default_rng(seed)
    x = np.empty((n, 3))
    x[0] = rng.standard_normal(3) * np.sqrt(var)
    for i in range(1, n):
        x[i] = rho * x[i - 1] + np.sqrt(var * (1 - rho**2)) * rng.standard_normal(3)
    return x


@pytest.mark.parametrize("rho, var", [(0.0, 1.0), (0.0, 2.5), (0.5, 1.0), (0.7, 2.0)])
def test_factor_is_the_variance_ratio_times_the_ar1_correlation_time(rho, var) -> None:
    # Two faces, each an AR(1) sequence over 2,000 frames; R = 0.01 I (the model), so the
    # whitened innovations are x / 0.1. Closed form: f = var, tau = (1 + rho) / (1 - rho).
    scale = InnovationScale(window=4000)
    R = 0.01 * np.eye(3)
    for face, seed in (("a", 1), ("b", 2)):
        for step, x in enumerate(_ar1(rho, var, 2000, seed)):
            scale.add(face, step, 0.1 * x, R, np.zeros((3, 3)))
    tau = (1 + rho) / (1 - rho)
    assert scale.variance_ratio == pytest.approx(var, rel=0.1)
    assert scale.correlation(1) == pytest.approx(rho, abs=0.05)
    assert scale.correlation_time == pytest.approx(tau, rel=0.2)
    assert scale.factor == pytest.approx(max(1.0, var * tau), rel=0.25)


def test_prediction_covariance_is_taken_out_and_the_factor_never_shrinks_the_model() -> None:
    rng = np.random.default_rng(0)
    R, HPHt = np.diag([1.0, 4.0, 9.0]), np.diag([1.0, 4.0, 9.0])
    scale = InnovationScale(window=5000)
    # Innovations with covariance H P Hᵀ + R exactly: the model is right, f = 1.
    for step in range(5000):
        scale.add("a", step, rng.standard_normal(3) * np.sqrt(2 * np.diag(R)), R, HPHt)
    assert scale.variance_ratio == pytest.approx(1.0, abs=0.08)
    # Quieter than the model (half the variance, white): the factor stays 1.
    quiet = InnovationScale()
    for step in range(400):
        quiet.add("a", step, rng.standard_normal(3) * np.sqrt(0.5), np.eye(3), np.zeros((3, 3)))
    assert quiet.variance_ratio < 0.7 and quiet.factor == 1.0


def test_nothing_is_measured_before_min_samples_and_gaps_break_pairs() -> None:
    scale = InnovationScale(min_samples=30)
    for step in range(29):
        scale.add("a", step, np.full(3, 5.0), np.eye(3), np.zeros((3, 3)))
    assert scale.factor == 1.0
    # Every other frame only: no pair one frame apart, so no lag-one correlation.
    gaps = InnovationScale()
    for step in range(0, 200, 2):
        gaps.add("a", step, np.ones(3), np.eye(3), np.zeros((3, 3)))
    assert gaps.correlation(1) == 0.0 and gaps.correlation(2) == pytest.approx(1.0)
