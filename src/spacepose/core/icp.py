"""Iterative closest point: point-to-point and point-to-plane (methods.md §1.5, Li Eqs. 6–7).

The loop follows Open3D's ``registration_icp`` step for step so that point-to-point results can
be checked against it: correspondences are the nearest target point strictly within the maximum
distance, the update is estimated from them, the transform is composed on the left, the
correspondences are searched again, and the loop stops when both the fitness and the inlier RMSE
change by less than their tolerances. Fitness, RMSE and the information matrix are those of the
last correspondence search, i.e. of the returned transform.

Unlike Open3D, an iteration that finds fewer than three correspondences raises
:class:`~spacepose.errors.RegistrationError` rather than returning the identity.

The correspondences and the matchers that find them at each transform are in
:mod:`spacepose.core.correspondences`, the linearised systems and the Gauss-Newton step in
:mod:`spacepose.core.icp_systems`.
"""

from __future__ import annotations

import warnings
from dataclasses import replace
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import Field
from scipy.spatial import cKDTree

from spacepose.core import se3
from spacepose.core.cloud import PointCloud, as_cloud, check_scale
from spacepose.core.config import stage_config
from spacepose.core.correspondences import Correspondences, FusedPlaneMatcher, Matcher
from spacepose.core.grid import VoxelIndex
from spacepose.core.icp_systems import point_to_point_information, solve_normal_equations
from spacepose.core.neighbors import SearchIndex
from spacepose.core.normals import NormalsConfig, estimate_normals
from spacepose.core.registration import RegistrationResult, far_centre, kabsch, moved_back
from spacepose.core.robust import RobustConfig
from spacepose.errors import DegenerateGeometryError, InputError, SpaceposeWarning


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
    """Validate a registration input: a :class:`PointCloud` or (N, 3) array with >= 3 points,
    not all at one place."""
    pc = as_cloud(cloud, name)
    if len(pc) < 3:
        raise InputError(f"{name} cloud needs at least 3 points for a rigid fit, got {len(pc)}")
    if _at_one_place(pc.points):
        # No rotation to fit; and every search would scan all the points in one grid cell
        # (40,000 copies of one point took 2.2 s, two million did not finish).
        where = None if pc.source == name else pc.source
        raise DegenerateGeometryError(
            f"all {len(pc)} points of the {name} cloud at one place: no rigid fit", where
        )
    return pc


def warn_if_other_unit(clouds: tuple[PointCloud | ArrayLike, ...], gate: float) -> None:
    """Warn when a registration's clouds look like millimetres (more than 50 units across,
    their points more than 0.25 apart: :func:`~spacepose.core.cloud.check_scale`) and lie
    farther apart than its gate: integer millimetres from a driver, registered with the
    default gate of 0.05 m, came out "converged" at the identity with 1.6 % of the points
    paired and no word. A cloud of ordinary size costs one min/max."""
    for name, cloud in zip(("source", "target"), clouds, strict=True):
        points = as_cloud(cloud, name).points
        check = check_scale(points)
        if check.millimetres and check.spacing > gate:
            problem = (
                f"the {name}'s points lie {check.spacing:.3g} apart (median) over "
                f"{check.extent:.3g} across, farther than the gate of {gate:g}: millimetres "
                "given to lengths in metres?"
            )
            warnings.warn(SpaceposeWarning(problem), stacklevel=3)
            return


def _at_one_place(points: NDArray[np.float64]) -> bool:
    """Whether every row of ``points`` (N, 3) equals the first. The first rows decide almost
    every cloud, so a registration's inputs are not scanned whole (``np.ptp`` over axis 0 took
    0.5 ms an 18,000-point cloud, 4 ms of a tracking step)."""
    head = points[:8]
    if (head != head[0]).any():
        return False
    return not (points != points[0]).any()


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


def icp(
    source: PointCloud | ArrayLike,
    target: PointCloud | ArrayLike,
    init_T_target_source: ArrayLike = np.eye(4),
    config: ICPConfig = ICPConfig(),
    workers: int = -1,
    target_tree: SearchIndex | None = None,
) -> RegistrationResult:
    """Align ``source`` to ``target`` by ICP (see :func:`icp_correspondences`).

    Warns
    -----
    SpaceposeWarning
        The clouds look like millimetres against a gate in metres
        (:func:`warn_if_other_unit`)."""
    config = stage_config(config, ICPConfig)
    warn_if_other_unit((source, target), config.max_correspondence_distance)
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
        :class:`~spacepose.core.correspondences.Correspondences` at the returned transform
        (what :func:`~spacepose.core.correspondences.find_correspondences` would return there,
        and for point-to-plane the normal equations), so that a caller computing statistics at
        the solution need not search or sum again.

    Raises
    ------
    InputError
        Fewer than 3 points, a non-rigid or non-finite initial transform, or a mismatched tree.
    RegistrationError
        Fewer than 3 correspondences within the gate at some iteration.
    DegenerateGeometryError
        Point-to-plane on a surface that leaves a degree of freedom free.
    """
    config = stage_config(config, ICPConfig)
    src = as_registration_cloud(source, "source")
    tgt = as_registration_cloud(target, "target")
    T = se3.as_transform(init_T_target_source, "init_T_target_source").copy()
    centre = far_centre(tgt.points) if target_tree is None else None
    if centre is not None:
        # Both clouds moved to the target's centre and solved there, as GICP is: summed about
        # a far origin the normal equations cancel to rounding (1,000 km out point-to-plane
        # came out 0.015° off, and 3,000 km out was called degenerate; point-to-point gave
        # negative variances). A caller's tree holds the far points: with one, the system is
        # solved about the centre instead, which serves up to the kilometres a sensor sees.
        S = se3.make_transform(np.eye(3), -centre)
        near, matches = icp_correspondences(
            src.transformed(S), tgt.transformed(S), S @ T @ se3.invert(S), config, workers
        )
        return moved_back(near, S), _moved_back(matches, S)
    plane = config.method == "point_to_plane"
    if plane and tgt.normals is None:
        tgt = estimate_normals(tgt, config.normals, workers=workers)
    tree = target_index(tgt, target_tree)
    gate = config.max_correspondence_distance
    if plane and isinstance(tree, VoxelIndex):
        evaluate = FusedPlaneMatcher(tree, tgt.normals, src.points, gate, config, workers)
    else:
        evaluate = Matcher(tree, tgt, src.points, gate, plane, config, workers)

    # A target far from its origin (a tracker's frame 300 m from its sensor) is solved about
    # its centre; its trees and normals stay as they are.
    about = far_centre(tgt.points) if plane else None
    matches = evaluate(T)
    converged = False
    iterations = 0
    while iterations < config.max_iterations:
        iterations += 1
        if plane:
            update = se3.exp(solve_normal_equations(*matches.system[:2], about=about))
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


def _moved_back(matches: Correspondences, S: NDArray[np.float64]) -> Correspondences:
    """``matches`` of clouds both moved by the shift ``S`` (4, 4), for the clouds where they
    were: the matched points moved back, the normal equations of the twist about the original
    origin (as :func:`~spacepose.core.registration.moved_back` moves the information)."""
    points = None if matches.points is None else se3.transform_points(se3.invert(S), matches.points)
    system = matches.system
    if system is not None:
        Ad = se3.adjoint(S)
        system = (Ad.T @ system[0] @ Ad, Ad.T @ system[1], system[2])
    return replace(matches, points=points, system=system)
