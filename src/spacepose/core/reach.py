"""Which returns of a frame are its surfaces (docs/methods.md §5.7): not the rows a driver writes
at the sensor's origin for a pixel or beam with no return, and not returns so far beyond the
frame's surfaces (a rendered Earth 400 km behind a target a few metres away) that they form no
surface at the frame's scale and no grid sized for it can number cells out to them.
"""

from __future__ import annotations

import numba
import numpy as np
from numpy.typing import ArrayLike, NDArray

from spacepose.core.cloud import PointCloud, as_points
from spacepose.core.threads import numba_threads

# Returns farther than this many times the frame's median range take no part in the clusters: a
# sensor samples them that many times more sparsely, and a cell of four median spacings holds
# three points of a surface facing it only out to about 2.3 times the median range, so they form
# no surface at this scale; and a grid fine enough for the near surfaces cannot number cells out
# to them (a rendered Earth 400 km behind a mock-up 1.2 m away).
_FARTHEST_RANGES = 100.0
# Fewest returns of a near group that puts a far one out of reach: as many as a tracked frame
# needs (the health check's default ``min_points``), not a few stray ones.
_GAP_RETURNS = 100
# Returns of the strided sample that splits a frame's ranges in two groups.
_SPLIT_SAMPLE = 16384


def returns(points: PointCloud | ArrayLike, workers: int = 1) -> NDArray[np.bool_]:
    """(N,) False for the points at the sensor's origin: the value many drivers write for a
    pixel or beam with no return (the real LiDAR pair of data/real holds 5,107 of 69,792);
    on ``workers`` threads (-1: all cores)."""
    valid, _ = _returns_and_extremes(np.ascontiguousarray(as_points(points)), workers)
    return valid


def within_reach(points: PointCloud | ArrayLike, workers: int = 1) -> NDArray[np.bool_]:
    """(N,) the returns (:func:`returns`) no farther than a hundred times the median range of
    the frame's returns (:data:`_FARTHEST_RANGES`) nor in a far group a hundredfold beyond a
    near one (:func:`_before_gap`), on ``workers`` threads (-1: all cores).

    The rest (a rendered Earth 400 km behind a mock-up 1.2 m away) is no surface at the
    frame's scale, and grids sized for its near surfaces cannot number cells out to it.
    """
    pts = np.ascontiguousarray(as_points(points))
    valid, (nearest, farthest) = _returns_and_extremes(pts, workers)
    # The median only when some return could lie beyond it (rarely: a 1280×720 frame's median
    # costs 10 ms, its extremes come with the returns' pass).
    if not farthest > _FARTHEST_RANGES * nearest:
        return valid
    ranges = np.sqrt(np.einsum("ij,ij->i", pts, pts))
    reach = _FARTHEST_RANGES * np.median(ranges[valid])
    return valid & (ranges <= min(reach, _before_gap(ranges[valid])))


def _before_gap(ranges: NDArray[np.float64]) -> float:
    """The range that splits the returns into a near and a far group whose medians lie more
    than a hundredfold apart (the split of least spread in log range, Otsu's on a histogram),
    when the near one holds at least :data:`_GAP_RETURNS` returns; inf otherwise.

    The median alone misses a far background that holds most of the returns: an Earth in 99 %
    of the view behind a satellite 8 m away was the median, and frames were lost ("cells ...
    too many to number"). Flying pixels between the two leave no empty gap in range. A near
    group of well under 1 % of the returns is not split off so (the split of least spread then
    falls within the far group).
    """
    # A strided sample finds the split (36 ms on 900,000 returns whole, under 2 ms so); the
    # near group is counted on all of them.
    logs = np.log10(ranges[:: max(1, len(ranges) // _SPLIT_SAMPLE)])
    counts, edges = np.histogram(logs, bins=256)
    below = np.cumsum(counts)[:-1]
    above = len(logs) - below
    sums = np.cumsum(counts * 0.5 * (edges[1:] + edges[:-1]))
    mean_below = sums[:-1] / np.maximum(below, 1)
    mean_above = (sums[-1] - sums[:-1]) / np.maximum(above, 1)
    k = int(np.argmax(below * above * (mean_above - mean_below) ** 2))
    cut = edges[k + 1]
    near, far = logs[logs <= cut], logs[logs > cut]
    if not len(far) or np.count_nonzero(ranges <= 10.0**cut) < _GAP_RETURNS:
        return np.inf
    apart = np.median(far) - np.median(near) > np.log10(_FARTHEST_RANGES)
    return float(10.0**cut) if apart else np.inf


def _returns_and_extremes(
    pts: NDArray[np.float64], workers: int
) -> tuple[NDArray[np.bool_], tuple[float, float]]:
    """The returns' mask (:func:`returns`) and the least and largest range among them (NaN,
    NaN without a return), in one compiled pass: the numpy ranges, their selection and their
    extremes took 7 ms of a 1280×720 frame."""
    out = np.empty(len(pts), dtype=np.bool_)
    lo = np.full(_EXTREME_BLOCKS, np.inf)
    hi = np.full(_EXTREME_BLOCKS, -np.inf)
    with numba_threads(workers):
        _returns_kernel(pts, out, lo, hi)
    if not np.isfinite(hi).any():
        return out, (np.nan, np.nan)
    # The square root of the extreme squares is the extreme range, to the bit (sqrt is
    # monotone and correctly rounded); min and max do not depend on the blocks' order.
    return out, (float(np.sqrt(lo.min())), float(np.sqrt(hi.max())))


# Fixed blocks of the extremes' pass, so that its work splits alike on any thread count.
_EXTREME_BLOCKS = 64


@numba.njit(cache=True, parallel=True)
def _returns_kernel(pts, out, lo, hi):
    n, blocks = len(pts), len(lo)
    for b in numba.prange(blocks):
        for i in range(b * n // blocks, (b + 1) * n // blocks):
            x, y, z = pts[i, 0], pts[i, 1], pts[i, 2]
            out[i] = x != 0.0 or y != 0.0 or z != 0.0
            if out[i]:
                r2 = x * x + y * y + z * z
                lo[b] = min(lo[b], r2)
                hi[b] = max(hi[b], r2)
