"""Correspondences of ICP: the nearest target point of each source point within a gate, and
what an update needs at one transform (methods.md §1.5, Li Eq. 7).

:func:`find_correspondences` searches once; :class:`CorrespondenceSearch` searches again for the
same source points moved between calls, skipping the points whose nearest target is certain.
The matchers :class:`Matcher` (any search index) and :class:`FusedPlaneMatcher` (point-to-plane
on a :class:`~spacepose.core.grid.VoxelIndex`, in one compiled pass) move the (N, 3) source
points by a ``T_target_source`` (4, 4), match them and return :class:`Correspondences`: indices
(M,), fitness, RMSE (m) and the matched points in the target frame or the point-to-plane normal
equations of :mod:`spacepose.core.icp_systems`, IRLS-weighted when a robust kernel is on. Fewer
than three matches raise :class:`~spacepose.errors.RegistrationError`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from spacepose.core import se3
from spacepose.core.cloud import PointCloud
from spacepose.core.grid import VoxelIndex
from spacepose.core.icp_systems import (
    SYSTEM_CHUNK,
    plane_matches_kernel,
    point_to_plane_system,
    robust_plane_kernel,
    system_from_sums,
)
from spacepose.core.neighbors import SearchIndex, hybrid
from spacepose.core.robust import (
    KERNEL_CODES,
    RobustConfig,
    RobustWeights,
    kernel_width,
    robust_weights,
    sandwich_variance,
)
from spacepose.core.threads import numba_threads
from spacepose.errors import RegistrationError

# Fewest query points for which CorrespondenceSearch lets the tree search use several threads.
_THREADED_QUERY_MIN = 2048


def find_correspondences(
    tree: SearchIndex,
    points: NDArray[np.float64],
    max_distance: float,
    workers: int = -1,
    hint: NDArray[np.int64] | None = None,
) -> tuple[NDArray[np.intp], NDArray[np.intp], NDArray[np.float64]]:
    """Nearest target point strictly within ``max_distance`` of each query point.

    Parameters
    ----------
    tree
        Search index of the target points.
    points
        (N, 3) source points already mapped into the target frame.
    max_distance
        Correspondence gate (m).
    workers
        Threads for the search.
    hint
        (N,) a target index near each point (-1: none), e.g. its last match: it only bounds
        a :class:`VoxelIndex` search (ignored by a cKDTree); the answer does not depend on it.

    Returns
    -------
    src_idx, tgt_idx, dist2
        (M,) indices of the matched source points, (M,) indices of their target points and
        (M,) squared distances.
    """
    if isinstance(tree, VoxelIndex):
        nearest, d2 = tree.nearest_within(points, max_distance, hint, workers=workers)
        src = np.flatnonzero(nearest >= 0)
        return src, nearest[src], d2[src]
    idx, dist = hybrid(tree, points, max_distance, 1, workers=workers)
    ok = idx[:, 0] >= 0
    return np.flatnonzero(ok), idx[ok, 0], dist[ok, 0] ** 2


class CorrespondenceSearch:
    """:func:`find_correspondences` for the same source points moved between calls.

    Each point remembers where it was last searched in the tree, its nearest target ``t`` then
    and the distance ``r`` of the second nearest (or twice the gate when there is none within
    it). A point that has since moved by ``δ`` still has ``t`` as its nearest target when
    ``|x − t| < r − δ``, since every other target is at least ``r − δ`` away (triangle
    inequality), and it certainly has no correspondence when ``|x − t|`` and ``r − δ`` both reach
    the gate. Only the other points are searched again (two nearest), so the late iterations,
    which move points by micrometres, cost a fraction of a search. The answer is the tree's (but
    for a distance equal to the gate to the last bit): a certified target is strictly nearer
    than every other one. GICP (tens of iterations) gains most.

    On a :class:`~spacepose.core.grid.VoxelIndex` the certificate is not needed: each point's
    compiled search simply starts at its last match (a cell or two after a small move), which
    costs less than the bookkeeping above. The certificate serves a ``cKDTree`` passed in.

    Parameters
    ----------
    tree
        Search index of the target points.
    max_distance
        Correspondence gate (m).
    workers
        Threads for the tree searches.
    """

    def __init__(self, tree: SearchIndex, max_distance: float, workers: int = -1) -> None:
        self.tree = tree
        self.max_distance = float(max_distance)
        self.workers = workers
        self._reach = 2.0 * self.max_distance
        self._data_scale = float(np.abs(tree.data).max())
        self._anchor = np.empty((0, 3))
        self._nearest = np.empty(0, dtype=np.intp)
        self._second = np.empty(0)

    def __call__(
        self, points: NDArray[np.float64]
    ) -> tuple[NDArray[np.intp], NDArray[np.intp], NDArray[np.float64]]:
        """Same outputs as :func:`find_correspondences` for the (N, 3) query points."""
        n = len(points)
        if isinstance(self.tree, VoxelIndex):
            # Its compiled search, warm-started at each point's last nearest, costs less than
            # the certificate bookkeeping below.
            hint = self._nearest if len(self._nearest) == n else None
            self._nearest, d2 = self.tree.nearest_within(
                points, self.max_distance, hint, self.workers
            )
            src = np.flatnonzero(self._nearest >= 0)
            return src, self._nearest[src], d2[src]
        if len(self._anchor) != n:
            # Nothing known: a zero bound leaves every point to the tree.
            self._anchor = np.array(points, dtype=np.float64)
            self._nearest = np.full(n, -1, dtype=np.intp)
            self._second = np.zeros(n)
        known = self._nearest >= 0
        diff = self.tree.data[np.where(known, self._nearest, 0)] - points
        dist = np.where(known, np.sqrt(np.einsum("ni,ni->n", diff, diff)), np.inf)
        step = points - self._anchor
        # Rounding in the distances (relative to the coordinates) must not fake a certificate.
        slack = 1e-12 * (1.0 + self._data_scale + float(np.abs(points).max()))
        bound = self._second - np.sqrt(np.einsum("ni,ni->n", step, step)) - slack
        gate = self.max_distance
        certain = np.where(dist < gate, dist < bound, gate <= bound)
        unsure = np.flatnonzero(~certain)
        if len(unsure):
            # A handful of points does not pay for starting threads.
            workers = self.workers if len(unsure) >= _THREADED_QUERY_MIN else 1
            d, idx = self.tree.query(
                points[unsure], k=2, distance_upper_bound=self._reach, workers=workers
            )
            found = idx < self.tree.n
            self._anchor[unsure] = points[unsure]
            self._nearest[unsure] = np.where(found[:, 0], idx[:, 0], -1)
            self._second[unsure] = np.where(found[:, 1], d[:, 1], self._reach)
            dist[unsure] = d[:, 0]
        src = np.flatnonzero(dist < gate)
        tgt = self._nearest[src]
        diff = self.tree.data[tgt] - points[src]
        return src, tgt, np.einsum("ni,ni->n", diff, diff)


@dataclass(frozen=True)
class Correspondences:
    """The correspondences of ICP at one transform and what an update from there needs.

    Attributes
    ----------
    src_idx, tgt_idx
        (M,) matched source points and their nearest target points.
    fitness, rmse
        Share of source points matched; RMSE (m) of the match distances (unweighted).
    points
        (M, 3) matched source points in the target frame (point-to-point and robust paths).
    system
        Point-to-plane only: ``(H, g, sse)`` of
        :func:`~spacepose.core.icp_systems.point_to_plane_system` at the matches (information,
        gradient, Σ r²), weighted by ``weights`` when a robust kernel is on.
    weights
        The robust kernel's IRLS weights of the matches and their σ; None without a kernel.
    residual_sigma
        With a robust kernel, the σ (m) that turns the weighted information into a covariance:
        :meth:`~spacepose.core.robust.RobustWeights.variance` of the point-to-plane distances
        (6 parameters; ``√(Σ r² / (M − 6))`` for unit weights), or of the point-to-point
        distances with no parameter count (the inlier RMSE for unit weights, as the unweighted
        result uses); None without a kernel.
    """

    src_idx: NDArray[np.intp]
    tgt_idx: NDArray[np.intp]
    fitness: float
    rmse: float
    points: NDArray[np.float64] | None = None
    system: tuple[NDArray[np.float64], NDArray[np.float64], float] | None = None
    weights: RobustWeights | None = None
    residual_sigma: float | None = None

    @property
    def weight_values(self) -> NDArray[np.float64] | None:
        """(M,) IRLS weights, or None without a robust kernel."""
        return None if self.weights is None else self.weights.weights


def _checked(n_matched: int, n_source: int, gate: float) -> None:
    if n_matched < 3:
        raise RegistrationError(
            f"ICP found {n_matched} correspondences within {gate:.3g} m (of {n_source} source "
            "points); the initial guess is too far off or the gate too small"
        )


def _robust_matches(
    config: RobustConfig,
    s: NDArray[np.intp],
    t: NDArray[np.intp],
    fitness: float,
    rmse: float,
    points: NDArray[np.float64],
    target_points: NDArray[np.float64],
    normals: NDArray[np.float64] | None,
) -> Correspondences:
    """:class:`Correspondences` of the matches ``s → t`` weighted by ``config``'s kernel.

    ``points`` (M, 3) are the moved source points, ``target_points`` (M, 3) their targets and
    ``normals`` the targets' normals (point-to-plane) or None (point-to-point)."""
    diff = points - target_points
    if normals is None:
        d = np.sqrt(np.einsum("ni,ni->n", diff, diff))
        w = robust_weights(d, config.robust_kernel, config.robust_scale)
        return Correspondences(s, t, fitness, rmse, points, None, w, np.sqrt(w.variance(d, 0)))
    r = np.einsum("ni,ni->n", diff, normals)
    w = robust_weights(r, config.robust_kernel, config.robust_scale)
    # One thread: the gathered rows are summed (0.1 ms for 6000) before a second thread wakes.
    system = point_to_plane_system(points, target_points, normals, 1, w.weights)
    return Correspondences(s, t, fitness, rmse, points, system, w, np.sqrt(w.variance(r)))


