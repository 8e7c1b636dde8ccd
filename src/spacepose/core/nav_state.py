"""The relative-navigation state: its error-state layout, the inertia-ratio parametrisation and
the discrete propagation of the error state (methods.md §2.4, Yu §3).

:class:`NavState` is a nominal state (truth or estimate) in the filter's frames, SI units:
``rho`` (3) target CoM − chaser CoM in O, ``v`` (3) its derivative in O, ``q_I_B`` (4) target
attitude B -> I (scalar last), ``omega_B`` (3) rate in B, ``k`` (3) inertia ratios, ``com`` (3)
= Δ, the offset B' origin -> B origin in B.

Error state (multiplicative for the attitude)
---------------------------------------------
``(δρ, δv, δθ, δω, δp, δΔ, δ_1, δ_2, ...)`` with the attitude error on the right, in B:
``R_I_B = R̂_I_B · exp([δθ]×)``. The slices ``RHO`` ... ``COM`` index its fixed part
(``N_FIXED`` = 17); the chaser-attitude consider state φ (``CHASER``, in C, rad) follows when
the filter holds it, then three per tracked rectangle (m, in B). Only two inertia parameters
``p = (k_x, k_y)`` are estimated because only two of the three ratios are independent:
``k_z = −(k_x + k_y) / (1 + k_x k_y)`` (:func:`k_from_params`, :func:`params_from_k`, and the
(3, 2) Jacobian :func:`dk_dp`).

Why these choices: the body-frame attitude error gives the classic MEKF kinematics
``δθ̇ = −[ω]× δθ + δω``. Estimating ``(k_x, k_y)`` themselves keeps Euler's equations linear in
two of the three parameters; log moment ratios were tried first and their strong nonlinearity
under a wide prior biased the filter (NEES far above its χ² bound during convergence).

Propagation
-----------
:func:`discretise`: the transition matrix Φ and the discrete process noise Q over an interval
dt (s) from the fixed part's error-state Jacobian F (17, 17, per s) and its white-noise
densities Qc (17, 17).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from spacepose.core import se3
from spacepose.core.cloud import MAX_ABS_COORDINATE
from spacepose.errors import InputError

# Error-state slices of the fixed part; rectangle location errors follow from index 17.
RHO, VEL, ATT, RATE, INERTIA, COM = (
    slice(0, 3),
    slice(3, 6),
    slice(6, 9),
    slice(9, 12),
    slice(12, 14),
    slice(14, 17),
)
N_FIXED = 17
# The chaser-attitude consider state, when present (EKFConfig.sigma_chaser_attitude_deg > 0).
CHASER = slice(N_FIXED, N_FIXED + 3)


@dataclass(frozen=True)
class NavState:
    """A navigation state (truth or estimate) in the filter's frames, SI units.

    Attributes
    ----------
    t
        Time, s, since the epoch where I and O coincide.
    rho, v
        (3,) relative position / velocity in O, m and m/s.
    q_I_B
        (4,) attitude B -> I, scalar last.
    omega_B
        (3,) rate in B, rad/s.
    k
        (3,) inertia ratios.
    com
        (3,) CoM offset Δ in B, m.
    """

    t: float
    rho: NDArray[np.float64]
    v: NDArray[np.float64]
    q_I_B: NDArray[np.float64]
    omega_B: NDArray[np.float64]
    k: NDArray[np.float64]
    com: NDArray[np.float64]


def k_from_params(p: ArrayLike) -> NDArray[np.float64]:
    """Inertia ratios k (3,) from the estimated pair ``p = (k_x, k_y)``.

    With Izz = 1: ``Ixx = (1 − k_y) / (1 + k_x k_y)``, ``Iyy = (1 + k_x) / (1 + k_x k_y)`` and
    ``k_z = Ixx − Iyy``.
    """
    kx, ky = np.asarray(p, dtype=np.float64)
    return np.array([kx, ky, -(kx + ky) / (1.0 + kx * ky)])


def params_from_k(k: ArrayLike) -> NDArray[np.float64]:
    """The estimated pair ``(k_x, k_y)`` (2,) from ratios k (3,), checked for consistency."""
    k = finite(k, (3,), "inertia ratios k")
    if np.any(np.abs(k[:2]) >= 1.0) or abs(k[2] - k_from_params(k[:2])[2]) > 1e-6:
        raise InputError(f"inertia ratios {k} are not those of positive principal moments")
    return k[:2].copy()


def dk_dp(p: NDArray[np.float64]) -> NDArray[np.float64]:
    """Jacobian (3, 2) of k with respect to ``p = (k_x, k_y)``."""
    kx, ky = p
    d = (1.0 + kx * ky) ** 2
    return np.array([[1.0, 0.0], [0.0, 1.0], [-(1.0 - ky**2) / d, -(1.0 - kx**2) / d]])


def discretise(
    F: NDArray[np.float64], Qc: NDArray[np.float64], dt: float
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Transition matrix Φ = exp(F dt) and discrete process noise Q = ∫ Φ(s) Qc Φ(s)ᵀ ds.

    Series in ``h = dt / 2ᵏ`` (Φ to fourth, Q to third order), doubled k times:
    ``Q ← Φ Q Φᵀ + Q``, ``Φ ← Φ Φ``. k is the least that keeps ``‖F' h‖∞ <= 0.05``, with F' the
    Jacobian without its ρ̇ = v identity block: that block is nilpotent, so it does not slow the
    series. Small matrices make this far cheaper than a Padé ``expm`` of the Van Loan matrix,
    and doubling makes a long gap cost its logarithm: composed step by step, a 10⁵ s gap took
    12 s (the attitude's rate block alone asks for 2·10⁶ steps).
    """
    F_rest = F.copy()
    F_rest[RHO, VEL] = 0.0
    norm = float(np.abs(F_rest).sum(axis=1).max()) * abs(dt)
    k = max(0, math.ceil(math.log2(norm / 0.05))) if norm > 0.05 else 0
    h = dt / 2.0**k
    A = F * h
    A2 = A @ A
    Phi_h = np.eye(len(F)) + A + A2 / 2.0 + A2 @ A / 6.0 + A2 @ A2 / 24.0
    FQ = F @ Qc
    F2Q = F @ FQ
    Q_h = Qc * h + (FQ + FQ.T) * h**2 / 2.0 + (F2Q + F2Q.T + 2.0 * FQ @ F.T) * h**3 / 6.0
    Phi, Q = Phi_h, Q_h
    for _ in range(k):
        Q = Phi @ Q @ Phi.T + Q
        Phi = Phi @ Phi
    return Phi, Q


