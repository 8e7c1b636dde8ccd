"""Whether a registration's residuals are noise or structure (docs/methods.md §5.3).

A rigid registration that found the right pose leaves point-to-plane residuals that are noise:
their mean over any patch of the surface is about zero, within ``σ / √n``. When part of the
cloud moves otherwise (a turntable and plinth carried by a slide under a target turning on it,
a second body), the registration settles on a compromise of the two motions, and each part is
left with a residual of its own sign over its whole surface. The information matrix does not see
it (its σ comes from the spread of the residuals, not from where they lie), so such a frame
passed every check while off by 5 to 20 σ.

:func:`residual_structure` measures it: the surface is cut into cubic cells, and in each cell
holding enough pairs the mean residual is divided by its standard error; the statistic is the
median of the squared z-scores over the cells, divided by white noise's (χ²₁'s median), so 1 for
white residuals. The median, because two views' different voxel samplings bias a few cells
(edges, thin parts) without biasing the pose, while a compromise of two motions biases most of
the surface: over the robustness grid's clean cells the right ok frames stay below 4.6, the
wall-and-table frames that were ok while wrong have a median of 10 at 0.5-3 m.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from spacepose.core.voxel import voxel_cells
from spacepose.errors import InputError

# A cell's mean is tested only when it holds this many pairs (a z-score of fewer is noise).
MIN_CELL_PAIRS = 4
# Floor of the residuals' spread, in voxels. Registering voxel centroids onto another view's
# surface leaves residuals of the sampling's own, alike in both samplings of a frame (a grid
# moved half a voxel keeps them): without noise (a renderer's depth) they spread 0.002-0.018 of
# the voxel and their cell means up to 0.013, which over white noise's σ / √n made every frame's
# structure 20-340 ("part of the cloud fits another motion") and its covariance 5-18 times wider.
# Every sensor profile of the robustness grid leaves 0.13-0.21 of the voxel the spacing gives,
# and is never floored.
SAMPLING_SPREAD_VOXELS = 0.05
# MAD to σ of a normal distribution.
_MAD_TO_SIGMA = 1.4826
# Median of a χ² with one degree of freedom: a white cell's z² has it.
_CHI2_1_MEDIAN = 0.454936


def residual_structure(
    points: NDArray[np.float64],
    residuals: NDArray[np.float64],
    cell: float,
    min_sigma: float = 0.0,
) -> float | None:
    """Median squared z-score of the cell means of registration residuals, over white noise's.

    Parameters
    ----------
    points
        (M, 3) the matched source points, any frame (m): they say where each residual lies.
    residuals
        (M,) signed point-to-plane residuals of those pairs (m).
    cell
        Edge of the cubic cells (m).
    min_sigma
        Floor of the residuals' spread (m): what sampling the surface leaves without noise
        (:data:`SAMPLING_SPREAD_VOXELS` of the voxel, the tracker's), below which cell means
        are the sampling's own, not a second motion's.

    Returns
    -------
    float or None
        The median over the cells holding at least :data:`MIN_CELL_PAIRS` pairs of
        ``z² = (Σ r)² / (n σ²)``, σ the residuals' robust spread (1.4826 · MAD, at least
        ``min_sigma``), divided by the
        median of a χ² with one degree of freedom (0.455): 1 for white residuals. None when no
        cell holds that many pairs, or the residuals have no spread.

    Raises
    ------
    InputError
        Shapes that do not match, values that are not finite, or a cell that is not a
        positive length.
    """
    points = np.asarray(points, dtype=np.float64)
    residuals = np.asarray(residuals, dtype=np.float64)
    if points.ndim != 2 or points.shape[1] != 3 or residuals.shape != (len(points),):
        raise InputError(
            f"residual structure needs (M, 3) points and (M,) residuals, got {points.shape} "
            f"and {residuals.shape}"
        )
    if not (np.isfinite(points).all() and np.isfinite(residuals).all()):
        raise InputError("residual structure needs finite points and residuals")
    if not np.isfinite(cell) or cell <= 0:
        raise InputError(f"residual structure cell must be a positive length, got {cell}")
    if not (np.isfinite(min_sigma) and min_sigma >= 0):
        raise InputError(f"residual structure min_sigma must be a length >= 0, got {min_sigma}")
    if len(residuals) < MIN_CELL_PAIRS:
        return None
    sigma = _MAD_TO_SIGMA * float(np.median(np.abs(residuals - np.median(residuals))))
    sigma = max(sigma, min_sigma)
    if not sigma > 0:
        return None
    _, index = voxel_cells(points, cell)
    counts = np.bincount(index)
    sums = np.bincount(index, weights=residuals)
    tested = counts >= MIN_CELL_PAIRS
    if not tested.any():
        return None
    z2 = sums[tested] ** 2 / (counts[tested] * sigma**2)
    return float(np.median(z2)) / _CHI2_1_MEDIAN
