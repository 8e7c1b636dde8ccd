"""Directions of a registered pose that the surfaces leave free (a plane, two planes sliding).

A registration's own information can claim what the data cannot give: GICP's regularised
covariances and the normals' noise put information on the in-plane translations of a plane and
its rotation about its normal. :func:`surface_degeneracy` judges the pair instead by the
point-to-plane information at the result, with the target's normals taken at a coarse voxel
(:data:`COARSE_FRACTION` of the radius) where their noise cannot pass for shape, made unit-free
as the tracker's health check does (:func:`~spacepose.core.health.normalised_condition`) and
held to the tracker's bounds (:class:`~spacepose.core.tracker_config.HealthConfig`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from spacepose.core import se3
from spacepose.core.cloud import PointCloud
from spacepose.core.correspondences import find_correspondences
from spacepose.core.grid import VoxelIndex
from spacepose.core.health import normalised_condition, normalising_map
from spacepose.core.icp_systems import point_to_plane_system
from spacepose.core.moments import on_a_line
from spacepose.core.normals import NormalsConfig, estimate_normals
from spacepose.core.scale import rms_radius
from spacepose.core.tracker_config import HealthConfig
from spacepose.core.voxel import voxel_cells

# Voxel of the check as a fraction of the cloud's radius R. The information a plane's normals
# put on its free directions is their scatter, which falls as the square of the neighbourhood:
# a 0.5 m plane with 3 mm noise scores 59 with the normals of its 6 mm registration voxels (a
# satellite mock-up scores 45-100), 1.4e6-1.8e7 at R/4 (R/6: 1.4e4-3.4e4); the lab, simulated
# and real pairs 7-49. Noise near the fine voxel (6 mm at 7 mm) brings a plane down to 8e3-1.4e4.
COARSE_FRACTION = 0.25
# Neighbours of a coarse normal and gate of the coarse matches, in coarse voxels (the fine
# point-to-plane stage's rule).
_NORMAL_NEIGHBOURS = 20
_GATE_VOXELS = 3.0
# A free direction is named a rotation (translation) when it lies within 45° of one.
_NAMED_COSINE = 0.5**0.5


@dataclass(frozen=True)
class Degeneracy:
    """How well the surfaces of a registered pair constrain the pose.

    Attributes
    ----------
    condition
        Normalised condition number of the coarse point-to-plane information (unit-free).
    bound
        The tracker's ``lost_condition``: above it the pose is degenerate.
    free
        (6, k) orthonormal unit-free twists ``(ρ, v_c)`` (rotations as displacements at
        ``radius``, about ``centroid``) whose information is below ``1 / ok_condition`` of the
        largest; k = 0 unless degenerate.
    centroid, radius
        Of the source moved into the target frame (m).
    """

    condition: float
    bound: float
    free: NDArray[np.float64]
    centroid: NDArray[np.float64]
    radius: float

    @property
    def degenerate(self) -> bool:
        """The pose has directions the data leave (nearly) free."""
        return self.free.shape[1] > 0

    def widen(self, covariance: NDArray[np.float64]) -> NDArray[np.float64]:
        """``covariance`` (6, 6, about the origin) with the radius as σ along the free directions.

        Nothing but the clouds' overlap bounds a free direction, so the pose is known there to
        about the cloud's size: ``radius`` for a translation, a radian for a rotation.
        """
        D = normalising_map(self.centroid, self.radius) @ self.free
        return covariance + self.radius**2 * D @ D.T

    def names(self) -> list[str]:
        """The free rotations (about an axis through the centroid) and translations, in words
        (target frame)."""
        out = []
        through = f" through {_vector(self.centroid, 3)} m"
        for block, kind, where in (
            (self.free[:3], "rotation about", through),
            (self.free[3:], "translation along", ""),
        ):
            # Principal directions of the free subspace's rotation (translation) part: a
            # singular value near 1 is a pure rotation (translation) about (along) that axis.
            axes, cosines, _ = np.linalg.svd(block)
            for axis, cosine in zip(axes.T, cosines, strict=False):
                if cosine > _NAMED_COSINE:
                    axis = axis * np.sign(axis[np.argmax(np.abs(axis))])
                    out.append(f"{kind} {_vector(axis, 2)}{where}")
        return out

    def summary(self) -> str:
        """One sentence: the condition against its bound, the free directions and their σ."""
        return (
            f"degenerate geometry (condition {self.condition:.3g} > {self.bound:.3g}): "
            f"{', '.join(self.names()) or 'every direction'} unconstrained; their sigma is set "
            f"to the cloud's radius ({self.radius:.3g} m, 1 rad)"
        )

    def to_dict(self) -> dict:
        """JSON-ready flag, condition number and the free directions' names."""
        return {
            "degenerate": self.degenerate,
            "condition_number": self.condition,
            "unconstrained": self.names(),
        }


