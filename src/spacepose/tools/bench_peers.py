"""The peers of ``spacepose bench`` (Open3D, small_gicp) and the environment every contender ran in.

:func:`load_peers` imports them (they come with the ``peers`` extra). :class:`Open3D` and
:class:`SmallGICP` run their counterparts of our stages with the same parameters, from the same
numpy inputs: turning those into the peer's own types is part of its time, as a Python caller pays
it. :class:`Peers` holds the ones a run compares against (None for the others).

Every contender gets the same thread count (:func:`thread_count`): Open3D's process-wide cap on its
TBB pool is set for the run and given back by :meth:`Open3D.close`. :func:`environment` records the
machine, the library versions and those thread settings.
"""

from __future__ import annotations

import datetime
import importlib
import importlib.metadata
import os
import platform
from dataclasses import dataclass
from types import ModuleType
from typing import Any

import numpy as np
import scipy
from numpy.typing import NDArray

from spacepose.core.cloud import PointCloud
from spacepose.core.gicp import GICPConfig
from spacepose.core.icp import ICPConfig
from spacepose.core.ransac import RansacConfig
from spacepose.errors import ConfigError

PEERS: tuple[str, ...] = ("open3d", "small_gicp")


def load_peers(names: tuple[str, ...] = PEERS) -> dict[str, ModuleType]:
    """Import the peer libraries.

    Raises
    ------
    ConfigError
        When one is not installed (they come with the ``peers`` extra).
    """
    modules = {}
    for name in names:
        try:
            modules[name] = importlib.import_module(name)
        except ImportError as exc:
            raise ConfigError(
                f"--peers needs {name}, which cannot be imported ({exc}); "
                "install open3d and small_gicp (the package's 'peers' extra)"
            ) from None
    return modules


def thread_count(workers: int) -> int:
    """Threads ``workers`` stands for: all cores for -1, else the number itself."""
    if workers == -1:
        return os.cpu_count() or 1
    if workers < 1:
        raise ConfigError(f"workers must be -1 (all cores) or a positive count, got {workers}")
    return workers


class Open3D:
    """Open3D's counterparts of our stages, with the same parameters."""

    def __init__(self, o3d: ModuleType, threads: int) -> None:
        self.o3d = o3d
        self.reg = o3d.pipelines.registration
        self._threads_before = o3d.utility.get_max_threads()
        # Process-wide cap on Open3D's TBB pool: the same thread count as ours.
        o3d.utility.set_max_threads(threads)

    def close(self) -> None:
        """Give Open3D back the thread count it had."""
        self.o3d.utility.set_max_threads(self._threads_before)

    def cloud(self, cloud: PointCloud, normals: bool = True) -> Any:
        # Open3D wants writeable arrays; PointCloud's are read-only, so copy (a cost any caller
        # of Open3D pays).
        pcd = self.o3d.geometry.PointCloud(self.o3d.utility.Vector3dVector(np.array(cloud.points)))
        if normals and cloud.normals is not None:
            pcd.normals = self.o3d.utility.Vector3dVector(np.array(cloud.normals))
        return pcd

    def voxel(self, cloud: PointCloud, voxel_size: float) -> Any:
        return self.cloud(cloud, normals=False).voxel_down_sample(voxel_size)

    def normals(self, cloud: PointCloud, k: int) -> Any:
        pcd = self.cloud(cloud, normals=False)
        pcd.estimate_normals(self.o3d.geometry.KDTreeSearchParamKNN(k))
        pcd.orient_normals_towards_camera_location(np.zeros(3))
        return pcd

    def fpfh(self, cloud: PointCloud, radius: float, max_nn: int) -> Any:
        search = self.o3d.geometry.KDTreeSearchParamHybrid(radius=radius, max_nn=max_nn)
        return self.reg.compute_fpfh_feature(self.cloud(cloud), search)

    def _feature(self, features: NDArray[np.float64]) -> Any:
        feature = self.reg.Feature()
        feature.data = np.ascontiguousarray(features.T)
        return feature

    def ransac(
        self,
        source: PointCloud,
        target: PointCloud,
        source_features: NDArray[np.float64],
        target_features: NDArray[np.float64],
        config: RansacConfig,
    ) -> NDArray[np.float64]:
        self.o3d.utility.random.seed(config.seed)
        gate = config.max_correspondence_distance
        result = self.reg.registration_ransac_based_on_feature_matching(
            self.cloud(source),
            self.cloud(target),
            self._feature(source_features),
            self._feature(target_features),
            config.mutual_filter,
            gate,
            self.reg.TransformationEstimationPointToPoint(False),
            3,
            [
                self.reg.CorrespondenceCheckerBasedOnEdgeLength(config.edge_length_ratio),
                self.reg.CorrespondenceCheckerBasedOnDistance(gate),
            ],
            self.reg.RANSACConvergenceCriteria(config.max_iterations, config.confidence),
        )
        return np.asarray(result.transformation)

    def _criteria(self, config: ICPConfig) -> Any:
        return self.reg.ICPConvergenceCriteria(
            relative_fitness=config.relative_fitness,
            relative_rmse=config.relative_rmse,
            max_iteration=config.max_iterations,
        )

    def icp(self, source: PointCloud, target: PointCloud, config: ICPConfig) -> NDArray:
        result = self.reg.registration_icp(
            self.cloud(source, normals=False),
            self.cloud(target),
            config.max_correspondence_distance,
            np.eye(4),
            self.reg.TransformationEstimationPointToPlane(),
            self._criteria(config),
        )
        return np.asarray(result.transformation)

    def prepared(self, frame: PointCloud, voxel_size: float, k: int) -> Any:
        """A frame as a tracker keeps it: voxel-downsampled, normals towards the sensor."""
        pcd = self.voxel(frame, voxel_size)
        pcd.estimate_normals(self.o3d.geometry.KDTreeSearchParamKNN(k))
        pcd.orient_normals_towards_camera_location(np.zeros(3))
        return pcd

    def track(
        self,
        frames: list[PointCloud],
        keyframe: Any,
        voxel_size: float,
        k: int,
        config: ICPConfig,
    ) -> list[NDArray]:
        """The tracker's core steps for each frame in turn: voxel downsampling, normals,
        point-to-plane ICP onto the frame before (``keyframe`` for the first, prepared) from
        the previous pose. Returns each frame's ``T_previous_frame`` (4, 4)."""
        poses = []
        for frame in frames:
            pcd = self.prepared(frame, voxel_size, k)
            result = self.reg.registration_icp(
                pcd,
                keyframe,
                config.max_correspondence_distance,
                np.eye(4),
                self.reg.TransformationEstimationPointToPlane(),
                self._criteria(config),
            )
            poses.append(np.asarray(result.transformation))
            keyframe = pcd
        return poses

    def gicp(self, source: PointCloud, target: PointCloud, config: GICPConfig) -> NDArray:
        # Points only: Open3D estimates the covariances itself, as ours does. It has no
        # update-size criterion; its ICP defaults stop it, with the same iteration limit.
        criteria = self._criteria(ICPConfig(max_iterations=config.max_iterations))
        result = self.reg.registration_generalized_icp(
            self.cloud(source, normals=False),
            self.cloud(target, normals=False),
            config.max_correspondence_distance,
            np.eye(4),
            self.reg.TransformationEstimationForGeneralizedICP(config.epsilon),
            criteria,
        )
        return np.asarray(result.transformation)


