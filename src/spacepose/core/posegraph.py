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

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numba
import numpy as np
from numpy.typing import ArrayLike, NDArray

from spacepose.core import se3
from spacepose.errors import DegenerateGeometryError, InputError

# Rotation angle above which the logarithm takes the axis from the quaternion: se3.log's.
_NEAR_PI = se3.NEAR_PI


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
    tolerance: float | tuple[float, float] = 1e-12,
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
        Stop when the largest entry of the update is below this; a pair ``(rotation rad,
        translation m)`` sets each part's own, so that a run in other units stops alike.

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
    try:
        tol = np.asarray(tolerance, dtype=np.float64)
    except (TypeError, ValueError):
        tol = np.full(3, np.nan)  # refused below
    if tol.shape not in ((), (2,)) or not np.all(tol > 0):
        raise InputError(
            f"pose graph tolerance must be a positive number or a (rotation, translation) pair, "
            f"got {tolerance!r}"
        )
    max_iterations = se3.whole_number(max_iterations, "pose graph max_iterations")
    X = se3.real_array(poses, "pose graph poses").copy()
    if X.ndim != 3 or X.shape[1:] != (4, 4) or len(X) == 0:
        raise InputError(f"pose graph poses must be a (W, 4, 4) stack, got shape {X.shape}")
    for n, pose in enumerate(X):
        se3.as_transform(pose, f"pose graph node {n}")
    W = len(X)
    if fixed is None or isinstance(fixed, str | bytes):
        raise InputError(f"pose graph fixed nodes must be whole numbers, got {fixed!r}")
    fixed_set = {se3.whole_number(f, "pose graph fixed node", 0) for f in np.atleast_1d(fixed)}
    if not fixed_set or not fixed_set <= set(range(W)):
        raise InputError(f"pose graph needs at least one fixed node among 0..{W - 1}, got {fixed}")
    if isinstance(edges, PoseGraphEdge) or not isinstance(edges, Sequence):
        raise InputError(
            f"pose graph edges must be a list of PoseGraphEdge, got {type(edges).__name__}"
        )
    for e in edges:
        if not isinstance(e, PoseGraphEdge):
            raise InputError(f"pose graph edges must be PoseGraphEdge, got {type(e).__name__}")
        se3.whole_number(e.i, "pose graph edge node i", 0)
        se3.whole_number(e.j, "pose graph edge node j", 0)
        if not (0 <= e.i < W and 0 <= e.j < W) or e.i == e.j:
            raise InputError(f"pose graph edge ({e.i}, {e.j}) must join two distinct nodes < {W}")
        se3.as_transform(e.T_j_i, f"pose graph edge ({e.i}, {e.j}) measurement")
        info = se3.real_array(e.information, f"pose graph edge ({e.i}, {e.j}) information")
        if info.shape != (6, 6) or not np.all(np.isfinite(info)):
            raise InputError(f"pose graph edge ({e.i}, {e.j}) information must be a finite 6x6")
        if np.abs(info - info.T).max() > 1e-9 * max(np.abs(info).max(), 1e-300):
            raise InputError(f"pose graph edge ({e.i}, {e.j}) information must be symmetric")
    free = [n for n in range(W) if n not in fixed_set]
    slot = {n: 6 * k for k, n in enumerate(free)}
    dim = 6 * len(free)
    # The edges as arrays for the compiled assembly; a fixed node's slot is -1.
    slots = np.array([slot.get(n, -1) for n in range(W)], dtype=np.int64)
    Z = np.array([e.T_j_i for e in edges], dtype=np.float64).reshape(-1, 4, 4)
    info = np.array([e.information for e in edges], dtype=np.float64).reshape(-1, 6, 6)
    ei = np.array([e.i for e in edges], dtype=np.int64)
    ej = np.array([e.j for e in edges], dtype=np.int64)

    def normal_equations() -> tuple[NDArray[np.float64], NDArray[np.float64], float]:
        return _normal_equations(X, Z, info, ei, ej, slots, dim)

    def solve(H: NDArray[np.float64], rhs: NDArray[np.float64]) -> NDArray[np.float64]:
        # The check on H scaled to a unit diagonal: the edges' information is about the sensor's
        # origin, and a target 300 m out makes each rotation a lever arm of that length
        # (eigenvalues 12 decades apart on a well-posed window).
        d = np.sqrt(np.maximum(np.diag(H), np.finfo(float).tiny))
        ev = np.linalg.eigvalsh(H / np.outer(d, d))
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
        step = np.abs(delta).reshape(-1, 2, 3).max(axis=(0, 2))
        if np.all(step < tol):
            converged = True
            break

    H, _, cost = normal_equations()
    covariances = np.zeros((W, 6, 6))
    if free:
        cov = solve(H, np.eye(dim))
        for n in free:
            covariances[n] = cov[slot[n] : slot[n] + 6, slot[n] : slot[n] + 6]
    return PoseGraphResult(X, covariances, iterations, converged, cost)


