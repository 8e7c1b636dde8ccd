"""Surface normals from neighbourhood covariances (methods.md §1.1).

The normal at a point is the eigenvector of the smallest eigenvalue of the covariance of its
neighbours (k nearest, or within a radius capped at k), oriented towards the sensor. How
consistent neighbouring normals are (Li et al.'s Fig. 5) is :mod:`spacepose.core.cloud_quality`.
"""

from __future__ import annotations

import numba
import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import Field, PositiveFloat

from spacepose.core.cloud import PointCloud, as_cloud, as_points
from spacepose.core.config import StageConfig, stage_config
from spacepose.core.moments import on_a_line
from spacepose.core.neighbors import SearchIndex, hybrid, knn, row_moments
from spacepose.core.threads import numba_threads
from spacepose.errors import DegenerateGeometryError, InputError

# Matrices per unit of parallel work: amortises scheduling, balances the two threads.
_CHUNK_ROWS = 256


class NormalsConfig(StageConfig):
    """Neighbourhood of the normal estimate.

    Attributes
    ----------
    k
        Number of nearest neighbours (the point included); with ``radius`` set, the cap on the
        neighbours inside the radius (Open3D's hybrid search). At most 1,000: a wider
        neighbourhood is no longer local (a ToF frame's normals take 10-50), and its search
        grows as k per point.
    radius
        Search radius in metres, or None for a pure k-nearest search.
    """

    k: int = Field(default=30, ge=3, le=1000)
    radius: PositiveFloat | None = None


