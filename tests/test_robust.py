"""Robust kernels: closed-form weights, the tuning constants' efficiency, the adaptive scale."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import integrate, stats

from spacepose.core.config import validate_config
from spacepose.core.icp import ICPConfig
from spacepose.core.robust import (
    MAD_TO_SIGMA,
    TUNING,
    adaptive_scale,
    kernel_slopes,
    kernel_weights,
    robust_weights,
)
from spacepose.errors import ConfigError


def test_weights_closed_form() -> None:
    u = np.array([0.0, 0.5, 1.0, 2.0, -4.0])
    np.testing.assert_allclose(kernel_weights(u, "huber"), [1, 1, 1, 0.5, 0.25])
    np.testing.assert_allclose(kernel_weights(u, "cauchy"), [1, 0.8, 0.5, 0.2, 1 / 17])
    np.testing.assert_allclose(kernel_weights(u, "geman_mcclure"), [1, 0.64, 0.25, 0.04, 1 / 289])
    np.testing.assert_array_equal(kernel_weights(u, "none"), 1.0)
    # ψ' = d(u w(u))/du against central differences (away from Huber's corner at |u| = 1).
    v, h = np.array([0.0, 0.3, 0.7, 1.6, -2.5]), 1e-6
    for kernel in ("none", "huber", "cauchy", "geman_mcclure"):
        numeric = (
            (v + h) * kernel_weights(v + h, kernel) - (v - h) * kernel_weights(v - h, kernel)
        ) / (2 * h)
        np.testing.assert_allclose(kernel_slopes(v, kernel), numeric, atol=1e-8)


@pytest.mark.parametrize("kernel", ["huber", "cauchy", "geman_mcclure"])
def test_tuning_constants_give_95_percent_efficiency(kernel: str) -> None:
    # Asymptotic efficiency E[ψ']² / E[ψ²] under a unit Gaussian, ψ(r) = r w(r/c), by quadrature
    # with ψ' from a central difference.
    c = TUNING[kernel]

    def psi(r: float) -> float:
        return r * kernel_weights(np.array([r / c]), kernel)[0]

    def dpsi(r: float, h: float = 1e-6) -> float:
        return (psi(r + h) - psi(r - h)) / (2 * h)

    pdf = stats.norm.pdf
    a = integrate.quad(lambda r: dpsi(r) * pdf(r), -12, 12, points=[-c, c], limit=200)[0]
    b = integrate.quad(lambda r: psi(r) ** 2 * pdf(r), -12, 12, points=[-c, c], limit=200)[0]
    assert a * a / b == pytest.approx(0.95, abs=2e-4)


def test_adaptive_scale_is_sigma_and_ignores_outliers() -> None:
    rng = np.random.default_rng(3)
    r = rng.normal(0, 0.004, 200_000)
    assert MAD_TO_SIGMA == pytest.approx(1 / stats.norm.ppf(0.75), rel=1e-12)
    assert adaptive_scale(r) == pytest.approx(0.004, rel=0.01)
    # 40 % gross outliers (25σ to 50σ): the median of |r| moves up the inliers' tail to their
    # (1 + 5/6)/2 quantile, so σ̂ = 1.4826 Φ⁻¹(11/12) σ = 2.05σ, and the outliers are weighted to
    # almost nothing.
    mixed = np.concatenate([r[:120_000], rng.uniform(0.1, 0.2, 80_000)])
    w = robust_weights(mixed, "geman_mcclure")
    assert w.scale == pytest.approx(MAD_TO_SIGMA * stats.norm.ppf(11 / 12) * 0.004, rel=0.01)
    assert w.weights[120_000:].max() < 0.01 and np.median(w.weights[:120_000]) > 0.95
    assert w.total == pytest.approx(w.weights.sum())


@pytest.mark.parametrize("kernel", ["cauchy", "geman_mcclure"])
def test_variance_is_the_m_estimator_variance(kernel: str) -> None:
    # Unit weights: Σ r² / (M − 6).
    rng = np.random.default_rng(5)
    r = rng.normal(0, 0.002, 400_000)
    plain = robust_weights(r, "none")
    assert plain.variance(r) == pytest.approx(r @ r / (len(r) - 6), rel=1e-12)
    # Gaussian residuals: s² (Σ w JᵀJ)⁻¹ must be Huber's E[ψ²]/E[ψ']² σ² (Σ JᵀJ)⁻¹ (= σ²/0.95
    # at the tuning constants), so s² = E[w] E[ψ²]/E[ψ']² σ², by quadrature.
    c = TUNING[kernel]
    w = robust_weights(r, kernel)

    def mean(f):
        return integrate.quad(lambda x: f(np.array([x / c]))[0] * stats.norm.pdf(x), -30, 30)[0]

    ew = mean(lambda u: kernel_weights(u, kernel))
    epsi2 = mean(lambda u: (c * u * kernel_weights(u, kernel)) ** 2)
    eslope = mean(lambda u: kernel_slopes(u, kernel))
    assert epsi2 / eslope**2 == pytest.approx(1 / 0.95, rel=1e-3)
    assert w.variance(r) == pytest.approx(ew * epsi2 / eslope**2 * 0.002**2, rel=0.01)


def test_fixed_scale_and_exact_fit() -> None:
    r = np.array([0.0, 1.0, -2.0])
    w = robust_weights(r, "cauchy", scale=1.0 / TUNING["cauchy"])
    np.testing.assert_allclose(w.weights, [1.0, 0.5, 0.2])
    assert w.scale == pytest.approx(1.0 / TUNING["cauchy"])
    # All residuals zero: unit weights, no division by zero.
    zero = robust_weights(np.zeros(5), "geman_mcclure")
    np.testing.assert_array_equal(zero.weights, 1.0)
    assert robust_weights(r, "none").total == 3.0


def test_config_fields() -> None:
    cfg = validate_config(ICPConfig, {"robust_kernel": "cauchy", "robust_scale": 0.01})
    assert (cfg.robust_kernel, cfg.robust_scale) == ("cauchy", 0.01)
    assert ICPConfig().robust_kernel == "none" and ICPConfig().robust_scale is None
    with pytest.raises(ConfigError, match="robust_kernel"):
        validate_config(ICPConfig, {"robust_kernel": "tukey"})
    with pytest.raises(ConfigError, match="robust_scale"):
        validate_config(ICPConfig, {"robust_scale": 0.0})
