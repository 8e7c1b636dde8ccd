"""mpp-MLS: micro-plane projection moving least squares (methods.md §1.2, Li §2.2, Eqs. 2–5).

Index points are chosen on a voxel grid (the point nearest each occupied voxel's centre), which
removes redundant points and evens out the spacing. Each index point r is then moved onto a local
surface fitted to its neighbours p_i with Gaussian weights θ(d) = exp(−d²/h²):

1. a reference plane (n, q) by weighted PCA, iterated: the weights are centred on q, q is the
   projection of r onto the plane, repeated ``projection_iterations`` times (Levin's MLS
   projection with the usual linearisation of Eq. 3);
2. a bivariate polynomial g of degree 2 or 3 fitted to the heights of the p_i over that plane
   (Eq. 4), in local coordinates scaled by h so the normal equations stay well conditioned;
3. the output point q + g(0, 0)·n, with the normal n tilted by the gradient of g at the origin.

Everything is batched over index points: padded neighbour arrays, einsum for the weighted
moments and normal equations, ``np.linalg.eigh`` and ``np.linalg.solve`` on stacks.

Degenerate neighbourhoods are detected, never allowed to crash: an index point with fewer than
``min_neighbors`` neighbours in its support, or whose neighbours are collinear, is dropped (an
isolated ToF "flying pixel" is an outlier, and no plane exists for a line); when only the
polynomial system is ill-conditioned, the point is projected onto the reference plane instead.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import Field, PositiveFloat, model_validator

from spacepose.core.cloud import PointCloud, as_cloud
from spacepose.core.config import StageConfig, stage_config
from spacepose.core.neighbors import as_tree, hybrid, weighted_moments
from spacepose.core.normals import orient_towards
from spacepose.errors import DegenerateGeometryError

# A neighbourhood whose middle/largest covariance eigenvalue ratio is below this is a line:
# its spread across the line is under 0.1 % of its length.
_COLLINEAR_RATIO = 1e-6
# Smallest/largest eigenvalue ratio of the (scaled) polynomial normal equations below which the
# fit is not trusted and the point is projected onto the reference plane.
_ILL_CONDITIONED = 1e-10
# Index points processed together: bounds the padded (chunk, max_neighbors, terms) arrays.
_CHUNK = 4096


class MLSConfig(StageConfig):
    """Parameters of :func:`mpp_mls`.

    Attributes
    ----------
    voxel_size
        Edge (m) of the voxel grid choosing the index points: the output spacing.
    h
        Smoothing scale (m) of the weight exp(−d²/h²); features smaller than h are smoothed.
    support_factor
        Support radius = ``support_factor · h`` (weights beyond 3h are below 1.3e-4).
    polynomial_order
        Degree of the local height polynomial g, 2 or 3.
    projection_iterations
        Weighted-PCA passes re-centring the weights on the projection q of r.
    min_neighbors
        Fewest neighbours (the point included) in the support for a fit; fewer → dropped.
    max_neighbors
        Cap on the neighbours used, nearest first (Open3D-style hybrid search).
    """

    voxel_size: PositiveFloat = 0.01
    h: PositiveFloat = 0.01
    support_factor: float = Field(default=3.0, gt=0)
    polynomial_order: Literal[2, 3] = 2
    projection_iterations: int = Field(default=3, ge=1)
    min_neighbors: int = Field(default=12, ge=3)
    max_neighbors: int = Field(default=100, ge=3)

    @model_validator(mode="after")
    def _neighbour_order(self) -> MLSConfig:
        # No point could keep more than max_neighbors: every one would be dropped.
        if self.min_neighbors > self.max_neighbors:
            raise ValueError(
                f"min_neighbors {self.min_neighbors} must not exceed max_neighbors "
                f"{self.max_neighbors}"
            )
        return self


@dataclass(frozen=True)
class MLSProjection:
    """Result of :func:`mls_project` for M index points.

    Attributes
    ----------
    points
        (M, 3) projected points (rows of dropped points are NaN).
    normals
        (M, 3) unit normals of the fitted surface, unoriented (NaN where dropped).
    status
        (M,) int8: 0 polynomial fit, 1 projected onto the reference plane (ill-conditioned
        polynomial), 2 dropped (too few neighbours), 3 dropped (collinear neighbours).
    """

    points: NDArray[np.float64]
    normals: NDArray[np.float64]
    status: NDArray[np.int8]

    FIT, PLANE, SPARSE, COLLINEAR = 0, 1, 2, 3

    @property
    def kept(self) -> NDArray[np.bool_]:
        """(M,) mask of the index points that produced an output point."""
        return self.status <= self.PLANE


def voxel_index_points(points: ArrayLike, voxel_size: float) -> NDArray[np.intp]:
    """Indices of the point nearest the centre of each occupied voxel.

    Parameters
    ----------
    points
        (N, 3) points; the grid is anchored at the frame origin, so the same voxels are used for
        every frame given in that frame.
    voxel_size
        Voxel edge (m).

    Returns
    -------
    (K,) indices into ``points``, one per occupied voxel, ordered by voxel; ties go to the
    lower index.
    """
    pts = np.asarray(points, dtype=np.float64)
    keys = np.floor(pts / voxel_size).astype(np.int64)
    _, voxel = np.unique(keys, axis=0, return_inverse=True)
    voxel = voxel.reshape(-1)
    d2 = np.sum((pts - (keys + 0.5) * voxel_size) ** 2, axis=1)
    order = np.lexsort((d2, voxel))
    first = np.r_[True, voxel[order][1:] != voxel[order][:-1]]
    return order[first]


def polynomial_terms(x: NDArray[np.float64], y: NDArray[np.float64], order: int) -> NDArray:
    """Monomials (..., m) of a bivariate polynomial: 1, x, y, x², xy, y² [, x³, x²y, xy², y³]."""
    terms = [np.ones_like(x), x, y, x * x, x * y, y * y]
    if order == 3:
        terms += [x * x * x, x * x * y, x * y * y, y * y * y]
    return np.stack(terms, axis=-1)


def fit_reference_planes(
    points: NDArray[np.float64],
    anchors: NDArray[np.float64],
    idx: NDArray[np.intp],
    h: float,
    iterations: int,
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Weighted-PCA reference planes of MLS (Eqs. 2–3, linearised), batched.

    Parameters
    ----------
    points
        (N, 3) cloud the neighbour indices refer to.
    anchors
        (M, 3) index points r.
    idx
        (M, k) neighbour indices, ``-1`` for padding.
    h
        Weight scale (m).
    iterations
        Passes: weights centred on q, plane through the weighted mean, q ← projection of r.

    Returns
    -------
    q, frames, eigenvalues
        (M, 3) projections of r onto the planes; (M, 3, 3) orthonormal frames whose columns are
        (normal, second, first principal direction); (M, 3) covariance eigenvalues, ascending.
    """
    q = anchors.copy()
    safe = np.where(idx >= 0, idx, 0)
    for _ in range(iterations):
        d2 = np.sum((points[safe] - q[:, None, :]) ** 2, axis=2)
        mean, cov, _ = weighted_moments(points, idx, np.exp(-d2 / h**2))
        eigenvalues, frames = np.linalg.eigh(cov)
        n = frames[:, :, 0]
        q = anchors - np.einsum("mi,mi->m", anchors - mean, n)[:, None] * n
    return q, frames, eigenvalues


