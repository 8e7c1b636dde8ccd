"""Generalized ICP (Segal et al. 2009; methods.md §1.5).

Each point carries a covariance from its k nearest neighbours, regularised to a plane: the
eigenvalues are replaced by ``(ε, 1, 1)`` (smallest along the normal), as Segal et al.,
small_gicp and Open3D do. The cost ``Σ dᵢᵀ (C_q + R C_p Rᵀ)⁻¹ dᵢ`` with ``dᵢ = R pᵢ + t − qᵢ`` is
minimised by Gauss-Newton (or Levenberg-Marquardt) on SE(3) with a left perturbation
``T ← exp(δ) T``; the weights ``(C_q + R C_p Rᵀ)⁻¹`` are held fixed within one linearisation, and
correspondences are searched again at every iteration.
"""

from __future__ import annotations

import numba
import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import Field

from spacepose.core import se3
from spacepose.core.cloud import PointCloud, check_rows
from spacepose.core.grid import numba_threads
from spacepose.core.icp import (
    CorrespondenceSearch,
    as_registration_cloud,
    solve_normal_equations,
    system_from_sums,
    target_index,
)
from spacepose.core.neighbors import SearchIndex, knn
from spacepose.core.normals import neighbourhood_normals
from spacepose.core.registration import RegistrationResult
from spacepose.core.robust import RobustConfig, robust_weights
from spacepose.errors import InputError, RegistrationError

# Levenberg-Marquardt damping schedule (the values small_gicp uses).
# Correspondences per chunk of the compiled normal equations (fixed: so is the sum order).
_CHUNK = 512
_LM_INIT_LAMBDA = 1e-3
_LM_FACTOR = 10.0
_LM_MAX_TRIALS = 10
# Floor of the a-posteriori variance factor (m² per unit of the regularised covariance): an exact
# fit (identical clouds) would otherwise give an infinite information matrix.
_MIN_VARIANCE_FACTOR = 1e-12


class GICPConfig(RobustConfig):
    """Parameters of :func:`gicp`.

    Attributes
    ----------
    k_covariance
        Neighbours (the point itself included) behind each point's covariance.
    epsilon
        Regularised eigenvalue along the normal, relative to 1 in the tangent plane.
    max_correspondence_distance
        Largest source-to-target distance (m) of a correspondence.
    max_iterations
        Largest number of linearisations.
    rotation_tolerance, translation_tolerance
        Stop when an update rotates by less than this (rad) and translates by less than this (m).
        1e-5 (0.6 mdeg, 0.01 mm) sits far below the noise of any registration here: on a lab
        frame pair it stops after 16 linearisations instead of running all 30 at 1e-7 (which
        correspondence changes never let it reach), 28 % faster, with the same error.
    lm
        Levenberg-Marquardt (a damped step is accepted only if it lowers the cost on the current
        correspondences) instead of plain Gauss-Newton.
    robust_kernel, robust_scale
        IRLS kernel on the Mahalanobis distances ``√(dᵀWd)`` and its σ (Mahalanobis units;
        None: adaptive), see :mod:`spacepose.core.robust`; the weights multiply each ``W``.
        ``"none"`` is plain least squares.
    """

    k_covariance: int = Field(20, ge=3)
    epsilon: float = Field(1e-3, gt=0, le=1)
    max_correspondence_distance: float = Field(0.05, gt=0)
    max_iterations: int = Field(30, ge=1)
    rotation_tolerance: float = Field(1e-5, gt=0)
    translation_tolerance: float = Field(1e-5, gt=0)
    lm: bool = True


