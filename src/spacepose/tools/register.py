"""Register one cloud onto another with scales derived from the data (``spacepose register``).

The same call must work on a 1 m ToF frame (millimetre spacing) and on a 50 m outdoor LiDAR scan
(centimetres near the sensor, metres far away), so no length is a constant:

- **voxel** ``v = max(2 · s, R / 50)``, with ``s`` the median nearest-neighbour spacing of a
  seeded subsample and ``R`` the 90th percentile of the distance to the median point (the
  cloud's radius, robust to a few far returns). The first term keeps a few points per voxel on
  a dense surface; the second caps the point count on a scan whose density falls with range
  (KISS-ICP's voxel-from-range idea): about 8 mm on the lab's ToF frames, 0.2 m on the real
  LiDAR pair (small_gicp's own test uses 0.25 m).
- **gates**: the fine gate is ``3 v``; without a coarse stage the registration starts at
  ``R / 4`` (an unknown initial error, up to a quarter of the cloud's radius) and halves the gate
  down to ``3 v``, each stage starting from the last. The last stage weighs its residuals with a
  robust kernel of adaptive scale (Geman–McClure by default), so that the 3-voxel gate does not
  let wrong surfaces pull; the earlier stages are plain least squares (see :func:`_stage`).
- **stopping**: GICP stops below a step of ``1e-3 v``, ICP below an RMSE change of ``1e-4 v``.
- **global** (optional): FPFH + RANSAC at the same voxel, or at a coarser one that leaves at
  most ``COARSE_POINTS`` per cloud (:func:`~spacepose.core.ransac.global_registration`), then
  the fine gate alone.
- **covariance**: the wider, in every direction, of the registration's information form and
  the cluster-robust form of its point-to-plane residuals in cells of three voxels
  (:func:`~spacepose.core.pose_covariance.clustered_covariance`, docs/methods.md §1.5).
- **degeneracy**: directions the surfaces leave free (a plane's in-plane translations and
  normal rotation) are flagged and widened in the covariance (:mod:`spacepose.core.degeneracy`).
- **frame**: the clouds are downsampled and solved about the target's centroid, so where the
  world's origin lies changes nothing but rounding.
"""

from __future__ import annotations

import math
import time
import warnings
from dataclasses import dataclass, replace
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import Field

from spacepose.core import se3
from spacepose.core.cloud import PointCloud, as_cloud, as_points
from spacepose.core.config import StageConfig, stage_config
from spacepose.core.correspondences import find_correspondences
from spacepose.core.degeneracy import Degeneracy, surface_degeneracy
from spacepose.core.gicp import GICPConfig, gicp
from spacepose.core.gicp_covariances import compute_covariances, plane_normals
from spacepose.core.grid import VoxelIndex
from spacepose.core.icp import ICPConfig, icp
from spacepose.core.normals import NormalsConfig, estimate_normals
from spacepose.core.pose_covariance import CLUSTER_VOXELS, clustered_covariance, wider_of
from spacepose.core.ransac import global_registration
from spacepose.core.registration import RegistrationResult, moved_back
from spacepose.core.relocalise import COARSE_POINTS
from spacepose.core.robust import RobustKernelName
from spacepose.core.scale import point_spacing
from spacepose.core.voxel import evenly_thinned, voxel_cells
from spacepose.errors import ConfigError, InputError, RegistrationError, SpaceposeWarning

Method = Literal["point_to_plane", "point_to_point", "gicp"]
# Stopping tolerances in voxels (the library defaults are metres tuned at the lab's 6 mm
# voxels: GICP stops below a 10 µm step, ICP below a 1 µm RMSE change).
_TRANSLATION_TOLERANCE = 1e-3
_RMSE_TOLERANCE = 1e-4
# Two clouds this many times apart in radius and in spacing alike are in different units
# (millimetres and metres are 1000 apart; two views of one scene differ by a few times).
_UNIT_FACTOR = 200.0
# A registration whose source fits this share of its fitness a quarter turn away tells no pose
# from another (register's warning, :func:`_warn_if_any_pose_fits`).
ANY_POSE_FITS = 0.8