def _vector(x: NDArray[np.float64], decimals: int) -> str:
    """``[x y z]`` rounded, without negative zeros."""
    return "[" + " ".join(f"{v:.{decimals}f}" for v in np.round(x, decimals) + 0.0) + "]"


@dataclass(frozen=True)
class CoarseSurface:
    """A target cloud at the coarse voxel of the check, with its normals (once per target: a
    tracker judges every frame against the same keyframe or model).

    Attributes
    ----------
    voxel
        The coarse voxel edge (m): :data:`COARSE_FRACTION` of the radius it was made for.
    cloud
        (M, 3) coarse cells with normals (target frame); fewer than 3 cells: no normals.
    index
        Their neighbour index.
    """

    voxel: float
    cloud: PointCloud
    index: VoxelIndex

    @classmethod
    def of(
        cls, target_points: NDArray[np.float64], radius: float, workers: int = -1
    ) -> CoarseSurface:
        """The coarse surface of ``target_points`` (M, 3) for clouds of ``radius`` (m)."""
        voxel = COARSE_FRACTION * radius
        cloud = PointCloud(voxel_cells(target_points, voxel)[0])
        # Fewer coarse cells than a plane needs, or all on a line: nothing is constrained.
        if len(cloud) >= 3 and not on_a_line(cloud.points):
            k = min(_NORMAL_NEIGHBOURS, len(cloud))
            config = NormalsConfig(k=k, radius=_GATE_VOXELS * voxel)
            cloud = estimate_normals(cloud, config, workers=workers)
        return cls(voxel, cloud, VoxelIndex(cloud.points))


def surface_degeneracy(
    source_points: NDArray[np.float64],
    target_points: NDArray[np.float64] | CoarseSurface,
    T_target_source: NDArray[np.float64],
    radius: float,
    health: HealthConfig = HealthConfig(),
    workers: int = -1,
) -> Degeneracy:
    """Judge which directions of ``T_target_source`` the two surfaces constrain.

    Parameters
    ----------
    source_points
        (N, 3) cloud in its own frame (m).
    target_points
        (M, 3) cloud in its own frame (m), or its :class:`CoarseSurface` made once.
    T_target_source
        (4, 4) the registration's result.
    radius
        Radius of the clouds (m); the coarse voxel is :data:`COARSE_FRACTION` of it (a given
        coarse surface keeps its own).
    health
        ``lost_condition`` (degenerate above it) and ``ok_condition`` (the free directions are
        those below ``1 / ok_condition`` of the best observed one).
    workers
        Threads for the neighbour searches.

    Returns
    -------
    Degeneracy
    """
    surface = target_points
    if not isinstance(surface, CoarseSurface):
        surface = CoarseSurface.of(np.asarray(target_points, dtype=np.float64), radius, workers)
    voxel, tgt = surface.voxel, surface.cloud
    source_points = np.asarray(source_points, dtype=np.float64)
    src = se3.transform_points(T_target_source, voxel_cells(source_points, voxel)[0])
    # A rigid motion moves the centroid and keeps the radius: no need to move every point.
    centroid = se3.transform_points(T_target_source, source_points.mean(axis=0)[None])[0]
    r = rms_radius(source_points)
    H = np.zeros((6, 6))
    if tgt.normals is not None:
        gate = _GATE_VOXELS * voxel
        s, t, _ = find_correspondences(surface.index, src, gate, workers)
        H = point_to_plane_system(src[s], tgt.points[t], tgt.normals[t])[0]
    condition = normalised_condition(H, centroid, r)
    free = np.zeros((6, 0))
    if not condition <= health.lost_condition:
        M = normalising_map(centroid, r)
        ev, vectors = np.linalg.eigh(M.T @ H @ M)
        free = vectors[:, ev <= ev[-1] / health.ok_condition]
    return Degeneracy(condition, health.lost_condition, free, centroid, r)
