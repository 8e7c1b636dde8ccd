"""``spacepose bench``: speed and accuracy of the pipeline's stages beside Open3D and small_gicp.

Every stage runs on the same simulated lab frames (ToF camera, default noise) for our code and
for each peer, in one process and interleaved (ours, open3d, small_gicp, ours, ...) so that a
change in machine load hits every contender alike. A peer's time includes turning the numpy
inputs into its own types, as a Python caller has to. Registrations (ICP, GICP, RANSAC) are
also scored against the simulator's ground truth beside the Cramér–Rao bound of the frame.

Inputs (methods.md §3 lab scenario, frames 0, 1, 2 of a three-frame run, and a longer run of
the same scenario for ``tracking_step``):

* ``normals``, ``mpp_mls``: frame 0 as rendered.
* ``voxel``: frame 0 voxel-downsampled at the default tracker's voxel (what it derives from it).
* ``fpfh``, ``ransac``: frames 0 and 1 voxel-downsampled (``coarse_voxel_size``), normals within
  2× and FPFH within 5× the voxel (Open3D's global-registration recipe); RANSAC gets the same
  features for every contender, so it compares the sampling and scoring alone.
* ``icp`` (point-to-plane, target normals given) and ``gicp``: frame 1 (source) onto frame 0
  (target) from the identity; truth ``T_s0_s1 = T_s0_target · T_s1_target⁻¹``.
* ``jicp_step``: the third step of a fresh :class:`~spacepose.core.jicp.JointICP` (Li's J-ICP).
* ``tracking_step``: the steady state of a running model-free
  :class:`~spacepose.core.tracker.Tracker` (preprocess + fine registration + health and
  covariance): the default tracker runs frames ``0 .. tracking_warmup_frames − 1`` once
  (untimed; its keyframe window is then full), and each timed call restores that state and
  tracks the next ``tracking_frames`` frames; the row is the time per frame. Open3D does its
  core steps on the same frames (voxel downsampling, normals, point-to-plane ICP onto the
  previous frame prepared as its keyframe, from the previous pose) without health checks or
  covariance.
* ``tracking_second_frame``: the cold start, the second frame of a fresh tracker (no motion
  history yet, so the motion model's wide robust first pass runs), beside Open3D's core steps
  against frame 0 prepared as a keyframe.
* ``ekf_step``: one predict + pose update of the orbit EKF, from the orbit truth.
* ``raw_<W>x<H>``: the ``tracking_step`` on raw frames of the lab mock-up before its wall at
  the ToF camera's full resolution (:mod:`spacepose.tools.bench_fullres`, 300k points at 640×480,
  900k at 1280×720): two untimed frames (the first, the scale estimate, and the second, the cold
  start, are reported beside the row), then ``raw_frames`` timed frames per call.
  The tracker's peak resident memory on a stream at the largest resolution is in ``memory``.

Set-up that a stage needs but is not part of it (the earlier frames of a tracker, restored from a
copy) is done before each timed call and not timed.
"""

from __future__ import annotations

import copy
import datetime
import importlib
import importlib.metadata
import json
import math
import os
import platform
import time
import tracemalloc
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType
from typing import Annotated, Any

import numpy as np
import scipy
from numpy.typing import NDArray
from pydantic import Field, PositiveFloat, PositiveInt
from rich.table import Table
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from spacepose.core import se3
from spacepose.core.cloud import PointCloud
from spacepose.core.config import StageConfig, load_config
from spacepose.core.fpfh import FPFHConfig, compute_fpfh
from spacepose.core.gicp import GICPConfig, gicp
from spacepose.core.icp import ICPConfig, icp
from spacepose.core.metrics import pose_errors
from spacepose.core.normals import NormalsConfig, estimate_normals
from spacepose.core.ransac import RansacConfig, feature_ransac
from spacepose.core.sim import (
    Frame,
    LabConfig,
    OrbitConfig,
    sensor_config,
    simulate_lab,
    simulate_orbit,
)
from spacepose.core.tracker_config import StageLengths
from spacepose.errors import ConfigError, InputError
from spacepose.tools.bench_fullres import max_rss_mb, raw_frames, stream_peak_rss

PEERS: tuple[str, ...] = ("open3d", "small_gicp")
STAGES: tuple[str, ...] = (
    "voxel",
    "normals",
    "mpp_mls",
    "fpfh",
    "ransac",
    "icp",
    "gicp",
    "jicp_step",
    "tracking_step",
    "tracking_second_frame",
    "ekf_step",
)
REGISTRATIONS: tuple[str, ...] = ("ransac", "icp", "gicp")
SCALING_STAGES: tuple[str, ...] = ("normals", "fpfh", "icp", "gicp")
FULL_SIZES: tuple[int, ...] = (5000, 10000, 20000, 40000, 80000)
QUICK_SIZES: tuple[int, ...] = (5000, 10000, 20000)
# ToF camera of the lab scenario (methods.md §3); the frames are rendered at multiples of it.
_BASE_WIDTH, _BASE_HEIGHT, _BASE_FOCAL = 640, 480, 483.6
# Render the scaling frames with this margin over the largest size, then subsample.
_RENDER_MARGIN = 1.15