class RegisterConfig(StageConfig):
    """Parameters of :func:`register`.

    Attributes
    ----------
    method
        Fine registration: ``"gicp"``, ``"point_to_plane"`` or ``"point_to_point"``.
    robust_kernel
        Robust kernel of the fine registration (adaptive scale), see
        :mod:`spacepose.core.robust`.
    voxel_size
        Voxel edge (m) of the downsampling; None: derived (module docstring).
    spacing_multiple, radius_fraction
        The derived voxel is ``max(spacing_multiple · s, radius_fraction · R)``.
    gate_voxels
        Fine correspondence gate in voxels.
    start_radius_fraction
        First gate of the coarse-to-fine schedule as a fraction of the radius R (no global
        stage); 0 starts at the fine gate.
    global_registration
        Run FPFH + RANSAC first.
    max_iterations
        Iteration limit of each fine stage.
    seed
        Seed of the spacing subsample (RANSAC keeps its own default seed).
    """

    method: Method = "gicp"
    robust_kernel: RobustKernelName = "geman_mcclure"
    voxel_size: float | None = Field(None, gt=0)
    spacing_multiple: float = Field(2.0, gt=0)
    radius_fraction: float = Field(1.0 / 50.0, gt=0)
    gate_voxels: float = Field(3.0, gt=0)
    start_radius_fraction: float = Field(0.25, ge=0)
    global_registration: bool = False
    max_iterations: int = Field(30, ge=1)
    seed: int = Field(0, ge=0)


@dataclass(frozen=True)
class CloudScale:
    """Length scales of one cloud.

    Attributes
    ----------
    spacing
        Median nearest-neighbour distance (m) of a seeded subsample.
    radius
        90th percentile of the distance to the median point (m).
    """

    spacing: float
    radius: float


@dataclass(frozen=True)
class RegisterResult:
    """Outcome of :func:`register`.

    Attributes
    ----------
    result
        The final fine registration (``T_target_source`` 4×4, fitness, inlier RMSE, ...).
    covariance
        (6, 6) covariance of ``T_target_source``: twist (omega, v), left perturbation, target
        frame (rad², m²); widened along the directions ``degeneracy`` finds free.
    iterations
        Iterations of every fine stage together.
    time_s
        Wall time from the clouds in memory to the result (downsampling included), s.
    voxel_size
        Voxel edge used (m).
    gates
        Correspondence gates of the fine stages, in order (m).
    n_source, n_target
        Points after downsampling.
    degeneracy
        Which directions the surfaces leave free (``degeneracy.degenerate``: some do).
    coarse
        The global registration's result, if it ran.
    """

    result: RegistrationResult
    covariance: NDArray[np.float64]
    iterations: int
    time_s: float
    voxel_size: float
    gates: tuple[float, ...]
    n_source: int
    n_target: int
    degeneracy: Degeneracy
    coarse: RegistrationResult | None = None

    def to_dict(self) -> dict:
        """JSON-ready summary (lists of floats; covariance order rx ry rz tx ty tz)."""
        r = self.result
        out = {
            "T_target_source": r.T_target_source.tolist(),
            "fitness": r.fitness,
            "inlier_rmse": r.inlier_rmse,
            "covariance": self.covariance.tolist(),
            "covariance_order": "rx ry rz tx ty tz (left perturbation, target frame; rad, m)",
            "iterations": self.iterations,
            "converged": r.converged,
            "n_correspondences": r.n_correspondences,
            "time_s": self.time_s,
            "voxel_size": self.voxel_size,
            "gates": list(self.gates),
            "n_source": self.n_source,
            "n_target": self.n_target,
            **self.degeneracy.to_dict(),
            "global": None,
        }
        if self.coarse is not None:
            out["global"] = {
                "T_target_source": self.coarse.T_target_source.tolist(),
                "fitness": self.coarse.fitness,
                "inlier_rmse": self.coarse.inlier_rmse,
            }
        return out


def cloud_scale(cloud: PointCloud | ArrayLike, seed: int = 0) -> CloudScale:
    """Median point spacing (:func:`~spacepose.core.scale.point_spacing`; 0 when every point
    coincides, which the voxel and the rigid fit then refuse by name) and robust radius of an
    (N, 3) cloud (N >= 2), metres."""
    pts = as_points(cloud)
    if len(pts) < 2:
        source = cloud.source if isinstance(cloud, PointCloud) else None
        raise InputError(f"a cloud needs at least 2 points for its spacing, got {len(pts)}", source)
    try:
        spacing = point_spacing(pts, seed=seed)
    except InputError:  # the points' one place: no spacing
        spacing = 0.0
    radius = np.percentile(np.linalg.norm(pts - np.median(pts, axis=0), axis=1), 90)
    return CloudScale(spacing, float(radius))


