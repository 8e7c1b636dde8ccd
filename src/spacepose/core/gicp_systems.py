"""GICP's weights and normal equations on given correspondences (methods.md §1.5).

For M matched pairs, the (M, 3) source points ``p`` already moved into the target frame and their
(M, 3) target points ``q``, with the (M, 3, 3) covariances of each side in its own cloud's frame
(:mod:`spacepose.core.gicp_covariances`) and the current rotation ``R_target_source``: the weights
``W = (C_q + R C_p Rᵀ)⁻¹`` (M, 3, 3), the squared Mahalanobis distances ``dᵀWd`` (M,) with
``d = p − q`` (m), and the system ``H = Σ JᵀWJ`` (6, 6), ``g = Σ JᵀWd`` (6,) and the cost
``Σ dᵀWd`` with ``J = [−skew(p) I]`` (3, 6). Twists are ``(omega, v)`` of a left perturbation
``T ← exp(δ) T``. The sums are compiled (:mod:`spacepose.core.gicp_kernels`) and taken in fixed
chunks, so any thread count gives the same bits. :func:`spacepose.core.gicp.gicp` fuses the same
sums with the correspondence search; these functions take the matches already gathered.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from spacepose.core.cloud import check_rows
from spacepose.core.gicp_kernels import CHUNK, system_kernel, weights_kernel
from spacepose.core.icp_systems import system_from_sums
from spacepose.core.threads import numba_threads
from spacepose.errors import InputError


def gicp_linearize(
    points: NDArray[np.float64],
    target_points: NDArray[np.float64],
    R: NDArray[np.float64],
    source_covariances: NDArray[np.float64],
    target_covariances: NDArray[np.float64],
    workers: int = 1,
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], float]:
    """Normal equations of the GICP cost at the current transform.

    :func:`gicp_weight_matrices` then :func:`gicp_system`: ``W = (C_q + R C_p Rᵀ)⁻¹``, then
    ``JᵀWJ``, ``JᵀWd`` and ``dᵀWd`` with ``J = [−skew(p) I]``.

    Parameters
    ----------
    points
        (M, 3) matched source points mapped into the target frame.
    target_points
        (M, 3) their target points.
    R
        (3, 3) current rotation ``R_target_source`` (rotates the source covariances).
    source_covariances, target_covariances
        (M, 3, 3) matched covariances, each in its own cloud's frame.
    workers
        Threads (-1: all cores).

    Returns
    -------
    H, g, W, cost
        6×6 ``Σ JᵀWJ``, (6,) ``Σ JᵀWd``, the (M, 3, 3) weights ``(C_q + R C_p Rᵀ)⁻¹`` and the
        cost ``Σ dᵀWd``; twist order (omega, v), left perturbation.

    Raises
    ------
    InputError
        As :func:`gicp_weight_matrices`.
    """
    W, _ = gicp_weight_matrices(
        points, target_points, R, source_covariances, target_covariances, workers
    )
    H, g, cost = gicp_system(points, target_points, W, workers)
    return H, g, W, cost


def gicp_weight_matrices(
    points: NDArray[np.float64],
    target_points: NDArray[np.float64],
    R: NDArray[np.float64],
    source_covariances: NDArray[np.float64],
    target_covariances: NDArray[np.float64],
    workers: int = 1,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """GICP's per-correspondence weights ``W = (C_q + R C_p Rᵀ)⁻¹`` and Mahalanobis residuals.

    Compiled, one pass per correspondence, the inverse from the adjugate (the numpy form took
    ~5 ms of each 18 000-point iteration). Arguments as :func:`gicp_linearize`.

    Returns
    -------
    W, m2
        (M, 3, 3) weights and (M,) squared Mahalanobis distances ``dᵀWd``, ``d = p − q``.

    Raises
    ------
    InputError
        When some ``C_q + R C_p Rᵀ`` is singular or not positive definite (e.g. zero
        covariances), or the arrays do not share their row count and shapes (the kernel
        indexes them unchecked).
    """
    check_rows(
        "gicp_linearize",
        points,
        target_points,
        source_covariances,
        target_covariances,
        shapes=((3,), (3,), (3, 3), (3, 3)),
    )
    if np.shape(R) != (3, 3):
        raise InputError(f"gicp_linearize needs a (3, 3) rotation, got {np.shape(R)}")
    m = len(points)
    W = np.empty((m, 3, 3))
    m2 = np.empty(m)
    with numba_threads(workers):
        singular = weights_kernel(
            np.ascontiguousarray(points, dtype=np.float64),
            np.ascontiguousarray(target_points, dtype=np.float64),
            np.ascontiguousarray(R, dtype=np.float64),
            np.ascontiguousarray(source_covariances, dtype=np.float64),
            np.ascontiguousarray(target_covariances, dtype=np.float64),
            W,
            m2,
        )
    if singular:
        raise InputError(
            "GICP needs positive definite covariances: C_target + R C_source Rᵀ is singular "
            f"or indefinite for {singular} correspondences (use compute_covariances)"
        )
    return W, m2


def gicp_system(
    points: NDArray[np.float64],
    target_points: NDArray[np.float64],
    W: NDArray[np.float64],
    workers: int = 1,
) -> tuple[NDArray[np.float64], NDArray[np.float64], float]:
    """``Σ JᵀWJ``, ``Σ JᵀWd`` and ``Σ dᵀWd`` over (M, 3) points, targets and (M, 3, 3) W.

    Compiled, rows summed in fixed chunks (the same bits on any thread count). A robust kernel
    passes ``wᵢ Wᵢ``: its IRLS weights folded into the matrices.

    Returns
    -------
    H, g, cost
        (6, 6), (6,) and the scalar cost; twist order (omega, v), left perturbation.
    """
    check_rows("gicp_system", points, target_points, W, shapes=((3,), (3,), (3, 3)))
    partial = np.zeros((max(1, -(-len(points) // CHUNK)), 28))
    with numba_threads(workers):
        system_kernel(
            np.ascontiguousarray(points, dtype=np.float64),
            np.ascontiguousarray(target_points, dtype=np.float64),
            np.ascontiguousarray(W, dtype=np.float64),
            partial,
        )
    total = partial.sum(axis=0)
    H, g = system_from_sums(total)
    return H, g, float(total[27])
