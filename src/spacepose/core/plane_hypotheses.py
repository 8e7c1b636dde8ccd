"""RANSAC hypotheses of one plane (methods.md §2.1): how many a confidence asks, the one with
most inliers, and the face inside a slab that cuts across two surfaces.

Points are (N, 3) in any one frame, lengths in metres.
"""

from __future__ import annotations

import math
import sys
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from spacepose.core import ransac
from spacepose.core.moments import distribution, fit_plane, is_collinear
from spacepose.core.plane_support import largest_component
from spacepose.core.ransac import sample_triples
from spacepose.core.scale import point_spacing
from spacepose.errors import DegenerateGeometryError

if TYPE_CHECKING:
    from spacepose.core.planes import PlaneConfig

# Largest number of distances held at once when scoring a batch (32 MB of float64).
_SCORE_BLOCK = 1 << 22


def iteration_bound(confidence: float, outlier_ratio: float) -> int:
    """RANSAC iterations ``ceil(log(1 − p) / log(1 − (1 − ε)³))`` for a 3-point sample (Yu §2.1)."""
    bound = ransac.iteration_bound(1.0 - outlier_ratio, confidence)
    # Inliers too rare to bound anything: the caller's max_iterations decides.
    return max(1, math.ceil(bound)) if math.isfinite(bound) else sys.maxsize


def count_inliers(
    points: NDArray[np.float64],
    normals: NDArray[np.float64],
    offsets: NDArray[np.float64],
    threshold: float,
) -> NDArray[np.intp]:
    """Inlier counts (B,) of B planes, scoring the points in chunks of a (B, chunk) matrix."""
    counts = np.zeros(len(normals), dtype=np.intp)
    chunk = max(1, _SCORE_BLOCK // max(len(normals), 1))
    for start in range(0, len(points), chunk):
        d = np.abs(normals @ points[start : start + chunk].T - offsets[:, None])
        counts += np.count_nonzero(d <= threshold, axis=1)
    return counts


# A plane's inliers whose spread along its normal is this share or more of a uniform spread
# over its slab (threshold / √3) fill the slab: a face under noise within a 3σ slab gives
# 0.57 (0.986σ), a cut across two surfaces about 1.
_SLAB_FILLED = 0.8
# Largest tilt (deg) of a cut from the faces it leans across: a step between parallel plates
# tilts it by its height over their width (1 cm over 0.6 m: 1.4°).
_CUT_TILT_DEG = 10.0


def best_hypothesis(
    pts: NDArray[np.float64], config: PlaneConfig, rng: np.random.Generator, threshold: float
) -> NDArray[np.intp]:
    """Inliers (indices into ``pts``, within ``threshold``) of the RANSAC hypothesis with most."""
    n_hyp = config.max_iterations
    if config.outlier_ratio is not None:
        n_hyp = min(n_hyp, iteration_bound(config.confidence, config.outlier_ratio))
    best_count, best_normal, best_offset = -1, None, 0.0
    for start in range(0, n_hyp, config.batch_size):
        triples = sample_triples(rng, len(pts), min(config.batch_size, n_hyp - start))
        p0, p1, p2 = pts[triples[:, 0]], pts[triples[:, 1]], pts[triples[:, 2]]
        e1, e2 = p1 - p0, p2 - p0
        cross = np.cross(e1, e2)
        norm = np.linalg.norm(cross, axis=1)
        scale = np.linalg.norm(e1, axis=1) * np.linalg.norm(e2, axis=1)
        valid = norm > 1e-9 * np.maximum(scale, 1e-300)
        if not np.any(valid):
            continue
        normals = cross[valid] / norm[valid, None]
        offsets = np.einsum("bi,bi->b", normals, p0[valid])
        counts = count_inliers(pts, normals, offsets, threshold)
        k = int(np.argmax(counts))  # first maximum: ties go to the earliest hypothesis
        if counts[k] > best_count:
            best_count, best_normal, best_offset = int(counts[k]), normals[k], offsets[k]
    if best_normal is None or best_count < 3:
        raise DegenerateGeometryError(
            f"no plane with 3 inliers among {n_hyp} hypotheses on {len(pts)} points"
        )
    return np.flatnonzero(np.abs(pts @ best_normal - best_offset) <= threshold)


def spread(pts: NDArray[np.float64], inliers: NDArray[np.intp]) -> float:
    """Standard deviation of the points along the normal of their least-squares plane."""
    if len(inliers) < 3:
        return np.inf
    normal, offset = fit_plane(pts[inliers])
    return float(np.std(pts[inliers] @ normal - offset))


def one_face(
    pts: NDArray[np.float64], inliers: NDArray[np.intp], config: PlaneConfig
) -> NDArray[np.intp]:
    """The inliers of the face in a plane that fills its slab (:func:`fills_its_slab`).

    A cut across two surfaces (a step between parallel plates, tilted to hold both) spreads
    its inliers evenly over the slab where a face's crowd its middle. Two planes may be the
    face's: the one through the cut's largest part connected by steps of three point spacings
    (the strips on either side of a step lie apart by its height), and the best hypothesis at
    half the slab, where a face beats the cut. Of the cut and those within
    :data:`_CUT_TILT_DEG` of it whose inliers (within the whole slab) do not fill it in turn,
    the inliers that spread least along their normal are kept: a slab through a curved surface
    also fills its slab, and a tangent cap found instead of it passed for a plane.
    """
    threshold = config.distance_threshold
    parts = largest_component(pts[inliers], 3.0 * point_spacing(pts[inliers]))
    # Its own draws: the search's stream goes on as if this were not tried, so a cut kept as
    # it was leaves every later plane as it was.
    thinner = best_hypothesis(pts, config, np.random.default_rng([config.seed, 1]), threshold / 2)
    candidates = [inliers[parts], thinner]
    cut_normal = fit_plane(pts[inliers])[0]
    best, best_spread = inliers, spread(pts, inliers)
    for support in candidates:
        if len(support) < 3 or is_collinear(distribution(pts[support])[1]):
            continue
        normal, offset = fit_plane(pts[support])
        if abs(float(normal @ cut_normal)) < np.cos(np.radians(_CUT_TILT_DEG)):
            continue  # not a face the cut leans across
        again = np.flatnonzero(np.abs(pts @ normal - offset) <= threshold)
        # A face crowds the middle of its slab; another slab through a curve fills it too.
        again_spread = spread(pts, again)
        if again_spread < best_spread and not fills_its_slab(pts, again, threshold):
            best, best_spread = again, again_spread
    return best


def fills_its_slab(pts: NDArray[np.float64], inliers: NDArray[np.intp], threshold: float) -> bool:
    """Whether the inliers spread over their slab as evenly as a uniform layer would."""
    return spread(pts, inliers) >= _SLAB_FILLED * threshold / math.sqrt(3.0)