def derived_voxel(scales: list[CloudScale], config: RegisterConfig) -> float:
    """``max(spacing_multiple · s, radius_fraction · R)`` over the clouds' scales (m)."""
    voxel = max(
        max(config.spacing_multiple * s.spacing, config.radius_fraction * s.radius) for s in scales
    )
    if not voxel > 0:
        raise InputError("the clouds have no extent: every point coincides")
    return voxel


def _unit_problem(scales: list[CloudScale]) -> str | None:
    """Why the two clouds look like two units, or None: they differ by a unit's factor in size
    and in spacing alike (a scan in millimetres onto one in metres), which fails far from the
    cause, as "0 correspondences within 140 m; the initial guess is too far off". A partial
    scan against a map differs in size, not in spacing."""
    small, large = sorted(scales, key=lambda s: s.radius)
    if min(small.radius, small.spacing) <= 0:  # coincident points: refused below as such
        return None
    if large.radius > _UNIT_FACTOR * small.radius and large.spacing > _UNIT_FACTOR * small.spacing:
        return (
            f"the clouds differ {large.radius / small.radius:.3g}-fold in size and spacing "
            f"(radius {scales[0].radius:.3g} m and {scales[1].radius:.3g} m): the same unit?"
        )
    return None


def gate_schedule(fine_gate: float, start_gate: float) -> tuple[float, ...]:
    """Gates halving from ``start_gate`` down to ``fine_gate`` (m), ``fine_gate`` last."""
    stages = max(0, math.ceil(math.log2(start_gate / fine_gate))) if start_gate > 0 else 0
    return tuple(fine_gate * 2.0**k for k in range(stages, -1, -1))