def finite(values: ArrayLike, shape: tuple[int, ...], name: str) -> NDArray[np.float64]:
    """``values`` as a float array, checked to have ``shape`` and finite entries (InputError
    naming them ``name`` otherwise)."""
    arr = se3.real_array(values, name)
    if arr.shape != shape or not np.all(np.isfinite(arr)):
        raise InputError(f"{name} must be finite with shape {shape}, got {arr.shape}")
    return arr


def seconds(value: object, name: str) -> float:
    """``value`` as a finite float, or an InputError naming ``name`` (a time or a rate: text, a
    yes/no or an array ended in a TypeError or passed as a number; NaN in "state6 has
    non-finite entries")."""
    try:
        if isinstance(value, bool | np.bool_ | str | bytes) or np.ndim(value) != 0:
            raise TypeError
        number = float(value)  # type: ignore[arg-type]
    except (TypeError, ValueError):
        number = math.nan
    if not math.isfinite(number):
        raise InputError(f"{name} must be a finite number, got {value!r:.60}")
    return number


# Rounding, relative to its largest entry, a measurement covariance's symmetry may carry.
_SKEW = 1e-6
# Largest |entry| of a measurement covariance: a squared coordinate's (sums stay finite).
_LARGEST_VARIANCE = MAX_ABS_COORDINATE**2


def measurement_covariance(values: ArrayLike, m: int) -> NDArray[np.float64]:
    """``values`` as an (m, m) measurement covariance: finite, its sums finite, symmetric to
    rounding and positive definite (InputError otherwise)."""
    C = finite(values, (m, m), "measurement covariance")
    if np.abs(C).max() > _LARGEST_VARIANCE:  # sums overflowed: "Eigenvalues did not converge"
        raise InputError(
            f"measurement covariance reaches {np.abs(C).max():.3g}, beyond "
            f"{_LARGEST_VARIANCE:.3g}: its sums overflow float64 (wrong units?)"
        )
    i, j = np.unravel_index(np.argmax(np.abs(C - C.T)), C.shape)
    if abs(C[i, j] - C[j, i]) > _SKEW * np.abs(C).max():  # averaged, it was another matrix
        raise InputError(
            f"measurement covariance is not symmetric (C[{i}, {j}] {C[i, j]:.3g}, C[{j}, {i}] "
            f"{C[j, i]:.3g}): no covariance"
        )
    C = 0.5 * (C + C.T)
    if np.linalg.eigvalsh(C)[0] <= 0:
        raise InputError("measurement covariance must be positive definite")
    return C