#: An untimed set-up that returns the call to time (set-up = state a step needs first).
Trial = Callable[[], Callable[[], Any]]


class BenchConfig(StageConfig):
    """What :func:`run_benchmark` measures, and on which data.

    Attributes
    ----------
    frame_scale
        Resolution of the stage frames relative to the 640×480 ToF camera (0.5: 320×240).
    scaling_sizes
        Point counts (at least two, each >= 100) of the scaling runs: random subsets of one
        high-resolution frame pair.
    warmup
        Untimed calls of every contender before the timed ones (first-call set-up costs).
    normals
        Neighbourhood of the ``normals`` stage and of the normals the registrations are given.
    coarse_voxel_size
        Voxel (m) of the clouds behind FPFH and RANSAC.
    max_correspondence_distance
        Gate (m) of ICP and GICP; the frame-to-frame motion is about 1 cm and 1°.
    max_iterations
        Iteration limit of ICP and GICP, for every contender.
    fpfh_spacing_factor
        FPFH radius of the scaling runs as a multiple of the point spacing, so that every size
        does the same work per point.
    tracking_warmup_frames
        Lab frames the ``tracking_step`` tracker runs untimed before the timed ones (by then the
        lab run's keyframe window is full).
    tracking_frames
        Lab frames each timed ``tracking_step`` call tracks (two keyframe periods of the lab run).
    full_resolutions
        (width, height) of the raw-frame rows, one row each; the last is also streamed for the
        tracker's peak memory. Empty: no raw rows.
    raw_frames
        Timed frames per call of a raw row (after its two untimed ones).
    stream_frames
        Frames of that stream.
    """

    frame_scale: PositiveFloat = 1.0
    # At least two sizes to fit an exponent; 100 points leave room for every k-neighbourhood.
    scaling_sizes: tuple[Annotated[int, Field(ge=100)], ...] = Field(FULL_SIZES, min_length=2)
    warmup: int = Field(1, ge=0)
    normals: NormalsConfig = NormalsConfig()
    coarse_voxel_size: PositiveFloat = 0.012
    max_correspondence_distance: PositiveFloat = 0.03
    max_iterations: int = Field(30, ge=1)
    fpfh_spacing_factor: PositiveFloat = 5.0
    tracking_warmup_frames: int = Field(9, ge=2)
    tracking_frames: PositiveInt = 8
    full_resolutions: tuple[tuple[PositiveInt, PositiveInt], ...] = ((640, 480), (1280, 720))
    raw_frames: PositiveInt = 4
    stream_frames: int = Field(8, ge=2)


def bench_config(quick: bool, path: str | Path | None = None) -> BenchConfig:
    """Defaults of a full or quick run (320×240 frames, scaling up to 20k points, raw frames at
    640×480 only, two timed raw frames per call).

    Parameters
    ----------
    quick
        Start from the quick defaults.
    path
        Optional YAML/JSON file; the options it sets replace the defaults (the rest are kept).

    Raises
    ------
    ConfigError
        An unreadable file or an invalid option.
    """
    quick_options = {"frame_scale": 0.5, "scaling_sizes": QUICK_SIZES}
    base = (
        BenchConfig(**quick_options, full_resolutions=((640, 480),), raw_frames=2, stream_frames=3)
        if quick
        else BenchConfig()
    )
    if path is None:
        return base
    overrides = load_config(BenchConfig, path)
    # Top-level options the file sets, as validated objects (a nested config stays a model).
    return base.model_copy(update={k: getattr(overrides, k) for k in overrides.model_fields_set})


# --------------------------------------------------------------------------------------------
# Timing primitives


@dataclass(frozen=True)
class Timing:
    """Wall times (ms) of the timed calls of one contender and what each call returned."""

    times_ms: list[float]
    outputs: list[Any]

    @property
    def last(self) -> Any:
        return self.outputs[-1]


def time_interleaved(
    trials: Mapping[str, Trial], repeats: int, warmup: int = 1
) -> dict[str, Timing]:
    """Time several contenders in turn: set up and call each once per round, ``repeats`` rounds.

    Parameters
    ----------
    trials
        Contender name -> untimed set-up returning the call to time.
    repeats
        Timed rounds.
    warmup
        Untimed rounds first.

    Returns
    -------
    dict[str, Timing]
        One per contender, in the order given.
    """
    for _ in range(warmup):
        for setup in trials.values():
            setup()()
    timings = {name: Timing([], []) for name in trials}
    for _ in range(repeats):
        for name, setup in trials.items():
            call = setup()
            tic = time.perf_counter()
            out = call()
            timings[name].times_ms.append(1e3 * (time.perf_counter() - tic))
            timings[name].outputs.append(out)
    return timings


