"""Iterative closest point: point-to-point and point-to-plane (METHODS §1.5, Li Eqs. 6–7).

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

from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import Field
from scipy.spatial import cKDTree

from spacepose.core import se3
from spacepose.core.cloud import PointCloud
from spacepose.core.config import StageConfig
from spacepose.core.neighbors import hybrid
from spacepose.core.normals import NormalsConfig, estimate_normals
from spacepose.core.registration import RegistrationResult, kabsch
from spacepose.errors import DegenerateGeometryError, InputError, RegistrationError

# Smallest/largest eigenvalue ratio of a Gauss-Newton system below which a direction is
# considered unconstrained (a plane, a cylinder): solving it would return noise, not a pose.
_DEGENERATE_RATIO = 1e-12
# Fewest query points for which CorrespondenceSearch lets the tree search use several threads.
_THREADED_QUERY_MIN = 2048


class ICPConfig(StageConfig):
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


def target_kdtree(target: PointCloud, target_tree: cKDTree | None) -> cKDTree:
    """The KD-tree of ``target``: ``target_tree`` if given (checked to match), else a new one."""
    if target_tree is None:
        return cKDTree(target.points)
    if not isinstance(target_tree, cKDTree) or target_tree.n != len(target) or target_tree.m != 3:
        raise InputError(
            f"target_tree must be a 3-D cKDTree built on the {len(target)} target points"
        )
    return target_tree


def find_correspondences(
    tree: cKDTree, points: NDArray[np.float64], max_distance: float, workers: int = -1
) -> tuple[NDArray[np.intp], NDArray[np.intp], NDArray[np.float64]]:
    """Nearest target point strictly within ``max_distance`` of each query point.

    Parameters
    ----------
    tree
        KD-tree of the target points.
    points
        (N, 3) source points already mapped into the target frame.
    max_distance
        Correspondence gate (m).
    workers
        Threads for the search.

    Returns
    -------
    src_idx, tgt_idx, dist2
        (M,) indices of the matched source points, (M,) indices of their target points and
        (M,) squared distances.
    """
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
    than every other one. GICP (tens of iterations) gains most; :func:`icp` uses it too: in
    tracking, started from a good prediction, it cut the CPU time of a lab tracking step from
    48 to 42 ms (a far start with a few large steps gains nothing but loses little).

    Parameters
    ----------
    tree
        KD-tree of the target points.
    max_distance
        Correspondence gate (m).
    workers
        Threads for the tree searches.
    """

    def __init__(self, tree: cKDTree, max_distance: float, workers: int = -1) -> None:
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


def point_to_point_information(points: NDArray[np.float64]) -> NDArray[np.float64]:
    """6×6 ``Σ JᵀJ`` of point-to-point residuals at the matched source points (target frame)."""
    J = point_to_point_jacobians(points)
    return np.einsum("nai,naj->ij", J, J)


def point_to_plane_rows(
    points: NDArray[np.float64], normals: NDArray[np.float64]
) -> NDArray[np.float64]:
    """(N, 6) rows ``h = (p × n, n)``: derivative of ``n·(exp(δ) p − q)`` at δ = 0."""
    return np.concatenate([np.cross(points, normals), normals], axis=1)


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


def point_to_plane_step(
    points: NDArray[np.float64], target_points: NDArray[np.float64], normals: NDArray[np.float64]
) -> NDArray[np.float64]:
    """One Gauss-Newton update (4, 4) for residuals ``n·(p − q)``, applied on the left.

    Parameters
    ----------
    points
        (M, 3) matched source points in the target frame.
    target_points, normals
        (M, 3) matched target points and their unit normals.
    """
    h = point_to_plane_rows(points, normals)
    r = np.einsum("ni,ni->n", points - target_points, normals)
    return se3.exp(solve_normal_equations(h.T @ h, h.T @ r))


def icp(
    source: PointCloud | ArrayLike,
    target: PointCloud | ArrayLike,
    init_T_target_source: ArrayLike = np.eye(4),
    config: ICPConfig = ICPConfig(),
    workers: int = -1,
    target_tree: cKDTree | None = None,
) -> RegistrationResult:
    """Align ``source`` to ``target`` by ICP (see :func:`icp_correspondences`)."""
    result, _, _ = icp_correspondences(
        source, target, init_T_target_source, config, workers, target_tree
    )
    return result


def icp_correspondences(
    source: PointCloud | ArrayLike,
    target: PointCloud | ArrayLike,
    init_T_target_source: ArrayLike = np.eye(4),
    config: ICPConfig = ICPConfig(),
    workers: int = -1,
    target_tree: cKDTree | None = None,
) -> tuple[RegistrationResult, NDArray[np.intp], NDArray[np.intp]]:
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
        Optional prebuilt ``cKDTree`` of the target points, reused when many frames are
        registered against one target.

    Returns
    -------
    result
        ``T_target_source``, fitness and inlier RMSE of the final correspondences, and the
        information ``Σ JᵀJ`` (1/m², twist (omega, v), left perturbation): point-to-point with
        ``J = [−skew(p) I]``, point-to-plane with rows ``h = (p × n, n)``.
    src_idx, tgt_idx
        (M,) the source points matched at the returned transform and their target points
        (what :func:`find_correspondences` would return there), so that a caller computing
        statistics at the solution need not search again.

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
    tree = target_kdtree(tgt, target_tree)
    gate = config.max_correspondence_distance
    search = CorrespondenceSearch(tree, gate, workers)

    def evaluate(
        T_cur: NDArray[np.float64],
    ) -> tuple[NDArray[np.float64], NDArray[np.intp], NDArray[np.intp], float, float]:
        moved = se3.transform_points(T_cur, src.points)
        s, t, d2 = search(moved)
        if len(s) < 3:
            raise RegistrationError(
                f"ICP found {len(s)} correspondences within {gate} m "
                f"(of {len(src)} source points); the initial guess is too far off or the gate "
                "too small"
            )
        return moved[s], s, t, len(s) / len(src), float(np.sqrt(d2.mean()))

    p, s_idx, t_idx, fitness, rmse = evaluate(T)
    converged = False
    iterations = 0
    while iterations < config.max_iterations:
        iterations += 1
        q = tgt.points[t_idx]
        update = point_to_plane_step(p, q, tgt.normals[t_idx]) if plane else kabsch(p, q)
        T = update @ T
        prev_fitness, prev_rmse = fitness, rmse
        p, s_idx, t_idx, fitness, rmse = evaluate(T)
        if (
            abs(prev_fitness - fitness) < config.relative_fitness
            and abs(prev_rmse - rmse) < config.relative_rmse
        ):
            converged = True
            break

    if plane:
        h = point_to_plane_rows(p, tgt.normals[t_idx])
        information = h.T @ h
    else:
        information = point_to_point_information(p)
    result = RegistrationResult(
        T_target_source=T,
        fitness=fitness,
        inlier_rmse=rmse,
        iterations=iterations,
        converged=converged,
        information=information,
        n_correspondences=len(t_idx),
    )
    return result, s_idx, t_idx
