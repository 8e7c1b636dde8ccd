"""Generalized ICP (Segal et al. 2009; methods.md §1.5).

Each point carries a covariance from its k nearest neighbours, regularised to a plane: the
eigenvalues are replaced by ``(ε, 1, 1)`` (smallest along the normal), as Segal et al.,
small_gicp and Open3D do. The cost ``Σ dᵢᵀ (C_q + R C_p Rᵀ)⁻¹ dᵢ`` with ``dᵢ = R pᵢ + t − qᵢ`` is
minimised by Gauss-Newton (or Levenberg-Marquardt) on SE(3) with a left perturbation
``T ← exp(δ) T``; the weights ``(C_q + R C_p Rᵀ)⁻¹`` are held fixed within one linearisation, and
correspondences are searched again at every iteration.

This module holds the configuration, the Levenberg-Marquardt loop and the compiled pass that
searches, weighs and sums at one transform; the per-point covariances are in
:mod:`spacepose.core.gicp_covariances`, the normal equations on gathered matches in
:mod:`spacepose.core.gicp_systems`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import Field

from spacepose.core import se3
from spacepose.core.cloud import PointCloud
from spacepose.core.config import stage_config
from spacepose.core.gicp_covariances import check_covariances, compute_covariances
from spacepose.core.gicp_kernels import CHUNK, gicp_pass_kernel, gicp_sums_kernel
from spacepose.core.grid import VoxelIndex
from spacepose.core.icp import as_registration_cloud, target_index, warn_if_other_unit
from spacepose.core.icp_systems import solve_normal_equations, system_from_sums
from spacepose.core.neighbors import SearchIndex
from spacepose.core.registration import RegistrationResult, far_centre, moved_back
from spacepose.core.robust import RobustConfig, robust_weights
from spacepose.core.threads import numba_threads
from spacepose.errors import InputError, RegistrationError

# Levenberg-Marquardt damping schedule (the values small_gicp uses).
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
        Neighbours (the point itself included) behind each point's covariance (at most 1,000,
        as a normal's).
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

    k_covariance: int = Field(20, ge=3, le=1000)
    epsilon: float = Field(1e-3, gt=0, le=1)
    max_correspondence_distance: float = Field(0.05, gt=0)
    max_iterations: int = Field(30, ge=1)
    rotation_tolerance: float = Field(1e-5, gt=0)
    translation_tolerance: float = Field(1e-5, gt=0)
    lm: bool = True


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

    Warns
    -----
    SpaceposeWarning
        The clouds look like millimetres against a gate in metres
        (:func:`~spacepose.core.icp.warn_if_other_unit`).
    """
    config = stage_config(config, GICPConfig)
    src = as_registration_cloud(source, "source")
    tgt = as_registration_cloud(target, "target")
    T = se3.as_transform(init_T_target_source, "init_T_target_source").copy()
    Cs = check_covariances(source_covariances, len(src), "source_covariances")
    Ct = check_covariances(target_covariances, len(tgt), "target_covariances")
    if Cs is None:
        Cs = compute_covariances(src, config.k_covariance, config.epsilon, workers)
    if Ct is None:
        Ct = compute_covariances(tgt, config.k_covariance, config.epsilon, workers)
    centre = far_centre(tgt.points)
    if centre is not None:
        # Solved about the target's centre (its covariances do not move): a 5 m box 1 km out
        # was called degenerate (information eigenvalues 0.27 .. 2.8e11).
        S = se3.make_transform(np.eye(3), -centre)
        near = gicp(
            src.transformed(S), tgt.transformed(S), S @ T @ se3.invert(S), config, workers, Cs, Ct
        )
        return moved_back(near, S)
    # Near its origin only: a far pair is checked once, in the call above.
    warn_if_other_unit((src, tgt), config.max_correspondence_distance)
    index = target_index(tgt, target_tree)
    if not isinstance(index, VoxelIndex):
        index = VoxelIndex(tgt.points)
    evaluate = _GICPPass(index, src.points, Cs, Ct, config, workers)

    lam = _LM_INIT_LAMBDA
    converged = False
    iterations = 0
    while iterations < config.max_iterations:
        iterations += 1
        lin = evaluate(T)
        if config.lm:
            # Damped steps on fixed correspondences and weights until one lowers the cost.
            for _ in range(_LM_MAX_TRIALS):
                delta = solve_normal_equations(lin.H, lin.g, damping=lam)
                if evaluate.cost(se3.exp(delta) @ T) <= lin.cost:
                    lam /= _LM_FACTOR
                    break
                lam *= _LM_FACTOR
            else:
                converged = True  # no damped step improves: T is a minimum to working precision
                break
        else:
            delta = solve_normal_equations(lin.H, lin.g)
        T = se3.exp(delta) @ T
        if (
            np.linalg.norm(delta[:3]) < config.rotation_tolerance
            and np.linalg.norm(delta[3:]) < config.translation_tolerance
        ):
            converged = True
            break

    lin = evaluate(T)
    return RegistrationResult(
        T_target_source=T,
        fitness=lin.count / len(src),
        inlier_rmse=lin.rmse,
        iterations=iterations,
        converged=converged,
        information=lin.H / max(lin.variance, _MIN_VARIANCE_FACTOR),
        n_correspondences=lin.count,
    )