def compute_covariances(
    points: PointCloud | ArrayLike, k: int = 20, epsilon: float = 1e-3, workers: int = -1
) -> NDArray[np.float64]:
    """Plane-regularised covariance of every point, from its k nearest neighbours.

    Parameters
    ----------
    points
        (N, 3) points (or a :class:`PointCloud`), N >= k.
    k
        Neighbours per point, the point itself included.
    epsilon
        Eigenvalue given to the normal direction; the two tangent directions get 1.
    workers
        Threads for the neighbour search.

    Returns
    -------
    (N, 3, 3) covariances ``V diag(ε, 1, 1) Vᵀ`` in the points' frame, V the eigenvectors of the
    neighbourhood scatter in ascending eigenvalue order.
    """
    pts = as_registration_cloud(points, "points").points
    if not 3 <= k <= len(pts):
        raise InputError(f"covariances need 3 <= k <= {len(pts)} (number of points), got k={k}")
    if not 0 < epsilon <= 1:
        raise InputError(f"covariance epsilon must be in (0, 1], got {epsilon}")
    _, idx = knn(pts, None, k, workers=workers)
    normals = neighbourhood_normals(pts, idx, workers)
    # V diag(ε, 1, 1) Vᵀ = I − (1 − ε) n nᵀ: only the smallest eigenvector n is needed.
    return np.eye(3) - (1.0 - epsilon) * normals[:, :, None] * normals[:, None, :]