def summarize(times_ms: list[float]) -> dict[str, float]:
    """Median, min and max (ms) of a list of times, and how many there are."""
    t = np.asarray(times_ms, dtype=np.float64)
    return {
        "median_ms": float(np.median(t)),
        "min_ms": float(t.min()),
        "max_ms": float(t.max()),
        "repeats": len(t),
    }


def fit_exponent(sizes: list[int], times_ms: list[float]) -> float:
    """Exponent b of ``t ∝ N^b``: least-squares slope of log t against log N."""
    return float(np.polyfit(np.log(sizes), np.log(times_ms), 1)[0])


def registration_error(T_est: NDArray[np.float64], T_gt: NDArray[np.float64]) -> dict:
    """Translation error (mm, norm of Δt) and rotation error (deg, angle of ΔR) of one estimate.

    ``ΔT = T_est · T_gt⁻¹`` as :func:`~spacepose.core.metrics.pose_errors` (Li Eq. 10).
    """
    dt, euler = pose_errors(T_est, T_gt)
    angle = Rotation.from_euler("ZYX", euler[0]).magnitude()
    return {
        "translation_mm": float(1e3 * np.linalg.norm(dt[0])),
        "rotation_deg": float(np.degrees(angle)),
    }


def crlb_summary(frame: Frame) -> dict:
    """Frame-to-frame Cramér–Rao bound of a frame: per-axis std and their root-sum-squares.

    The twist is about the sensor origin, as the errors of :func:`registration_error` are.
    """
    std = frame.crlb(frame_to_frame=True).std
    return {
        "translation_mm": float(1e3 * np.linalg.norm(std[3:])),
        "rotation_deg": float(np.degrees(np.linalg.norm(std[:3]))),
        "std_rotation_deg": np.degrees(std[:3]).tolist(),
        "std_translation_mm": (1e3 * std[3:]).tolist(),
    }


# --------------------------------------------------------------------------------------------
# Data


@dataclass(frozen=True)
class BenchData:
    """Frames and derived clouds every stage draws on.

    Attributes
    ----------
    frames
        Three consecutive lab frames (sensor frames).
    clouds
        Frames 0 and 1 with normals (``BenchConfig.normals``).
    coarse
        Frames 0 and 1 voxel-downsampled, with normals.
    features
        FPFH (N, 33) of ``coarse``.
    T_gt
        (4, 4) true ``T_s0_s1``: frame-1 sensor coordinates into frame 0.
    """

    frames: tuple[Frame, ...]
    clouds: tuple[PointCloud, PointCloud]
    coarse: tuple[PointCloud, PointCloud]
    features: tuple[NDArray[np.float64], NDArray[np.float64]]
    T_gt: NDArray[np.float64]


def render_frames(scale: float, count: int, seed: int) -> tuple[Frame, ...]:
    """The first ``count`` frames of the lab run with the ToF camera at ``scale``× resolution."""
    sensor = sensor_config(
        "tof",
        width=max(1, round(_BASE_WIDTH * scale)),
        height=max(1, round(_BASE_HEIGHT * scale)),
        focal_px=_BASE_FOCAL * scale,
    )
    sim = simulate_lab(LabConfig(frames=count, seed=seed, sensor=sensor))
    return tuple(sim.frame(k) for k in range(count))


def relative_truth(target: Frame, source: Frame) -> NDArray[np.float64]:
    """True ``T_target_source`` between two frames' sensor frames."""
    return target.T_sensor_target @ se3.invert(source.T_sensor_target)


def prepare_data(config: BenchConfig, seed: int, workers: int) -> BenchData:
    """Render the frames and compute the normals and features the stages take as inputs."""
    from spacepose.core.voxel import voxel_downsample

    frames = render_frames(config.frame_scale, 3, seed)
    clouds = tuple(estimate_normals(f.cloud, config.normals, workers=workers) for f in frames[:2])
    voxel = config.coarse_voxel_size
    coarse = tuple(
        estimate_normals(
            voxel_downsample(f.cloud, voxel), NormalsConfig(radius=2.0 * voxel), workers=workers
        )
        for f in frames[:2]
    )
    fpfh = _coarse_fpfh(config)
    features = tuple(compute_fpfh(c, fpfh, workers) for c in coarse)
    return BenchData(frames, clouds, coarse, features, relative_truth(frames[0], frames[1]))


def _coarse_fpfh(config: BenchConfig) -> FPFHConfig:
    return FPFHConfig(radius=5.0 * config.coarse_voxel_size, max_nn=100)


