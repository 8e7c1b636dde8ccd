"""Covariances of registrations (docs/methods.md §5.3, §5.5): σ² H⁻¹ from the point-to-plane
residuals, its cluster-robust (sandwich) form, an isotropic floor about a point, and a keyframe
chain's drift shaped like the registration's own uncertainty.

All are (6, 6), left perturbations with the twist ordered (ω, v), about the origin of the frame
they are expressed in.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from spacepose.core import se3
from spacepose.core.correspondences import Correspondences, find_correspondences
from spacepose.core.icp_systems import point_to_plane_system
from spacepose.core.keyframes import PreparedCloud
from spacepose.errors import RegistrationError

# Edge of the cells whose residuals are taken as one correlated group, in voxels: a voxel's
# centroids in two samplings are biased alike over a few neighbouring cells (an edge, a bend).
# On noisy views of two meshes (20 seeds a case, the sandwich alone) cells of 1, 3 and 10 voxels
# gave a worst-axis RMS error/σ of 1.16-1.99, 1.13-1.80 and 1.05-2.11 (6 voxels: 1.11, one case):
# larger cells see more of a shared bias but are fewer, and their sum is noisier.
CLUSTER_VOXELS = 3.0


def plane_covariance(
    T_target_source: NDArray[np.float64],
    source_points: NDArray[np.float64],
    target: PreparedCloud,
    max_distance: float,
    workers: int = -1,
    correspondences: Correspondences | None = None,
    min_sigma: float = 0.0,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Covariance of a registration from its point-to-plane residuals at the solution.

    ``σ² (Σ h hᵀ)⁻¹`` with ``h = (p × n, n)`` over the final correspondences (target normals)
    and ``σ²`` the variance of the normal distances: the same noise model whichever method
    produced ``T_target_source``, so ICP, GICP and J-ICP report comparable uncertainties.

    ``correspondences`` are the matches at ``T_target_source`` when the registration already
    has them (:func:`~spacepose.core.icp.icp_correspondences`; its point-to-plane sums are used
    as they are); otherwise they are searched within ``max_distance``. ``min_sigma`` (m) floors
    σ: the spread sampling a surface leaves without noise (a renderer's depth), which no
    residual of a noise-free frame falls below.

    Returns
    -------
    covariance
        (6, 6) covariance of ``T_target_source``, left perturbation in the target frame.
    step
        (6,) the Gauss-Newton point-to-plane step from ``T_target_source`` (same frame): about
        zero at the surface optimum, large when a registration stopped elsewhere.

    Raises
    ------
    RegistrationError
        Fewer than 7 correspondences within ``max_distance``.
    """
    sigma2 = None
    if correspondences is not None and correspondences.system is not None:
        n_matches = len(correspondences.src_idx)
        H, g, sse = correspondences.system
        if correspondences.weights is not None:
            # Robust sums: the M-estimator's own variance, not the weighted Σ r².
            sigma2 = correspondences.residual_sigma**2
    else:
        moved = se3.transform_points(T_target_source, source_points)
        if correspondences is None:
            s, t, _ = find_correspondences(target.tree, moved, max_distance, workers)
        else:
            s, t = correspondences.src_idx, correspondences.tgt_idx
        n_matches = len(s)
        H, g, sse = point_to_plane_system(moved[s], target.cloud.points[t], target.cloud.normals[t])
    if n_matches < 7:
        raise RegistrationError(f"{n_matches} correspondences are too few for a covariance")
    if sigma2 is None:
        sigma2 = sse / (n_matches - 6)
    sigma2 = max(sigma2, min_sigma**2)
    H_inv = np.linalg.pinv(H, hermitian=True)
    return sigma2 * H_inv, -H_inv @ g


