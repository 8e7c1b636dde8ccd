"""Pose-graph optimisation on SE(3) for a small window of frames (methods.md §1.6).

Nodes are poses ``X_i = T_i_ref`` (frame ``ref`` into frame i). An edge ``(i, j)`` carries a
measurement ``Z = T_j_i`` (frame i into frame j, e.g. a registration of cloud i onto cloud j)
with a 6×6 information matrix for a left perturbation of ``T_j_i``, twist order (omega, v). The
residual of an edge is ``e = log(Z · X_i · X_j⁻¹)``, the left-perturbation error of the
prediction ``X_j X_i⁻¹``; nodes are perturbed on the left, ``X ← exp(δ) X``, and to first order

    e(δ_i, δ_j) ≈ e − δ_j + Ad(X_j X_i⁻¹) δ_i.

Gauss-Newton minimises ``Σ eᵀ Ω e`` over the free nodes. The windows are small (≲ 10 nodes, 60
unknowns), so the normal equations are assembled densely block by block.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from spacepose.core import se3
from spacepose.errors import DegenerateGeometryError, InputError


@dataclass(frozen=True)
class PoseGraphEdge:
    """A relative measurement between two nodes.

    Attributes
    ----------
    i, j
        Node indices; the measurement maps frame i into frame j.
    T_j_i
        (4, 4) measured transform.
    information
        (6, 6) symmetric positive semi-definite information of ``T_j_i`` (left perturbation,
        twist order (omega, v)).
    """

    i: int
    j: int
    T_j_i: NDArray[np.float64]
    information: NDArray[np.float64]


@dataclass(frozen=True)
class PoseGraphResult:
    """Optimised poses and their uncertainty.

    Attributes
    ----------
    poses
        (W, 4, 4) optimised ``X_i = T_i_ref``.
    covariances
        (W, 6, 6) marginal covariances of each pose (left perturbation; zero for fixed nodes).
    iterations
        Gauss-Newton iterations run.
    converged
        Whether the update fell below the tolerance before the iteration limit.
    cost
        Final ``Σ eᵀ Ω e``.
    """

    poses: NDArray[np.float64]
    covariances: NDArray[np.float64]
    iterations: int
    converged: bool
    cost: float


def edge_residual(edge: PoseGraphEdge, poses: NDArray[np.float64]) -> NDArray[np.float64]:
    """Residual twist ``log(T_j_i · X_i · X_j⁻¹)`` (6,) of one edge at the given poses."""
    return se3.log(edge.T_j_i @ poses[edge.i] @ se3.invert(poses[edge.j]))


def optimize_pose_graph(
    poses: ArrayLike,
    edges: Sequence[PoseGraphEdge],
    fixed: Sequence[int] = (0,),
    max_iterations: int = 20,
    tolerance: float = 1e-12,
) -> PoseGraphResult:
    """Gauss-Newton on SE(3) over the nodes not in ``fixed``.

    Parameters
    ----------
    poses
        (W, 4, 4) initial poses ``X_i = T_i_ref``.
    edges
        Relative measurements; each must reference valid, distinct nodes.
    fixed
        Nodes held at their initial value (at least one, to remove the gauge freedom).
    max_iterations
        Largest number of Gauss-Newton steps.
    tolerance
        Stop when the largest entry of the update is below this.

    Returns
    -------
    PoseGraphResult
        Optimised poses and marginal covariances ``(JᵀΩJ)⁻¹`` of the free nodes.

    Raises
    ------
    InputError
        Bad poses, edges or fixed set.
    DegenerateGeometryError
        When the edges do not constrain every free node in all 6 degrees of freedom.
    """
    X = np.array(poses, dtype=np.float64)
    if X.ndim != 3 or X.shape[1:] != (4, 4) or len(X) == 0:
        raise InputError(f"pose graph poses must be a (W, 4, 4) stack, got shape {X.shape}")
    for n, pose in enumerate(X):
        se3.as_transform(pose, f"pose graph node {n}")
    W = len(X)
    fixed_set = {int(f) for f in fixed}
    if not fixed_set or not fixed_set <= set(range(W)):
        raise InputError(f"pose graph needs at least one fixed node among 0..{W - 1}, got {fixed}")
    for e in edges:
        if not (0 <= e.i < W and 0 <= e.j < W) or e.i == e.j:
            raise InputError(f"pose graph edge ({e.i}, {e.j}) must join two distinct nodes < {W}")
        se3.as_transform(e.T_j_i, f"pose graph edge ({e.i}, {e.j}) measurement")
        info = np.asarray(e.information)
        if info.shape != (6, 6) or not np.all(np.isfinite(info)):
            raise InputError(f"pose graph edge ({e.i}, {e.j}) information must be a finite 6x6")
    free = [n for n in range(W) if n not in fixed_set]
    slot = {n: 6 * k for k, n in enumerate(free)}
    dim = 6 * len(free)

    def normal_equations() -> tuple[NDArray[np.float64], NDArray[np.float64], float]:
        H = np.zeros((dim, dim))
        b = np.zeros(dim)
        cost = 0.0
        for e in edges:
            r = edge_residual(e, X)
            omega = np.asarray(e.information, dtype=np.float64)
            cost += float(r @ omega @ r)
            blocks = {e.j: -np.eye(6), e.i: se3.adjoint(X[e.j] @ se3.invert(X[e.i]))}
            blocks = {n: J for n, J in blocks.items() if n in slot}
            for n, Jn in blocks.items():
                b[slot[n] : slot[n] + 6] += Jn.T @ omega @ r
                for m, Jm in blocks.items():
                    H[slot[n] : slot[n] + 6, slot[m] : slot[m] + 6] += Jn.T @ omega @ Jm
        return H, b, cost

    def solve(H: NDArray[np.float64], rhs: NDArray[np.float64]) -> NDArray[np.float64]:
        ev = np.linalg.eigvalsh(H)
        if ev[0] <= 1e-12 * max(ev[-1], np.finfo(float).tiny):
            raise DegenerateGeometryError(
                "the pose graph edges leave a free node unconstrained (information is singular)"
            )
        return np.linalg.solve(H, rhs)

    converged = not free  # nothing to optimise
    iterations = 0
    while free and iterations < max_iterations:
        iterations += 1
        H, b, _ = normal_equations()
        delta = solve(H, -b)
        for n in free:
            X[n] = se3.exp(delta[slot[n] : slot[n] + 6]) @ X[n]
        if np.abs(delta).max() < tolerance:
            converged = True
            break

    H, _, cost = normal_equations()
    covariances = np.zeros((W, 6, 6))
    if free:
        cov = solve(H, np.eye(dim))
        for n in free:
            covariances[n] = cov[slot[n] : slot[n] + 6, slot[n] : slot[n] + 6]
    return PoseGraphResult(X, covariances, iterations, converged, cost)