def register(
    source: PointCloud | ArrayLike,
    target: PointCloud | ArrayLike,
    init_T_target_source: ArrayLike | None = None,
    config: RegisterConfig = RegisterConfig(),
    workers: int = -1,
) -> RegisterResult:
    """Register ``source`` onto ``target`` with data-derived scales (module docstring).

    Parameters
    ----------
    source, target
        Clouds (PointCloud or (N, 3) arrays), each in its own frame (m).
    init_T_target_source
        (4, 4) initial guess; None: the identity (or the global registration's result).
    config
        Method, kernel and scale rules.
    workers
        Threads for the neighbour searches.

    Returns
    -------
    RegisterResult
        The final registration, its covariance, iterations, time and the scales used.

    Raises
    ------
    ConfigError
        An initial guess given with ``config.global_registration`` (which starts from none).
    """
    config = stage_config(config, RegisterConfig)
    if config.global_registration and init_T_target_source is not None:
        # The global stage starts from no pose: the given one was replaced without a word.
        raise ConfigError(
            "an initial transform (--init) is given with global registration (--global), which "
            "starts from no pose and would replace it: give one of them"
        )
    tic = time.perf_counter()
    source, target = as_cloud(source, "source"), as_cloud(target, "target")
    T = se3.as_transform(
        np.eye(4) if init_T_target_source is None else init_T_target_source,
        "init_T_target_source",
    ).copy()
    for cloud in (source, target):
        if len(cloud) < 3:
            raise InputError(f"{len(cloud)} point(s): a rigid fit needs 3", cloud.source)
    scales = [cloud_scale(c, config.seed) for c in (source, target)]
    unit_problem = _unit_problem(scales)
    names = f"{source.source or 'source'} and {target.source or 'target'}"
    voxel = config.voxel_size or derived_voxel(scales, config)
    for cloud, scale in zip((source, target), scales, strict=True):
        if config.voxel_size is not None and voxel > scale.radius:
            # A given voxel wider than the cloud leaves a handful of centroids that fit
            # anything (a derived one follows the spacing; coincident points fail below).
            raise InputError(
                f"voxel {voxel:.4g} m is wider than the cloud (radius {scale.radius:.4g} m)",
                cloud.source,
            )
    # Solved about the target's centre: about a far origin (a map in world coordinates, 1 km
    # out) each rotation is a lever arm of that distance, and the normal equations lose the
    # surfaces' information to rounding (their condition passed 10¹⁵ and ICP called them
    # degenerate). ``S`` moves the centre to the origin; every pose and covariance goes back.
    # The voxel grid is laid there too, so that where the world's origin lies changes no
    # sample: the same clouds 1,000 km out give the same pose and covariance.
    S = se3.make_transform(np.eye(3), -np.mean(target.points, axis=0))
    src, tgt = (_downsampled(cloud.transformed(S), voxel) for cloud in (source, target))
    T = S @ T @ se3.invert(S)
    for cloud in (src, tgt):
        if len(cloud) < 3 and unit_problem is not None:
            # The voxel is the larger cloud's: the smaller one, not its points, is the fault.
            raise InputError(unit_problem, names)
        if len(cloud) < 3:
            raise InputError(
                f"{len(cloud)} distinct point(s) at the {voxel:.4g} m voxel: a rigid fit needs 3 "
                "(do its points all coincide?)",
                cloud.source,
            )
    if unit_problem is not None:
        warnings.warn(SpaceposeWarning(unit_problem, names), stacklevel=2)
    coarse = None
    fine_gate = config.gate_voxels * voxel
    start = config.start_radius_fraction * max(s.radius for s in scales)
    if config.global_registration:
        coarse = global_registration(*_coarse(src, tgt, voxel), workers=workers)
        T, start = coarse.T_target_source, 0.0
    gates = gate_schedule(fine_gate, start)
    tree = VoxelIndex(tgt.points)
    fine, tgt = _fine_registration(src, tgt, tree, config, voxel, workers)
    iterations = 0
    for gate in gates:
        result = fine(T, gate, gate == gates[-1])
        T, iterations = result.T_target_source, iterations + result.iterations
    radius = max(s.radius for s in scales)
    degeneracy = surface_degeneracy(src.points, tgt.points, T, radius, workers=workers)
    # GICP's information is noise-weighted already; ICP's scales by its residual σ. Neither
    # sees residuals correlated over the surface: the cluster-robust form does, and the wider
    # of the two is kept.
    covariance = result.covariance(sigma=1.0 if config.method == "gicp" else None)
    moved = se3.transform_points(T, src.points)
    if not degeneracy.degenerate:  # a plane turned about its normal: said as free directions
        _warn_if_any_pose_fits(tree, moved, result.fitness, fine_gate, names, workers)
    s, t, _ = find_correspondences(tree, moved, fine_gate, workers)
    residuals = np.einsum("ij,ij->i", moved[s] - tgt.points[t], tgt.normals[t])
    try:
        clustered = clustered_covariance(
            moved[s], tgt.normals[t], residuals, CLUSTER_VOXELS * voxel
        )
        covariance = wider_of(covariance, clustered)
    except RegistrationError:  # too few cells to see a correlation: the information alone
        pass
    if degeneracy.degenerate:  # the registration's own information claims too much there
        covariance = degeneracy.widen(covariance)
    # Back where the clouds were: the covariance moved, not inverted from a moved information
    # (about a far origin that information is as ill-conditioned as the system was).
    back = se3.adjoint(se3.invert(S))  # a left twist about the centre -> about the origin
    centroid = se3.transform_points(se3.invert(S), degeneracy.centroid[None])[0]
    return RegisterResult(
        moved_back(result, S),
        back @ covariance @ back.T,
        iterations,
        time.perf_counter() - tic,
        voxel,
        gates,
        len(src),
        len(tgt),
        replace(degeneracy, centroid=centroid),
        None if coarse is None else moved_back(coarse, S),
    )