# --------------------------------------------------------------------------------------------
# Compiled assembly: a window's graph is a few nodes and edges, and the Python version of this
# loop (a logarithm, an inverse and an adjoint per edge) cost 2-4 ms a tracked lab frame.


def _normal_equations(
    X: NDArray[np.float64],
    Z: NDArray[np.float64],
    info: NDArray[np.float64],
    ei: NDArray[np.int64],
    ej: NDArray[np.int64],
    slots: NDArray[np.int64],
    dim: int,
) -> tuple[NDArray[np.float64], NDArray[np.float64], float]:
    """``(H, b, cost)`` of Gauss-Newton over the edges (module notes): ``H = Σ JᵀΩJ``,
    ``b = Σ JᵀΩe``, ``cost = Σ eᵀΩe``, with blocks at each free node's slot."""
    H = np.zeros((dim, dim))
    b = np.zeros(dim)
    cost = _assemble(X, Z, info, ei, ej, slots, H, b)
    return H, b, cost


@numba.njit(cache=True)
def _assemble(X, Z, info, ei, ej, slots, H, b):
    cost = 0.0
    J = np.zeros((2, 6, 6))
    for k in range(len(ei)):
        i, j = ei[k], ej[k]
        A = X[j] @ _inverse(X[i])  # X_j X_i⁻¹
        r = _log(Z[k] @ _inverse(A))  # log(Z X_i X_j⁻¹)
        omega = info[k]
        wr = omega @ r
        cost += r @ wr
        # e ≈ e − δ_j + Ad(X_j X_i⁻¹) δ_i
        J[0] = _adjoint(A)
        J[1] = -np.eye(6)
        nodes = (i, j)
        for a in range(2):
            sa = slots[nodes[a]]
            if sa < 0:
                continue
            b[sa : sa + 6] += J[a].T @ wr
            for c in range(2):
                sc = slots[nodes[c]]
                if sc >= 0:
                    H[sa : sa + 6, sc : sc + 6] += J[a].T @ omega @ J[c]
    return cost


@numba.njit(cache=True)
def _inverse(T):
    out = np.eye(4)
    Rt = T[:3, :3].T.copy()
    out[:3, :3] = Rt
    out[:3, 3] = -(Rt @ T[:3, 3].copy())
    return out


@numba.njit(cache=True)
def _skew(v):
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


@numba.njit(cache=True)
def _adjoint(T):
    R = T[:3, :3].copy()
    Ad = np.zeros((6, 6))
    Ad[:3, :3] = R
    Ad[3:, 3:] = R
    Ad[3:, :3] = _skew(T[:3, 3].copy()) @ R
    return Ad


@numba.njit(cache=True)
def _log(T):
    """se3.log: the twist (omega, v) of a transform, the axis from the skew part below
    ``_NEAR_PI`` and from the quaternion above."""
    R = T[:3, :3]
    w = np.array([R[2, 1] - R[1, 2], R[0, 2] - R[2, 0], R[1, 0] - R[0, 1]])
    sin = 0.5 * math.sqrt(w @ w)
    theta = math.atan2(sin, 0.5 * (R[0, 0] + R[1, 1] + R[2, 2] - 1.0))
    if theta > _NEAR_PI:
        omega = _near_pi_rotvec(R)
        theta = math.sqrt(omega @ omega)
    elif sin > 0.0:
        omega = 0.5 * w * (theta / sin)
    else:
        omega = 0.5 * w
    W = _skew(omega)
    if theta < 1e-8:
        V = np.eye(3) + 0.5 * W
    else:
        a = (1.0 - math.cos(theta)) / theta**2
        c = (theta - math.sin(theta)) / theta**3
        V = np.eye(3) + a * W + c * (W @ W)
    out = np.empty(6)
    out[:3] = omega
    out[3:] = np.linalg.solve(V, T[:3, 3].copy())
    return out


@numba.njit(cache=True)
def _near_pi_rotvec(R):
    """Rotation vector of ``R`` through its unit quaternion (largest-component method)."""
    tr = R[0, 0] + R[1, 1] + R[2, 2]
    q = np.empty(4)  # x, y, z, w
    d = np.array([R[0, 0], R[1, 1], R[2, 2], tr])
    k = int(np.argmax(d))
    if k == 3:
        q[3] = 1.0 + tr
        q[0] = R[2, 1] - R[1, 2]
        q[1] = R[0, 2] - R[2, 0]
        q[2] = R[1, 0] - R[0, 1]
    else:
        i, j, m = k, (k + 1) % 3, (k + 2) % 3
        q[i] = 1.0 - tr + 2.0 * R[i, i]
        q[j] = R[j, i] + R[i, j]
        q[m] = R[m, i] + R[i, m]
        q[3] = R[m, j] - R[j, m]
    q /= math.sqrt(q @ q)
    if q[3] < 0.0:
        q = -q
    xyz = q[:3].copy()
    s = math.sqrt(xyz @ xyz)
    if s == 0.0:
        return np.zeros(3)
    return xyz * (2.0 * math.atan2(s, q[3]) / s)
