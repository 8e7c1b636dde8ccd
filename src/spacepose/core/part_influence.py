"""How far a registration's pose rests on any one part of the surface (docs/methods.md §5.3).

A registration of a rigid body is an average over its surface: every part of it agrees, within
noise, on one motion. When part of the cloud moves otherwise (a turntable and plinth under a
turning target, a second body) the pose is a compromise, and leaving that part out moves it by
far more than its σ. :func:`part_influence` measures this directly: the surface is cut into
cubic parts, and for each part the point-to-plane least-squares pose without its pairs is taken
one Gauss-Newton step from the solution (a group jackknife, Cook's distance in regression). The
shift of the pose, measured by the registration's own covariance, is the part's influence
``Δᵀ Σ⁻¹ Δ``; the frame's is the largest over its parts.

Unlike a test of the residuals' whiteness, this one is scaled by the covariance the tracker
reports, which already carries the residuals' correlation over the surface (the design effect
of :mod:`~spacepose.core.residual_structure`): a sensor whose noise is correlated over patches
widens σ and the shift together, while a part that pulls the pose elsewhere moves it by many σ
however the noise is shaped. An influence above 9 means one part moves the pose by more than
3 σ (in the worst direction): the σ does not describe the pose. A part that holds much of the
information moves it by about σ on noise alone, so its bound grows with its leverage.
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np
from numpy.typing import NDArray

from spacepose.core.voxel import voxel_cells
from spacepose.errors import InputError

# A part is left out only if it holds this many pairs: fewer move the pose by noise alone.
MIN_PART_PAIRS = 30
# χ²₆'s 0.999 quantile (scipy.stats.chi2.ppf(0.999, 6)): the bound of a part whose leverage is 1.
_CHI2_6_999 = 22.457744484825323


@dataclass(frozen=True)
class PartInfluence:
    """The largest influence of one part on a registration.

    Attributes
    ----------
    largest
        ``Δ_pᵀ Σ⁻¹ Δ_p`` of the part that exceeds its bound most: the squared Mahalanobis
        shift of the pose when its pairs are left out (unit-free; 9 is 3 σ).
    bound
        That part's bound: the larger of ``sigmas²`` and what noise alone exceeds with
        probability 10⁻³ (``λ χ²₆``, λ the part's largest leverage; see
        :func:`part_influence`).
    share
        Share of the pairs in that part.
    parts
        Number of parts left out in turn.
    """

    largest: float
    bound: float
    share: float
    parts: int

    @property
    def excessive(self) -> bool:
        """The part moves the pose beyond both bounds."""
        return self.largest > self.bound


def part_influence(
    points: NDArray[np.float64],
    normals: NDArray[np.float64],
    residuals: NDArray[np.float64],
    covariance: NDArray[np.float64],
    part_size: float,
    weights: NDArray[np.float64] | None = None,
    sigmas: float = 3.0,
) -> PartInfluence | None:
    """Largest shift of a point-to-plane registration's pose when one part of it is left out.

    Parameters
    ----------
    points
        (M, 3) matched source points in the reference frame, at the registered pose (m).
    normals
        (M, 3) unit normals of their matched reference points.
    residuals
        (M,) signed point-to-plane residuals ``n · (p − q)`` (m).
    covariance
        (6, 6) covariance of the pose (left perturbation ``(ω, v)`` in the reference frame,
        about its origin), the one the shift is measured by.
    part_size
        Edge of the cubic parts (m).
    weights
        (M,) IRLS weights of the pairs (a robust kernel's); None: all 1.
    sigmas
        A shift counts when it is more than this many σ (its square bounds ``Δᵀ Σ⁻¹ Δ``).

    Notes
    -----
    With white noise and ``Σ ∝ H⁻¹``, the shift of leaving part p out is normal with covariance
    ``Σ H (H − H_p)⁻¹ − Σ``, so ``Δᵀ Σ⁻¹ Δ`` is a sum of χ²₁ weighted by the eigenvalues of
    ``(H − H_p)⁻¹ H_p`` (the part's leverage: about share / (1 − share)). A part small against
    the whole moves the pose by a fraction of σ; one holding half of the information moves it
    by about σ in each direction, and noise alone exceeds 9 there with probability 0.06. The
    bound is therefore also ``λ_max`` times χ²₆'s 0.999 quantile.

    Returns
    -------
    PartInfluence or None
        None when fewer than two parts hold :data:`MIN_PART_PAIRS` pairs (nothing to compare).

    Raises
    ------
    InputError
        Shapes that do not match, values that are not finite, or a part size that is not a
        positive length.
    """
    points = np.asarray(points, dtype=np.float64)
    normals = np.asarray(normals, dtype=np.float64)
    residuals = np.asarray(residuals, dtype=np.float64)
    covariance = np.asarray(covariance, dtype=np.float64)
    m = len(points)
    w = np.ones(m) if weights is None else np.asarray(weights, dtype=np.float64)
    if (
        points.shape != (m, 3)
        or normals.shape != (m, 3)
        or residuals.shape != (m,)
        or w.shape != (m,)
        or covariance.shape != (6, 6)
    ):
        raise InputError(
            f"part influence needs (M, 3) points and normals, (M,) residuals and weights and a "
            f"(6, 6) covariance, got {points.shape}, {normals.shape}, {residuals.shape}, "
            f"{w.shape} and {covariance.shape}"
        )
    arrays = (points, normals, residuals, w, covariance)
    if not all(np.isfinite(a).all() for a in arrays):
        raise InputError("part influence needs finite points, normals, residuals and weights")
    if (w < 0).any():
        raise InputError("part influence needs weights >= 0")
    if not np.isfinite(part_size) or part_size <= 0:
        raise InputError(f"part influence part size must be a positive length, got {part_size}")
    if m == 0:
        return None
    _, part = voxel_cells(points, part_size)
    counts = np.bincount(part)
    tested = np.flatnonzero(counts >= MIN_PART_PAIRS)
    if len(tested) < 2:
        return None
    H_parts, g_parts = _part_sums(part, points, normals, w, residuals, len(counts))
    H, g = H_parts.sum(axis=0), g_parts.sum(axis=0)
    # The step of all pairs from the solution (about zero at a converged registration; kept so
    # that a robust solution's unweighted remainder does not count as influence).
    step_all = -np.linalg.pinv(H, hermitian=True) @ g
    info = np.linalg.pinv(covariance, hermitian=True)
    H_out = H[None] - H_parts[tested]
    g_out = g[None] - g_parts[tested]
    step_out = -np.einsum("pij,pj->pi", np.linalg.pinv(H_out, hermitian=True), g_out)
    shift = step_out - step_all[None]
    influence = np.einsum("pi,ij,pj->p", shift, info, shift)
    leverage = _largest_leverage(H_out, H_parts[tested])
    bound = np.maximum(sigmas**2, _CHI2_6_999 * leverage)
    k = int(np.argmax(influence / bound))
    return PartInfluence(
        float(influence[k]), float(bound[k]), float(counts[tested[k]] / m), len(tested)
    )


@numba.njit(cache=True)
def _part_sums(
    part: NDArray[np.intp],
    points: NDArray[np.float64],
    normals: NDArray[np.float64],
    w: NDArray[np.float64],
    r: NDArray[np.float64],
    n_parts: int,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Each part's ``Σ w h hᵀ`` (P, 6, 6) and ``Σ w h r`` (P, 6), ``h = (p × n, n)`` the
    residual's derivative in (ω, v), in one serial pass (numpy's unbuffered scatter-add cost
    15 ms on a lab frame's 12,000 pairs)."""
    H = np.zeros((n_parts, 6, 6))
    g = np.zeros((n_parts, 6))
    h = np.empty(6)
    for i in range(len(part)):
        x, y, z = points[i, 0], points[i, 1], points[i, 2]
        nx, ny, nz = normals[i, 0], normals[i, 1], normals[i, 2]
        h[0], h[1], h[2] = y * nz - z * ny, z * nx - x * nz, x * ny - y * nx
        h[3], h[4], h[5] = nx, ny, nz
        p = part[i]
        for a in range(6):
            wa = w[i] * h[a]
            g[p, a] += wa * r[i]
            for b in range(6):
                H[p, a, b] += wa * h[b]
    return H, g


def _largest_leverage(
    H_rest: NDArray[np.float64], H_part: NDArray[np.float64]
) -> NDArray[np.float64]:
    """(P,) largest eigenvalue of each ``(H_rest)⁻¹ H_part`` (both (P, 6, 6)): that of the
    symmetric ``Wᵀ H_part W`` with ``W = V Λ^(-1/2)`` from ``H_rest = V Λ Vᵀ``. A part whose
    removal leaves a direction unobserved has infinite leverage (so an infinite bound)."""
    ev, V = np.linalg.eigh(H_rest)
    singular = ev[:, 0] <= 1e-12 * np.maximum(ev[:, -1], 0.0)
    W = V / np.sqrt(np.where(singular[:, None], 1.0, ev))[:, None, :]
    largest = np.linalg.eigvalsh(np.swapaxes(W, 1, 2) @ H_part @ W)[:, -1]
    return np.where(singular, np.inf, largest)
