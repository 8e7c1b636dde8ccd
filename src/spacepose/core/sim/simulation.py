"""A simulated run (methods.md §3): the scene, the sensor, the true poses; frames on demand.

A :class:`Simulation` holds everything that defines a run (target, sensor, poses, background,
seed); its frames are rendered on demand, frame k from ``default_rng([seed, k])``, so any frame
can be regenerated alone and a run never has to sit in memory whole. The lab and orbit
scenarios that build one are in :mod:`spacepose.core.sim.scenarios`.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
import trimesh
from numpy.typing import NDArray

from spacepose.core.cloud import PointCloud
from spacepose.core.crlb import CramerRaoBound, crlb
from spacepose.core.sim.sensors import SensorConfig, scan
from spacepose.core.sim.targets import Target, sample_surface
from spacepose.core.trajectory import Trajectory
from spacepose.errors import ConfigError

if TYPE_CHECKING:
    from spacepose.core.sim.scenarios import LabConfig, OrbitConfig


@dataclass(frozen=True, eq=False)
class Frame:
    """One simulated frame.

    Attributes
    ----------
    timestamp
        Seconds from the start of the run.
    cloud
        Measured points (N, 3) in the sensor frame, with per-point σ (m; along the ray for range
        sensors, per axis for ``gaussian``).
    true_normals
        (N, 3) unit normals of the surfaces hit, pointing towards the sensor, sensor frame.
    T_sensor_target
        (4, 4) true pose of the target (model) frame in the sensor frame.
    on_target
        (N,) True where the ray hit the target, False on the background.
    flying
        (N,) True for flying pixels (outliers between two depths).
    sigma_normal
        (N,) noise σ along the true normal, ``σ_r·|cos θ|`` for range sensors, m.
    """

    timestamp: float
    cloud: PointCloud
    true_normals: NDArray[np.float64]
    T_sensor_target: NDArray[np.float64]
    on_target: NDArray[np.bool_]
    flying: NDArray[np.bool_]
    sigma_normal: NDArray[np.float64]

    def crlb(self, frame_to_frame: bool = False) -> CramerRaoBound:
        """Cramér–Rao bound of registering this frame's target points (methods.md §4).

        Uses the target's non-flying points, their true normals and ``σ_i = σ_r·|cos θ_i|``.
        The twist is about the sensor-frame origin, rotation first (see :mod:`spacepose.core.crlb`).

        Raises
        ------
        ConfigError
            For a noise-free frame (``noise_scale = 0``), whose bound is zero.
        """
        keep = self.on_target & ~self.flying
        if not np.any(self.sigma_normal[keep] > 0):
            raise ConfigError("a noise-free frame (noise_scale 0) has no Cramér-Rao bound")
        return crlb(
            self.cloud.points[keep],
            self.true_normals[keep],
            self.sigma_normal[keep],
            frame_to_frame=frame_to_frame,
        )


@dataclass(frozen=True, eq=False)
class Simulation:
    """A simulated run: the scene, the sensor, the true poses; frames rendered on demand.

    Attributes
    ----------
    name
        ``"lab"`` or ``"orbit"``.
    config
        The scenario config (every parameter, the seed included).
    target
        The target in its model frame (= the target frame of the poses).
    timestamps
        (N,) seconds.
    T_sensor_target
        (N, 4, 4) true poses.
    background
        Extra scene parts, each a mesh with its (N, 4, 4) poses in the sensor frame.
    truth
        Orbit only: (N, 20) table with the columns
        :data:`~spacepose.core.sim.scenarios.TRUTH_COLUMNS`.
    extras
        Scenario facts derived from the config (mean motion, R_O_C, ...), JSON-ready.
    albedo
        Reflectance of the target and of each background part, in that order (empty: all 1).
    """

    name: str
    config: LabConfig | OrbitConfig
    target: Target
    timestamps: NDArray[np.float64]
    T_sensor_target: NDArray[np.float64]
    background: tuple[tuple[trimesh.Trimesh, NDArray[np.float64]], ...] = ()
    truth: NDArray[np.float64] | None = None
    extras: dict[str, Any] | None = None
    albedo: tuple[float, ...] = ()

    def __len__(self) -> int:
        return len(self.timestamps)

    @property
    def sensor(self) -> SensorConfig:
        return self.config.sensor

    @property
    def groundtruth(self) -> Trajectory:
        """True ``T_sensor_target`` per frame."""
        return Trajectory(self.timestamps, self.T_sensor_target, source=f"{self.name} simulation")

    def frame(self, k: int) -> Frame:
        """Render frame ``k`` (0-based); the same k and seed always give the same frame."""
        if not 0 <= k < len(self):
            raise ConfigError(f"frame index {k} out of range 0..{len(self) - 1}")
        meshes = [self.target.mesh.copy().apply_transform(self.T_sensor_target[k])]
        meshes += [mesh.copy().apply_transform(poses[k]) for mesh, poses in self.background]
        scene = trimesh.Trimesh(
            np.concatenate([m.vertices for m in meshes]),
            np.concatenate(
                [m.faces + off for m, off in zip(meshes, _offsets(meshes), strict=True)]
            ),
            process=False,
        )
        rng = np.random.default_rng([self.config.seed, k])
        albedo = np.repeat(self.albedo, [len(m.faces) for m in meshes]) if self.albedo else None
        s = scan(scene, self.sensor, rng, albedo)
        if len(s.points) == 0:
            # Say why, not only that the cloud is empty: the options put nothing in view.
            r = float(np.linalg.norm(self.T_sensor_target[k][:3, 3]))
            raise ConfigError(
                f"{self.name} frame {k}: the sensor sees nothing (target {r:.3g} m away; the "
                f"sensor returns {self.sensor.min_range:g}-{self.sensor.max_range:g} m): check "
                "the range, target size and model scale"
            )
        return Frame(
            timestamp=float(self.timestamps[k]),
            cloud=PointCloud(s.points, sigma=s.sigma, source=f"{self.name} frame {k}"),
            true_normals=s.true_normals,
            T_sensor_target=self.T_sensor_target[k].copy(),
            on_target=s.face < len(self.target.mesh.faces),
            flying=s.flying,
            sigma_normal=s.sigma_normal,
        )

    def frames(self) -> Iterator[Frame]:
        """Every frame in order."""
        return (self.frame(k) for k in range(len(self)))

    def model_cloud(self) -> PointCloud:
        """Surface samples of the target with normals, target frame (``config.model_points``)."""
        return sample_surface(self.target, self.config.model_points, seed=self.config.seed)

    def scenario(self) -> dict[str, Any]:
        """JSON-ready description of the run: every parameter, the seed and derived facts."""
        return {
            "scenario": self.name,
            "seed": self.config.seed,
            "frames": len(self),
            "config": self.config.model_dump(mode="json"),
            "sensor_fov_deg": list(self.sensor.fov_deg),
            "target": self.target.name,
            "rectangles": [r.to_dict() for r in self.target.rectangles],
            **(self.extras or {}),
        }


def _offsets(meshes: list[trimesh.Trimesh]) -> list[int]:
    counts = [len(m.vertices) for m in meshes]
    return [int(v) for v in np.concatenate([[0], np.cumsum(counts)[:-1]])]
