"""Which of a plane's points are a face (methods.md §2.1, §2.2): its connected part, its dense
connected region, and whether its inliers are a face at all or a slab cut through a curved
surface. Lengths come from the points themselves."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree

from spacepose.core.clusters import cluster_labels

# A plane whose inliers' own surface normals lie further than this from its normal, at the
# median, is a slab through a curved surface (cuts_a_curve): a face's lie within a few
# degrees, its edges' aside; a ring cut through a sphere at h from its centre, at acos(h/R).
_CURVED_DEG = 30.0
# Neighbours of an inlier that give its surface normal, and the most inliers asked.
_SURFACE_NEIGHBOURS = 10
_SURFACE_SAMPLE = 500
# A neighbourhood spans a surface when its middle spread (eigenvalue) is at least this share
# of its largest: ten points of a grid give 0.3-1, of a scan line or one point copied ~0.
_SURFACE_SPREAD = 0.05
# A neighbourhood reaches at least this many of the plane's own noise σ (its inliers' spread
# along its normal): ten neighbours of a 1 M-point plate lay within 1.5 mm under 1 mm of noise,
# their normals mostly noise, and the plate was taken for a cut through a curved surface.
_NOISE_REACH = 5.0
# Points a neighbourhood that reach gives holds at most, about (the cloud thinned by a stride).
_BALL_POINTS = 256
# A plane parallel to a face found before it within this angle, whose inliers lie within two
# of its slabs, may be that face's noise beyond its slab (is_a_tail).
_TAIL_DEG = 10.0


def largest_component(points: ArrayLike, radius: float) -> NDArray[np.intp]:
    """Indices (sorted) of the largest group of points connected by steps shorter than radius.

    Ties go to the group holding the lowest index, so the result is deterministic.
    """
    labels = cluster_labels(np.asarray(points, dtype=np.float64), radius)
    return np.flatnonzero(labels == np.argmax(np.bincount(labels)))


def dense_support(
    points: ArrayLike, normal: ArrayLike, k: int = 8, spread: float = 2.0
) -> NDArray[np.intp]:
    """Indices (sorted) of the dense connected region of a plane's points: the face itself.

    A RANSAC slab keeps every stray point that falls inside it, and those far from the face pull
    its distribution matrix (Y1's uniform outliers moved the sides by a centimetre). On the face
    the points lie at the sampling's spacing; strays inside the slab lie far sparser. In the
    plane's own coordinates each point's distance to its k-th neighbour measures the local
    spacing; the points whose spacing is at most ``spread`` times the median one are dense, and
    of them the largest group connected by steps of ``spread`` median spacings is kept. Every
    length comes from the points themselves. ``spread`` 2 keeps a face's edges (neighbours in a
    half disc: √2 times the spacing) and, on average, its corners (a quarter disc: twice), and
    drops strays more than about one spacing outside the edge. Measured on Y1-style clouds
    (10 × 18 cm, 1,250 points, 1,250 outliers in a box), with the ``random`` edge estimate of
    :func:`spacepose.core.rectangle_measurement.measure_rectangle`: sides 0.51 ± 0.43 and
    −0.20 ± 0.63 mm off and the centre 0.37 ± 0.20 mm off over 10 seeds (the whole slab: 8.4
    and 10.6 mm, 1.7 mm). Over 30 seeds, a ``spread`` of 2.5 keeps more strays along the long
    edges (short side up to 3.6 mm off) and 1.5 trims the face (long side 1.1 mm short on
    average).

    Parameters
    ----------
    points
        (K, 3) points of one plane (any frame, m), K > k.
    normal
        (3,) the plane's unit normal.
    k
        Neighbour rank of the spacing.
    spread
        Largest spacing of a dense point, in median spacings.

    Returns
    -------
    Indices into ``points``; all of them when there are k or fewer.
    """
    pts = np.asarray(points, dtype=np.float64)
    if len(pts) <= k:
        return np.arange(len(pts))
    n = np.asarray(normal, dtype=np.float64)
    helper = np.eye(3)[int(np.argmin(np.abs(n)))]
    u = np.cross(n, helper)
    u /= np.linalg.norm(u)
    uv = pts @ np.column_stack([u, np.cross(n, u)])
    # Spacings of the distinct places: copies of one row (a driver's mark written 2,000 times)
    # are no density, and a median spacing of 0 cut every link.
    places, place_of = np.unique(uv, axis=0, return_inverse=True)
    if len(places) <= k:
        return np.arange(len(pts))
    spacing = cKDTree(places).query(places, k=k + 1)[0][:, k][place_of.ravel()]
    step = spread * float(np.median(spacing))
    dense = np.flatnonzero(spacing <= step)
    return dense[largest_component(np.column_stack([uv[dense], np.zeros(len(dense))]), step)]


def cuts_a_curve(
    points: NDArray[np.float64], tree: cKDTree, inliers: NDArray[np.intp], normal: NDArray
) -> bool:
    """Whether a plane's inliers are a slab cut through a curved surface, not a face: the
    surface's own normals there (of each inlier's :data:`_SURFACE_NEIGHBOURS` nearest points
    in the whole cloud; a strided sample of at most :data:`_SURFACE_SAMPLE` inliers) lie more
    than :data:`_CURVED_DEG` from the plane's, at the median. A 5 mm slab through a 1 m
    sphere seen by a ToF camera took rings of ~100 points, reported as 1 x 1 m "planes".

    Only neighbourhoods that span a surface count (the middle of their three spreads at least
    :data:`_SURFACE_SPREAD` of the largest): a scan line's points, or copies of one point (a
    driver's mark of no return), have no normal of their own; with fewer than half such, no
    judgement (False)."""
    sample = inliers[:: max(1, len(inliers) // _SURFACE_SAMPLE)]
    k = min(_SURFACE_NEIGHBOURS, len(points))
    distance, idx = tree.query(points[sample], k=k)
    distance, idx = (np.asarray(a).reshape(len(sample), k) for a in (distance, idx))
    reach = _NOISE_REACH * float(np.std(points[inliers] @ normal))
    spread = float(np.median(distance[:, -1]))
    if reach > spread:
        # Denser than the noise: each neighbourhood reaches past it (at least k points), in a
        # strided share of the cloud when a ball would hold more than _BALL_POINTS (a surface:
        # k (reach / spread)² points), so that 10 M points under 1 cm of noise do not list
        # 10⁵ neighbours for each of 500 samples.
        # (Copies of one point as neighbours, a spread of 0: the whole cloud is one ball.)
        held = k * (reach / spread) ** 2 if spread > 0.0 else len(points)
        stride = max(1, int(held // _BALL_POINTS))
        near = points if stride == 1 else points[::stride]
        balls = (tree if stride == 1 else cKDTree(near)).query_ball_point(points[sample], reach)
        scatter = np.stack(
            [
                _scatter(near[g]) if len(g) >= k else _scatter(points[i])
                for g, i in zip(balls, idx, strict=True)
            ]
        )
    else:
        centred = points[idx] - points[idx].mean(axis=1, keepdims=True)
        scatter = np.einsum("mki,mkj->mij", centred, centred)
    spreads, axes = np.linalg.eigh(scatter)
    surface = spreads[:, 1] > _SURFACE_SPREAD * spreads[:, 2]
    if surface.sum() < 0.5 * len(sample):
        return False
    along = np.abs(axes[surface, :, 0] @ normal)
    return float(np.median(along)) < np.cos(np.radians(_CURVED_DEG))


def is_a_tail(
    points: NDArray[np.float64],
    tree: cKDTree,
    inliers: NDArray[np.intp],
    normal: NDArray,
    faces: list[tuple[NDArray, float, NDArray[np.intp]]],
    slab: float,
) -> bool:
    """Whether a plane's inliers are the noise tails of faces found before it: of the faces
    parallel to it within :data:`_TAIL_DEG` whose slab, twice widened, holds it at the median,
    most of its inliers (a strided sample of at most :data:`_SURFACE_SAMPLE`) have their
    nearest other point among those faces' inliers. A Gaussian's 0.27 % beyond ±3σ lie
    scattered over the face, among its points; a second face's own points neighbour each
    other. On a 100,000-point plate under 1 mm of noise the points beyond its 3 mm slab were
    taken for two more planes of 107–134 points at ±3 mm; between two plates a step apart the
    tails of both made one.

    Parameters
    ----------
    points
        (N, 3) the whole cloud; ``tree`` its k-d tree.
    inliers
        (M,) indices of the plane's inliers; ``normal`` (3,) its unit normal.
    faces
        ``(normal (3,), offset, inliers)`` of the faces found before it (``n·p = offset``).
    slab
        The planes' inlier distance (m).
    """
    sample = inliers[:: max(1, len(inliers) // _SURFACE_SAMPLE)]
    near = [
        face_inliers
        for face_normal, offset, face_inliers in faces
        if abs(float(normal @ face_normal)) >= np.cos(np.radians(_TAIL_DEG))
        and np.median(np.abs(points[sample] @ face_normal - offset)) <= 2.0 * slab
    ]
    if not near:
        return False
    _, idx = tree.query(points[sample], k=min(2, len(points)))
    nearest = np.asarray(idx).reshape(len(sample), -1)[:, -1]  # the first is the point itself
    return bool(np.isin(nearest, np.concatenate(near)).mean() > 0.5)


def _scatter(points: NDArray[np.float64]) -> NDArray[np.float64]:
    """(3, 3) scatter matrix of (N, 3) points about their mean."""
    centred = points - points.mean(axis=0)
    return centred.T @ centred
