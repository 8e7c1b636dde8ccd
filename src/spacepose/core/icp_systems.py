"""Linearised systems of ICP: the point-to-point information, the point-to-plane normal
equations and their compiled sums, and the Gauss-Newton step (methods.md §1.5).

Twists are ``δ = (omega, v)`` of a left perturbation ``T ← exp(δ) T``, and every point is a
matched source point already moved into the target frame. Point-to-point: the (3, 6) Jacobian of
``p`` is ``[−skew(p) I]`` and the information ``Σ w JᵀJ`` (6, 6). Point-to-plane: the residual
``r = n·(p − q)`` (m) has the row ``h = (p × n, n)`` (6,), and the system is ``H = Σ w h hᵀ``
(6, 6; 1/m²), ``g = Σ w h r`` (6,) and ``Σ w r²`` (m²) over the M matches, w the IRLS weights
(all 1 without a robust kernel). :func:`solve_normal_equations` turns ``(H, g)`` into the twist
of one step, and refuses a degenerate H; GICP uses it and :func:`system_from_sums` too.

The compiled kernels sum rows in fixed chunks of ``SYSTEM_CHUNK``, each in its own fixed order,
so any thread count gives the same bits. Two of them fuse the point-to-plane sums with the
correspondence search on a :class:`~spacepose.core.grid.VoxelIndex` (move, match, sum; then
weigh with a robust kernel) for the matcher of :mod:`spacepose.core.correspondences`.
"""

from __future__ import annotations

import numba
import numpy as np
from numpy.typing import NDArray

from spacepose.core import se3
from spacepose.core.cloud import check_rows
from spacepose.core.grid_nearest import move_and_match
from spacepose.core.robust import weight_and_slope
from spacepose.core.threads import numba_threads
from spacepose.errors import DegenerateGeometryError

# Smallest/largest eigenvalue ratio of a Gauss-Newton system below which a direction is
# considered unconstrained (a plane, a cylinder): solving it would return noise, not a pose.
_DEGENERATE_RATIO = 1e-12
# Rows per chunk of the compiled point-to-plane sums (fixed, so the sum order is too).
SYSTEM_CHUNK = 512


def point_to_point_jacobians(points: NDArray[np.float64]) -> NDArray[np.float64]:
    """(N, 3, 6) Jacobians ``[−skew(p) I]`` of ``exp(δ) p`` at δ = 0, twist order (omega, v)."""
    J = np.empty((len(points), 3, 6))
    J[:, :, :3] = -se3.skew(points)
    J[:, :, 3:] = np.eye(3)
    return J


def point_to_point_information(
    points: NDArray[np.float64], weights: NDArray[np.float64] | None = None
) -> NDArray[np.float64]:
    """6×6 ``Σ w JᵀJ`` of point-to-point residuals at the matched source points (M, 3) (target
    frame), with optional (M,) IRLS weights (None: all 1)."""
    J = point_to_point_jacobians(points)
    if weights is None:
        return np.einsum("nai,naj->ij", J, J)
    return np.einsum("n,nai,naj->ij", weights, J, J)


