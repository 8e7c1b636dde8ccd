"""Fast Point Feature Histograms (METHODS §1.3; Rusu et al. 2009; Li §2.3.1).

The definition follows Open3D's ``compute_fpfh_feature`` number for number (bin edges, the swap
rule, the 1/d² weighting, the per-sub-histogram scaling to 100), so the two can be compared
directly. Everything is computed on flat arrays of (point, neighbour) pairs, one block of points
at a time: the histograms with ``np.bincount`` and the weighted neighbour sum as one sparse
matrix product.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import Field, PositiveFloat
from scipy import sparse
from scipy.spatial import cKDTree

from spacepose.core.cloud import PointCloud, as_cloud
from spacepose.core.config import StageConfig
from spacepose.core.neighbors import hybrid
from spacepose.errors import InputError

N_BINS = 11
N_FEATURES = 3 * N_BINS
# compute_fpfh: (point, neighbour) pairs per block of points (the bound on the pair memory); pairs
# per chunk of the feature arithmetic (about 400 kB per array: fastest of 4k..64k measured);
# points probed for the neighbour counts; share of probes over max_nn above which the radius
# search is not used.
_PAIRS_PER_BLOCK = 262144
_PAIRS_PER_CHUNK = 16384
_PROBE_POINTS = 64
_RADIUS_SEARCH_MAX_CAPPED = 0.2


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
    v = _cross(d, ns)
    v_norm = np.sqrt(_dot(v, v))
    v = v / np.where(v_norm > 0, v_norm, 1.0)[:, None]
    w = _cross(ns, v)
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


def _cross(a: NDArray[np.float64], b: NDArray[np.float64]) -> NDArray[np.float64]:
    """Row-wise cross product (P, 3), with np.cross's arithmetic but without its axis handling."""
    out = np.empty_like(a)
    out[:, 0] = a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1]
    out[:, 1] = a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2]
    out[:, 2] = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
    return out


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
    cloud: PointCloud | ArrayLike, config: FPFHConfig = FPFHConfig(), workers: int = -1
) -> NDArray[np.float64]:
    """FPFH descriptor of every point.

    Parameters
    ----------
    cloud
        Points (N, 3) with normals (N, 3); the normals' orientation matters (f1 and f3 are signed).
        An (N, 3) array is taken as a cloud without normals, which is refused with a clear
        :class:`~spacepose.errors.InputError` (estimate them with ``estimate_normals``, which
        takes the same array).
    config
        Hybrid neighbourhood (radius, max_nn).
    workers
        Threads for the neighbour search.

    Returns
    -------
    (N, 33) descriptors: three 11-bin sub-histograms (f1, f2, f3). A point without neighbours
    gets a zero row.

    Notes
    -----
    The points are processed in blocks, sized from the neighbour counts of a few probe points,
    so that the memory is bounded by the (N, 33) histograms, the sparse 1/d² weight matrix
    (12 bytes per pair) and one block's pairs, whatever the cloud size. When few points have
    more than ``max_nn − 1`` neighbours in the radius, a block's neighbours come from one
    dual-tree radius search (about three times faster than a k-nearest search with a bound)
    and only those few are searched again for their ``max_nn`` nearest, as Open3D keeps them;
    otherwise every point gets the k-nearest search.
    """
    cloud = as_cloud(cloud, "cloud")
    if not cloud.has_normals:
        raise InputError(
            "FPFH needs a cloud with normals (run estimate_normals first)", cloud.source
        )
    pts, nrm = cloud.points, cloud.normals
    n = len(pts)
    tree = cKDTree(pts)
    probe = np.unique(np.linspace(0, n - 1, min(n, _PROBE_POINTS)).astype(np.intp))
    in_radius = tree.query_ball_point(pts[probe], config.radius, return_length=True)
    # Points over the cap need a k-nearest search on top of the radius search: past a share of
    # them (measured break-even near 30 %), the k-nearest search alone is cheaper.
    radius_search = np.mean(in_radius > config.max_nn) <= _RADIUS_SEARCH_MAX_CAPPED
    per_row = float(np.mean(in_radius if radius_search else np.minimum(in_radius, config.max_nn)))
    # Big blocks: every search call has a fixed cost (threads, a tree for the radius search).
    block_rows = int(np.clip(_PAIRS_PER_BLOCK / max(per_row, 1.0), 16, 4096))
    spfh = np.empty((n, N_FEATURES))
    # Rows of the sparse weight matrix, built block by block in row order (CSR directly).
    index_dtype = np.int32 if n * config.max_nn < 2**31 else np.int64
    row_counts, columns, weights = np.zeros(n, dtype=index_dtype), [], []
    for start in range(0, n, block_rows):
        block = np.arange(start, min(start + block_rows, n))
        i, j, d2 = _block_pairs(tree, block, config, radius_search, workers)
        spfh[block] = _spfh(pts, nrm, i, j, len(block), start)
        # Neighbours' SPFH weighted by 1/d²; coincident neighbours carry no weight (as Open3D).
        keep = d2 > 0
        row_counts[block] = np.bincount(i[keep] - start, minlength=len(block))
        columns.append(j[keep].astype(index_dtype))
        weights.append(1.0 / d2[keep])
    indptr = np.concatenate([np.zeros(1, index_dtype), np.cumsum(row_counts, dtype=index_dtype)])
    W = sparse.csr_matrix((np.concatenate(weights), np.concatenate(columns), indptr), (n, n))
    weighted = np.asarray(W @ spfh).reshape(n, 3, N_BINS)
    total = weighted.sum(axis=2, keepdims=True)
    scale = np.divide(100.0, total, out=np.zeros_like(total), where=total != 0)
    return (weighted * scale).reshape(n, N_FEATURES) + spfh


