"""The two pipelines of the ``li-global`` experiment, ours and Open3D's, and their settings.

:func:`ours_global` and :func:`open3d_global` register the lab model onto a ToF frame from the
same raw points with the same lengths (:func:`coarse_lengths`): voxels, normals, FPFH, feature
RANSAC, then one point-to-plane ICP of the frame onto the model, inverted. Each answers an
:class:`Outcome`. :class:`GlobalExperimentConfig` holds the experiment's parameters, and
:func:`load_open3d` finds Open3D if it is installed. Why the pipelines run as they do:
:mod:`spacepose.tools.experiments.li_global`.
"""

from __future__ import annotations

import importlib
import time
from dataclasses import dataclass
from types import ModuleType
from typing import Any

import numpy as np
from numpy.typing import NDArray
from pydantic import Field, PositiveFloat

from spacepose.core import se3
from spacepose.core.cloud import PointCloud
from spacepose.core.config import StageConfig
from spacepose.core.fpfh import compute_fpfh
from spacepose.core.icp import ICPConfig, icp
from spacepose.core.normals import NormalsConfig, estimate_normals
from spacepose.core.ransac import RansacConfig, feature_ransac
from spacepose.core.scale import derive_scale
from spacepose.core.tracker_config import StageLengths, TrackerConfig, stage_lengths
from spacepose.core.voxel import voxel_downsample
from spacepose.errors import RegistrationError


class GlobalExperimentConfig(StageConfig):
    """Parameters of the ``li-global`` experiment.

    Attributes
    ----------
    poses, quick_poses
        Random initial poses in full and in quick mode.
    max_translation
        Each translation component of the random pose is uniform in ±this (m).
    coarse
        The tracker config whose lengths (:func:`coarse_lengths`: voxel and coarse voxel from
        the frame's spacing, normals, FPFH and RANSAC radii from them) both pipelines use: the
        tracker's defaults but for a larger RANSAC budget (see
        :mod:`spacepose.tools.experiments.li_global`).
    icp
        The final ICP. Its 10 mm gate takes in the RANSAC result (errors of a few mm and up to
        about 12°); the tracker's 5 mm gate is for frame-to-frame motion after a prediction.
    max_rotation_deg, max_translation_error
        Success thresholds: rotation error (deg) and model-origin position error (m).
    """

    poses: int = Field(100, ge=1)
    quick_poses: int = Field(10, ge=1)
    max_translation: float = Field(0.3, ge=0)
    coarse: TrackerConfig = TrackerConfig(
        ransac=RansacConfig(
            mutual_filter=False,
            max_iterations=1_000_000,
            confidence=0.99999,
        )
    )
    icp: ICPConfig = ICPConfig(max_correspondence_distance=0.01, method="point_to_plane")
    max_rotation_deg: PositiveFloat = 1.0
    max_translation_error: PositiveFloat = 0.01


@dataclass(frozen=True)
class Outcome:
    """One pipeline on one trial.

    Attributes
    ----------
    T_target_source
        (4, 4) estimate, or None when the pipeline gave no pose (no RANSAC consensus, ICP lost).
    coarse_T_target_source
        (4, 4) RANSAC estimate before ICP, or None.
    seconds
        Wall time from the raw clouds to the final pose.
    """

    T_target_source: NDArray[np.float64] | None
    coarse_T_target_source: NDArray[np.float64] | None
    seconds: float


def _outward(cloud: PointCloud, config: NormalsConfig, workers: int) -> PointCloud:
    """Normals of a closed model turned away from its centroid."""
    inward = estimate_normals(cloud, config, cloud.points.mean(axis=0), workers)
    return inward.with_normals(-inward.normals)


def ours_global(
    source: PointCloud,
    target: PointCloud,
    config: GlobalExperimentConfig = GlobalExperimentConfig(),
    workers: int = -1,
) -> Outcome:
    """Our pipeline: voxels → normals → FPFH → RANSAC → point-to-plane ICP.

    RANSAC registers the model onto the frame; the ICP registers the frame onto the model, as
    the tracker does, and is inverted (see :mod:`spacepose.tools.experiments.li_global` for why).

    Parameters
    ----------
    source
        Model points (N, 3) in the source frame (normals, if any, are ignored).
    target
        Frame points (M, 3) in the sensor frame (the sensor at the origin).
    config
        Coarse settings and the final ICP.
    workers
        Threads for the neighbour searches.

    Returns
    -------
    The estimated ``T_target_source``; None when RANSAC finds no consensus or ICP no
    correspondences.
    """
    tic = time.perf_counter()
    cfg = coarse_lengths(config, target)
    fine_s = voxel_downsample(PointCloud(source.points), cfg.voxel)
    fine_t = voxel_downsample(PointCloud(target.points), cfg.voxel)
    sparse_s = _outward(voxel_downsample(fine_s, cfg.coarse_voxel), cfg.coarse_normals, workers)
    sparse_t = estimate_normals(
        voxel_downsample(fine_t, cfg.coarse_voxel), cfg.coarse_normals, workers=workers
    )
    fs = compute_fpfh(sparse_s, cfg.fpfh, workers)
    ft = compute_fpfh(sparse_t, cfg.fpfh, workers)
    try:
        coarse = feature_ransac(sparse_s, sparse_t, fs, ft, cfg.ransac, workers).T_target_source
    except RegistrationError:
        return Outcome(None, None, time.perf_counter() - tic)
    fine_s = _outward(fine_s, config.coarse.normals, workers)
    try:
        res = icp(fine_t, fine_s, se3.invert(coarse), config.icp, workers)
    except RegistrationError:
        return Outcome(None, coarse, time.perf_counter() - tic)
    return Outcome(se3.invert(res.T_target_source), coarse, time.perf_counter() - tic)