def fit_height_polynomials(
    local: NDArray[np.float64],
    weights: NDArray[np.float64],
    order: int,
) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """Weighted least-squares height polynomials (Eq. 4), batched.

    Parameters
    ----------
    local
        (M, k, 3) neighbour coordinates (x/h, y/h, height) in each reference frame.
    weights
        (M, k) weights θ (0 for padding).
    order
        Polynomial degree, 2 or 3.

    Returns
    -------
    coefficients, ok
        (M, m) coefficients in the order of :func:`polynomial_terms` (zeros where not ok) and
        the (M,) mask of well-conditioned fits.
    """
    A = polynomial_terms(local[..., 0], local[..., 1], order)
    normal = np.einsum("mk,mki,mkj->mij", weights, A, A)
    rhs = np.einsum("mk,mki,mk->mi", weights, A, local[..., 2])
    ev = np.linalg.eigvalsh(normal)
    ok = ev[:, 0] > _ILL_CONDITIONED * np.maximum(ev[:, -1], np.finfo(float).tiny)
    coefficients = np.zeros(rhs.shape)
    if np.any(ok):
        coefficients[ok] = np.linalg.solve(normal[ok], rhs[ok][..., None])[..., 0]
    return coefficients, ok


def mls_project(
    points: ArrayLike,
    anchors: ArrayLike,
    config: MLSConfig = MLSConfig(),
    workers: int = -1,
) -> MLSProjection:
    """Project anchor points onto the MLS surface of ``points``.

    Parameters
    ----------
    points
        (N, 3) cloud defining the surface.
    anchors
        (M, 3) index points r to project (usually a subset of ``points``).
    config
        Weight scale, support, polynomial degree, iterations and neighbour limits.
    workers
        Threads for the neighbour search.
    """
    pts = np.asarray(points, dtype=np.float64)
    r_all = np.asarray(anchors, dtype=np.float64)
    tree = as_tree(pts)
    out_p = np.full(r_all.shape, np.nan)
    out_n = np.full(r_all.shape, np.nan)
    status = np.zeros(len(r_all), dtype=np.int8)
    h = config.h
    for start in range(0, len(r_all), _CHUNK):
        rows = slice(start, start + _CHUNK)
        r = r_all[rows]
        idx, _ = hybrid(tree, r, config.support_factor * h, config.max_neighbors, workers=workers)
        sparse = (idx >= 0).sum(axis=1) < config.min_neighbors
        q, frames, ev = fit_reference_planes(pts, r, idx, h, config.projection_iterations)
        collinear = ~sparse & (ev[:, 1] <= _COLLINEAR_RATIO * ev[:, 2])
        n, v, u = frames[:, :, 0], frames[:, :, 1], frames[:, :, 2]
        rel = np.where((idx >= 0)[..., None], pts[np.where(idx >= 0, idx, 0)] - q[:, None], 0.0)
        local = np.stack(
            [
                np.einsum("mki,mi->mk", rel, u) / h,
                np.einsum("mki,mi->mk", rel, v) / h,
                np.einsum("mki,mi->mk", rel, n),
            ],
            axis=-1,
        )
        w = np.where(idx >= 0, np.exp(-np.sum(rel**2, axis=2) / h**2), 0.0)
        coef, ok = fit_height_polynomials(local, w, config.polynomial_order)
        # Gradient of g at the origin in metres: the local x, y were divided by h.
        gx, gy = coef[:, 1] / h, coef[:, 2] / h
        normals = n - gx[:, None] * u - gy[:, None] * v
        out_p[rows] = q + coef[:, :1] * n
        out_n[rows] = normals / np.linalg.norm(normals, axis=1, keepdims=True)
        st = np.where(ok, MLSProjection.FIT, MLSProjection.PLANE)
        st = np.where(collinear, MLSProjection.COLLINEAR, st)
        status[rows] = np.where(sparse, MLSProjection.SPARSE, st)
    dropped = status > MLSProjection.PLANE
    out_p[dropped] = np.nan
    out_n[dropped] = np.nan
    return MLSProjection(out_p, out_n, status)