def point_to_plane_system(
    points: NDArray[np.float64],
    target_points: NDArray[np.float64],
    normals: NDArray[np.float64],
    workers: int = 1,
    weights: NDArray[np.float64] | None = None,
) -> tuple[NDArray[np.float64], NDArray[np.float64], float]:
    """Gauss-Newton system of the residuals ``r = n·(p − q)``: ``H = Σ w h hᵀ``, ``g = Σ w h r``.

    ``h = (p × n, n)`` is the derivative of ``n·(exp(δ) p − q)`` at δ = 0 (twist (omega, v),
    left perturbation). Compiled: the numpy form (rows, products, BLAS) cost about 0.4 ms per
    ICP iteration on a 5000-point lab frame, more than the correspondence search.

    Parameters
    ----------
    points
        (M, 3) matched source points in the target frame.
    target_points, normals
        (M, 3) matched target points and their unit normals.
    workers
        Threads (-1: all cores); rows are summed in fixed chunks, so the result does not
        depend on it.
    weights
        (M,) IRLS weights w (a robust kernel's); None: all 1 (the same bits as weights of 1).

    Returns
    -------
    H, g, sse
        (6, 6) information ``Σ w h hᵀ`` (1/m²), (6,) gradient ``Σ w h r`` and ``Σ w r²`` (m²).

    Raises
    ------
    InputError
        The arrays do not line up (the kernel indexes them unchecked).
    """
    w = np.ones(len(points)) if weights is None else np.ascontiguousarray(weights, np.float64)
    check_rows(
        "point_to_plane_system", points, target_points, normals, w, shapes=((3,),) * 3 + ((),)
    )
    chunks = max(1, -(-len(points) // SYSTEM_CHUNK))
    partial = np.zeros((chunks, 28))
    with numba_threads(workers):
        _plane_system_kernel(
            np.ascontiguousarray(points, dtype=np.float64),
            np.ascontiguousarray(target_points, dtype=np.float64),
            np.ascontiguousarray(normals, dtype=np.float64),
            w,
            partial,
        )
    total = partial.sum(axis=0)
    H, g = system_from_sums(total)
    return H, g, float(total[27])


# Row-major upper triangle of a 6×6 matrix: the 21 entries the kernel accumulates.
_UPPER = np.triu_indices(6)


@numba.njit(cache=True, parallel=True)
def _plane_system_kernel(points, target_points, normals, weights, partial):
    """Per chunk of rows: :func:`_accumulate_plane` of each (28 sums)."""
    m = len(points)
    for c in numba.prange(len(partial)):
        h = np.empty(6)
        for i in range(c * SYSTEM_CHUNK, min(m, (c + 1) * SYSTEM_CHUNK)):
            _accumulate_plane(partial[c], points[i], target_points[i], normals[i], weights[i], h)


@numba.njit(cache=True, inline="always")
def _accumulate_plane(acc, p, q, n, w, h):
    """Add one residual ``r = n·(p − q)`` with row ``h = (p × n, n)`` and weight ``w`` to
    ``acc``: the upper triangle of w h hᵀ (21), w h r (6), w r² (1). ``h`` (6,) is scratch.
    (``w · x`` is ``x`` to the bit for w = 1.)"""
    h[0] = p[1] * n[2] - p[2] * n[1]
    h[1] = p[2] * n[0] - p[0] * n[2]
    h[2] = p[0] * n[1] - p[1] * n[0]
    h[3], h[4], h[5] = n[0], n[1], n[2]
    r = _plane_residual(p, q, n)
    pos = 0
    for a in range(6):
        wa = w * h[a]
        for b in range(a, 6):
            acc[pos] += wa * h[b]
            pos += 1
    for a in range(6):
        acc[21 + a] += w * h[a] * r
    acc[27] += w * r * r


@numba.njit(cache=True, inline="always")
def _plane_residual(p, q, n):
    """Signed point-to-plane distance ``n·(p − q)``."""
    return n[0] * (p[0] - q[0]) + n[1] * (p[1] - q[1]) + n[2] * (p[2] - q[2])


@numba.njit(cache=True, parallel=True)
def plane_matches_kernel(
    grid,
    rings,
    targets,
    normals,
    src,
    R,
    t,
    gate,
    hint,
    nearest,
    anchors,
    bounds,
    moved,
    residuals,
    partial,
):
    """Point-to-plane ICP's work at one transform, per chunk of source points: move each point
    (``R p + t``), find its nearest target within the gate (:func:`certified_nearest` from its
    last answer ``hint`` and the certificate ``anchors``/``bounds`` of its last search, both
    updated in place), count the match and Σ d² (sums 28, 29) and either accumulate
    :func:`_accumulate_plane` (sums 0..27) or, when ``moved`` has a row per point, store the
    moved point there and its residual ``n·(p − q)`` in ``residuals`` instead (a robust kernel
    weighs the rows once the residuals' scale is known: :func:`robust_plane_kernel`)."""
    m = len(src)
    accumulate = len(moved) != m
    for c in numba.prange(len(partial)):
        acc = partial[c]
        q = np.empty(3)
        h = np.empty(6)
        for i in range(c * SYSTEM_CHUNK, min(m, (c + 1) * SYSTEM_CHUNK)):
            j, d2 = move_and_match(grid, rings, src, R, t, gate, hint, anchors, bounds, i, q)
            nearest[i] = j
            if j >= 0:
                acc[28] += 1.0
                acc[29] += d2
                if accumulate:
                    _accumulate_plane(acc, q, targets[j], normals[j], 1.0, h)
                else:
                    moved[i] = q
                    residuals[i] = _plane_residual(q, targets[j], normals[j])


@numba.njit(cache=True, parallel=True)
def robust_plane_kernel(moved, targets, normals, nearest, residuals, c, code, w, slopes, partial):
    """The weighted sums of the matches (``nearest`` >= 0) that :func:`plane_matches_kernel`
    stored, per chunk of source points: each weight and slope of the kernel ``code`` at
    ``residuals / c`` (:func:`~spacepose.core.robust.weight_and_slope`) into ``w`` and
    ``slopes`` (code 0, c unused: all 1), :func:`_accumulate_plane` (sums 0..27), then
    Σ (w r)² (28) and Σ ψ' (29)."""
    m = len(moved)
    for k in numba.prange(len(partial)):
        acc = partial[k]
        h = np.empty(6)
        for i in range(k * SYSTEM_CHUNK, min(m, (k + 1) * SYSTEM_CHUNK)):
            j = nearest[i]
            if j < 0:
                continue
            r = residuals[i]
            w[i], slopes[i] = weight_and_slope(r / c, code)
            _accumulate_plane(acc, moved[i], targets[j], normals[j], w[i], h)
            acc[28] += (w[i] * r) ** 2
            acc[29] += slopes[i]


def system_from_sums(total: NDArray[np.float64]) -> tuple[NDArray[np.float64], ...]:
    """(H (6, 6), g (6,)) from 27 compiled sums: the row-major upper triangle of H (21), then g
    (as :func:`_accumulate_plane` and GICP's kernel lay them out)."""
    H = np.empty((6, 6))
    H[_UPPER] = total[:21]
    H.T[_UPPER] = total[:21]
    return H, total[21:27]


def solve_normal_equations(
    H: NDArray[np.float64],
    g: NDArray[np.float64],
    damping: float = 0.0,
    about: NDArray[np.float64] | None = None,
) -> NDArray[np.float64]:
    """Twist ``δ = −(H + damping·I)⁻¹ g``; raises when H leaves a direction unconstrained.

    The check is on the undamped H so that Levenberg-Marquardt damping cannot hide a
    degenerate surface behind a well-conditioned system. ``about`` (3,): the system, of a
    twist about the origin, is solved for the twist about this point instead and the result
    returned about the origin: about a far origin every rotation is a lever arm of that
    distance and a well-posed surface looks degenerate (a 0.5 m target 300 m out: information
    eigenvalues 8e-5 .. 1e8).

    Raises
    ------
    DegenerateGeometryError
        When the smallest eigenvalue of H is below 1e-12 of the largest (e.g. every
        correspondence lies on one plane, so three degrees of freedom are free).
    """
    Ad = None
    if about is not None:
        # A twist ξ_c about c is ξ = Ad ξ_c about the origin: the cost in ξ_c has Adᵀ H Ad.
        Ad = se3.adjoint(se3.make_transform(np.eye(3), about))
        H, g = Ad.T @ H @ Ad, Ad.T @ g
    ev = np.linalg.eigvalsh(H)
    if ev[0] <= _DEGENERATE_RATIO * ev[-1]:
        raise DegenerateGeometryError(
            "the correspondences do not constrain all 6 degrees of freedom "
            f"(information eigenvalues {ev[0]:.3g} .. {ev[-1]:.3g}); the surface is degenerate"
        )
    delta = -np.linalg.solve(H + damping * np.eye(len(H)), g)
    return delta if Ad is None else Ad @ delta
