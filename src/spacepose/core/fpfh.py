"""Fast Point Feature Histograms (METHODS §1.3; Rusu et al. 2009; Li §2.3.1).

The definition follows Open3D's ``compute_fpfh_feature`` number for number (bin edges, the swap
rule, the 1/d² weighting, the per-sub-histogram scaling to 100), so the two can be compared
directly. Everything is computed on flat arrays of (point, neighbour) pairs: the histograms with
``np.bincount`` and the weighted neighbour sum as one sparse matrix product.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray
from pydantic import Field, PositiveFloat
from scipy import sparse

from spacepose.core.cloud import PointCloud
from spacepose.core.config import StageConfig
from spacepose.core.neighbors import hybrid
from spacepose.errors import InputError

N_BINS = 11
N_FEATURES = 3 * N_BINS


class FPFHConfig(StageConfig):
    """Neighbourhood of the descriptor (Open3D's hybrid search).

    Attributes
    ----------
    radius
        Search radius in metres; typically 5× the point spacing.
    max_nn
        Cap on the neighbours inside the radius, the point itself included (as in Open3D).
    """

    radius: PositiveFloat = 0.05
    max_nn: int = Field(default=100, ge=2)


def pair_features(
    p1: NDArray[np.float64],
    n1: NDArray[np.float64],
    p2: NDArray[np.float64],
    n2: NDArray[np.float64],
) -> NDArray[np.float64]:
    """Darboux-frame features of point pairs, batched.

    Parameters
    ----------
    p1, n1, p2, n2
        (P, 3) positions and unit normals of the two points of each pair.

    Returns
    -------
    (P, 3) features ``(f1, f2, f3)``: f1 the angle in [−π, π], f2 and f3 cosines in [−1, 1].
    The pair is ordered so that the source normal makes the smaller angle with the line joining
    the points; a zero-length pair, or a normal parallel to that line, gives all zeros.

    When the two normals are equal to rounding (neighbours whose normals came from the same
    neighbour set), the swap, hence the sign of f3, is decided by the last bit of the dot
    products; they are summed in Eigen's order so that the choice matches Open3D's.
    """
    d = p2 - p1
    length = np.sqrt(_dot(d, d))
    safe = np.where(length > 0, length, 1.0)
    a1 = _dot(n1, d) / safe
    a2 = _dot(n2, d) / safe
    # Open3D compares arccos|a1| > arccos|a2|; arccos is decreasing, and comparing |a1| < |a2|
    # directly is what its build does in effect: pairs whose normals are equal to the last bit
    # (same neighbour set) then resolve the same way, while a libm arccos can map two
    # neighbouring doubles to one value and flip the sign of f3.
    swap = np.abs(a1) < np.abs(a2)
    ns = np.where(swap[:, None], n2, n1)
    nt = np.where(swap[:, None], n1, n2)
    d = np.where(swap[:, None], -d, d)
    f3 = np.where(swap, -a2, a1)
    v = np.cross(d, ns)
    v_norm = np.sqrt(_dot(v, v))
    v = v / np.where(v_norm > 0, v_norm, 1.0)[:, None]
    w = np.cross(ns, v)
    f2 = _dot(v, nt)
    f1 = np.arctan2(_dot(w, nt), _dot(ns, nt))
    out = np.column_stack([f1, f2, f3])
    out[(length == 0) | (v_norm == 0)] = 0.0
    return out


def _dot(a: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
    """Row-wise dot product summed left to right, the order Eigen uses for 3-vectors.

    The swap rule compares two nearly equal angles for pairs with near-identical normals; summing
    in the same order as Open3D keeps those ties resolving the same way.
    """
    return a[:, 0] * b[:, 0] + a[:, 1] * b[:, 1] + a[:, 2] * b[:, 2]


def feature_bins(features: NDArray[np.float64]) -> NDArray[np.intp]:
    """Histogram bins (P, 3) of pair features in 0..10: f1 over [−π, π], f2 and f3 over [−1, 1]."""
    scaled = np.column_stack(
        [
            N_BINS * (features[:, 0] + np.pi) / (2.0 * np.pi),
            N_BINS * (features[:, 1] + 1.0) * 0.5,
            N_BINS * (features[:, 2] + 1.0) * 0.5,
        ]
    )
    return np.clip(np.floor(scaled), 0, N_BINS - 1).astype(np.intp)


def compute_fpfh(
    cloud: PointCloud, config: FPFHConfig = FPFHConfig(), workers: int = -1
) -> NDArray[np.float64]:
    """FPFH descriptor of every point.

    Parameters
    ----------
    cloud
        Points (N, 3) with normals (N, 3); the normals' orientation matters (f1 and f3 are signed).
    config
        Hybrid neighbourhood (radius, max_nn).
    workers
        Threads for the neighbour search.

    Returns
    -------
    (N, 33) descriptors: three 11-bin sub-histograms (f1, f2, f3). A point without neighbours
    gets a zero row.
    """
    if not cloud.has_normals:
        raise InputError(
            "FPFH needs a cloud with normals (run estimate_normals first)", cloud.source
        )
    pts, nrm = cloud.points, cloud.normals
    n = len(pts)
    idx, dist = hybrid(pts, pts, config.radius, config.max_nn, workers=workers)
    # Exclude each point itself by index (a duplicate point may take the first column).
    rows = np.broadcast_to(np.arange(n)[:, None], idx.shape)
    pair = (idx >= 0) & (idx != rows)
    # If duplicates pushed the point itself out of its max_nn results, Open3D still drops the
    # first result; drop it too so that at most max_nn - 1 neighbours remain.
    extra = pair.sum(axis=1) > config.max_nn - 1
    pair[extra, 0] = False
    i, j = rows[pair], idx[pair]
    count = np.bincount(i, minlength=n)

    bins = feature_bins(pair_features(pts[i], nrm[i], pts[j], nrm[j]))
    incr = 100.0 / count[i]
    flat = (i[:, None] * N_FEATURES + bins + np.arange(3) * N_BINS).ravel()
    spfh = np.bincount(flat, weights=np.repeat(incr, 3), minlength=n * N_FEATURES).reshape(
        n, N_FEATURES
    )

    # Neighbours' SPFH weighted by 1/d²; coincident neighbours carry no weight (as Open3D).
    d2 = dist[pair] ** 2
    keep = d2 > 0
    W = sparse.csr_matrix((1.0 / d2[keep], (i[keep], j[keep])), shape=(n, n))
    weighted = np.asarray(W @ spfh).reshape(n, 3, N_BINS)
    total = weighted.sum(axis=2, keepdims=True)
    scale = np.divide(100.0, total, out=np.zeros_like(total), where=total != 0)
    return (weighted * scale).reshape(n, N_FEATURES) + spfh