def _ransac_config(config: BenchConfig, seed: int) -> RansacConfig:
    return RansacConfig(max_correspondence_distance=1.5 * config.coarse_voxel_size, seed=seed)


def _icp_config(config: BenchConfig) -> ICPConfig:
    return ICPConfig(
        max_correspondence_distance=config.max_correspondence_distance,
        max_iterations=config.max_iterations,
        method="point_to_plane",
    )


def _gicp_config(config: BenchConfig) -> GICPConfig:
    return GICPConfig(
        max_correspondence_distance=config.max_correspondence_distance,
        max_iterations=config.max_iterations,
    )


# --------------------------------------------------------------------------------------------
# Peers


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


class _Open3D:
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


class _SmallGICP:
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
class _Peers:
    open3d: _Open3D | None = None
    small_gicp: _SmallGICP | None = None


def _ready(call: Callable[[], Any]) -> Trial:
    """A trial without set-up."""
    return lambda: call


# --------------------------------------------------------------------------------------------
# Stages: the trials of every contender of a stage, on identical inputs


def _voxel_trials(cloud: PointCloud, voxel_size: float, peers: _Peers) -> dict[str, Trial]:
    from spacepose.core.voxel import voxel_downsample

    trials = {"ours": _ready(lambda: voxel_downsample(cloud, voxel_size))}
    if peers.open3d is not None:
        trials["open3d"] = _ready(lambda: peers.open3d.voxel(cloud, voxel_size))
    return trials


def _normals_trials(
    cloud: PointCloud, config: NormalsConfig, workers: int, peers: _Peers
) -> dict[str, Trial]:
    trials = {"ours": _ready(lambda: estimate_normals(cloud, config, workers=workers))}
    if peers.open3d is not None:
        trials["open3d"] = _ready(lambda: peers.open3d.normals(cloud, config.k))
    if peers.small_gicp is not None:
        trials["small_gicp"] = _ready(lambda: peers.small_gicp.normals(cloud, config.k))
    return trials


def _fpfh_trials(cloud: PointCloud, config: FPFHConfig, workers: int, peers: _Peers) -> dict:
    trials = {"ours": _ready(lambda: compute_fpfh(cloud, config, workers))}
    if peers.open3d is not None:
        trials["open3d"] = _ready(lambda: peers.open3d.fpfh(cloud, config.radius, config.max_nn))
    return trials


def _icp_trials(
    source: PointCloud, target: PointCloud, config: ICPConfig, workers: int, peers: _Peers
) -> dict[str, Trial]:
    trials = {
        "ours": _ready(lambda: icp(source, target, np.eye(4), config, workers).T_target_source)
    }
    if peers.open3d is not None:
        trials["open3d"] = _ready(lambda: peers.open3d.icp(source, target, config))
    return trials


def _gicp_trials(
    source: PointCloud, target: PointCloud, config: GICPConfig, workers: int, peers: _Peers
) -> dict[str, Trial]:
    # Points only for every contender: each builds its own tree and covariances.
    src, tgt = PointCloud(source.points), PointCloud(target.points)
    trials = {"ours": _ready(lambda: gicp(src, tgt, np.eye(4), config, workers).T_target_source)}
    if peers.open3d is not None:
        trials["open3d"] = _ready(lambda: peers.open3d.gicp(src, tgt, config))
    if peers.small_gicp is not None:
        trials["small_gicp"] = _ready(lambda: peers.small_gicp.gicp(src, tgt, config))
    return trials


def _ransac_trials(data: BenchData, config: RansacConfig, workers: int, peers: _Peers) -> dict:
    (tgt, src), (f_tgt, f_src) = data.coarse, data.features
    trials = {
        "ours": _ready(
            lambda: feature_ransac(src, tgt, f_src, f_tgt, config, workers).T_target_source
        )
    }
    if peers.open3d is not None:
        trials["open3d"] = _ready(lambda: peers.open3d.ransac(src, tgt, f_src, f_tgt, config))
    return trials


def _mls_trials(data: BenchData, workers: int) -> dict[str, Trial]:
    from spacepose.core.mls import MLSConfig, mpp_mls

    cloud = data.frames[0].cloud
    return {"ours": _ready(lambda: mpp_mls(cloud, MLSConfig(), workers))}


def _jicp_trials(data: BenchData, workers: int) -> dict[str, Trial]:
    from spacepose.core.jicp import JointICP

    f0, f1, f2 = (f.cloud for f in data.frames)
    config = _tracker_lengths(f0).jicp

    def setup() -> Callable[[], Any]:
        joint = JointICP(config, workers)
        joint.step(f0)
        joint.step(f1)
        return lambda: joint.step(f2)

    return {"ours": setup}