def _warn_if_any_pose_fits(
    tree: VoxelIndex,
    moved: NDArray[np.float64],
    fitness: float,
    gate: float,
    names: str,
    workers: int,
) -> None:
    """Warn when the registered source, turned a quarter turn about each axis through its
    centroid, fits the target nearly as well (:data:`ANY_POSE_FITS` of its fitness): the
    clouds hold no surface that tells one pose from another (points filling a volume). 90 %
    uniform outliers around a satellite's views were registered 109° and 4.5 m off at a
    fitness of 1.0 and a σ of 0.013°, without a word (turned: 1.0 of the fitness; 50 % of
    outliers, 0.49° off at 6σ: 1.0 too). Turned, the real pair's scans fit 0.30 of their
    fitness, the satellite's clean views 0.24 and a cube's 0.20."""
    centroid = moved.mean(axis=0)
    turned = []
    for axis in np.eye(3):
        R = se3.exp(np.r_[0.5 * np.pi * axis, 0.0, 0.0, 0.0])[:3, :3]
        rotated = (moved - centroid) @ R.T + centroid
        s, _, _ = find_correspondences(tree, rotated, gate, workers)
        turned.append(len(s) / len(moved))
    if fitness > 0 and max(turned) >= ANY_POSE_FITS * fitness:
        problem = (
            f"the source turned a quarter turn fits the target as well (fitness "
            f"{max(turned):.2f} against {fitness:.2f}): the clouds hold no surface that tells "
            "one pose from another (points filling a volume, or mostly outliers?): neither the "
            "fitness nor the σ vouches for the pose"
        )
        warnings.warn(SpaceposeWarning(problem, names), stacklevel=3)


def _coarse(src: PointCloud, tgt: PointCloud, voxel: float) -> tuple[PointCloud, PointCloud, float]:
    """The clouds global registration describes, and their voxel: at most ``COARSE_POINTS``
    each, by a voxel grown as a surface's count falls (then thinned evenly: a volume's does
    not). FPFH matching in 33 dimensions slowed to seconds beyond: two blobs of random points
    (37,000 voxels each) took 54 s."""
    n = max(len(src), len(tgt))
    if n <= COARSE_POINTS:
        return src, tgt, voxel
    voxel *= math.sqrt(n / COARSE_POINTS)
    src, tgt = (evenly_thinned(_downsampled(c, voxel), COARSE_POINTS) for c in (src, tgt))
    return src, tgt, voxel


def _downsampled(cloud: PointCloud, voxel: float) -> PointCloud:
    """The voxel centroids of ``cloud``, its name kept for the errors."""
    try:
        return PointCloud(voxel_cells(cloud.points, voxel)[0], source=cloud.source)
    except InputError as exc:  # a voxel far too fine for the cloud's extent
        raise InputError(f"voxel {voxel:.4g} m: {exc.reason}", cloud.source) from None


def _fine_registration(
    src: PointCloud,
    tgt: PointCloud,
    tree: VoxelIndex,
    config: RegisterConfig,
    voxel: float,
    workers: int,
):
    """A function ``(T, gate) -> RegistrationResult`` that reuses the target's index
    ``tree``, its normals and both clouds' covariances across the stages, and the target with
    its normals (every method's covariance needs them)."""
    if config.method == "gicp":
        base = GICPConfig(
            max_iterations=config.max_iterations,
            robust_kernel=config.robust_kernel,
            translation_tolerance=_TRANSLATION_TOLERANCE * voxel,
        )
        k = min(base.k_covariance, len(src), len(tgt))
        Cs, Ct = (compute_covariances(c, k, base.epsilon, workers) for c in (src, tgt))

        def run_gicp(T: NDArray[np.float64], gate: float, last: bool) -> RegistrationResult:
            cfg = base.model_copy(update=_stage(gate, last, config))
            return gicp(src, tgt, T, cfg, workers, Cs, Ct, tree)

        return run_gicp, tgt.with_normals(plane_normals(Ct))
    tgt = estimate_normals(tgt, NormalsConfig(k=20, radius=3.0 * voxel), workers=workers)
    base = ICPConfig(
        method=config.method,
        max_iterations=config.max_iterations,
        robust_kernel=config.robust_kernel,
        relative_rmse=_RMSE_TOLERANCE * voxel,
    )

    def run_icp(T: NDArray[np.float64], gate: float, last: bool) -> RegistrationResult:
        cfg = base.model_copy(update=_stage(gate, last, config))
        return icp(src, tgt, T, cfg, workers, tree)

    return run_icp, tgt


def _stage(gate: float, last: bool, config: RegisterConfig) -> dict:
    """Config fields of one fine stage: its gate, and the robust kernel on the last stage only.

    The adaptive scale follows the majority of the current residuals; far from the answer
    that majority can be the surfaces the present misalignment leaves in place (a road along
    the motion), and a redescending kernel would then hold the start. The halving gates are the
    robustifier of the early stages."""
    return {
        "max_correspondence_distance": gate,
        "robust_kernel": config.robust_kernel if last else "none",
    }
