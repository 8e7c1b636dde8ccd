"""Surface normals from neighbourhood covariances, and their consistency (METHODS §1.1, Li Eq. 1).

The normal at a point is the eigenvector of the smallest eigenvalue of the covariance of its
neighbours (k nearest, or within a radius capped at k), oriented towards the sensor. The
consistency measure of Li et al. (Fig. 5) is the distribution of the angles between the normals
of neighbouring points.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import Field, PositiveFloat
from scipy.spatial import cKDTree

from spacepose.core.cloud import PointCloud
from spacepose.core.config import StageConfig
from spacepose.core.neighbors import as_tree, hybrid, knn, local_covariances
from spacepose.errors import InputError


class NormalsConfig(StageConfig):
    """Neighbourhood of the normal estimate.

    Attributes
    ----------
    k
        Number of nearest neighbours (the point included); with ``radius`` set, the cap on the
        neighbours inside the radius (Open3D's hybrid search).
    radius
        Search radius in metres, or None for a pure k-nearest search.
    """

    k: int = Field(default=30, ge=3)
    radius: PositiveFloat | None = None


def normals_from_covariances(
    covariances: NDArray[np.float64],
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Unoriented normals and eigenvalues of a stack of 3×3 covariances.

    Parameters
    ----------
    covariances
        (M, 3, 3) symmetric positive semi-definite matrices.

    Returns
    -------
    normals, eigenvalues
        (M, 3) unit eigenvectors of the smallest eigenvalue, and the (M, 3) eigenvalues in
        ascending order (``λ0 / Σλ`` is the surface variation).

    Notes
    -----
    Closed form and vectorised (a batched ``eigh`` costs as much as the neighbour search). The
    trigonometric eigenvalues (Smith 1961) are exact to rounding only for an eigenvalue set
    apart from the other two, so the eigenvector of the more isolated extreme eigenvalue is
    taken first, as the kernel of ``A − λI``; the other two then come from the 2×2 problem in
    its orthogonal complement, solved with a Jacobi rotation. Every eigenvalue is then exact to
    rounding relative to ``‖A‖`` (as ``eigh``); when ``λ0`` is a double eigenvalue (a
    line-shaped neighbourhood) the normal is one unit vector of its eigenplane.
    """
    A = np.asarray(covariances, dtype=np.float64)
    lam = _trigonometric_eigenvalues(A)
    # ">=" sends a multiple of the identity down the λ0 branch, where it gets the x axis (eigh's
    # choice too).
    low_isolated = lam[:, 1] - lam[:, 0] >= lam[:, 2] - lam[:, 1]
    shift = np.where(low_isolated, lam[:, 0], lam[:, 2])
    e = _kernel_directions(A - shift[:, None, None] * np.eye(3))
    u, v = _orthonormal_complement(e)
    Au, Av = np.einsum("mij,mj->mi", A, u), np.einsum("mij,mj->mi", A, v)
    a, b, c = _dot(u, Au), _dot(u, Av), _dot(v, Av)
    # Jacobi rotation of the 2×2 block [[a, b], [b, c]]: θ turns u onto the larger eigenvector.
    theta = 0.5 * np.arctan2(2.0 * b, a - c)
    sin, cos = np.sin(theta)[:, None], np.cos(theta)[:, None]
    mean, radius = 0.5 * (a + c), np.hypot(0.5 * (a - c), b)
    lam_e = _dot(e, np.einsum("mij,mj->mi", A, e))
    normals = np.where(low_isolated[:, None], e, cos * v - sin * u)
    eigenvalues = np.where(
        low_isolated[:, None],
        np.column_stack([lam_e, mean - radius, mean + radius]),
        np.column_stack([mean - radius, mean + radius, lam_e]),
    )
    return normals, eigenvalues


def _trigonometric_eigenvalues(A: NDArray[np.float64]) -> NDArray[np.float64]:
    """Ascending eigenvalues (M, 3) of symmetric 3×3 matrices from the cubic's cosine form."""
    q = np.trace(A, axis1=1, axis2=2) / 3.0
    d0, d1, d2 = A[:, 0, 0] - q, A[:, 1, 1] - q, A[:, 2, 2] - q
    a01, a02, a12 = A[:, 0, 1], A[:, 0, 2], A[:, 1, 2]
    p = np.sqrt((d0**2 + d1**2 + d2**2 + 2.0 * (a01**2 + a02**2 + a12**2)) / 6.0)
    # (A − qI) / p has eigenvalues 2cos(φ + 2πj/3), with cos 3φ = det((A − qI) / p) / 2.
    det = d0 * (d1 * d2 - a12**2) - a01 * (a01 * d2 - a12 * a02) + a02 * (a01 * a12 - d1 * a02)
    safe = np.where(p > 0, p, 1.0)
    phi = np.arccos(np.clip(0.5 * det / safe**3, -1.0, 1.0)) / 3.0
    largest = q + 2.0 * p * np.cos(phi)
    smallest = q + 2.0 * p * np.cos(phi + 2.0 * np.pi / 3.0)
    return np.column_stack([smallest, 3.0 * q - largest - smallest, largest])


def _kernel_directions(M: NDArray[np.float64]) -> NDArray[np.float64]:
    """Unit vectors (M, 3) spanning the kernel of rank-2 3×3 matrices: a cross product of rows.

    The longest of the three cross products is the best conditioned; a matrix with no two
    independent rows (rank <= 1, only for a multiple of the identity here) gets the x axis.
    """
    r0, r1, r2 = M[:, 0], M[:, 1], M[:, 2]
    cross = np.stack([np.cross(r0, r1), np.cross(r0, r2), np.cross(r1, r2)], axis=1)
    norm2 = np.einsum("mci,mci->mc", cross, cross)
    best = np.argmax(norm2, axis=1)
    rows = np.arange(len(M))
    vec, length = cross[rows, best], np.sqrt(norm2[rows, best])[:, None]
    return np.where(length > 0, vec / np.where(length > 0, length, 1.0), (1.0, 0.0, 0.0))


def _orthonormal_complement(e: NDArray[np.float64]) -> tuple[NDArray, NDArray]:
    """Two unit vectors (M, 3) completing unit vectors ``e`` (M, 3) to right-handed bases."""
    # Cross with the axis least aligned with e, so the product is never short.
    axis = np.eye(3)[np.argmin(np.abs(e), axis=1)]
    u = np.cross(e, axis)
    u /= np.sqrt(_dot(u, u))[:, None]
    return u, np.cross(e, u)


def _dot(a: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
    return np.einsum("mi,mi->m", a, b)


def orient_towards(
    points: ArrayLike, normals: ArrayLike, viewpoint: ArrayLike = (0.0, 0.0, 0.0)
) -> NDArray[np.float64]:
    """Flip normals (N, 3) so that each points towards ``viewpoint`` (3,), same frame as points."""
    pts = np.asarray(points, dtype=np.float64)
    n = np.asarray(normals, dtype=np.float64)
    to_view = np.asarray(viewpoint, dtype=np.float64).reshape(3) - pts
    flip = np.einsum("ij,ij->i", n, to_view) < 0
    return np.where(flip[:, None], -n, n)


def estimate_normals(
    cloud: PointCloud,
    config: NormalsConfig = NormalsConfig(),
    viewpoint: ArrayLike = (0.0, 0.0, 0.0),
    workers: int = -1,
    tree: cKDTree | None = None,
) -> PointCloud:
    """The cloud with a unit normal per point, oriented towards ``viewpoint``.

    Parameters
    ----------
    cloud
        Points (N, 3) in the sensor frame (or any frame ``viewpoint`` is given in).
    config
        Neighbourhood: ``k`` nearest, or within ``radius`` capped at ``k``.
    viewpoint
        (3,) position the normals are turned towards; the sensor origin by default.
    workers
        Threads for the neighbour search.
    tree
        A KD-tree of ``cloud.points`` already built by the caller (a tracker keeps one per
        keyframe), so it is not built twice.

    Returns
    -------
    A new :class:`PointCloud` with the same points and σ and the estimated normals.

    Notes
    -----
    A point with fewer than 3 neighbours inside ``radius`` has no defined plane; it gets the
    unit line of sight towards ``viewpoint`` as its normal rather than an arbitrary axis.
    """
    pts = cloud.points
    if len(pts) < 3:
        raise InputError(f"normal estimation needs at least 3 points, got {len(pts)}", cloud.source)
    if tree is None:
        tree = as_tree(pts)
    elif tree.n != len(pts):
        raise InputError(f"the tree holds {tree.n} points, the cloud {len(pts)}", cloud.source)
    k = min(config.k, len(pts))
    if config.radius is None:
        _, idx = knn(tree, pts, k, workers=workers)
    else:
        idx, _ = hybrid(tree, pts, config.radius, k, workers=workers)
    normals, _ = normals_from_covariances(local_covariances(pts, idx))
    sparse = (idx >= 0).sum(axis=1) < 3
    if np.any(sparse):
        sight = np.asarray(viewpoint, dtype=np.float64).reshape(3) - pts[sparse]
        norm = np.linalg.norm(sight, axis=1, keepdims=True)
        # A point exactly at the viewpoint has no line of sight: fall back to the boresight.
        normals[sparse] = np.where(norm > 0, sight / np.where(norm > 0, norm, 1.0), (0, 0, -1))
    return cloud.with_normals(orient_towards(pts, normals, viewpoint))


@dataclass(frozen=True)
class NormalConsistency:
    """Distribution of the angles between the normals of neighbouring points (Li Fig. 5).

    Attributes
    ----------
    angles_deg
        (P,) angle ``arccos(n_i · n_j)`` in degrees for every point i and each of its neighbours
        j, in 0–180° (normals are compared as stored, not folded to 0–90°).
    bin_edges_deg
        (B + 1,) histogram edges in degrees, 0 to 180.
    counts
        (B,) number of angles per bin.
    share_below_20
        Share of the angles below 20°, in [0, 1].
    """

    angles_deg: NDArray[np.float64]
    bin_edges_deg: NDArray[np.float64]
    counts: NDArray[np.int64]
    share_below_20: float

    @property
    def shares(self) -> NDArray[np.float64]:
        """(B,) share of the angles per bin."""
        return self.counts / max(int(self.counts.sum()), 1)


def normal_consistency(
    cloud: PointCloud, k: int = 10, bin_width_deg: float = 10.0, workers: int = -1
) -> NormalConsistency:
    """Angles between each point's normal and those of its k nearest neighbours.

    Parameters
    ----------
    cloud
        Points with normals (N, 3).
    k
        Number of neighbours per point, the point itself excluded.
    bin_width_deg
        Histogram bin width in degrees; must divide 180.
    workers
        Threads for the neighbour search.
    """
    if not cloud.has_normals:
        raise InputError("normal consistency needs a cloud with normals", cloud.source)
    if len(cloud) < k + 1:
        raise InputError(f"normal consistency with k={k} needs more than {k} points", cloud.source)
    n_bins = 180.0 / bin_width_deg
    if bin_width_deg <= 0 or abs(n_bins - round(n_bins)) > 1e-9:
        raise InputError(f"bin_width_deg must divide 180, got {bin_width_deg}")
    _, idx = knn(cloud.points, cloud.points, k + 1, workers=workers)
    # Drop each point itself (not simply column 0, which a duplicate point may occupy).
    own = idx == np.arange(len(idx))[:, None]
    own[own.sum(axis=1) == 0, -1] = True
    i = np.repeat(np.arange(len(idx)), k)
    j = idx[~own]
    cos = np.einsum("ij,ij->i", cloud.normals[i], cloud.normals[j])
    angles = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    edges = np.linspace(0.0, 180.0, round(n_bins) + 1)
    counts, _ = np.histogram(angles, bins=edges)
    return NormalConsistency(angles, edges, counts, float(np.mean(angles < 20.0)))
