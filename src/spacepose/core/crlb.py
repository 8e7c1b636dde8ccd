"""Cramér–Rao lower bound of point-to-plane registration (methods.md §4).

For a residual ``r_i = n_iᵀ (p_i − q_i)`` with noise of standard deviation σ_i along the
normal, a left perturbation ``p ← exp(δ) p`` with ``δ = (ω, v)`` changes the residual by
``h_iᵀ δ`` with ``h_i = (p_i × n_i, n_i)``. The Fisher information is ``J = Σ h_i h_iᵀ / σ_i²``
and every unbiased estimator of ``δ`` has covariance ``≥ J⁻¹``. The twist is about the origin
of the frame the points are given in, rotation first, like every 6×6 matrix in the package.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from spacepose.core.cloud import as_points
from spacepose.core.se3 import real_array
from spacepose.errors import InputError

#: Eigenvalues of J below ``RANK_RTOL × max eigenvalue`` count as unobservable directions.
RANK_RTOL = 1e-9


def range_sigma_along_normal(
    sigma_r: float | ArrayLike, rays: ArrayLike, normals: ArrayLike
) -> NDArray[np.float64]:
    """Noise along the normal of a range measurement: ``σ_r · |cos θ|``.

    Parameters
    ----------
    sigma_r
        Range noise standard deviation (scalar or (N,)), metres, along the ray.
    rays
        (N, 3) ray directions (any length, e.g. the points themselves for rays from the sensor
        origin), sensor frame.
    normals
        (N, 3) surface normals (any length), same frame.

    Returns
    -------
    (N,) σ along the normal, metres. A ray at grazing incidence gives σ → 0: the range noise
    then moves the point within the surface, which the point-to-plane residual does not see.
    """
    r = as_points(rays, "rays")
    n = as_points(normals, "normals")
    if len(r) != len(n):
        raise InputError(f"{len(r)} rays for {len(n)} normals")
    r_len = np.linalg.norm(r, axis=1)
    n_len = np.linalg.norm(n, axis=1)
    if np.any(r_len == 0) or np.any(n_len == 0):
        raise InputError("rays and normals must be non-zero vectors")
    cos = np.abs(np.einsum("ij,ij->i", r, n)) / (r_len * n_len)
    sigma = real_array(sigma_r, "sigma_r")
    if sigma.ndim > 1 or sigma.size not in (1, len(r)):
        raise InputError(f"sigma_r must be one value or one per ray ({len(r)}), got {sigma.shape}")
    if not (np.isfinite(sigma).all() and (sigma >= 0).all()):
        raise InputError("sigma_r must be finite and >= 0 (a standard deviation, metres)")
    return sigma * cos


def fisher_point_to_plane(
    points: ArrayLike, normals: ArrayLike, sigma: float | ArrayLike
) -> NDArray[np.float64]:
    """Fisher information (6, 6) of point-to-plane residuals, twist order ``(ω, v)``.

    Parameters
    ----------
    points
        (N, 3) points, metres; the rotation part is about the origin of their frame.
    normals
        (N, 3) unit normals at the points.
    sigma
        Noise standard deviation along the normal (scalar or (N,)), metres, all > 0.

    Returns
    -------
    ``J = Σ h_i h_iᵀ / σ_i²`` with ``h_i = (p_i × n_i, n_i)``, in units of (1/rad², 1/(rad·m),
    1/m²) by block.

    Raises
    ------
    InputError
        Shapes disagree, a value is not finite, σ is not > 0, or a normal is not of unit length
        (within 1e-3): a normal of length 2 counted its point 4 times, one of zero length not
        at all, and the bound came out wrong without a word.
    """
    p = as_points(points, "points")
    n = as_points(normals, "normals")
    if len(p) != len(n):
        raise InputError(f"{len(p)} points for {len(n)} normals")
    length = np.sqrt(np.einsum("ij,ij->i", n, n))
    off = np.flatnonzero(np.abs(length - 1.0) > 1e-3)
    if len(off):
        raise InputError(
            f"normals must be unit vectors: {len(off)} of {len(n)} are not (first at row "
            f"{off[0]}, length {length[off[0]]:.6g})"
        )
    s = real_array(sigma, "sigma")
    s = np.full(len(p), float(s)) if s.ndim == 0 else s
    if s.shape != (len(p),):
        raise InputError(f"sigma must be a scalar or have shape ({len(p)},), got {s.shape}")
    if not np.all(np.isfinite(s) & (s > 0)):
        raise InputError("sigma must be finite and > 0 for every point")
    h = np.hstack([np.cross(p, n), n])
    with np.errstate(over="ignore", divide="ignore", under="ignore", invalid="ignore"):
        J = np.einsum("ni,nj->ij", h / s[:, None] ** 2, h)
        squares = s**2
    if not (np.isfinite(J).all() and np.all((squares > 0) & np.isfinite(squares))):
        # 1e-300 m made J infinite (numpy's "Eigenvalues did not converge" followed); 1e300 m
        # left no information at all, with numpy's overflow warning.
        raise InputError(
            f"sigma from {s.min():.3g} to {s.max():.3g} m: its inverse square, or the "
            "information, leaves float64's range (wrong units?)"
        )
    return J


@dataclass(frozen=True, eq=False)
class CramerRaoBound:
    """The bound on the covariance of a registration twist ``(ω, v)``.

    Attributes
    ----------
    covariance
        (6, 6) ``J⁺`` (pseudo-inverse; doubled for frame-to-frame registration).
    std
        (6,) ``sqrt(diag(covariance))`` in rad and m; ``inf`` for a parameter that has a
        component along an unobservable direction, whose variance is unbounded.
    rank
        Rank of the Fisher information.
    degenerate
        ``rank < 6``: some motion leaves every residual unchanged (e.g. a single plane).
    null_directions
        (6, k) orthonormal basis of the unobservable twists (k = 6 − rank).
    information
        (6, 6) the Fisher information ``J`` itself (halved for frame-to-frame).
    """

    covariance: NDArray[np.float64]
    std: NDArray[np.float64]
    rank: int
    degenerate: bool
    null_directions: NDArray[np.float64]
    information: NDArray[np.float64]


def crlb(
    points: ArrayLike,
    normals: ArrayLike,
    sigma: float | ArrayLike,
    frame_to_frame: bool = False,
    rtol: float = RANK_RTOL,
) -> CramerRaoBound:
    """Cramér–Rao bound of point-to-plane registration of ``points`` onto their planes.

    Parameters
    ----------
    points, normals, sigma
        As :func:`fisher_point_to_plane`.
    frame_to_frame
        Both clouds are noisy (frame-to-frame tracking rather than registration to a model):
        the residual variance is about twice as large, so the bound doubles.
    rtol
        Eigenvalues of J below ``rtol × max eigenvalue`` are treated as zero. Scale-dependent:
        rotation and translation blocks have different units.

    Returns
    -------
    CramerRaoBound; a degenerate geometry is reported (``degenerate``, ``null_directions``),
    not raised.
    """
    real = isinstance(rtol, int | float | np.floating) and not isinstance(rtol, bool)
    if not (real and 0.0 <= rtol < 1.0):
        # NaN kept no eigenvalue (a zero covariance, σ inf, rank 0); text ended in a TypeError.
        raise InputError(f"crlb: rtol must be a number in [0, 1), got {rtol!r}")
    J = fisher_point_to_plane(points, normals, sigma)
    if frame_to_frame:
        J = 0.5 * J
    eigval, eigvec = np.linalg.eigh(J)
    keep = eigval > rtol * max(eigval[-1], 0.0)
    rank = int(keep.sum())
    V = eigvec[:, keep]
    covariance = (V / eigval[keep]) @ V.T
    null = eigvec[:, ~keep]
    std = np.sqrt(np.clip(np.diag(covariance), 0.0, None))
    # A parameter touched by a null direction is unbounded, not "known to 0".
    std[np.einsum("ik,ik->i", null, null) > 1e-12] = np.inf
    return CramerRaoBound(
        covariance=covariance,
        std=std,
        rank=rank,
        degenerate=rank < 6,
        null_directions=null,
        information=J,
    )