@dataclass(frozen=True)
class _Linearization:
    """GICP's normal equations at one transform: ``H`` (6, 6), ``g`` (6,), the cost Σ w dᵀWd,
    the a-posteriori variance factor, the match count and the Euclidean inlier RMSE (m)."""

    H: NDArray[np.float64]
    g: NDArray[np.float64]
    cost: float
    variance: float
    count: int
    rmse: float


class _GICPPass:
    """GICP's correspondences, weights and normal equations at a transform in one compiled pass
    over a :class:`VoxelIndex` (no moved copy of the cloud, no gathered rows). Each point's
    search starts at its previous match and is skipped while the certificate of its last search
    holds, as in ICP's point-to-plane pass. The pass keeps each match's weight ``W`` (times its
    robust weight) for :meth:`cost`, Levenberg-Marquardt's trial steps on fixed matches."""

    def __init__(
        self,
        index: VoxelIndex,
        source_points: NDArray[np.float64],
        Cs: NDArray[np.float64],
        Ct: NDArray[np.float64],
        config: GICPConfig,
        workers: int,
    ) -> None:
        n = len(source_points)
        self.index, self.config, self.workers = index, config, workers
        self.gate = float(config.max_correspondence_distance)
        self.rings = index.rings(self.gate)
        self.source_points = np.ascontiguousarray(source_points, dtype=np.float64)
        self.Cs = np.ascontiguousarray(Cs, dtype=np.float64)
        self.Ct = np.ascontiguousarray(Ct, dtype=np.float64)
        self.nearest = np.full(n, -1, dtype=np.int64)
        # Each point's last search: where it was made and its certificate (0: none yet).
        self.anchors = np.zeros((n, 3))
        self.bounds = np.zeros(n)
        self.W = np.zeros((n, 3, 3))
        self.m2 = np.zeros(n)
        self.chunks = max(1, -(-n // CHUNK))

    def __call__(self, T: NDArray[np.float64]) -> _Linearization:
        robust = self.config.robust_kernel != "none"
        n = len(self.source_points)
        partial = np.zeros((self.chunks, 2 if robust else 30))
        nearest = np.empty(n, dtype=np.int64)
        R, t = np.ascontiguousarray(T[:3, :3]), np.ascontiguousarray(T[:3, 3])
        with numba_threads(self.workers):
            singular = gicp_pass_kernel(
                self.index.kernel_grid,
                self.rings,
                self.index.data,
                self.source_points,
                self.Cs,
                self.Ct,
                R,
                t,
                self.gate,
                self.nearest,
                nearest,
                self.anchors,
                self.bounds,
                self.W,
                self.m2,
                partial,
            )
        self.nearest = nearest
        total = partial.sum(axis=0)
        count = int(total[-2])
        if count < 3:
            raise RegistrationError(
                f"GICP found {count} correspondences within {self.gate:.3g} m (of {n} source "
                "points); the initial guess is too far off or the gate too small"
            )
        if singular:
            raise InputError(
                "GICP needs positive definite covariances: C_target + R C_source Rᵀ is singular "
                f"or indefinite for {singular} correspondences (use compute_covariances)"
            )
        rmse = float(np.sqrt(total[-1] / count))
        if not robust:
            H, g = system_from_sums(total)
            cost = float(total[27])
            return _Linearization(H, g, cost, cost / max(count - 6, 1), count, rmse)
        s = np.flatnonzero(nearest >= 0)
        m = np.sqrt(self.m2[s])
        w = robust_weights(m, self.config.robust_kernel, self.config.robust_scale)
        # Scaling every row (unmatched ones by 0, unused) is 4x faster than W[s] *= ...
        weights = np.zeros(n)
        weights[s] = w.weights
        self.W *= weights[:, None, None]
        partial = np.zeros((self.chunks, 28))
        with numba_threads(self.workers):
            gicp_sums_kernel(self.index.data, self.source_points, R, t, nearest, self.W, partial)
        total = partial.sum(axis=0)
        H, g = system_from_sums(total)
        return _Linearization(H, g, float(total[27]), w.variance(m), count, rmse)

    def cost(self, T: NDArray[np.float64]) -> float:
        """Σ w dᵀWd at ``T`` over the last call's matches and weights."""
        partial = np.zeros((self.chunks, 1))
        with numba_threads(self.workers):
            gicp_sums_kernel(
                self.index.data,
                self.source_points,
                np.ascontiguousarray(T[:3, :3]),
                np.ascontiguousarray(T[:3, 3]),
                self.nearest,
                self.W,
                partial,
            )
        return float(partial.sum())