class SmallGICP:
    """small_gicp's counterparts: normals and GICP (with its covariance preprocessing)."""

    def __init__(self, sg: ModuleType, threads: int) -> None:
        self.sg = sg
        self.threads = threads

    def _prepared(self, points: NDArray[np.float64], k: int, covariances: bool) -> tuple:
        pc = self.sg.PointCloud(points)
        tree = self.sg.KdTree(pc, num_threads=self.threads)
        estimate = self.sg.estimate_covariances if covariances else self.sg.estimate_normals
        estimate(pc, tree, num_neighbors=k, num_threads=self.threads)
        return pc, tree

    def normals(self, cloud: PointCloud, k: int) -> Any:
        return self._prepared(cloud.points, k, covariances=False)[0]

    def gicp(self, source: PointCloud, target: PointCloud, config: GICPConfig) -> NDArray:
        src, _ = self._prepared(source.points, config.k_covariance, covariances=True)
        tgt, tree = self._prepared(target.points, config.k_covariance, covariances=True)
        result = self.sg.align(
            tgt,
            src,
            tree,
            np.eye(4),
            registration_type="GICP",
            max_correspondence_distance=config.max_correspondence_distance,
            num_threads=self.threads,
            max_iterations=config.max_iterations,
            rotation_epsilon=config.rotation_tolerance,
            translation_epsilon=config.translation_tolerance,
        )
        return np.asarray(result.T_target_source)


@dataclass(frozen=True)
class Peers:
    """The peers this run can time (None: not installed or not asked for)."""

    open3d: Open3D | None = None
    small_gicp: SmallGICP | None = None


# --------------------------------------------------------------------------------------------
# Environment


def _threading_layer() -> str | None:
    """numba's threading layer once a parallel kernel has run (None before)."""
    import numba

    try:
        return numba.threading_layer()
    except ValueError:
        return None


def environment(workers: int, threads: int, peers: dict[str, ModuleType]) -> dict:
    """Machine, library versions and the thread settings every contender ran with."""

    def version(name: str) -> str | None:
        try:
            return importlib.metadata.version(name)
        except importlib.metadata.PackageNotFoundError:
            return None

    return {
        "date": datetime.datetime.now(datetime.UTC).isoformat(timespec="seconds"),
        "platform": platform.platform(),
        "python": platform.python_version(),
        "cpu_count": os.cpu_count(),
        "cpu_affinity": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else None,
        "load_average": list(os.getloadavg()) if hasattr(os, "getloadavg") else None,
        "numpy": np.__version__,
        "scipy": scipy.__version__,
        "numba": version("numba"),
        "open3d": version("open3d"),
        "small_gicp": version("small_gicp"),
        "threads": {
            "workers": workers,
            "ours_workers": workers,
            "resolved": threads,
            "numba_threading_layer": _threading_layer(),
            "open3d_set_max_threads": threads if "open3d" in peers else None,
            "small_gicp_num_threads": threads if "small_gicp" in peers else None,
            "env": {
                k: os.environ.get(k)
                for k in (
                    "OMP_NUM_THREADS",
                    "OMP_WAIT_POLICY",
                    "OPENBLAS_NUM_THREADS",
                    "MKL_NUM_THREADS",
                )
            },
        },
    }