def coarse_lengths(config: GlobalExperimentConfig, frame: PointCloud) -> StageLengths:
    """The tracker's lengths for the frame's scale (voxel from its spacing, as the tracker)."""
    cfg = config.coarse
    scale = derive_scale(frame.points, cfg.points_per_frame, cfg.voxel_size)
    return stage_lengths(cfg, scale.voxel, scale.radius)


def _search(o3d: ModuleType, config: NormalsConfig) -> Any:
    """Open3D's neighbourhood for a :class:`NormalsConfig` (k nearest, or within radius ≤ k)."""
    if config.radius is None:
        return o3d.geometry.KDTreeSearchParamKNN(config.k)
    return o3d.geometry.KDTreeSearchParamHybrid(radius=config.radius, max_nn=config.k)


def open3d_global(
    o3d: ModuleType,
    source: PointCloud,
    target: PointCloud,
    config: GlobalExperimentConfig = GlobalExperimentConfig(),
) -> Outcome:
    """Open3D's pipeline with the parameters of :func:`ours_global`, on the same points, in
    the same directions (RANSAC model onto frame, ICP frame onto model).

    Open3D's RANSAC is seeded with ``config.coarse.ransac.seed``; its threads are the caller's
    business (``o3d.utility.set_max_threads``).

    Parameters
    ----------
    o3d
        The ``open3d`` module (:func:`load_open3d`).
    source
        Model points (N, 3) in the source frame (normals, if any, are ignored).
    target
        Frame points (M, 3) in the sensor frame (the sensor at the origin).
    config
        Coarse settings and the final ICP.

    Returns
    -------
    The estimated ``T_target_source``. Open3D answers a failure with the identity (or its
    input), never None: the error says how wrong it is.
    """
    reg = o3d.pipelines.registration
    tic = time.perf_counter()
    cfg = coarse_lengths(config, target)
    clouds = []
    for cloud in (source, target):
        # Open3D wants writeable arrays; PointCloud's are read-only.
        pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.array(cloud.points)))
        fine = pcd.voxel_down_sample(cfg.voxel)
        clouds.append((fine, fine.voxel_down_sample(cfg.coarse_voxel)))
    (fine_s, sparse_s), (fine_t, sparse_t) = clouds
    for sparse in (sparse_s, sparse_t):
        sparse.estimate_normals(_search(o3d, cfg.coarse_normals))
    sparse_t.orient_normals_towards_camera_location(np.zeros(3))
    _o3d_outward(o3d, sparse_s)
    fpfh = o3d.geometry.KDTreeSearchParamHybrid(radius=cfg.fpfh.radius, max_nn=cfg.fpfh.max_nn)
    fs = reg.compute_fpfh_feature(sparse_s, fpfh)
    ft = reg.compute_fpfh_feature(sparse_t, fpfh)
    rc = cfg.ransac
    o3d.utility.random.seed(rc.seed)
    gate = rc.max_correspondence_distance
    coarse = reg.registration_ransac_based_on_feature_matching(
        sparse_s,
        sparse_t,
        fs,
        ft,
        rc.mutual_filter,
        gate,
        reg.TransformationEstimationPointToPoint(False),
        3,
        [
            reg.CorrespondenceCheckerBasedOnEdgeLength(rc.edge_length_ratio),
            reg.CorrespondenceCheckerBasedOnDistance(gate),
        ],
        reg.RANSACConvergenceCriteria(rc.max_iterations, rc.confidence),
    )
    fine_s.estimate_normals(_search(o3d, config.coarse.normals))
    _o3d_outward(o3d, fine_s)
    ic = config.icp
    fine = reg.registration_icp(
        fine_t,
        fine_s,
        ic.max_correspondence_distance,
        se3.invert(np.array(coarse.transformation)),
        reg.TransformationEstimationPointToPlane(),
        reg.ICPConvergenceCriteria(ic.relative_fitness, ic.relative_rmse, ic.max_iterations),
    )
    # Open3D answers a failure with the identity (or its input) rather than an error: keep
    # whatever it returns and let the error say how wrong it is.
    return Outcome(
        se3.invert(np.array(fine.transformation)),
        np.array(coarse.transformation),
        time.perf_counter() - tic,
    )


def _o3d_outward(o3d: ModuleType, pcd: Any) -> None:
    """Turn an Open3D model cloud's normals away from its centroid, in place."""
    pcd.orient_normals_towards_camera_location(np.asarray(pcd.points).mean(axis=0))
    pcd.normals = o3d.utility.Vector3dVector(-np.asarray(pcd.normals))


def load_open3d() -> tuple[ModuleType | None, str]:
    """Open3D if importable, and its version or the reason it is missing.

    Returns
    -------
    ``(open3d, version)``, or ``(None, why it is not importable)``.
    """
    try:
        o3d = importlib.import_module("open3d")
    except ImportError as exc:
        return None, f"not importable ({exc}): ours and plain ran alone"
    return o3d, str(o3d.__version__)
