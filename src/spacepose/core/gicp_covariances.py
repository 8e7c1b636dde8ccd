"""Per-point covariances of Generalized ICP (Segal et al. 2009; methods.md §1.5).

Each point of an (N, 3) cloud gets a (3, 3) covariance from its k nearest neighbours (the point
itself included), regularised to a plane: the eigenvalues of the neighbourhood scatter are
replaced by ``(ε, 1, 1)``, smallest along the normal n, which gives ``I − (1 − ε) n nᵀ`` (as
Segal et al., small_gicp and Open3D do). The covariances are in the cloud's own frame and
dimensionless: they fix the *shape* of the noise only, its scale (m²) is estimated from the
residuals by :func:`spacepose.core.gicp.gicp`. :func:`check_covariances` validates (N, 3, 3)
covariances a caller computed once per frame and passes in.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from spacepose.core.cloud import PointCloud
from spacepose.core.icp import as_registration_cloud
from spacepose.core.neighbors import knn
from spacepose.core.normals import neighbourhood_normals
from spacepose.core.se3 import real_array
from spacepose.errors import InputError


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


def plane_normals(C: NDArray[np.float64]) -> NDArray[np.float64]:
    """(N, 3) unit normals (sign arbitrary) of plane-regularised covariances (N, 3, 3)
    ``I − (1 − ε) n nᵀ`` with ε < 1: the neighbourhood normals they were made from, without a
    second neighbour search."""
    M = np.eye(3) - C  # (1 − ε) n nᵀ: each column is n times a component of n
    diagonal = np.einsum("nii->ni", M)
    column = np.take_along_axis(M, np.argmax(diagonal, axis=1)[:, None, None], axis=2)[..., 0]
    length = np.linalg.norm(column, axis=1, keepdims=True)
    if not np.all(length > 0):
        # ε = 1 (isotropic covariances) holds no normal: 0/0 gave NaN normals without a word.
        raise InputError("covariances with ε = 1 (isotropic) carry no plane normal")
    return column / length


def check_covariances(C: ArrayLike | None, n: int, name: str) -> NDArray[np.float64] | None:
    """``C`` as float64 (N, 3, 3) covariances, None when it is None (``name`` for the error).

    Raises
    ------
    InputError
        When ``C`` is not finite or not of shape (n, 3, 3), or a matrix is no covariance: not
        symmetric, or not positive semidefinite (both were registered without a word).
    """
    if C is None:
        return None
    C = real_array(C, name)
    if C.shape != (n, 3, 3) or not np.all(np.isfinite(C)):
        raise InputError(f"{name} must be finite with shape ({n}, 3, 3), got {C.shape}")
    with np.errstate(all="ignore"):  # the products of entries beyond 1e100 overflow
        problem = _no_covariance(C)
    if problem is not None:
        raise InputError(f"{name}: {problem}")
    return C


# Rounding, relative to a covariance's scale, its symmetry may carry (a rotated R C Rᵀ) and its
# principal minors, relative to the scale's powers.
_SKEW = 1e-6
_ROUNDING = 1e-9


def _no_covariance(C: NDArray[np.float64]) -> str | None:
    """Why a matrix of the (N, 3, 3) stack ``C`` is no covariance (the first such), or None: it
    must be symmetric and positive semidefinite, its principal minors (diagonal, 2 x 2 and
    determinant) all >= 0 to rounding. Element-wise, as a tracker passes its frame's in."""
    a, b, c = C[:, 0, 0], C[:, 1, 1], C[:, 2, 2]
    x, y, z = C[:, 0, 1], C[:, 0, 2], C[:, 1, 2]
    # A covariance's largest entry is on its diagonal: the scale of its rounding.
    scale = np.maximum(np.maximum(np.abs(a), np.abs(b)), np.abs(c))
    skew = np.maximum(np.abs(x - C[:, 1, 0]), np.abs(y - C[:, 2, 0]))
    asymmetric = np.maximum(skew, np.abs(z - C[:, 2, 1])) > _SKEW * scale
    minor_ab, minor_ac, minor_bc = a * b - x * x, a * c - y * y, b * c - z * z
    det = a * minor_bc - x * (x * c - z * y) + y * (x * z - b * y)
    negative = np.minimum(np.minimum(a, b), c) < -_ROUNDING * scale
    negative |= np.minimum(np.minimum(minor_ab, minor_ac), minor_bc) < -_ROUNDING * scale**2
    negative |= det < -_ROUNDING * scale**3
    if np.any(asymmetric):
        k = int(np.argmax(asymmetric))
        i, j = np.unravel_index(np.argmax(np.abs(C[k] - C[k].T)), (3, 3))
        return (
            f"matrix {k} of {len(C)} is not symmetric (C[{i}, {j}] {C[k, i, j]:.3g}, "
            f"C[{j}, {i}] {C[k, j, i]:.3g}): no covariance"
        )
    if np.any(negative):
        k = int(np.argmax(negative))
        return (
            f"matrix {k} of {len(C)} is not positive semidefinite (its smallest eigenvalue is "
            f"{np.linalg.eigvalsh(C[k]).min():.3g}): no covariance"
        )
    return None