def clustered_covariance(
    points: NDArray[np.float64],
    normals: NDArray[np.float64],
    residuals: NDArray[np.float64],
    cell: float,
    weights: NDArray[np.float64] | None = None,
) -> NDArray[np.float64]:
    """Cluster-robust covariance of a point-to-plane registration at its solution.

    The information form ``σ² H⁻¹`` holds when every residual is independent with one σ. Two
    samplings of a surface break both: residuals grow with the leverage of edges and bends,
    and neighbouring pairs share their bias. The sandwich ``H⁻¹ (Σ_c g_c g_cᵀ) H⁻¹ · G/(G−1)``,
    with ``H = Σ w h hᵀ``, ``g_c = Σ w h r`` summed over the pairs of each cubic cell of edge
    ``cell`` and G the cells, counts both (the cluster-robust variance of least squares;
    docs/methods.md §1.5).

    Parameters
    ----------
    points
        (M, 3) matched source points, moved into the target frame by the solution.
    normals, residuals
        (M, 3) their target points' unit normals and (M,) signed point-to-plane residuals (m).
    cell
        Edge (m) of the residual groups.
    weights
        (M,) robust kernel weights of the pairs; None: all 1.

    Returns
    -------
    (6, 6) covariance of ``T_target_source``, left perturbation in the target frame about its
    origin, twist (omega, v).

    Raises
    ------
    RegistrationError
        Fewer than 7 pairs, or pairs in fewer than 7 cells.
    """
    h = np.hstack([np.cross(points, normals), normals])
    w = np.ones(len(h)) if weights is None else weights
    _, group = np.unique(np.floor(points / cell).astype(np.int64), axis=0, return_inverse=True)
    groups = int(group.max()) + 1 if len(group) else 0
    if len(h) < 7 or groups < 7:
        raise RegistrationError(
            f"{len(h)} correspondences in {groups} cells are too few for a covariance"
        )
    g = np.zeros((groups, 6))
    np.add.at(g, group.ravel(), h * (w * residuals)[:, None])
    H_inv = np.linalg.pinv((h * w[:, None]).T @ h, hermitian=True)
    return groups / (groups - 1) * (H_inv @ (g.T @ g) @ H_inv)


def wider_of(first: NDArray[np.float64], second: NDArray[np.float64]) -> NDArray[np.float64]:
    """(6, 6) covariance as wide as ``first`` and ``second`` in every direction: ``first``
    plus the part of ``second − first`` that is positive."""
    ev, V = np.linalg.eigh(0.5 * ((second - first) + (second - first).T))
    return first + (V * np.maximum(ev, 0.0)) @ V.T


def isotropic_about(point: NDArray[np.float64], sigma: tuple[float, float]) -> NDArray[np.float64]:
    """(6, 6) covariance of an isotropic ``sigma`` = (rad, m) twist about ``point`` (3,),
    expressed about the origin of the same frame."""
    s_r, s_t = sigma
    cov_c = np.diag([s_r**2] * 3 + [s_t**2] * 3)
    # A twist about the point c is (ω, v + skew(c) ω) about the origin.
    M = np.eye(6)
    M[3:, :3] = se3.skew(point)
    return M @ cov_c @ M.T


def shaped_drift(
    prepared: PreparedCloud, drift: tuple[float, float], own: NDArray[np.float64]
) -> NDArray[np.float64]:
    """(6, 6) covariance (frame k, about the origin) of a keyframe chain's drift.

    ``drift`` (rad, m) is the chain's 1-σ
    (:func:`~spacepose.core.window_registration.chain_drift`) as a displacement at the target's
    radius; it is spread over the directions in proportion to the frame's own registration
    covariance ``own`` (about the centroid, rotations scaled by the radius): a bias builds up
    where the registration is least constrained (across the line of sight on the lab run, not
    in depth).
    """
    c, r = prepared.centroid, prepared.radius
    s = drift[1] + r * drift[0]
    if s <= 0:
        return np.zeros((6, 6))
    # Twist about the origin -> about the centroid, rotations in metres at the radius.
    to_c = np.eye(6)
    to_c[3:, :3] = -se3.skew(c)
    N = np.diag([r] * 3 + [1.0] * 3) @ to_c
    own_n = N @ own @ N.T
    top = float(np.linalg.eigvalsh(0.5 * (own_n + own_n.T))[-1])
    shape = own_n / top if top > 0 else np.eye(6)
    N_inv = np.linalg.inv(N)
    return N_inv @ (s**2 * shape) @ N_inv.T
