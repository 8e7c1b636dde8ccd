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


def surface_degeneracy(
    source_points: NDArray[np.float64],
    target_points: NDArray[np.float64],
    T_target_source: NDArray[np.float64],
    radius: float,
    health: HealthConfig = HealthConfig(),
    workers: int = -1,
) -> Degeneracy:
    """Judge which directions of ``T_target_source`` the two surfaces constrain.

    Parameters
    ----------
    source_points, target_points
        (N, 3), (M, 3) clouds, each in its own frame (m).
    T_target_source
        (4, 4) the registration's result.
    radius
        Radius of the clouds (m); the coarse voxel is :data:`COARSE_FRACTION` of it.
    health
        ``lost_condition`` (degenerate above it) and ``ok_condition`` (the free directions are
        those below ``1 / ok_condition`` of the best observed one).
    workers
        Threads for the neighbour searches.

    Returns
    -------
    Degeneracy
    """
    voxel = COARSE_FRACTION * radius
    src = se3.transform_points(T_target_source, voxel_cells(source_points, voxel)[0])
    tgt = PointCloud(voxel_cells(target_points, voxel)[0])
    moved = se3.transform_points(T_target_source, source_points)
    centroid, r = moved.mean(axis=0), rms_radius(moved)
    H = np.zeros((6, 6))
    if len(tgt) >= 3:  # fewer coarse cells than a plane needs: nothing is constrained
        k = min(_NORMAL_NEIGHBOURS, len(tgt))
        tgt = estimate_normals(
            tgt, NormalsConfig(k=k, radius=_GATE_VOXELS * voxel), workers=workers
        )
        s, t, _ = find_correspondences(VoxelIndex(tgt.points), src, _GATE_VOXELS * voxel, workers)
        H = point_to_plane_system(src[s], tgt.points[t], tgt.normals[t])[0]
    condition = normalised_condition(H, centroid, r)
    free = np.zeros((6, 0))
    if not condition <= health.lost_condition:
        M = normalising_map(centroid, r)
        ev, vectors = np.linalg.eigh(M.T @ H @ M)
        free = vectors[:, ev <= ev[-1] / health.ok_condition]
    return Degeneracy(condition, health.lost_condition, free, centroid, r)