class Matcher:
    """Correspondences at a transform through :class:`CorrespondenceSearch` (any index)."""

    def __init__(
        self,
        tree: SearchIndex,
        target: PointCloud,
        source_points: NDArray[np.float64],
        gate: float,
        plane: bool,
        config: RobustConfig,
        workers: int,
    ) -> None:
        self.search = CorrespondenceSearch(tree, gate, workers)
        self.target, self.source_points, self.gate, self.plane = target, source_points, gate, plane
        self.config, self.workers = config, workers

    def __call__(self, T: NDArray[np.float64]) -> Correspondences:
        moved = se3.transform_points(T, self.source_points)
        s, t, d2 = self.search(moved)
        _checked(len(s), len(moved), self.gate)
        p = np.take(moved, s, axis=0)
        fitness, rmse = len(s) / len(moved), float(np.sqrt(d2.mean()))
        normals = self.target.normals[t] if self.plane else None
        if self.config.robust_kernel != "none":
            q = self.target.points[t]
            return _robust_matches(self.config, s, t, fitness, rmse, p, q, normals)
        system = None
        if self.plane:
            system = point_to_plane_system(p, self.target.points[t], normals)
        return Correspondences(s, t, fitness, rmse, p, system)


class FusedPlaneMatcher:
    """Point-to-plane correspondences and normal equations at a transform in one compiled pass
    over a :class:`VoxelIndex` (no moved copy of the cloud, no gathered rows): about half the
    time of the generic path per iteration on a lab frame. Each point's search starts at its
    previous match, and is skipped while the certificate of its last search still holds (the
    late iterations move points by micrometres): 1.6× less time over the lab tracker's
    registrations (1.2-1.9× each), the same bits. With a robust kernel the pass stores the
    moved points instead, and the weighted sums follow once the residuals' scale is known."""

    def __init__(
        self,
        index: VoxelIndex,
        normals: NDArray[np.float64],
        source_points: NDArray[np.float64],
        gate: float,
        config: RobustConfig,
        workers: int,
    ) -> None:
        self.index, self.gate, self.config, self.workers = index, float(gate), config, workers
        self.rings = index.rings(gate)
        self.normals = np.ascontiguousarray(normals, dtype=np.float64)
        self.source_points = np.ascontiguousarray(source_points, dtype=np.float64)
        self.nearest = np.full(len(source_points), -1, dtype=np.int64)
        # Each point's last search: where it was made and its certificate (0: none yet).
        self.anchors = np.zeros((len(source_points), 3))
        self.bounds = np.zeros(len(source_points))

    def __call__(self, T: NDArray[np.float64]) -> Correspondences:
        n = len(self.source_points)
        robust = self.config.robust_kernel != "none"
        partial = np.zeros((max(1, -(-n // SYSTEM_CHUNK)), 30))
        nearest = np.empty(n, dtype=np.int64)
        moved = np.empty((n if robust else 0, 3))
        residuals = np.empty(n if robust else 0)
        with numba_threads(self.workers):
            plane_matches_kernel(
                self.index.kernel_grid,
                self.rings,
                self.index.data,
                self.normals,
                self.source_points,
                np.ascontiguousarray(T[:3, :3]),
                np.ascontiguousarray(T[:3, 3]),
                self.gate,
                self.nearest,
                nearest,
                self.anchors,
                self.bounds,
                moved,
                residuals,
                partial,
            )
        self.nearest = nearest
        total = partial.sum(axis=0)
        count = int(total[28])
        _checked(count, n, self.gate)
        s = np.flatnonzero(nearest >= 0)
        t = nearest[s]
        rmse = float(np.sqrt(total[29] / count))
        if robust:
            return self._weighted(s, t, count / n, rmse, moved, residuals)
        H, g = system_from_sums(total)
        return Correspondences(s, t, count / n, rmse, system=(H, g, float(total[27])))

    def _weighted(
        self,
        s: NDArray[np.intp],
        t: NDArray[np.intp],
        fitness: float,
        rmse: float,
        moved: NDArray[np.float64],
        residuals: NDArray[np.float64],
    ) -> Correspondences:
        """:func:`_robust_matches` of the pass's stored matches, weighed and summed compiled."""
        r = residuals[s]
        sigma, c = kernel_width(r, self.config.robust_kernel, self.config.robust_scale)
        n = len(moved)
        w, slopes = np.empty(n), np.empty(n)
        partial = np.zeros((max(1, -(-n // SYSTEM_CHUNK)), 30))
        with numba_threads(self.workers):
            robust_plane_kernel(
                moved,
                self.index.data,
                self.normals,
                self.nearest,
                residuals,
                c,
                KERNEL_CODES[self.config.robust_kernel] if c > 0.0 else 0,
                w,
                slopes,
                partial,
            )
        total = partial.sum(axis=0)
        H, g = system_from_sums(total)
        weights = RobustWeights(w[s], sigma, slopes[s])
        variance = sandwich_variance(float(total[28]), weights.total, float(total[29]), len(s))
        system = (H, g, float(total[27]))
        # np.take: a fifth of the time of moved[s] for (N, 3) rows (63 -> 13 µs at 5000).
        points = np.take(moved, s, axis=0)
        return Correspondences(s, t, fitness, rmse, points, system, weights, np.sqrt(variance))
