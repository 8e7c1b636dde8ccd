"""The inputs of ``spacepose bench``'s stages, and the truth their registrations are scored against.

:func:`prepare_data` renders three consecutive frames of the lab run (methods.md §3, the ToF camera
at ``BenchConfig.frame_scale`` times its 640×480, :func:`render_frames`) and derives what the
stages take from them (:class:`BenchData`): frames 0 and 1 with normals, and the same two
voxel-downsampled, with normals and FPFH. :func:`coarse_fpfh`, :func:`ransac_config`,
:func:`icp_config` and :func:`gicp_config` turn a :class:`~spacepose.tools.bench.BenchConfig` into
the parameters every contender of a stage gets.

:func:`registration_error` scores a registration against the simulator's truth
(:func:`relative_truth`), which the bench reports beside the frame-to-frame Cramér–Rao bound of the
frame (:func:`crlb_summary`).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from spacepose.core import se3
from spacepose.core.cloud import PointCloud
from spacepose.core.fpfh import FPFHConfig, compute_fpfh
from spacepose.core.gicp import GICPConfig
from spacepose.core.icp import ICPConfig
from spacepose.core.metrics import pose_errors
from spacepose.core.normals import NormalsConfig, estimate_normals
from spacepose.core.ransac import RansacConfig
from spacepose.core.sim import Frame, LabConfig, sensor_config, simulate_lab

if TYPE_CHECKING:
    from spacepose.tools.bench import BenchConfig

# ToF camera of the lab scenario (methods.md §3); the frames are rendered at multiples of it.
_BASE_WIDTH, _BASE_HEIGHT, _BASE_FOCAL = 640, 480, 483.6


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
    fpfh = coarse_fpfh(config)
    features = tuple(compute_fpfh(c, fpfh, workers) for c in coarse)
    return BenchData(frames, clouds, coarse, features, relative_truth(frames[0], frames[1]))


def coarse_fpfh(config: BenchConfig) -> FPFHConfig:
    return FPFHConfig(radius=5.0 * config.coarse_voxel_size, max_nn=100)


def ransac_config(config: BenchConfig, seed: int) -> RansacConfig:
    return RansacConfig(max_correspondence_distance=1.5 * config.coarse_voxel_size, seed=seed)


def icp_config(config: BenchConfig) -> ICPConfig:
    return ICPConfig(
        max_correspondence_distance=config.max_correspondence_distance,
        max_iterations=config.max_iterations,
        method="point_to_plane",
    )


def gicp_config(config: BenchConfig) -> GICPConfig:
    return GICPConfig(
        max_correspondence_distance=config.max_correspondence_distance,
        max_iterations=config.max_iterations,
    )


# --------------------------------------------------------------------------------------------
# Scores against the truth


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
