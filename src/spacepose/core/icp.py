"""Iterative closest point: point-to-point and point-to-plane (methods.md §1.5, Li Eqs. 6–7).

The loop follows Open3D's ``registration_icp`` step for step so that point-to-point results can
be checked against it: correspondences are the nearest target point strictly within the maximum
distance, the update is estimated from them, the transform is composed on the left, the
correspondences are searched again, and the loop stops when both the fitness and the inlier RMSE
change by less than their tolerances. Fitness, RMSE and the information matrix are those of the
last correspondence search, i.e. of the returned transform.

Unlike Open3D, an iteration that finds fewer than three correspondences raises
:class:`~spacepose.errors.RegistrationError` rather than returning the identity.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numba
import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import Field
from scipy.spatial import cKDTree

from spacepose.core import se3
from spacepose.core.cloud import PointCloud, check_rows
from spacepose.core.grid import VoxelIndex, move_and_match, numba_threads
from spacepose.core.neighbors import SearchIndex, hybrid
from spacepose.core.normals import NormalsConfig, estimate_normals
from spacepose.core.registration import RegistrationResult, kabsch
from spacepose.core.robust import (
    KERNEL_CODES,
    RobustConfig,
    RobustWeights,
    kernel_width,
    robust_weights,
    sandwich_variance,
    weight_and_slope,
)
from spacepose.errors import DegenerateGeometryError, InputError, RegistrationError

# Smallest/largest eigenvalue ratio of a Gauss-Newton system below which a direction is
# considered unconstrained (a plane, a cylinder): solving it would return noise, not a pose.
_DEGENERATE_RATIO = 1e-12
# Fewest query points for which CorrespondenceSearch lets the tree search use several threads.
_THREADED_QUERY_MIN = 2048
# Rows per chunk of the compiled point-to-plane sums (fixed, so the sum order is too).
_SYSTEM_CHUNK = 512


class ICPConfig(RobustConfig):
    """Parameters of :func:`icp`.

    Attributes
    ----------
    max_correspondence_distance
        Largest source-to-target distance (m) of a correspondence.
    max_iterations
        Largest number of updates.
    relative_fitness, relative_rmse
        Stop when the fitness and the inlier RMSE (m) both change by less than these between two
        iterations (Open3D's ``ICPConvergenceCriteria``; despite the name the change is absolute).
    method
        ``"point_to_point"`` (closed-form Kabsch update) or ``"point_to_plane"`` (one
        Gauss-Newton step on SE(3) per iteration).
    normals
        Neighbourhood of the target normals point-to-plane estimates when the target has none.
    robust_kernel, robust_scale
        IRLS kernel on the residuals (point-to-plane: the signed normal distance;
        point-to-point: the Euclidean distance) and its σ (m; None: adaptive), see
        :mod:`spacepose.core.robust`. ``"none"`` is plain least squares.
    """

    max_correspondence_distance: float = Field(0.05, gt=0)
    max_iterations: int = Field(30, ge=1)
    relative_fitness: float = Field(1e-6, ge=0)
    relative_rmse: float = Field(1e-6, ge=0)
    method: Literal["point_to_point", "point_to_plane"] = "point_to_point"
    normals: NormalsConfig = NormalsConfig()


def as_registration_cloud(cloud: PointCloud | ArrayLike, name: str) -> PointCloud:
    """Validate a registration input: a :class:`PointCloud` or (N, 3) array with >= 3 points."""
    pc = cloud if isinstance(cloud, PointCloud) else PointCloud(cloud, source=name)
    if len(pc) < 3:
        raise InputError(f"{name} cloud needs at least 3 points for a rigid fit, got {len(pc)}")
    return pc


def target_index(target: PointCloud, target_tree: SearchIndex | None) -> SearchIndex:
    """The search index of ``target``: ``target_tree`` if given (checked to match), else a new
    :class:`~spacepose.core.grid.VoxelIndex`."""
    if target_tree is None:
        return VoxelIndex(target.points)
    if (
        not isinstance(target_tree, cKDTree | VoxelIndex)
        or target_tree.n != len(target)
        or target_tree.m != 3
    ):
        raise InputError(
            "target_tree must be a 3-D cKDTree or VoxelIndex built on the "
            f"{len(target)} target points"
        )
    return target_tree


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


def point_to_point_jacobians(points: NDArray[np.float64]) -> NDArray[np.float64]:
    """(N, 3, 6) Jacobians ``[−skew(p) I]`` of ``exp(δ) p`` at δ = 0, twist order (omega, v)."""
    J = np.empty((len(points), 3, 6))
    J[:, :, :3] = -se3.skew(points)
    J[:, :, 3:] = np.eye(3)
    return J


def point_to_point_information(
    points: NDArray[np.float64], weights: NDArray[np.float64] | None = None
) -> NDArray[np.float64]:
    """6×6 ``Σ w JᵀJ`` of point-to-point residuals at the matched source points (M, 3) (target
    frame), with optional (M,) IRLS weights (None: all 1)."""
    J = point_to_point_jacobians(points)
    if weights is None:
        return np.einsum("nai,naj->ij", J, J)
    return np.einsum("n,nai,naj->ij", weights, J, J)


def point_to_plane_system(
    points: NDArray[np.float64],
    target_points: NDArray[np.float64],
    normals: NDArray[np.float64],
    workers: int = 1,
    weights: NDArray[np.float64] | None = None,
) -> tuple[NDArray[np.float64], NDArray[np.float64], float]:
    """Gauss-Newton system of the residuals ``r = n·(p − q)``: ``H = Σ w h hᵀ``, ``g = Σ w h r``.

    ``h = (p × n, n)`` is the derivative of ``n·(exp(δ) p − q)`` at δ = 0 (twist (omega, v),
    left perturbation). Compiled: the numpy form (rows, products, BLAS) cost about 0.4 ms per
    ICP iteration on a 5000-point lab frame, more than the correspondence search.

    Parameters
    ----------
    points
        (M, 3) matched source points in the target frame.
    target_points, normals
        (M, 3) matched target points and their unit normals.
    workers
        Threads (-1: all cores); rows are summed in fixed chunks, so the result does not
        depend on it.
    weights
        (M,) IRLS weights w (a robust kernel's); None: all 1 (the same bits as weights of 1).

    Returns
    -------
    H, g, sse
        (6, 6) information ``Σ w h hᵀ`` (1/m²), (6,) gradient ``Σ w h r`` and ``Σ w r²`` (m²).

    Raises
    ------
    InputError
        The arrays do not line up (the kernel indexes them unchecked).
    """
    w = np.ones(len(points)) if weights is None else np.ascontiguousarray(weights, np.float64)
    check_rows(
        "point_to_plane_system", points, target_points, normals, w, shapes=((3,),) * 3 + ((),)
    )
    chunks = max(1, -(-len(points) // _SYSTEM_CHUNK))
    partial = np.zeros((chunks, 28))
    with numba_threads(workers):
        _plane_system_kernel(
            np.ascontiguousarray(points, dtype=np.float64),
            np.ascontiguousarray(target_points, dtype=np.float64),
            np.ascontiguousarray(normals, dtype=np.float64),
            w,
            partial,
        )
    total = partial.sum(axis=0)
    H, g = system_from_sums(total)
    return H, g, float(total[27])


# Row-major upper triangle of a 6×6 matrix: the 21 entries the kernel accumulates.
_UPPER = np.triu_indices(6)


@numba.njit(cache=True, parallel=True)
def _plane_system_kernel(points, target_points, normals, weights, partial):
    """Per chunk of rows: :func:`_accumulate_plane` of each (28 sums)."""
    m = len(points)
    for c in numba.prange(len(partial)):
        h = np.empty(6)
        for i in range(c * _SYSTEM_CHUNK, min(m, (c + 1) * _SYSTEM_CHUNK)):
            _accumulate_plane(partial[c], points[i], target_points[i], normals[i], weights[i], h)


@numba.njit(cache=True, inline="always")
def _accumulate_plane(acc, p, q, n, w, h):
    """Add one residual ``r = n·(p − q)`` with row ``h = (p × n, n)`` and weight ``w`` to
    ``acc``: the upper triangle of w h hᵀ (21), w h r (6), w r² (1). ``h`` (6,) is scratch.
    (``w · x`` is ``x`` to the bit for w = 1.)"""
    h[0] = p[1] * n[2] - p[2] * n[1]
    h[1] = p[2] * n[0] - p[0] * n[2]
    h[2] = p[0] * n[1] - p[1] * n[0]
    h[3], h[4], h[5] = n[0], n[1], n[2]
    r = _plane_residual(p, q, n)
    pos = 0
    for a in range(6):
        wa = w * h[a]
        for b in range(a, 6):
            acc[pos] += wa * h[b]
            pos += 1
    for a in range(6):
        acc[21 + a] += w * h[a] * r
    acc[27] += w * r * r


@numba.njit(cache=True, inline="always")
def _plane_residual(p, q, n):
    """Signed point-to-plane distance ``n·(p − q)``."""
    return n[0] * (p[0] - q[0]) + n[1] * (p[1] - q[1]) + n[2] * (p[2] - q[2])


@numba.njit(cache=True, parallel=True)
def _plane_matches_kernel(
    grid,
    rings,
    targets,
    normals,
    src,
    R,
    t,
    gate,
    hint,
    nearest,
    anchors,
    bounds,
    moved,
    residuals,
    partial,
):
    """Point-to-plane ICP's work at one transform, per chunk of source points: move each point
    (``R p + t``), find its nearest target within the gate (:func:`certified_nearest` from its
    last answer ``hint`` and the certificate ``anchors``/``bounds`` of its last search, both
    updated in place), count the match and Σ d² (sums 28, 29) and either accumulate
    :func:`_accumulate_plane` (sums 0..27) or, when ``moved`` has a row per point, store the
    moved point there and its residual ``n·(p − q)`` in ``residuals`` instead (a robust kernel
    weighs the rows once the residuals' scale is known: :func:`_robust_plane_kernel`)."""
    m = len(src)
    accumulate = len(moved) != m
    for c in numba.prange(len(partial)):
        acc = partial[c]
        q = np.empty(3)
        h = np.empty(6)
        for i in range(c * _SYSTEM_CHUNK, min(m, (c + 1) * _SYSTEM_CHUNK)):
            j, d2 = move_and_match(grid, rings, src, R, t, gate, hint, anchors, bounds, i, q)
            nearest[i] = j
            if j >= 0:
                acc[28] += 1.0
                acc[29] += d2
                if accumulate:
                    _accumulate_plane(acc, q, targets[j], normals[j], 1.0, h)
                else:
                    moved[i] = q
                    residuals[i] = _plane_residual(q, targets[j], normals[j])


@numba.njit(cache=True, parallel=True)
def _robust_plane_kernel(moved, targets, normals, nearest, residuals, c, code, w, slopes, partial):
    """The weighted sums of the matches (``nearest`` >= 0) that :func:`_plane_matches_kernel`
    stored, per chunk of source points: each weight and slope of the kernel ``code`` at
    ``residuals / c`` (:func:`~spacepose.core.robust.weight_and_slope`) into ``w`` and
    ``slopes`` (code 0, c unused: all 1), :func:`_accumulate_plane` (sums 0..27), then
    Σ (w r)² (28) and Σ ψ' (29)."""
    m = len(moved)
    for k in numba.prange(len(partial)):
        acc = partial[k]
        h = np.empty(6)
        for i in range(k * _SYSTEM_CHUNK, min(m, (k + 1) * _SYSTEM_CHUNK)):
            j = nearest[i]
            if j < 0:
                continue
            r = residuals[i]
            w[i], slopes[i] = weight_and_slope(r / c, code)
            _accumulate_plane(acc, moved[i], targets[j], normals[j], w[i], h)
            acc[28] += (w[i] * r) ** 2
            acc[29] += slopes[i]


def system_from_sums(total: NDArray[np.float64]) -> tuple[NDArray[np.float64], ...]:
    """(H (6, 6), g (6,)) from 27 compiled sums: the row-major upper triangle of H (21), then g
    (as :func:`_accumulate_plane` and GICP's kernel lay them out)."""
    H = np.empty((6, 6))
    H[_UPPER] = total[:21]
    H.T[_UPPER] = total[:21]
    return H, total[21:27]


def solve_normal_equations(
    H: NDArray[np.float64], g: NDArray[np.float64], damping: float = 0.0
) -> NDArray[np.float64]:
    """Twist ``δ = −(H + damping·I)⁻¹ g``; raises when H leaves a direction unconstrained.

    The check is on the undamped H so that Levenberg-Marquardt damping cannot hide a
    degenerate surface behind a well-conditioned system.

    Raises
    ------
    DegenerateGeometryError
        When the smallest eigenvalue of H is below 1e-12 of the largest (e.g. every
        correspondence lies on one plane, so three degrees of freedom are free).
    """
    ev = np.linalg.eigvalsh(H)
    if ev[0] <= _DEGENERATE_RATIO * ev[-1]:
        raise DegenerateGeometryError(
            "the correspondences do not constrain all 6 degrees of freedom "
            f"(information eigenvalues {ev[0]:.3g} .. {ev[-1]:.3g}); the surface is degenerate"
        )
    return -np.linalg.solve(H + damping * np.eye(len(H)), g)


def icp(
    source: PointCloud | ArrayLike,
    target: PointCloud | ArrayLike,
    init_T_target_source: ArrayLike = np.eye(4),
    config: ICPConfig = ICPConfig(),
    workers: int = -1,
    target_tree: SearchIndex | None = None,
) -> RegistrationResult:
    """Align ``source`` to ``target`` by ICP (see :func:`icp_correspondences`)."""
    result, _ = icp_correspondences(
        source, target, init_T_target_source, config, workers, target_tree
    )
    return result


def icp_correspondences(
    source: PointCloud | ArrayLike,
    target: PointCloud | ArrayLike,
    init_T_target_source: ArrayLike = np.eye(4),
    config: ICPConfig = ICPConfig(),
    workers: int = -1,
    target_tree: SearchIndex | None = None,
) -> tuple[RegistrationResult, Correspondences]:
    """Align ``source`` to ``target`` by ICP; also return the final correspondences.

    Parameters
    ----------
    source, target
        Clouds ((N, 3) arrays or :class:`PointCloud`), each in its own frame. Point-to-plane uses
        the target's normals, estimated with ``config.normals`` when it has none.
    init_T_target_source
        (4, 4) initial guess mapping source coordinates into the target frame.
    config
        Gate, iteration limit, tolerances and method.
    workers
        Threads for the neighbour searches (results do not depend on it).
    target_tree
        Optional prebuilt search index (``cKDTree``, VoxelIndex) of the target points, reused
        when many frames are registered against one target.

    Returns
    -------
    result
        ``T_target_source``, fitness and inlier RMSE of the final correspondences, and the
        information ``Σ JᵀJ`` (1/m², twist (omega, v), left perturbation): point-to-point with
        ``J = [−skew(p) I]``, point-to-plane with rows ``h = (p × n, n)``. With a robust kernel
        the information is ``Σ w JᵀJ`` at the final weights and ``residual_sigma`` the σ that
        makes ``result.covariance()`` the M-estimator's covariance.
    correspondences
        :class:`Correspondences` at the returned transform (what :func:`find_correspondences`
        would return there, and for point-to-plane the normal equations), so that a caller
        computing statistics at the solution need not search or sum again.

    Raises
    ------
    InputError
        Fewer than 3 points, a non-rigid or non-finite initial transform, or a mismatched tree.
    RegistrationError
        Fewer than 3 correspondences within the gate at some iteration.
    DegenerateGeometryError
        Point-to-plane on a surface that leaves a degree of freedom free.
    """
    src = as_registration_cloud(source, "source")
    tgt = as_registration_cloud(target, "target")
    T = se3.as_transform(init_T_target_source, "init_T_target_source").copy()
    plane = config.method == "point_to_plane"
    if plane and tgt.normals is None:
        tgt = estimate_normals(tgt, config.normals, workers=workers)
    tree = target_index(tgt, target_tree)
    gate = config.max_correspondence_distance
    if plane and isinstance(tree, VoxelIndex):
        evaluate = _FusedPlaneMatcher(tree, tgt.normals, src.points, gate, config, workers)
    else:
        evaluate = _Matcher(tree, tgt, src.points, gate, plane, config, workers)

    matches = evaluate(T)
    converged = False
    iterations = 0
    while iterations < config.max_iterations:
        iterations += 1
        if plane:
            update = se3.exp(solve_normal_equations(*matches.system[:2]))
        else:
            update = kabsch(matches.points, tgt.points[matches.tgt_idx], matches.weight_values)
        T = update @ T
        previous, matches = matches, evaluate(T)
        if (
            abs(previous.fitness - matches.fitness) < config.relative_fitness
            and abs(previous.rmse - matches.rmse) < config.relative_rmse
        ):
            converged = True
            break

    if plane:
        information = matches.system[0]
    else:
        information = point_to_point_information(matches.points, matches.weight_values)
    result = RegistrationResult(
        T_target_source=T,
        fitness=matches.fitness,
        inlier_rmse=matches.rmse,
        iterations=iterations,
        converged=converged,
        information=information,
        n_correspondences=len(matches.tgt_idx),
        residual_sigma=matches.residual_sigma,
    )
    return result, matches


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
        Point-to-plane only: ``(H, g, sse)`` of :func:`point_to_plane_system` at the matches
        (information, gradient, Σ r²), weighted by ``weights`` when a robust kernel is on.
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
            f"ICP found {n_matched} correspondences within {gate} m (of {n_source} source "
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


class _Matcher:
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


class _FusedPlaneMatcher:
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
        partial = np.zeros((max(1, -(-n // _SYSTEM_CHUNK)), 30))
        nearest = np.empty(n, dtype=np.int64)
        moved = np.empty((n if robust else 0, 3))
        residuals = np.empty(n if robust else 0)
        with numba_threads(self.workers):
            _plane_matches_kernel(
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
        partial = np.zeros((max(1, -(-n // _SYSTEM_CHUNK)), 30))
        with numba_threads(self.workers):
            _robust_plane_kernel(
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
