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

from dataclasses import dataclass

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
# Offsets of the 13 neighbouring cells after a cell (the other 13 are the same pairs, seen from
# the other cell).
_FORWARD_NEIGHBOURS = [
    (i, j, k) for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1) if (i, j, k) > (0, 0, 0)
]


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
    found = structure_of(points, residuals, cell, min_sigma)
    return None if found is None else found.within


def shared_structure(
    points: NDArray[np.float64],
    residuals: NDArray[np.float64],
    cell: float,
    min_sigma: float = 0.0,
) -> float | None:
    """Whether neighbouring cells share their residuals' offset: the median over every pair of
    tested cells that touch (26-neighbours) of the product of their z-scores, over χ²₁'s
    median (the cells and z-scores of :func:`residual_structure`).

    A second motion biases a whole part, and the cells of it agree: each product is about the
    part's ``z²``. Noise shared only between nearby pixels (a camera's spatial filter) inflates
    each cell's z² (:func:`residual_structure`: 4-15 at 1.2 m for a Gaussian of 2-4 pixels) but
    leaves neighbouring cells nearly independent, their products' median near 0, as white
    noise's is.

    Returns
    -------
    float or None
        The statistic (about 0 without a shared offset; negative when neighbours disagree);
        None when no two tested cells touch, or as :func:`residual_structure`.

    Raises
    ------
    InputError
        As :func:`residual_structure`.
    """
    found = structure_of(points, residuals, cell, min_sigma)
    return None if found is None else found.shared


@dataclass(frozen=True)
class Structure:
    """A registration's residual structure, both statistics over the same cells.

    Attributes
    ----------
    within
        :func:`residual_structure`: how much more each cell's mean varies than white noise's
        (1 for white residuals); the design effect of the pairs' covariance.
    shared
        :func:`shared_structure`: how much neighbouring cells share their offsets (about 0
        without a shared offset); None when no two tested cells touch.
    """

    within: float
    shared: float | None

    def shows_another_motion(self, bound: float, shared_bound: float | None = None) -> bool:
        """Cells whose means stray beyond ``bound`` (:attr:`within`), and, with a
        ``shared_bound``, neighbours that share their offsets beyond it (:attr:`shared`, when
        any touch): a second motion biases whole parts, a camera's spatially filtered noise
        only nearby pixels."""
        if self.within <= bound:
            return False
        return shared_bound is None or self.shared is None or self.shared > shared_bound


def structure_of(
    points: NDArray[np.float64],
    residuals: NDArray[np.float64],
    cell: float,
    min_sigma: float = 0.0,
) -> Structure | None:
    """Both statistics of :func:`residual_structure` and :func:`shared_structure` from one
    pass over the cells (same parameters); None when no cell is tested or the residuals have
    no spread.

    Raises
    ------
    InputError
        As :func:`residual_structure`.
    """
    scores = _cell_scores(points, residuals, cell, min_sigma)
    if scores is None:
        return None
    ijk, sums, counts, sigma = scores
    within = float(np.median(sums**2 / (counts * sigma**2))) / _CHI2_1_MEDIAN
    z = sums / (np.sqrt(counts) * sigma)
    low = ijk.min(axis=0) - 1
    dims = ijk.max(axis=0) - low + 2
    keys = ((ijk[:, 0] - low[0]) * dims[1] + ijk[:, 1] - low[1]) * dims[2] + ijk[:, 2] - low[2]
    order = np.argsort(keys)
    sorted_keys = keys[order]
    products = []
    for offset in _FORWARD_NEIGHBOURS:
        other = keys + (offset[0] * dims[1] + offset[1]) * dims[2] + offset[2]
        at = np.minimum(np.searchsorted(sorted_keys, other), len(keys) - 1)
        found = sorted_keys[at] == other
        products.append(z[found] * z[order[at[found]]])
    pairs = np.concatenate(products)
    shared = float(np.median(pairs)) / _CHI2_1_MEDIAN if len(pairs) else None
    return Structure(within, shared)


def _cell_scores(
    points: NDArray[np.float64], residuals: NDArray[np.float64], cell: float, min_sigma: float
) -> tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.int64], float] | None:
    """The tested cells' integer coordinates (C, 3), their residuals' sums (C,) and counts
    (C,), and the residuals' spread σ (m), after the inputs are checked; None when no cell is
    tested or the residuals have no spread."""
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
    centroids, index = voxel_cells(points, cell)
    counts = np.bincount(index)
    sums = np.bincount(index, weights=residuals)
    tested = counts >= MIN_CELL_PAIRS
    if not tested.any():
        return None
    # A cell's centroid lies inside it: its floor is the cell's index.
    ijk = np.floor(centroids[tested] / cell).astype(np.int64)
    return ijk, sums[tested], counts[tested], sigma
