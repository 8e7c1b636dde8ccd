"""Compiled kernels of :mod:`spacepose.core.gicp` and :mod:`spacepose.core.gicp_systems`:
per-correspondence weights ``W = (C_q + R C_p Rᵀ)⁻¹``, the normal equations ``Σ JᵀWJ``,
``Σ JᵀWd``, ``Σ dᵀWd`` and the fused pass (move, match, weigh, sum) of one GICP linearisation.

Rows are summed in fixed chunks of :data:`CHUNK`, each in its own fixed order, so any thread
count gives the same bits.
"""

from __future__ import annotations

import numba
import numpy as np

from spacepose.core.grid_nearest import move_and_match

# Rows per chunk of the compiled sums (fixed: so is the sum order).
CHUNK = 512


@numba.njit(cache=True, parallel=True)
def weights_kernel(points, target_points, R, Cs, Ct, W, m2):
    """Fill ``W`` and ``m2 = dᵀWd`` row by row (:func:`_weight_row`); return how many rows had
    no positive definite ``C_q + R C_p Rᵀ`` (their W and m2 are 0)."""
    m = len(points)
    singular = 0
    for c in numba.prange(max(1, -(-m // CHUNK))):
        RC = np.empty((3, 3))
        d = np.empty(3)
        for i in range(c * CHUNK, min(m, (c + 1) * CHUNK)):
            for a in range(3):
                d[a] = points[i, a] - target_points[i, a]
            m2[i] = _weight_row(R, Cs[i], Ct[i], d, W[i], RC)
            if m2[i] < 0.0:
                singular += 1
                m2[i] = 0.0
    return singular


@numba.njit(cache=True, inline="always")
def _weight_row(R, Cs, Ct, d, W, RC):
    """``W = (Ct + R Cs Rᵀ)⁻¹`` (3, 3) in place from the adjugate, and return ``dᵀWd``; -1 (and
    W = 0) when the sum is not positive definite (Sylvester's criterion). ``RC`` is scratch."""
    for a in range(3):
        for b in range(3):
            RC[a, b] = R[a, 0] * Cs[0, b] + R[a, 1] * Cs[1, b] + R[a, 2] * Cs[2, b]
    c00 = Ct[0, 0] + RC[0, 0] * R[0, 0] + RC[0, 1] * R[0, 1] + RC[0, 2] * R[0, 2]
    c01 = Ct[0, 1] + RC[0, 0] * R[1, 0] + RC[0, 1] * R[1, 1] + RC[0, 2] * R[1, 2]
    c02 = Ct[0, 2] + RC[0, 0] * R[2, 0] + RC[0, 1] * R[2, 1] + RC[0, 2] * R[2, 2]
    c11 = Ct[1, 1] + RC[1, 0] * R[1, 0] + RC[1, 1] * R[1, 1] + RC[1, 2] * R[1, 2]
    c12 = Ct[1, 2] + RC[1, 0] * R[2, 0] + RC[1, 1] * R[2, 1] + RC[1, 2] * R[2, 2]
    c22 = Ct[2, 2] + RC[2, 0] * R[2, 0] + RC[2, 1] * R[2, 1] + RC[2, 2] * R[2, 2]
    a00, a01, a02 = c11 * c22 - c12 * c12, c02 * c12 - c01 * c22, c01 * c12 - c02 * c11
    det = c00 * a00 + c01 * a01 + c02 * a02
    if not (det > 0 and c00 > 0 and c00 * c11 - c01 * c01 > 0):
        W[:, :] = 0.0
        return -1.0
    inv = 1.0 / det
    W[0, 0], W[0, 1], W[0, 2] = a00 * inv, a01 * inv, a02 * inv
    W[1, 1] = (c00 * c22 - c02 * c02) * inv
    W[1, 2] = (c01 * c02 - c00 * c12) * inv
    W[2, 2] = (c00 * c11 - c01 * c01) * inv
    W[1, 0], W[2, 0], W[2, 1] = W[0, 1], W[0, 2], W[1, 2]
    m2 = 0.0
    for a in range(3):
        for b in range(3):
            m2 += d[a] * W[a, b] * d[b]
    return m2


@numba.njit(cache=True, parallel=True)
def system_kernel(points, target_points, W, partial):
    """Per chunk of rows: :func:`_accumulate_gicp` of each (28 sums)."""
    m = len(points)
    for c in numba.prange(len(partial)):
        J, WJ, Wd, d = _scratch()
        for i in range(c * CHUNK, min(m, (c + 1) * CHUNK)):
            for a in range(3):
                d[a] = points[i, a] - target_points[i, a]
            _accumulate_gicp(partial[c], points[i], d, W[i], J, WJ, Wd)


@numba.njit(cache=True, inline="always")
def _scratch():
    """Scratch of :func:`_accumulate_gicp`: J (3, 6) with its constant identity block, WJ (3, 6),
    Wd (3,) and d (3,)."""
    J = np.zeros((3, 6))
    for a in range(3):
        J[a, 3 + a] = 1.0
    return J, np.empty((3, 6)), np.empty(3), np.empty(3)


@numba.njit(cache=True, inline="always")
def _accumulate_gicp(acc, p, d, W, J, WJ, Wd):
    """Add one correspondence (moved source point p, residual d = p − q, weight W) to ``acc``:
    the upper triangle of JᵀWJ (21), JᵀWd (6) and dᵀWd (1), ``J = [−skew(p) I]``."""
    px, py, pz = p[0], p[1], p[2]
    # J = [−skew(p) I]: the derivative of exp(δ) p at δ = 0.
    J[0, 1], J[0, 2] = pz, -py
    J[1, 0], J[1, 2] = -pz, px
    J[2, 0], J[2, 1] = py, -px
    for a in range(3):
        Wd[a] = W[a, 0] * d[0] + W[a, 1] * d[1] + W[a, 2] * d[2]
        for b in range(6):
            WJ[a, b] = W[a, 0] * J[0, b] + W[a, 1] * J[1, b] + W[a, 2] * J[2, b]
    pos = 0
    for a in range(6):
        for b in range(a, 6):
            acc[pos] += J[0, a] * WJ[0, b] + J[1, a] * WJ[1, b] + J[2, a] * WJ[2, b]
            pos += 1
    for a in range(6):
        acc[21 + a] += J[0, a] * Wd[0] + J[1, a] * Wd[1] + J[2, a] * Wd[2]
    acc[27] += d[0] * Wd[0] + d[1] * Wd[1] + d[2] * Wd[2]


@numba.njit(cache=True, parallel=True)
def gicp_pass_kernel(
    grid, rings, targets, src, Cs, Ct, R, t, gate, hint, nearest, anchors, bounds, W, m2, partial
):
    """GICP's work at one transform, per chunk of source points: move each point (``R p + t``),
    find its nearest target within the gate (:func:`certified_nearest` from its last answer
    ``hint`` and its certificate ``anchors``/``bounds``, updated in place), store its weight
    ``W`` and ``m2 = dᵀWd`` (:func:`_weight_row`), count the match and Σ |d|² (sums 28, 29) and,
    when ``partial`` has 30 columns, accumulate :func:`_accumulate_gicp` (sums 0..27). Returns
    how many matches had no positive definite ``C_q + R C_p Rᵀ``."""
    n = len(src)
    accumulate = partial.shape[1] == 30
    singular = 0
    for c in numba.prange(len(partial)):
        acc = partial[c]
        J, WJ, Wd, d = _scratch()
        RC = np.empty((3, 3))
        p = np.empty(3)
        for i in range(c * CHUNK, min(n, (c + 1) * CHUNK)):
            j, d2 = move_and_match(grid, rings, src, R, t, gate, hint, anchors, bounds, i, p)
            nearest[i] = j
            if j < 0:
                continue
            acc[-2] += 1.0
            acc[-1] += d2
            for a in range(3):
                d[a] = p[a] - targets[j, a]
            m2[i] = _weight_row(R, Cs[i], Ct[j], d, W[i], RC)
            if m2[i] < 0.0:
                singular += 1
            elif accumulate:
                _accumulate_gicp(acc, p, d, W[i], J, WJ, Wd)
    return singular


@numba.njit(cache=True, parallel=True)
def gicp_sums_kernel(targets, src, R, t, nearest, W, partial):
    """Per chunk of source points, over the matched ones (``nearest`` >= 0) moved by ``R, t``
    with their stored ``W``: :func:`_accumulate_gicp` (``partial`` of 28 columns) or only the
    cost Σ dᵀWd (1 column; Levenberg-Marquardt's trial steps)."""
    n = len(src)
    system = partial.shape[1] == 28
    for c in numba.prange(len(partial)):
        acc = partial[c]
        J, WJ, Wd, d = _scratch()
        p = np.empty(3)
        for i in range(c * CHUNK, min(n, (c + 1) * CHUNK)):
            j = nearest[i]
            if j < 0:
                continue
            for a in range(3):
                p[a] = R[a, 0] * src[i, 0] + R[a, 1] * src[i, 1] + R[a, 2] * src[i, 2] + t[a]
                d[a] = p[a] - targets[j, a]
            if system:
                _accumulate_gicp(acc, p, d, W[i], J, WJ, Wd)
            else:
                for a in range(3):
                    Wd[a] = W[i, a, 0] * d[0] + W[i, a, 1] * d[1] + W[i, a, 2] * d[2]
                acc[0] += d[0] * Wd[0] + d[1] * Wd[1] + d[2] * Wd[2]