def normals_from_covariances(
    covariances: NDArray[np.float64], workers: int = 1
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Unoriented normals and eigenvalues of a stack of 3×3 covariances.

    Parameters
    ----------
    covariances
        (M, 3, 3) symmetric positive semi-definite matrices.
    workers
        Threads (-1: all cores); the result does not depend on it.

    Returns
    -------
    normals, eigenvalues
        (M, 3) unit eigenvectors of the smallest eigenvalue, and the (M, 3) eigenvalues in
        ascending order (``λ0 / Σλ`` is the surface variation).

    Notes
    -----
    Closed form, compiled per matrix (a batched ``eigh`` costs as much as the neighbour search).
    The trigonometric eigenvalues (Smith 1961) are exact to rounding only for an eigenvalue set
    apart from the other two, so the eigenvector of the more isolated extreme eigenvalue is
    taken first, as the kernel of ``A − λI``; the other two then come from the 2×2 problem in
    its orthogonal complement, solved with a Jacobi rotation. Every eigenvalue is then exact to
    rounding relative to ``‖A‖`` (as ``eigh``); when ``λ0`` is a double eigenvalue (a
    line-shaped neighbourhood) the normal is one unit vector of its eigenplane.
    """
    A = np.asarray(covariances, dtype=np.float64)
    if A.ndim != 3 or A.shape[1:] != (3, 3):
        raise InputError(f"covariances must be an (M, 3, 3) array, got shape {A.shape}")
    normals = np.empty((len(A), 3))
    eigenvalues = np.empty((len(A), 3))
    with numba_threads(workers):
        _eigen_kernel(np.ascontiguousarray(A), normals, eigenvalues)
    return normals, eigenvalues


def neighbourhood_normals(
    points: ArrayLike, idx: NDArray[np.intp], workers: int = 1
) -> NDArray[np.float64]:
    """Unoriented unit normals (M, 3) of neighbourhoods: the smallest eigenvector of each one's
    covariance, ``normals_from_covariances(local_covariances(points, idx))`` in one compiled
    pass (no (M, k) or (M, 3, 3) temporaries, one thread start instead of two).

    Parameters
    ----------
    points
        (N, 3) points the indices refer to.
    idx
        (M, k) neighbour indices into ``points``, ``-1`` for padding.
    workers
        Threads (-1: all cores); the result does not depend on it.
    """
    pts = np.ascontiguousarray(as_points(points, "points"), dtype=np.float64)
    idx = np.asarray(idx)
    if idx.ndim != 2 or not np.issubdtype(idx.dtype, np.integer):
        raise InputError(f"neighbour indices must be an (M, k) integer array, got {idx.shape}")
    if idx.size and idx.max() >= len(pts):
        raise InputError(f"neighbour indices reach {idx.max()}, beyond the {len(pts)} points")
    normals = np.empty((len(idx), 3))
    with numba_threads(workers):
        _neighbourhood_normals_kernel(pts, np.ascontiguousarray(idx, dtype=np.int64), normals)
    return normals


@numba.njit(cache=True, parallel=True)
def _neighbourhood_normals_kernel(pts, idx, normals):
    m = len(idx)
    no_weights = np.empty(0)
    for chunk in numba.prange((m + _CHUNK_ROWS - 1) // _CHUNK_ROWS):
        mean = np.empty(3)
        cov = np.empty((3, 3))
        eigenvalues = np.empty(3)
        for i in range(chunk * _CHUNK_ROWS, min(m, (chunk + 1) * _CHUNK_ROWS)):
            row_moments(pts, idx[i], no_weights, mean, cov)
            _symmetric_eigen(cov, normals[i], eigenvalues)


def plane_offsets(
    points: NDArray[np.float64],
    normals: NDArray[np.float64],
    idx: NDArray[np.intp],
    workers: int = 1,
) -> NDArray[np.float64]:
    """Signed distance of each point from the plane through its neighbours' centroid.

    Parameters
    ----------
    points
        (N, 3) points (any frame).
    normals
        (N, 3) unit normal of each point's plane.
    idx
        (N, k) neighbour indices into ``points`` (:func:`~spacepose.core.neighbors.knn`), ``N``
        for a neighbour missing within the search's bound.
    workers
        Threads (-1: all cores); the result does not depend on it.

    Returns
    -------
    (N,) ``n · (p − mean of its k neighbours)`` (m); NaN where a neighbour is missing.

    Raises
    ------
    InputError
        Points or normals not finite (N, 3), or indices not (N, k) within ``0..N``.
    """
    pts = np.ascontiguousarray(as_points(points, "points"), dtype=np.float64)
    nrm = np.ascontiguousarray(as_points(normals, "normals"), dtype=np.float64)
    idx = np.asarray(idx)
    n = len(pts)
    if len(nrm) != n:
        raise InputError(f"{len(nrm)} normals for {n} points")
    if (
        idx.ndim != 2
        or len(idx) != n
        or idx.shape[1] < 1
        or not np.issubdtype(idx.dtype, np.integer)
    ):
        raise InputError(f"neighbour indices must be an ({n}, k) integer array, got {idx.shape}")
    if idx.min() < 0 or idx.max() > n:
        raise InputError(f"neighbour indices must lie in 0..{n} ({n}: missing)")
    out = np.empty(n)
    with numba_threads(workers):
        _plane_offsets_kernel(pts, nrm, np.ascontiguousarray(idx, dtype=np.int64), out)
    return out


@numba.njit(cache=True, parallel=True)
def _plane_offsets_kernel(pts, normals, idx, out):
    n, k = idx.shape
    for chunk in numba.prange((n + _CHUNK_ROWS - 1) // _CHUNK_ROWS):
        for i in range(chunk * _CHUNK_ROWS, min(n, (chunk + 1) * _CHUNK_ROWS)):
            if idx[i, k - 1] >= n:
                out[i] = np.nan
                continue
            cx = cy = cz = 0.0
            for j in range(k):
                q = idx[i, j]
                cx += pts[q, 0]
                cy += pts[q, 1]
                cz += pts[q, 2]
            out[i] = (
                normals[i, 0] * (pts[i, 0] - cx / k)
                + normals[i, 1] * (pts[i, 1] - cy / k)
                + normals[i, 2] * (pts[i, 2] - cz / k)
            )


@numba.njit(cache=True, parallel=True)
def _eigen_kernel(A, normals, eigenvalues):
    """:func:`_symmetric_eigen` of every matrix of ``A`` (M, 3, 3), in chunks of rows."""
    m = len(A)
    for chunk in numba.prange((m + _CHUNK_ROWS - 1) // _CHUNK_ROWS):
        for i in range(chunk * _CHUNK_ROWS, min(m, (chunk + 1) * _CHUNK_ROWS)):
            _symmetric_eigen(A[i], normals[i], eigenvalues[i])


@numba.njit(cache=True)
def _symmetric_eigen(A, normal, eigenvalues):
    """Write the unit eigenvector of the smallest eigenvalue of the symmetric 3×3 ``A`` into
    ``normal`` (3,) and its ascending eigenvalues into ``eigenvalues`` (3,)."""
    a00, a01, a02 = A[0, 0], A[0, 1], A[0, 2]
    a10, a11, a12 = A[1, 0], A[1, 1], A[1, 2]
    a20, a21, a22 = A[2, 0], A[2, 1], A[2, 2]
    # Trigonometric eigenvalues: (A − qI) / p has eigenvalues 2cos(φ + 2πj/3), with
    # cos 3φ = det((A − qI) / p) / 2.
    q = (a00 + a11 + a22) / 3.0
    d0, d1, d2 = a00 - q, a11 - q, a22 - q
    p = np.sqrt((d0 * d0 + d1 * d1 + d2 * d2 + 2.0 * (a01 * a01 + a02 * a02 + a12 * a12)) / 6.0)
    det = d0 * (d1 * d2 - a12 * a12) - a01 * (a01 * d2 - a12 * a02) + a02 * (a01 * a12 - d1 * a02)
    safe = p if p > 0 else 1.0
    phi = np.arccos(min(max(0.5 * det / safe**3, -1.0), 1.0)) / 3.0
    largest = q + 2.0 * p * np.cos(phi)
    smallest = q + 2.0 * p * np.cos(phi + 2.0 * np.pi / 3.0)
    middle = 3.0 * q - largest - smallest
    # ">=" sends a multiple of the identity down the λ0 branch, where it gets the x axis (eigh's
    # choice too).
    low_isolated = middle - smallest >= largest - middle
    shift = smallest if low_isolated else largest
    # Kernel of the rank-2 A − shift·I: the longest cross product of two of its rows is the best
    # conditioned; no two independent rows (a multiple of the identity) gives the x axis.
    r00, r11, r22 = a00 - shift, a11 - shift, a22 - shift
    best = _cross(r00, a01, a02, a10, r11, a12)
    for cand in (_cross(r00, a01, a02, a20, a21, r22), _cross(a10, r11, a12, a20, a21, r22)):
        if _dot(cand, cand) > _dot(best, best):
            best = cand
    length = np.sqrt(_dot(best, best))
    e = (best[0] / length, best[1] / length, best[2] / length) if length > 0 else (1.0, 0.0, 0.0)
    # Complete e to a right-handed basis (u, v): cross with the axis least aligned with e, so
    # the product is never short.
    ax, ay, az = abs(e[0]), abs(e[1]), abs(e[2])
    if ax <= ay and ax <= az:
        u = _cross(e[0], e[1], e[2], 1.0, 0.0, 0.0)
    elif ay <= az:
        u = _cross(e[0], e[1], e[2], 0.0, 1.0, 0.0)
    else:
        u = _cross(e[0], e[1], e[2], 0.0, 0.0, 1.0)
    norm_u = np.sqrt(_dot(u, u))
    u = (u[0] / norm_u, u[1] / norm_u, u[2] / norm_u)
    v = _cross(e[0], e[1], e[2], u[0], u[1], u[2])
    Au = (
        a00 * u[0] + a01 * u[1] + a02 * u[2],
        a10 * u[0] + a11 * u[1] + a12 * u[2],
        a20 * u[0] + a21 * u[1] + a22 * u[2],
    )
    Av = (
        a00 * v[0] + a01 * v[1] + a02 * v[2],
        a10 * v[0] + a11 * v[1] + a12 * v[2],
        a20 * v[0] + a21 * v[1] + a22 * v[2],
    )
    Ae = (
        a00 * e[0] + a01 * e[1] + a02 * e[2],
        a10 * e[0] + a11 * e[1] + a12 * e[2],
        a20 * e[0] + a21 * e[1] + a22 * e[2],
    )
    a, b, c = _dot(u, Au), _dot(u, Av), _dot(v, Av)
    mean, radius = 0.5 * (a + c), np.hypot(0.5 * (a - c), b)
    lam_e = _dot(e, Ae)
    if low_isolated:
        normal[0], normal[1], normal[2] = e
        eigenvalues[0], eigenvalues[1], eigenvalues[2] = lam_e, mean - radius, mean + radius
    else:
        # Jacobi rotation of the 2×2 block [[a, b], [b, c]]: θ turns u onto the larger
        # eigenvector, so the normal is v turned by θ.
        theta = 0.5 * np.arctan2(2.0 * b, a - c)
        sin, cos = np.sin(theta), np.cos(theta)
        normal[0] = cos * v[0] - sin * u[0]
        normal[1] = cos * v[1] - sin * u[1]
        normal[2] = cos * v[2] - sin * u[2]
        eigenvalues[0], eigenvalues[1], eigenvalues[2] = mean - radius, mean + radius, lam_e


@numba.njit(cache=True, inline="always")
def _cross(x0, x1, x2, y0, y1, y2):
    return (x1 * y2 - x2 * y1, x2 * y0 - x0 * y2, x0 * y1 - x1 * y0)


@numba.njit(cache=True, inline="always")
def _dot(x, y):
    return x[0] * y[0] + x[1] * y[1] + x[2] * y[2]


def orient_towards(
    points: ArrayLike, normals: ArrayLike, viewpoint: ArrayLike = (0.0, 0.0, 0.0)
) -> NDArray[np.float64]:
    """Flip normals (N, 3) so that each points towards ``viewpoint`` (3,), same frame as points."""
    pts = np.asarray(points, dtype=np.float64)
    n = np.asarray(normals, dtype=np.float64)
    to_view = _viewpoint(viewpoint) - pts
    flip = np.einsum("ij,ij->i", n, to_view) < 0
    return np.where(flip[:, None], -n, n)


def estimate_normals(
    cloud: PointCloud | ArrayLike,
    config: NormalsConfig = NormalsConfig(),
    viewpoint: ArrayLike = (0.0, 0.0, 0.0),
    workers: int = -1,
    tree: SearchIndex | None = None,
) -> PointCloud:
    """The cloud with a unit normal per point, oriented towards ``viewpoint``.

    Parameters
    ----------
    cloud
        Points (N, 3) in the sensor frame (or any frame ``viewpoint`` is given in): a
        :class:`PointCloud` or an (N, 3) array.
    config
        Neighbourhood: ``k`` nearest, or within ``radius`` capped at ``k``.
    viewpoint
        (3,) position the normals are turned towards; the sensor origin by default.
    workers
        Threads for the neighbour search.
    tree
        A search index of ``cloud.points`` already built by the caller (a tracker keeps one per
        keyframe), so it is not built twice.

    Returns
    -------
    A new :class:`PointCloud` with the same points and σ and the estimated normals.

    Raises
    ------
    DegenerateGeometryError
        Every point on one line or at one place.
    InputError
        No point with 3 neighbours within ``radius`` (every normal would be a line of sight).

    Notes
    -----
    A point with fewer than 3 neighbours inside ``radius`` has no defined plane; it gets the
    unit line of sight towards ``viewpoint`` as its normal rather than an arbitrary axis.
    """
    config = stage_config(config, NormalsConfig)
    cloud = as_cloud(cloud, "cloud")
    pts = cloud.points
    if len(pts) < 3:
        raise InputError(f"normal estimation needs at least 3 points, got {len(pts)}", cloud.source)
    if tree is not None and not isinstance(tree, SearchIndex):
        raise InputError(
            f"tree must be a cKDTree or VoxelIndex of the cloud, got {type(tree).__name__}",
            cloud.source,
        )
    if tree is not None and tree.n != len(pts):
        raise InputError(f"the tree holds {tree.n} points, the cloud {len(pts)}", cloud.source)
    if on_a_line(pts):
        # Every neighbourhood is a line or a point: any normal would be an arbitrary axis.
        raise DegenerateGeometryError(
            f"all {len(pts)} points lie on a line or at one place: no surface to take normals of",
            cloud.source,
        )
    k = min(config.k, len(pts))
    # Without a tree, the search builds the index that suits it.
    searched = pts if tree is None else tree
    if config.radius is None:
        _, idx = knn(searched, None, k, workers=workers)
    else:
        idx, _ = hybrid(searched, pts, config.radius, k, workers=workers)
    normals = neighbourhood_normals(pts, idx, workers)
    # A k-nearest search always finds k >= 3 neighbours; a radius search may find fewer.
    sparse = None if config.radius is None else (idx >= 0).sum(axis=1) < 3
    if sparse is not None and sparse.all():
        # Every normal would be a line of sight, none a surface's (a radius of 1e-9 m).
        raise InputError(
            f"no point has 3 neighbours within the normals' radius {config.radius:.3g} m: "
            "a radius under the point spacing?",
            cloud.source,
        )
    if sparse is not None and np.any(sparse):
        sight = _viewpoint(viewpoint) - pts[sparse]
        norm = np.linalg.norm(sight, axis=1, keepdims=True)
        # A point exactly at the viewpoint has no line of sight: fall back to the boresight.
        normals[sparse] = np.where(norm > 0, sight / np.where(norm > 0, norm, 1.0), (0, 0, -1))
    return cloud.with_normals(orient_towards(pts, normals, viewpoint))


def _viewpoint(viewpoint: ArrayLike) -> NDArray[np.float64]:
    """A viewpoint as a finite (3,) point."""
    try:
        v = np.asarray(viewpoint, dtype=np.float64).reshape(3)
    except (TypeError, ValueError):
        raise InputError(f"viewpoint must be 3 numbers, got {viewpoint!r:.60}") from None
    if not np.all(np.isfinite(v)):
        raise InputError(f"viewpoint must be finite, got {v.tolist()}")
    return v