def _second_frame_trials(
    f0: Frame, f1: Frame, workers: int, peers: _Peers, first_ms: list[float] | None = None
) -> dict[str, Trial]:
    """A fresh default tracker's second frame ``f1`` (``f0`` first, untimed, its time appended
    to ``first_ms``) beside Open3D's core steps against ``f0`` prepared as a keyframe."""
    from spacepose.core.tracker import Tracker, TrackerConfig

    config = TrackerConfig()

    def setup() -> Callable[[], Any]:
        tracker = Tracker(config, None, workers)
        tic = time.perf_counter()
        tracker.track_frame(f0.cloud, f0.timestamp)
        if first_ms is not None:
            first_ms.append(1e3 * (time.perf_counter() - tic))
        return lambda: [tracker.track_frame(f1.cloud, f1.timestamp)]

    return {"ours": setup, **_open3d_tracking(f0, [f1], peers)}


def _steady_trials(
    frames: list[Frame], warmup: int, workers: int, peers: _Peers, warm_ms: list[float]
) -> dict[str, Trial]:
    """A running default tracker on ``frames[warmup:]``: it tracks ``frames[:warmup]`` once,
    untimed (each frame's time appended to ``warm_ms``), and every set-up restores a copy of
    that state; beside Open3D's core steps on the same frames."""
    from spacepose.core.tracker import Tracker, TrackerConfig

    tracker = Tracker(TrackerConfig(), None, workers)
    for frame in frames[:warmup]:
        tic = time.perf_counter()
        tracker.track_frame(frame.cloud, frame.timestamp)
        warm_ms.append(1e3 * (time.perf_counter() - tic))
    timed = frames[warmup:]

    def setup() -> Callable[[], Any]:
        running = copy.deepcopy(tracker)
        return lambda: [running.track_frame(f.cloud, f.timestamp) for f in timed]

    return {"ours": setup, **_open3d_tracking(frames[0], timed, peers, frames[warmup - 1])}


def _open3d_tracking(
    first: Frame, timed: list[Frame], peers: _Peers, previous: Frame | None = None
) -> dict[str, Trial]:
    """Open3D's trial tracking ``timed`` frame to frame, with the voxel and normals the default
    tracker derives from ``first``; ``previous`` (default ``first``) is prepared untimed as the
    keyframe of the first timed frame. Empty without Open3D."""
    o3d = peers.open3d
    if o3d is None:
        return {}
    from spacepose.core.tracker import TrackerConfig

    lengths, k = _tracker_lengths(first.cloud), TrackerConfig().normals.k
    clouds = [f.cloud for f in timed]

    def setup() -> Callable[[], Any]:
        keyframe = o3d.prepared((previous or first).cloud, lengths.voxel, k)
        return lambda: o3d.track(clouds, keyframe, lengths.voxel, k, lengths.keyframe_graph.icp)

    return {"open3d": setup}


def _tracker_lengths(first: PointCloud) -> StageLengths:
    """The default tracker's lengths for a first frame (what a fresh tracker derives)."""
    from spacepose.core.scale import derive_scale
    from spacepose.core.tracker_config import TrackerConfig, stage_lengths

    config = TrackerConfig()
    scale = derive_scale(first.points, config.points_per_frame, config.voxel_size)
    return stage_lengths(config, scale.voxel, scale.radius)


def _ekf_trials(seed: int) -> dict[str, Trial]:
    from spacepose.core.ekf import RelativeNavEKF
    from spacepose.core.nav_state import NavState

    sim = simulate_orbit(OrbitConfig(frames=2, seed=seed))
    row0, row1 = sim.truth
    initial = NavState(
        t=row0[0],
        rho=row0[1:4],
        v=row0[4:7],
        q_I_B=row0[7:11],
        omega_B=row0[11:14],
        k=row0[14:17],
        com=row0[17:20],
    )
    extras = sim.extras or {}
    # A pose measurement with 1 mrad / 5 mm noise, the order of a registration at 25 m.
    cov6 = np.diag([1e-3**2] * 3 + [5e-3**2] * 3)
    T_meas = sim.T_sensor_target[1]

    def setup() -> Callable[[], Any]:
        ekf = RelativeNavEKF(extras["mean_motion"], np.array(extras["R_O_C"]), initial)

        def step() -> bool:
            ekf.predict(row1[0])
            return ekf.update_pose(T_meas, cov6)

        return step

    return {"ours": setup}


def _stage_entry(timings: dict[str, Timing], n_points: int) -> dict:
    ours = summarize(timings["ours"].times_ms)
    peers = {name: summarize(t.times_ms) for name, t in timings.items() if name != "ours"}
    return {
        **ours,
        "n_points": int(n_points),
        "peer": peers,
        "ratio": {name: p["median_ms"] / ours["median_ms"] for name, p in peers.items()},
    }


def _per_frame(timing: Timing) -> Timing:
    """A tracking contender's call times divided by the frames each call tracked (every output
    is the list of one call's per-frame results)."""
    return Timing(
        [t / len(out) for t, out in zip(timing.times_ms, timing.outputs, strict=True)],
        timing.outputs,
    )