def _check_covariances(C: ArrayLike | None, n: int, name: str) -> NDArray[np.float64] | None:
    if C is None:
        return None
    C = np.asarray(C, dtype=np.float64)
    if C.shape != (n, 3, 3) or not np.all(np.isfinite(C)):
        raise InputError(f"{name} must be finite with shape ({n}, 3, 3), got {C.shape}")
    return C


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
        singular = _weights_kernel(
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
    partial = np.zeros((max(1, -(-len(points) // _CHUNK)), 28))
    with numba_threads(workers):
        _system_kernel(
            np.ascontiguousarray(points, dtype=np.float64),
            np.ascontiguousarray(target_points, dtype=np.float64),
            np.ascontiguousarray(W, dtype=np.float64),
            partial,
        )
    total = partial.sum(axis=0)
    H, g = system_from_sums(total)
    return H, g, float(total[27])


@numba.njit(cache=True, parallel=True)
def _weights_kernel(points, target_points, R, Cs, Ct, W, m2):
    """Fill ``W`` and ``m2 = dᵀWd`` row by row; return how many rows had no positive definite
    ``C_q + R C_p Rᵀ`` (their W and m2 are 0)."""
    m = len(points)
    singular = 0
    for c in numba.prange(max(1, -(-m // _CHUNK))):
        RC = np.empty((3, 3))
        C = np.empty((3, 3))
        for i in range(c * _CHUNK, min(m, (c + 1) * _CHUNK)):
            for a in range(3):
                for b in range(3):
                    RC[a, b] = R[a, 0] * Cs[i, 0, b] + R[a, 1] * Cs[i, 1, b] + R[a, 2] * Cs[i, 2, b]
            for a in range(3):
                for b in range(a, 3):
                    C[a, b] = (
                        Ct[i, a, b] + RC[a, 0] * R[b, 0] + RC[a, 1] * R[b, 1] + RC[a, 2] * R[b, 2]
                    )
            # Inverse from the adjugate; Sylvester's criterion for positive definiteness.
            c00, c01, c02, c11, c12, c22 = C[0, 0], C[0, 1], C[0, 2], C[1, 1], C[1, 2], C[2, 2]
            a00, a01, a02 = c11 * c22 - c12 * c12, c02 * c12 - c01 * c22, c01 * c12 - c02 * c11
            det = c00 * a00 + c01 * a01 + c02 * a02
            if not (det > 0 and c00 > 0 and c00 * c11 - c01 * c01 > 0):
                singular += 1
                W[i] = 0.0
                m2[i] = 0.0
                continue
            inv = 1.0 / det
            W[i, 0, 0], W[i, 0, 1], W[i, 0, 2] = a00 * inv, a01 * inv, a02 * inv
            W[i, 1, 1] = (c00 * c22 - c02 * c02) * inv
            W[i, 1, 2] = (c01 * c02 - c00 * c12) * inv
            W[i, 2, 2] = (c00 * c11 - c01 * c01) * inv
            W[i, 1, 0], W[i, 2, 0], W[i, 2, 1] = W[i, 0, 1], W[i, 0, 2], W[i, 1, 2]
            m2[i] = 0.0
            for a in range(3):
                da = points[i, a] - target_points[i, a]
                for b in range(3):
                    m2[i] += da * W[i, a, b] * (points[i, b] - target_points[i, b])
    return singular


@numba.njit(cache=True, parallel=True)
def _system_kernel(points, target_points, W, partial):
    """Per chunk of rows: the upper triangle of Σ JᵀWJ (21), Σ JᵀWd (6) and Σ dᵀWd."""
    m = len(points)
    for c in numba.prange(len(partial)):
        acc = partial[c]
        J = np.zeros((3, 6))
        WJ = np.empty((3, 6))
        Wd = np.empty(3)
        d = np.empty(3)
        for a in range(3):
            J[a, 3 + a] = 1.0
        for i in range(c * _CHUNK, min(m, (c + 1) * _CHUNK)):
            px, py, pz = points[i, 0], points[i, 1], points[i, 2]
            # J = [−skew(p) I]: the derivative of exp(δ) p at δ = 0.
            J[0, 1], J[0, 2] = pz, -py
            J[1, 0], J[1, 2] = -pz, px
            J[2, 0], J[2, 1] = py, -px
            for a in range(3):
                d[a] = points[i, a] - target_points[i, a]
            for a in range(3):
                Wd[a] = W[i, a, 0] * d[0] + W[i, a, 1] * d[1] + W[i, a, 2] * d[2]
                for b in range(6):
                    WJ[a, b] = W[i, a, 0] * J[0, b] + W[i, a, 1] * J[1, b] + W[i, a, 2] * J[2, b]
            pos = 0
            for a in range(6):
                for b in range(a, 6):
                    acc[pos] += J[0, a] * WJ[0, b] + J[1, a] * WJ[1, b] + J[2, a] * WJ[2, b]
                    pos += 1
            for a in range(6):
                acc[21 + a] += J[0, a] * Wd[0] + J[1, a] * Wd[1] + J[2, a] * Wd[2]
            acc[27] += d[0] * Wd[0] + d[1] * Wd[1] + d[2] * Wd[2]


def mahalanobis_sum(d: NDArray[np.float64], W: NDArray[np.float64]) -> float:
    """``Σ dᵢᵀ Wᵢ dᵢ`` over residuals d (M, 3) and weights W (M, 3, 3)."""
    return float(np.einsum("na,na->", d, np.einsum("nab,nb->na", W, d)))


def gicp(
    source: PointCloud | ArrayLike,
    target: PointCloud | ArrayLike,
    init_T_target_source: ArrayLike = np.eye(4),
    config: GICPConfig = GICPConfig(),
    workers: int = -1,
    source_covariances: ArrayLike | None = None,
    target_covariances: ArrayLike | None = None,
    target_tree: SearchIndex | None = None,
) -> RegistrationResult:
    """Align ``source`` to ``target`` by Generalized ICP.

    Parameters
    ----------
    source, target
        Clouds ((N, 3) arrays or :class:`PointCloud`), each in its own frame.
    init_T_target_source
        (4, 4) initial guess mapping source coordinates into the target frame.
    config
        Covariance, gate, iteration and solver parameters.
    workers
        Threads for the neighbour searches (results do not depend on it).
    source_covariances, target_covariances
        Optional (N, 3, 3) covariances from :func:`compute_covariances`, each in its cloud's
        frame, so that a tracker computes them once per frame; computed when omitted.
    target_tree
        Optional prebuilt search index (``cKDTree``, VoxelIndex) of the target points.

    Returns
    -------
    RegistrationResult
        ``T_target_source``; fitness and Euclidean inlier RMSE of the final correspondences; and
        ``information = Σ JᵀWJ / s²`` with ``s² = Σ dᵀWd / (M − 6)`` the a-posteriori variance
        factor over the M correspondences. The regularised covariances only fix the *shape* of
        the noise, so its scale is taken from the residuals; M − 6 rather than 3M − 6 degrees
        of freedom because the (ε, 1, 1) shape makes each correspondence informative along its
        normal only (the tangential terms are ε times weaker). The information is therefore
        noise-weighted: ``result.covariance(sigma=1.0)`` is the covariance of
        ``T_target_source``. It treats the estimated covariances as exact, so it is somewhat
        optimistic when the clouds are sparse and noisy. With a robust kernel every sum is
        weighted (``W ← w W``) and ``s²`` is Huber's M-estimator variance factor of the
        Mahalanobis distances (:meth:`~spacepose.core.robust.RobustWeights.variance`).

    Raises
    ------
    InputError
        Fewer than 3 points (or fewer than ``k_covariance``), bad covariances, a non-rigid or
        non-finite initial transform.
    RegistrationError
        Fewer than 3 correspondences within the gate at some iteration.
    DegenerateGeometryError
        A surface that leaves a degree of freedom free.
    """
    src = as_registration_cloud(source, "source")
    tgt = as_registration_cloud(target, "target")
    T = se3.as_transform(init_T_target_source, "init_T_target_source").copy()
    Cs = _check_covariances(source_covariances, len(src), "source_covariances")
    Ct = _check_covariances(target_covariances, len(tgt), "target_covariances")
    if Cs is None:
        Cs = compute_covariances(src, config.k_covariance, config.epsilon, workers)
    if Ct is None:
        Ct = compute_covariances(tgt, config.k_covariance, config.epsilon, workers)
    gate = config.max_correspondence_distance
    search = CorrespondenceSearch(target_index(tgt, target_tree), gate, workers)

    def correspond(
        T_cur: NDArray[np.float64],
    ) -> tuple[NDArray[np.intp], NDArray[np.intp], NDArray[np.float64], float]:
        moved = se3.transform_points(T_cur, src.points)
        s, t, d2 = search(moved)
        if len(s) < 3:
            raise RegistrationError(
                f"GICP found {len(s)} correspondences within {gate} m (of {len(src)} source "
                "points); the initial guess is too far off or the gate too small"
            )
        return s, t, moved[s], float(np.sqrt(d2.mean()))

    robust = config.robust_kernel != "none"

    def linearize(
        T_cur: NDArray[np.float64], s: NDArray[np.intp], t: NDArray[np.intp], p: NDArray
    ) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64], float, float]:
        """Normal equations at T_cur (p: the matched source points already moved by it), with
        the robust weights folded into W, and the a-posteriori variance factor."""
        q = tgt.points[t]
        W, m2 = gicp_weight_matrices(p, q, T_cur[:3, :3], Cs[s], Ct[t], workers)
        w = None
        if robust:
            w = robust_weights(np.sqrt(m2), config.robust_kernel, config.robust_scale)
            W *= w.weights[:, None, None]
        H, g, cost = gicp_system(p, q, W, workers)
        variance = cost / max(len(s) - 6, 1) if w is None else w.variance(np.sqrt(m2))
        return H, g, cost, W, variance

    lam = _LM_INIT_LAMBDA
    converged = False
    iterations = 0
    while iterations < config.max_iterations:
        iterations += 1
        s, t, p, _ = correspond(T)
        H, g, cost, W, _ = linearize(T, s, t, p)
        if config.lm:
            src_s, tgt_t = src.points[s], tgt.points[t]
            # Damped steps on fixed correspondences and weights until one lowers the cost.
            for _ in range(_LM_MAX_TRIALS):
                delta = solve_normal_equations(H, g, damping=lam)
                moved = se3.transform_points(se3.exp(delta) @ T, src_s)
                if mahalanobis_sum(moved - tgt_t, W) <= cost:
                    lam /= _LM_FACTOR
                    break
                lam *= _LM_FACTOR
            else:
                converged = True  # no damped step improves: T is a minimum to working precision
                break
        else:
            delta = solve_normal_equations(H, g)
        T = se3.exp(delta) @ T
        if (
            np.linalg.norm(delta[:3]) < config.rotation_tolerance
            and np.linalg.norm(delta[3:]) < config.translation_tolerance
        ):
            converged = True
            break

    s, t, p, rmse = correspond(T)
    H, _, _, _, variance = linearize(T, s, t, p)
    return RegistrationResult(
        T_target_source=T,
        fitness=len(s) / len(src),
        inlier_rmse=rmse,
        iterations=iterations,
        converged=converged,
        information=H / max(variance, _MIN_VARIANCE_FACTOR),
        n_correspondences=len(s),
    )
