"""Robust kernels for ICP and GICP: iteratively reweighted least squares with a data-driven scale.

A registration that gates correspondences at a distance wider than the noise (to converge from
farther away, or because the noise is unknown) also pairs points with the wrong surface: a wall
behind the target, a ghost surface, clutter. Squared residuals let those pairs pull the estimate
by their full lever; an M-estimator caps or removes their influence. Each linearisation
minimises ``Σ w(rᵢ) rᵢ²`` with the weights ``w(r) = ψ(r)/r`` of a kernel ``ρ`` frozen at the
current residuals (IRLS, as KISS-ICP and small_gicp do):

===============  =========================  ======================================
kernel           weight ``w(u)``, u = r/c   c for 95 % efficiency under Gaussian noise
===============  =========================  ======================================
huber            ``min(1, 1/|u|)``          1.345 σ
cauchy           ``1 / (1 + u²)``           2.385 σ
geman_mcclure    ``1 / (1 + u²)²``          3.787 σ
===============  =========================  ======================================

The scale σ is either fixed by the caller (metres for ICP; the units of the residual) or, by
default, adaptive: ``1.4826 · median |r|`` over the current correspondences (the median absolute
deviation about zero; breakdown point 50 %). It shrinks as the registration converges, so the
first iterations, whose residuals are still dominated by the misalignment, are barely weighted
and the last ones see the noise alone. It needs no threshold in metres: it follows the data at
any range and noise level.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import Field

from spacepose.core.config import StageConfig

RobustKernelName = Literal["none", "huber", "cauchy", "geman_mcclure"]

# Kernel width c as a multiple of σ giving 95 % asymptotic efficiency on Gaussian residuals
# (E[ψ']² / E[ψ²] = 0.95, solved by quadrature).
TUNING = {"huber": 1.345, "cauchy": 2.3849, "geman_mcclure": 3.7874}
# σ of a zero-mean Gaussian per unit of its median absolute value (1 / Φ⁻¹(3/4)).
MAD_TO_SIGMA = 1.482602218505602
# Smallest adaptive scale, relative to the largest residual: an exact fit (all residuals zero)
# keeps unit weights instead of dividing by zero.
_MIN_RELATIVE_SCALE = 1e-12


class RobustConfig(StageConfig):
    """Robust-kernel fields shared by the ICP and GICP configs.

    Attributes
    ----------
    robust_kernel
        ``"none"`` (plain least squares), ``"huber"``, ``"cauchy"`` or ``"geman_mcclure"``.
    robust_scale
        Residual σ the kernel width is a multiple of (metres for ICP; Mahalanobis units for
        GICP); None: adaptive, ``1.4826 · median |r|`` of the current correspondences.
    """

    robust_kernel: RobustKernelName = "none"
    robust_scale: float | None = Field(None, gt=0)


@dataclass(frozen=True)
class RobustWeights:
    """IRLS weights of one set of residuals.

    Attributes
    ----------
    weights
        (M,) weights ``w(r/c)`` in (0, 1].
    scale
        σ (units of the residuals) the kernel width ``c = TUNING[kernel] · σ`` was taken from.
    slopes
        (M,) ``ψ'`` at each residual (``d(r w(r/c))/dr``; negative where a redescending kernel
        falls off).
    """

    weights: NDArray[np.float64]
    scale: float
    slopes: NDArray[np.float64]

    @property
    def total(self) -> float:
        """``Σ w``: the effective number of residuals behind a weighted sum."""
        return float(self.weights.sum())

    def variance(self, residuals: ArrayLike, n_params: int = 6) -> float:
        """Variance factor that turns the weighted information ``Σ w JᵀJ`` into a covariance.

        Huber's asymptotic covariance of an M-estimator, ``Σ ψ² / (M − p) / (Σ ψ' / M)² ·
        (Σ JᵀJ)⁻¹``, expressed on the weighted information (``Σ JᵀJ ≈ (M / Σ w) Σ w JᵀJ``):
        ``s² = Σ ψ² · Σ w · M / ((M − p) (Σ ψ')²)`` with ``ψ = w r``. With unit weights it is
        ``Σ r² / (M − p)``. Holding the final weights fixed instead (``Σ w r² / (Σ w − p)``)
        understates it by 14 % in variance for Gaussian residuals (Geman–McClure or Cauchy at
        95 % efficiency), because the down-weighted tails carry the noise too.

        Parameters
        ----------
        residuals
            (M,) the residuals these weights belong to.
        n_params
            Parameters estimated from them (6 for a pose).
        """
        r = np.asarray(residuals, dtype=np.float64)
        m = len(r)
        psi = self.weights * r
        slope = float(self.slopes.sum())
        if slope <= 0:
            # Most residuals beyond the kernel's fall-off: no sandwich; fixed weights instead.
            slope = self.total
        return float(psi @ psi) * self.total * m / (max(m - n_params, 1) * slope**2)


def adaptive_scale(residuals: ArrayLike) -> float:
    """Robust σ of zero-mean residuals: ``1.4826 · median |r|`` (0 for no residuals)."""
    r = np.abs(np.asarray(residuals, dtype=np.float64))
    return MAD_TO_SIGMA * float(np.median(r)) if len(r) else 0.0


def kernel_weights(u: NDArray[np.float64], kernel: RobustKernelName) -> NDArray[np.float64]:
    """IRLS weight ``w(u) = ψ(u)/u`` of ``kernel`` at residuals ``u`` (M,) in units of c."""
    if kernel == "none":
        return np.ones(len(u))
    a = np.abs(u)
    if kernel == "huber":
        return 1.0 / np.maximum(a, 1.0)
    if kernel == "cauchy":
        return 1.0 / (1.0 + a * a)
    return 1.0 / (1.0 + a * a) ** 2


def kernel_slopes(u: NDArray[np.float64], kernel: RobustKernelName) -> NDArray[np.float64]:
    """``ψ'(u) = d(u w(u))/du`` of ``kernel`` at residuals ``u`` (M,) in units of c."""
    a2 = np.asarray(u, dtype=np.float64) ** 2
    if kernel == "none":
        return np.ones(len(a2))
    if kernel == "huber":
        return (a2 <= 1.0).astype(np.float64)
    if kernel == "cauchy":
        return (1.0 - a2) / (1.0 + a2) ** 2
    return (1.0 - 3.0 * a2) / (1.0 + a2) ** 3


def robust_weights(
    residuals: ArrayLike, kernel: RobustKernelName, scale: float | None = None
) -> RobustWeights:
    """Weights of ``residuals`` (M,) under ``kernel`` with a fixed or adaptive σ.

    Parameters
    ----------
    residuals
        (M,) signed or unsigned residuals (point-to-plane distances, Euclidean distances,
        Mahalanobis distances), any unit.
    kernel
        Kernel name; ``"none"`` gives unit weights.
    scale
        σ in the residuals' unit; None takes :func:`adaptive_scale` of these residuals.

    Returns
    -------
    RobustWeights
        The (M,) weights and the σ used.
    """
    r = np.asarray(residuals, dtype=np.float64)
    sigma = adaptive_scale(r) if scale is None else float(scale)
    floor = _MIN_RELATIVE_SCALE * float(np.abs(r).max()) if len(r) else 0.0
    if kernel == "none" or sigma <= floor:
        # No kernel, or nearly every residual zero (an exact fit): nothing to down-weight.
        return RobustWeights(np.ones(len(r)), sigma, np.ones(len(r)))
    u = r / (TUNING[kernel] * sigma)
    return RobustWeights(kernel_weights(u, kernel), sigma, kernel_slopes(u, kernel))