def _tracking_shares(timing: Timing) -> dict:
    """Per-frame stage times the tracker reported over the timed calls, and their shares.

    ``status`` is the last frame's health label and ``statuses`` counts every timed frame's: a
    lost frame would time the wrong work; ``tracker`` says which default pipeline was timed.
    """
    from spacepose.core.tracker import STAGES as TRACKER_STAGES
    from spacepose.core.tracker import TrackerConfig

    results = [result for call in timing.outputs for result in call]
    reports = [result.time_ms for result in results]
    medians = {s: float(np.median([r.get(s, 0.0) for r in reports])) for s in TRACKER_STAGES}
    # Shares as ratios of sums over the frames: the stages partition each frame's total, so the
    # shares add up to 1 (medians of the parts need not add up to the median of the whole).
    sums = {s: float(sum(r.get(s, 0.0) for r in reports)) for s in TRACKER_STAGES}
    total = sums["total"]
    statuses = [result.status for result in results]
    return {
        "tracker": TrackerConfig().model_dump(
            include={"method", "use_mls", "points_per_frame", "voxel_size"}
        ),
        "status": statuses[-1],
        "statuses": {s: statuses.count(s) for s in sorted(set(statuses))},
        "frames_per_call": len(timing.last),
        "median_ms": medians,
        "mean_ms": {s: v / len(reports) for s, v in sums.items()},
        "share": {s: v / total for s, v in sums.items() if s != "total" and total > 0},
    }


# --------------------------------------------------------------------------------------------
# Scaling


def scaling_clouds(
    sizes: tuple[int, ...], base: Frame, seed: int, frame_scale: float
) -> tuple[list[tuple[PointCloud, PointCloud]], list[float]]:
    """Random subsets of one high-resolution frame pair, one pair of clouds per size.

    Parameters
    ----------
    sizes
        Point counts wanted.
    base
        A frame rendered at ``frame_scale``; its point count sets the resolution of the pair,
        rendered so that it holds ``max(sizes)`` points with a margin.
    seed, frame_scale
        Seed of the frames and the subsets; resolution of ``base``.

    Returns
    -------
    pairs, spacings
        (target = frame 0, source = frame 1) subsets, independent like two scans; and each
        size's point spacing (m): the rendered frame's median neighbour distance times
        ``sqrt(rendered / N)``, as a random subset thins the density in proportion.
    """
    scale = frame_scale * math.sqrt(_RENDER_MARGIN * max(sizes) / len(base.cloud))
    frames = render_frames(scale, 2, seed)
    full = frames[1].cloud.points
    spacing = float(np.median(cKDTree(full).query(full, k=2)[0][:, 1]))
    rng = np.random.default_rng(seed)
    pairs, spacings = [], []
    for n in sizes:
        subsets = []
        for f in frames:
            keep = np.sort(rng.choice(len(f.cloud), size=min(n, len(f.cloud)), replace=False))
            subsets.append(f.cloud.select(keep))
        pairs.append((subsets[0], subsets[1]))
        spacings.append(spacing * math.sqrt(len(full) / len(subsets[1])))
    return pairs, spacings


def run_scaling(
    config: BenchConfig,
    base: Frame,
    seed: int,
    workers: int,
    repeats: int,
    peers: _Peers,
) -> dict:
    """Times of normals, FPFH, ICP and GICP over ``config.scaling_sizes``, and their exponents.

    Neighbourhoods are fixed in neighbours, not metres (normals k, GICP k, FPFH radius a fixed
    multiple of the point spacing), so the exponent measures the algorithm, not a neighbour
    count growing with density.
    """
    pairs, spacings = scaling_clouds(config.scaling_sizes, base, seed, config.frame_scale)
    series: dict[str, dict[str, list[float]]] = {s: {} for s in SCALING_STAGES}
    sizes = []
    for (target, source), spacing in zip(pairs, spacings, strict=True):
        sizes.append(len(source))
        target_n = estimate_normals(target, config.normals, workers=workers)
        source_n = estimate_normals(source, config.normals, workers=workers)
        fpfh = FPFHConfig(radius=config.fpfh_spacing_factor * spacing, max_nn=100)
        stage_trials = {
            "normals": _normals_trials(source, config.normals, workers, peers),
            "fpfh": _fpfh_trials(source_n, fpfh, workers, peers),
            "icp": _icp_trials(source, target_n, _icp_config(config), workers, peers),
            "gicp": _gicp_trials(source, target, _gicp_config(config), workers, peers),
        }
        for stage, trials in stage_trials.items():
            timings = time_interleaved(trials, repeats, config.warmup)
            for name, t in timings.items():
                series[stage].setdefault(name, []).append(summarize(t.times_ms)["median_ms"])
    return {
        "sizes": sizes,
        "fpfh_radius_m": [config.fpfh_spacing_factor * s for s in spacings],
        "stages": {
            stage: {
                name: {"median_ms": times, "exponent": fit_exponent(sizes, times)}
                for name, times in by_name.items()
            }
            for stage, by_name in series.items()
        },
    }