def _block_pairs(
    tree: cKDTree, block: NDArray[np.intp], config: FPFHConfig, radius_search: bool, workers: int
) -> tuple[NDArray[np.intp], NDArray[np.intp], NDArray[np.float64]]:
    """(point, neighbour) pairs of a block of points, self excluded, as Open3D's hybrid search.

    Returns the point indices i (ascending), neighbour indices j and squared distances of the
    pairs.
    """
    pts = tree.data
    if not radius_search:
        idx, dist = hybrid(tree, pts[block], config.radius, config.max_nn, workers=workers)
        i, j, dist = _neighbour_pairs(block, idx, dist, config.max_nn)
        return i, j, dist**2
    found = cKDTree(pts[block]).sparse_distance_matrix(tree, config.radius, output_type="ndarray")
    i, j, dist = found["i"] + block[0], found["j"], found["v"]
    # Strictly inside the radius as the k-nearest search with a bound; self excluded.
    keep = (dist < config.radius) & (i != j)
    i, j, dist = i[keep], j[keep], dist[keep]
    over = np.bincount(i - block[0], minlength=len(block)) > config.max_nn - 1
    if np.any(over):
        keep = ~over[i - block[0]]
        capped = block[over]
        idx, cdist = hybrid(tree, pts[capped], config.radius, config.max_nn, workers=workers)
        ci, cj, cd = _neighbour_pairs(capped, idx, cdist, config.max_nn)
        i, j = np.concatenate([i[keep], ci]), np.concatenate([j[keep], cj])
        dist = np.concatenate([dist[keep], cd])
    # Row order (a radix sort of the 16-bit block rows): the later gathers and histogram sums
    # then walk memory in order.
    order = np.argsort((i - block[0]).astype(np.int16), kind="stable")
    return i[order], j[order], dist[order] ** 2


def _neighbour_pairs(
    rows: NDArray[np.intp], idx: NDArray[np.intp], dist: NDArray[np.float64], max_nn: int
) -> tuple[NDArray[np.intp], NDArray[np.intp], NDArray[np.float64]]:
    """(point, neighbour) pairs of hybrid-search results (max_nn nearest, self included).

    Returns the point indices i, neighbour indices j and distances of the pairs.
    """
    own = np.broadcast_to(rows[:, None], idx.shape)
    # Exclude each point itself by index (a duplicate point may take the first column).
    pair = (idx >= 0) & (idx != own)
    # If duplicates pushed the point itself out of its max_nn results, Open3D still drops the
    # first result; drop it too so that at most max_nn - 1 neighbours remain.
    extra = pair.sum(axis=1) > max_nn - 1
    pair[extra, 0] = False
    return own[pair], idx[pair], dist[pair]


def _spfh(
    pts: NDArray[np.float64],
    nrm: NDArray[np.float64],
    i: NDArray[np.intp],
    j: NDArray[np.intp],
    n_rows: int,
    first: int,
) -> NDArray[np.float64]:
    """Simplified point feature histograms (n_rows, 33) of points ``first .. first + n_rows``.

    Each sub-histogram of a point with neighbours sums to 100 (Open3D's scaling).
    """
    local = i - first
    incr = 100.0 / np.bincount(local, minlength=n_rows)[local]  # per pair: 100 / its row's count
    out = np.zeros((n_rows, N_FEATURES))
    # Chunks of pairs keep the temporaries in cache; the pairs are in row order, so a chunk
    # covers the rows local[c] .. local[end - 1] only.
    for c in range(0, len(i), _PAIRS_PER_CHUNK):
        chunk = slice(c, c + _PAIRS_PER_CHUNK)
        a, b, rows = i[chunk], j[chunk], local[chunk]
        bins = feature_bins(pair_features(pts[a], nrm[a], pts[b], nrm[b]))
        r0, r1 = rows[0], rows[-1] + 1
        flat = ((rows - r0)[:, None] * N_FEATURES + bins + np.arange(3) * N_BINS).ravel()
        counts = np.bincount(
            flat,
            weights=np.repeat(incr[chunk], 3),
            minlength=(r1 - r0) * N_FEATURES,
        )
        out[r0:r1] += counts.reshape(r1 - r0, N_FEATURES)
    return out
