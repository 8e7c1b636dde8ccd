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

import numba
import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import Field

from spacepose.core.config import StageConfig
from spacepose.errors import InputError

RobustKernelName = Literal["none", "huber", "cauchy", "geman_mcclure"]

# Kernel numbers of the compiled weight function (:func:`weight_and_slope`).
KERNEL_CODES = {"none": 0, "huber": 1, "cauchy": 2, "geman_mcclure": 3}
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
        psi = self.weights * r
        return sandwich_variance(
            float(psi @ psi), self.total, float(self.slopes.sum()), len(r), n_params
        )


def sandwich_variance(psi2: float, total: float, slope: float, m: int, n_params: int = 6) -> float:
    """:meth:`RobustWeights.variance` from its sums: ``Σ ψ²``, ``Σ w``, ``Σ ψ'`` over ``m``
    residuals, ``n_params`` parameters (for a compiled pass that accumulates them)."""
    if slope <= 0:
        # Most residuals beyond the kernel's fall-off: no sandwich; fixed weights instead.
        slope = total
    return psi2 * total * m / (max(m - n_params, 1) * slope**2)


def adaptive_scale(residuals: ArrayLike) -> float:
    """Robust σ of zero-mean residuals: ``1.4826 · median |r|``.

    No residuals give 0, the scale of an exact fit: :func:`kernel_width` then leaves every
    weight at 1 (nothing to down-weight), which is what a registration with no matches yet
    needs.

    Raises
    ------
    InputError
        A residual is NaN or inf (σ was NaN, or the median of the finite ones, without a word).
    """
    r = np.abs(np.asarray(residuals, dtype=np.float64))
    _finite_peak(r, "adaptive_scale")
    return _median_scale(r)


def _finite_peak(r: NDArray[np.float64], name: str) -> float:
    """``max |r|`` of absolute residuals ``r`` (0 for none); InputError unless finite."""
    peak = float(r.max()) if len(r) else 0.0
    if not peak < np.inf:  # NaN compares False
        raise InputError(f"{name}: the residuals have non-finite entries (NaN or inf)")
    return peak


def _median_scale(r: NDArray[np.float64]) -> float:
    """:func:`adaptive_scale` of finite absolute residuals ``r``."""
    return MAD_TO_SIGMA * float(np.median(r)) if len(r) else 0.0


def kernel_weights(u: NDArray[np.float64], kernel: RobustKernelName) -> NDArray[np.float64]:
    """IRLS weight ``w(u) = ψ(u)/u`` of ``kernel`` at residuals ``u`` (M,) in units of c."""
    return _weights_slopes(np.asarray(u, dtype=np.float64), KERNEL_CODES[kernel])[0]


def kernel_slopes(u: NDArray[np.float64], kernel: RobustKernelName) -> NDArray[np.float64]:
    """``ψ'(u) = d(u w(u))/du`` of ``kernel`` at residuals ``u`` (M,) in units of c."""
    return _weights_slopes(np.asarray(u, dtype=np.float64), KERNEL_CODES[kernel])[1]


@numba.njit(cache=True, inline="always")
def weight_and_slope(u, code):
    """``(w(u), ψ'(u))`` of the kernel numbered ``code`` (:data:`KERNEL_CODES`) at one residual
    ``u`` in units of c: the formulas every weight here comes from, for compiled passes too."""
    a2 = u * u
    if code == 1:
        return 1.0 / max(abs(u), 1.0), 1.0 if a2 <= 1.0 else 0.0
    if code == 2:
        return 1.0 / (1.0 + a2), (1.0 - a2) / ((1.0 + a2) * (1.0 + a2))
    if code == 3:
        b = 1.0 + a2
        return 1.0 / (b * b), (1.0 - 3.0 * a2) / (b * b * b)
    return 1.0, 1.0


@numba.njit(cache=True)
def _weights_slopes(u, code):
    w, slope = np.empty(len(u)), np.empty(len(u))
    for i in range(len(u)):
        w[i], slope[i] = weight_and_slope(u[i], code)
    return w, slope


def kernel_width(
    residuals: NDArray[np.float64], kernel: RobustKernelName, scale: float | None
) -> tuple[float, float]:
    """``(σ, c)`` of :func:`robust_weights` for residuals (M,): the fixed or adaptive σ and the
    kernel width ``c = TUNING[kernel] · σ``, c = 0 when every weight is 1 (no kernel, or nearly
    every residual zero: an exact fit, nothing to down-weight)."""
    r = np.abs(residuals)
    peak = _finite_peak(r, "robust weights")
    sigma = _median_scale(r) if scale is None else float(scale)
    floor = _MIN_RELATIVE_SCALE * peak
    if kernel == "none" or sigma <= floor:
        return sigma, 0.0
    return sigma, TUNING[kernel] * sigma


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
    sigma, c = kernel_width(r, kernel, scale)
    if c == 0.0:
        return RobustWeights(np.ones(len(r)), sigma, np.ones(len(r)))
    weights, slopes = _weights_slopes(r / c, KERNEL_CODES[kernel])
    return RobustWeights(weights, sigma, slopes)