# --------------------------------------------------------------------------------------------
# Memory and environment


def peak_memory(trials: Mapping[str, Trial]) -> dict:
    """tracemalloc peak (MB) above the baseline of one call of each of our stages."""
    per_stage = {}
    tracemalloc.start()
    try:
        for name, setup in trials.items():
            call = setup()
            tracemalloc.reset_peak()
            base, _ = tracemalloc.get_traced_memory()
            call()
            per_stage[name] = (tracemalloc.get_traced_memory()[1] - base) / 2**20
    finally:
        tracemalloc.stop()
    return {"tracemalloc_peak_mb": per_stage, "pipeline_peak_mb": max(per_stage.values())}


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


# --------------------------------------------------------------------------------------------
# One call


def run_benchmark(
    quick: bool = False,
    peers: bool = False,
    repeats: int = 5,
    seed: int = 0,
    workers: int = -1,
    config: BenchConfig | None = None,
) -> dict:
    """Time every stage (and the peers' counterparts), score the registrations, measure memory.

    Parameters
    ----------
    quick
        Smaller frames and scaling sizes (:func:`bench_config`).
    peers
        Also run Open3D and small_gicp (both must be installed).
    repeats
        Timed calls per contender and stage (after ``config.warmup`` untimed ones).
    seed
        Seed of the simulated frames, the subsets and every RANSAC.
    workers
        Threads for our neighbour searches (-1: all cores); the peers get the same count.
    config
        Overrides the defaults chosen by ``quick``.

    Returns
    -------
    JSON-ready dict: ``environment``, ``config``, ``stages`` (per stage ``median_ms``,
    ``min_ms``, ``max_ms``, ``n_points``, ``peer``, ``ratio`` = peer median / our median;
    ``tracking_step`` also ``substages``), ``accuracy`` (per registration, each contender's
    errors and the Cramér–Rao bound), ``memory`` and ``scaling``.

    Raises
    ------
    ConfigError
        ``repeats`` < 1, a bad ``workers``, or ``peers`` without the peer libraries.
    """
    if repeats < 1:
        raise ConfigError(f"repeats must be at least 1, got {repeats}")
    threads = thread_count(workers)
    config = config or bench_config(quick)
    modules = load_peers() if peers else {}
    contenders = _Peers(
        open3d=_Open3D(modules["open3d"], threads) if "open3d" in modules else None,
        small_gicp=_SmallGICP(modules["small_gicp"], threads) if "small_gicp" in modules else None,
    )
    try:
        result = _measure(config, repeats, seed, workers, contenders)
    finally:
        if contenders.open3d is not None:
            contenders.open3d.close()
    return {"environment": environment(workers, threads, modules), **result}


