"""The residual structure statistic (core/residual_structure.py) against closed forms."""

from __future__ import annotations

import numpy as np
import pytest
from scipy import stats

from spacepose.core.residual_structure import MIN_CELL_PAIRS, residual_structure
from spacepose.errors import InputError


def _plane(n_side: int, spacing: float) -> np.ndarray:
    u, v = np.meshgrid(np.arange(n_side) * spacing, np.arange(n_side) * spacing)
    return np.column_stack([u.ravel(), v.ravel(), np.zeros(u.size)])


def test_white_residuals_give_one() -> None:
    """Independent residuals: each cell's z-score is standard normal, so the median of the
    squares over 400 cells is χ²₁'s (the statistic 1) within its sampling error (about ±0.15)."""
    rng = np.random.default_rng(0)
    points = _plane(100, 0.01)  # 10,000 pairs, 1 m square
    values = [
        residual_structure(points, rng.normal(0.0, 0.002, len(points)), 0.05) for _ in range(5)
    ]
    assert np.mean(values) == pytest.approx(1.0, abs=0.1)
    assert max(values) < 1.35


def test_a_bias_per_part_gives_a_noncentral_chi2_median() -> None:
    """Two halves biased by ±b: a cell of n pairs has z = Σr / (√n σ̂) with σ̂ the MAD's σ of
    the mixture, so z² σ̂² / σ² is a noncentral χ²₁ of λ = n b² / σ² (scipy's ncx2)."""
    rng = np.random.default_rng(1)
    points = _plane(100, 0.01)
    sigma, b = 0.002, 0.0008
    r = rng.normal(0.0, sigma, len(points)) + np.where(points[:, 0] < 0.5, b, -b)
    value = residual_structure(points, r, 0.05)
    s_hat = stats.median_abs_deviation(r, scale="normal")
    expected = (sigma / s_hat) ** 2 * stats.ncx2.median(1, 25 * b**2 / sigma**2)
    assert value == pytest.approx(expected / stats.chi2.median(1), rel=0.1)
    assert value > 5.0
    # The same residuals in a random order over the surface: white again.
    assert residual_structure(points, rng.permutation(r), 0.05) < 1.35


def test_a_few_structured_cells_do_not_move_the_median() -> None:
    """A tenth of the surface biased by 2 σ (an edge two samplings see differently) leaves the
    median where white noise has it: what counts is a bias over most of the surface."""
    rng = np.random.default_rng(3)
    points = _plane(100, 0.01)
    r = rng.normal(0.0, 0.002, len(points)) + np.where(points[:, 0] < 0.1, 0.004, 0.0)
    assert residual_structure(points, r, 0.05) < 1.5


def test_cells_with_too_few_pairs_are_not_tested() -> None:
    points = _plane(10, 0.1)  # one pair per 5 cm cell
    r = np.random.default_rng(2).normal(0.0, 0.001, len(points))
    assert residual_structure(points, r, 0.05) is None
    assert residual_structure(points[: MIN_CELL_PAIRS - 1], r[: MIN_CELL_PAIRS - 1], 1.0) is None
    assert residual_structure(points, np.zeros(len(points)), 1.0) is None  # no spread


def test_bad_inputs_raise() -> None:
    points = _plane(10, 0.01)
    with pytest.raises(InputError, match="residuals"):
        residual_structure(points, np.zeros(3), 0.05)
    with pytest.raises(InputError, match="positive"):
        residual_structure(points, np.zeros(len(points)), 0.0)
    bad = points.copy()
    bad[3, 1] = np.nan
    with pytest.raises(InputError, match="finite"):
        residual_structure(bad, np.zeros(len(points)), 0.05)


def test_a_spread_floor_divides_cell_means_by_it_and_leaves_noise_above_it() -> None:
    """Residuals with a fixed bias ±b per half and no noise (a renderer's depth): their spread
    is the MAD's, 1.4826 b, so a cell of 25 pairs has z² = 25 / 1.4826², over χ²₁'s median
    (0.455): 25. Floored at 5 b, z² = 25 b² / (5 b)² = 1. Noisy residuals of a spread above the
    floor give the same value to the bit as without it."""
    points = _plane(100, 0.01)
    b = 1e-5
    r = np.where(points[:, 0] < 0.5, b, -b)
    assert residual_structure(points, r, 0.05) == pytest.approx(25.0 / 1.4826**2 / 0.454936)
    floored = residual_structure(points, r, 0.05, min_sigma=5.0 * b)
    assert floored == pytest.approx(1.0 / 0.454936, rel=1e-6)
    noisy = np.random.default_rng(4).normal(0.0, 0.002, len(points)) + r
    assert residual_structure(points, noisy, 0.05, 0.001) == residual_structure(points, noisy, 0.05)
    with pytest.raises(InputError, match="min_sigma"):
        residual_structure(points, noisy, 0.05, -1.0)


def test_shared_structure_tells_a_biased_part_from_noise_shared_between_neighbours() -> None:
    """Two halves biased by ±b: neighbouring cells share the offset, and the median of their
    z-scores' products is about the cells' z² (the within statistic; 12.3 and 11.8 here).
    White noise: about 0. Noise smoothed over one 5 mm pair spacing (a camera's spatial
    filter) raises each 5 cm cell's z² eleven times but leaves neighbouring cells nearly
    independent (shared −0.6): that is no second motion."""
    from scipy import ndimage

    from spacepose.core.residual_structure import Structure, shared_structure, structure_of

    rng = np.random.default_rng(6)
    points = _plane(200, 0.005)  # 40,000 pairs, 1 m square, cells of 100 pairs
    b, sigma = 0.0005, 0.002
    biased = rng.normal(0.0, sigma, len(points)) + np.where(points[:, 0] < 0.5, b, -b)
    both = structure_of(points, biased, 0.05)
    assert both.within > 5.0 and both.shared > 0.7 * both.within
    assert shared_structure(points, biased, 0.05) == both.shared
    white = shared_structure(points, rng.normal(0.0, sigma, len(points)), 0.05)
    assert abs(white) < 0.3
    smooth = ndimage.gaussian_filter(rng.normal(0.0, 1.0, (200, 200)), 1.0).ravel()
    filtered = structure_of(points, sigma * smooth / smooth.std(), 0.05)
    assert filtered.within > 5.0 and abs(filtered.shared) < 1.0
    assert not filtered.shows_another_motion(5.0, 1.0)
    assert both.shows_another_motion(5.0, 1.0)
    assert Structure(6.0, None).shows_another_motion(5.0, 1.0)  # no neighbours: within alone
    assert not Structure(6.0, 0.5).shows_another_motion(5.0, 1.0)