def mpp_mls(
    cloud: PointCloud | ArrayLike,
    config: MLSConfig = MLSConfig(),
    workers: int = -1,
    viewpoint: ArrayLike = (0.0, 0.0, 0.0),
) -> PointCloud:
    """Denoise and downsample a cloud by mpp-MLS; the output carries normals.

    Parameters
    ----------
    cloud
        Raw points (N, 3), usually in the sensor frame: a :class:`PointCloud` or an (N, 3)
        array.
    config
        Voxel size, smoothing scale h and fit options.
    workers
        Threads for the neighbour searches.
    viewpoint
        (3,) position the output normals are turned towards (the sensor origin by default).

    Returns
    -------
    One point per occupied voxel that has a well-defined neighbourhood, projected onto the
    local MLS surface, with unit normals. Index points with too few or collinear neighbours are
    dropped (see the module notes).

    Raises
    ------
    DegenerateGeometryError
        When every index point is dropped (the cloud is too sparse for h, or a line).
    """
    config = stage_config(config, MLSConfig)
    cloud = as_cloud(cloud, "cloud")
    anchors = cloud.points[voxel_index_points(cloud.points, config.voxel_size)]
    proj = mls_project(cloud.points, anchors, config, workers)
    kept = proj.kept
    if not np.any(kept):
        raise DegenerateGeometryError(
            f"mpp-MLS kept no point: all {len(anchors)} index points have fewer than "
            f"{config.min_neighbors} neighbours within {config.support_factor * config.h} m "
            "or collinear ones",
            cloud.source,
        )
    # Index points from neighbouring voxels can project into one voxel (a surface lying along a
    # grid plane gives two layers of index points): keep one projected point per voxel.
    out_p, out_n = proj.points[kept], proj.normals[kept]
    unique = voxel_index_points(out_p, config.voxel_size)
    normals = orient_towards(out_p[unique], out_n[unique], viewpoint)
    return PointCloud(out_p[unique], normals, source=cloud.source)