def _measure(
    config: BenchConfig, repeats: int, seed: int, workers: int, contenders: _Peers
) -> dict:
    """Everything :func:`run_benchmark` reports but the environment."""
    data = prepare_data(config, seed, workers)
    (tgt, src), (tgt_coarse, _) = data.clouds, data.coarse
    frame0 = data.frames[0].cloud
    # The steady tracking row runs on a longer lab run (time per frame, after its warm-up).
    warm = config.tracking_warmup_frames
    lab = render_frames(config.frame_scale, warm + config.tracking_frames, seed)
    stage_trials: dict[str, dict[str, Trial]] = {
        "voxel": _voxel_trials(frame0, _tracker_lengths(frame0).voxel, contenders),
        "normals": _normals_trials(data.frames[0].cloud, config.normals, workers, contenders),
        "mpp_mls": _mls_trials(data, workers),
        "fpfh": _fpfh_trials(tgt_coarse, _coarse_fpfh(config), workers, contenders),
        "ransac": _ransac_trials(data, _ransac_config(config, seed), workers, contenders),
        "icp": _icp_trials(src, tgt, _icp_config(config), workers, contenders),
        "gicp": _gicp_trials(src, tgt, _gicp_config(config), workers, contenders),
        "jicp_step": _jicp_trials(data, workers),
        "tracking_step": _steady_trials(lab, warm, workers, contenders, []),
        "tracking_second_frame": _second_frame_trials(*data.frames[:2], workers, contenders),
        "ekf_step": _ekf_trials(seed),
    }
    n_points = {
        "voxel": len(frame0),
        "normals": len(data.frames[0].cloud),
        "mpp_mls": len(data.frames[0].cloud),
        "fpfh": len(tgt_coarse),
        "ransac": len(data.coarse[1]),
        "icp": len(src),
        "gicp": len(src),
        "jicp_step": len(data.frames[2].cloud),
        "tracking_step": len(lab[warm].cloud),
        "tracking_second_frame": len(data.frames[1].cloud),
        "ekf_step": 0,
    }
    # Raw rows: two untimed frames (their times reported beside), then the timed ones.
    raw, warm_ms = {}, {}
    for k, (width, height) in enumerate(config.full_resolutions):
        streamed = k == len(config.full_resolutions) - 1
        count = 2 + config.raw_frames
        rendered = max(count, config.stream_frames) if streamed else count
        frames = raw_frames(width, height, rendered, seed)
        name = f"raw_{width}x{height}"
        warm_ms[name] = []
        stage_trials[name] = _steady_trials(frames[:count], 2, workers, contenders, warm_ms[name])
        n_points[name] = len(frames[2].cloud)
        if streamed:
            raw = {"width": width, "height": height, "frames": frames[: config.stream_frames]}
    stages, accuracy = {}, {}
    bound = crlb_summary(data.frames[0])
    for name, trials in stage_trials.items():
        timings = time_interleaved(trials, repeats, config.warmup)
        tracking = name.startswith(("tracking_", "raw_"))
        if tracking:
            timings = {who: _per_frame(t) for who, t in timings.items()}
        stages[name] = _stage_entry(timings, n_points[name])
        if name in REGISTRATIONS:
            accuracy[name] = {
                who: registration_error(t.last, data.T_gt) for who, t in timings.items()
            }
            accuracy[name]["crlb"] = bound
        if tracking:
            stages[name]["substages"] = _tracking_shares(timings["ours"])
        if name in warm_ms:
            # One untimed run of each (every set-up restores a copy of the state after them).
            first, second = warm_ms[name]
            stages[name]["first_frame_ms"], stages[name]["second_frame_ms"] = first, second
    memory = peak_memory({name: trials["ours"] for name, trials in stage_trials.items()})
    scaling = run_scaling(config, data.frames[0], seed, workers, repeats, contenders)
    memory["max_rss_mb"] = max_rss_mb()
    if raw:
        memory["tracker_stream"] = {
            "width": raw["width"],
            "height": raw["height"],
            **stream_peak_rss(raw["frames"], workers),
        }
    return {
        "config": {**config.model_dump(mode="json"), "repeats": repeats, "seed": seed},
        "stages": stages,
        "accuracy": accuracy,
        "memory": memory,
        "scaling": scaling,
    }


# --------------------------------------------------------------------------------------------
# Output


def _json_ready(value: Any) -> Any:
    """A copy with non-finite floats as None, so the file is strict JSON."""
    if isinstance(value, dict):
        return {k: _json_ready(v) for k, v in value.items()}
    if isinstance(value, list | tuple):
        return [_json_ready(v) for v in value]
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def write_bench(result: dict, path: str | Path) -> Path:
    """Write a :func:`run_benchmark` result as JSON (non-finite numbers as null).

    Raises
    ------
    InputError
        When the file cannot be written.
    """
    path = Path(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(json.dumps(_json_ready(result), indent=2, allow_nan=False) + "\n")
    except OSError as exc:
        raise InputError(f"cannot write the benchmark: {exc.strerror}", path) from None
    return path


def _ms(entry: dict | None) -> str:
    return "-" if entry is None else f"{entry['median_ms']:.1f}"


def stage_table(result: dict) -> Table:
    """Rich table of the stage times: ours (median, min–max) and each peer with its ratio."""
    names = [p for p in PEERS if any(p in s["peer"] for s in result["stages"].values())]
    table = Table(title="stage times (ms, median of repeats; tracking rows: per frame)")
    for col in ("stage", "N", "ours", "ours min-max", *(f"{p} (x ours)" for p in names)):
        table.add_column(col, justify="left" if col == "stage" else "right")
    for stage, s in result["stages"].items():
        peers = [
            f"{_ms(s['peer'][p])} ({s['ratio'][p]:.2f})" if p in s["peer"] else "-" for p in names
        ]
        spread = f"{s['min_ms']:.1f}-{s['max_ms']:.1f}"
        table.add_row(stage, str(s["n_points"] or "-"), _ms(s), spread, *peers)
    return table


def accuracy_table(result: dict) -> Table:
    """Rich table of the registration errors beside the Cramér–Rao bound."""
    table = Table(title="registration error vs truth (frame-to-frame CRLB std)")
    for col in ("stage", "who", "translation mm", "rotation deg"):
        table.add_column(col, justify="left" if col in ("stage", "who") else "right")
    for stage, by_who in result["accuracy"].items():
        for who, err in by_who.items():
            label = "CRLB" if who == "crlb" else who
            table.add_row(
                stage, label, f"{err['translation_mm']:.3f}", f"{err['rotation_deg']:.4f}"
            )
    return table
