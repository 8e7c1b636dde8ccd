"""Directions of a registered pose that the surfaces leave free (a plane sliding or turning
about its normal, a sphere turning, a cylinder turning about its axis).

A registration's own information can claim what the data cannot give: GICP's regularised
covariances and the normals' noise put information on every direction, free ones included, and
when a curved surface is paired across a distance the pairing itself adds some (a point matched
to a sample farther along the curve has a lever arm about the axis). :func:`surface_degeneracy`
judges the pair instead by rows taken at points of the target's surface with normals centred on
them, at a coarse scale (:class:`CoarseSurface`), and counts a row on a direction only as far as
it leans on it by more than the normals' noise and tilt can (:func:`aligned_information`). The
result is made unit-free as the tracker's health check does
(:func:`~spacepose.core.health.normalising_map`) and held to the tracker's bounds
(:class:`~spacepose.core.tracker_config.HealthConfig`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numba
import numpy as np
from numpy.typing import ArrayLike, NDArray

from spacepose.core import se3
from spacepose.core.cloud import PointCloud, as_cloud, as_points
from spacepose.core.correspondences import find_correspondences
from spacepose.core.grid import VoxelIndex
from spacepose.core.health import normalising_map
from spacepose.core.moments import on_a_line
from spacepose.core.neighbors import hybrid
from spacepose.core.normals import normals_from_covariances
from spacepose.core.scale import rms_radius
from spacepose.core.tracker_config import HealthConfig
from spacepose.core.voxel import voxel_cells
from spacepose.errors import InputError

# Sampling cell and normal neighbourhood as fractions of the cloud's radius R. The plane fit
# of the points within R/4 of a sample leans on a free direction by its noise, by the cells it
# is summed over (_MOMENT_CELLS) and, at the rim of the visible surface, by the tilt of a
# one-sided neighbourhood: on a sphere, a cylinder and a plane at 1.5 m (3 seeds each), at most
# 0.054 / 0.067 / 0.007 under 2 mm of range noise, 0.052 / 0.069 / 0.024 under 6 mm, and
# 0.09-0.17 on the curved ones under 12 mm.
SAMPLE_FRACTION = 0.125
NORMAL_FRACTION = 0.25
# A sample's normal sums the points' moments over cells of R/16 (a quarter of its reach), at
# most the 96 nearest cells (a surface crossing the ball fills about 50, at most 78 on a lab
# keyframe).
_MOMENT_CELLS = 4
_NORMAL_CAP = 96
# Sine of the angle by which a row must lean on a direction to count there (5.7°): 1.45 times
# what 6 mm of noise (3x the ToF camera's at 1.5 m) gives a free direction, below what the
# grid's targets give their weakest one (methods.md §5.3).
ALIGNMENT = 0.1
# Gate of the coarse matches, in sampling cells.
_GATE_VOXELS = 3.0
# A free direction is named a rotation (translation) when it lies within 45° of one.
_NAMED_COSINE = 0.5**0.5


@dataclass(frozen=True)
class Degeneracy:
    """How well the surfaces of a registered pair constrain the pose.

    Attributes
    ----------
    condition
        Largest over smallest :func:`aligned_information` of the coarse surface the frame
        overlaps (unit-free); inf when some direction gets none.
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
        """The free rotations (about an axis through a point on it) and translations, in
        words (target frame)."""
        out = []
        for block, kind in (
            (self.free[:3], "rotation about"),
            (self.free[3:], "translation along"),
        ):
            # Principal directions of the free subspace's rotation (translation) part: a
            # singular value near 1 is a pure rotation (translation) about (along) that axis.
            axes, cosines, mix = np.linalg.svd(block)
            for axis, cosine, coefficients in zip(axes.T, cosines, mix, strict=False):
                if cosine > _NAMED_COSINE:
                    axis = axis * np.sign(axis[np.argmax(np.abs(axis))])
                    where = ""
                    if kind == "rotation about":
                        where = f" through {_vector(self._on_axis(coefficients / cosine), 3)} m"
                    out.append(f"{kind} {_vector(axis, 2)}{where}")
        return out

    def _on_axis(self, coefficients: NDArray[np.float64]) -> NDArray[np.float64]:
        """The point nearest the centroid on the axis of the free twist ``free @ coefficients``
        (a unit rotation part): a sphere's free turns pass through its centre, a cylinder's
        through its axis, not through the centroid of the part in view."""
        twist = self.free @ coefficients
        omega, v_c = twist[:3] / self.radius, twist[3:]
        # A turn ω about an axis through p moves the centroid c by ω × (c − p).
        return self.centroid - np.cross(v_c, omega) / (omega @ omega)

    def summary(self) -> str:
        """One sentence: the condition against its bound, the free directions and their σ."""
        return (
            f"degenerate geometry (condition {self.condition:.3g} > {self.bound:.3g}): "
            f"{', '.join(self.names()) or 'every direction'} unconstrained; their sigma is set "
            f"to the cloud's radius ({self.radius:.3g} m, 1 rad)"
        )

    def to_dict(self) -> dict:
        """JSON-ready flag, condition number (None when infinite: JSON has no infinity) and the
        free directions' names."""
        return {
            "degenerate": self.degenerate,
            "condition_number": self.condition if np.isfinite(self.condition) else None,
            "unconstrained": self.names(),
        }


def aligned_information(
    rows: NDArray[np.float64],
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The information of point-to-plane rows along their principal directions, each row
    counting only as far as it leans on the direction by more than :data:`ALIGNMENT`.

    Parameters
    ----------
    rows
        (K, 6) unit-free rows (``h`` in the twist ``(ρ, v_c)`` of
        :func:`~spacepose.core.health.normalising_map`).

    Returns
    -------
    information, directions
        (6,) ``Σ max(0, (h·u)² − ALIGNMENT² |h|²)`` along each direction ``u``; (6, 6) the
        directions, columns: the eigenvectors of ``Σ h hᵀ``, weakest first.

    Raises
    ------
    InputError
        ``rows`` not a finite (K, 6) array.
    """
    rows = np.asarray(rows, dtype=np.float64)
    if rows.ndim != 2 or rows.shape[1] != 6 or not np.isfinite(rows).all():
        raise InputError(f"rows must be a finite (K, 6) array, got shape {rows.shape}")
    directions = np.linalg.eigh(rows.T @ rows)[1]
    along = (rows @ directions) ** 2
    size = np.sum(rows**2, axis=1, keepdims=True)
    return np.sum(np.maximum(0.0, along - ALIGNMENT**2 * size), axis=0), directions


def _vector(x: NDArray[np.float64], decimals: int) -> str:
    """``[x y z]`` rounded, without negative zeros."""
    return "[" + " ".join(f"{v:.{decimals}f}" for v in np.round(x, decimals) + 0.0) + "]"


@dataclass(frozen=True)
class CoarseSurface:
    """A target cloud's surface as the check reads it: in each of its cells of
    :data:`SAMPLE_FRACTION` of the radius, the point nearest the cell's centroid, with the
    plane fitted to the target's points within :data:`NORMAL_FRACTION` of the radius around it
    (made once per target: a tracker judges every frame against the same keyframe or model).

    Each sample's point-to-plane row ``h = (p × n, n)`` is taken at its own point with a normal
    centred on it: a sphere, a cylinder or a plane then gives their free directions nothing, up
    to the fit's noise (which falls with the neighbourhood's size) and, at the visible
    surface's rim, the tilt of a one-sided neighbourhood.

    Attributes
    ----------
    voxel
        The sampling cell's edge (m).
    points
        (M, 3) the samples (target frame, m): what frames are matched to.
    rows
        (M, 6) their rows ``(p × n, n)`` about the target frame's origin (zero for a sample
        with fewer than 3 points around it); None when the cloud has no surface (under 3
        points, or all on a line).
    index
        Neighbour index of ``points``.
    """

    voxel: float
    points: NDArray[np.float64]
    rows: NDArray[np.float64] | None
    index: VoxelIndex

    @classmethod
    def of(cls, target: PointCloud | ArrayLike, radius: float, workers: int = -1) -> CoarseSurface:
        """The coarse surface of ``target`` (its points; normals are not used) for clouds of
        ``radius`` (m)."""
        points = as_cloud(target, "target").points
        voxel = SAMPLE_FRACTION * radius
        samples = _nearest_to_centroids(points, voxel)
        rows = None
        if len(points) >= 3 and not on_a_line(points):
            reach = NORMAL_FRACTION * radius
            normals, count = _ball_normals(points, samples, reach, workers)
            rows = np.c_[np.cross(samples, normals), normals]
            rows[count < 3] = 0.0
        return cls(voxel, samples, rows, VoxelIndex(samples))


def _nearest_to_centroids(points: NDArray[np.float64], voxel: float) -> NDArray[np.float64]:
    """(M, 3) in each occupied cell of ``voxel`` (m) the point nearest the cell's centroid: a
    point of the surface, where a curved one's centroid lies inside it."""
    centroids, cell = voxel_cells(points, voxel)
    return points[_nearest_in_cells(np.sum((points - centroids[cell]) ** 2, axis=1), cell)]


@numba.njit(cache=True)
def _nearest_in_cells(d2, cell):
    """Per cell, the index of its point of least ``d2`` (the first of equals)."""
    m = cell.max() + 1
    best = np.full(m, np.inf)
    index = np.zeros(m, dtype=np.int64)
    for i in range(len(d2)):
        if d2[i] < best[cell[i]]:
            best[cell[i]], index[cell[i]] = d2[i], i
    return index


def _ball_normals(
    points: NDArray[np.float64], centres: NDArray[np.float64], reach: float, workers: int
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """The normals of the plane fits of the ``points`` (N, 3) within about ``reach`` (m) of each
    centre (K, 3), (K, 3) unit, and (K,) how many points each took.

    The points' moments are summed per cell of ``reach / _MOMENT_CELLS`` once, and a centre's
    neighbourhood is the cells whose centroids lie within ``reach``: a search among a few
    hundred cells, not among every point (a capped search for each centre's 400 nearest points
    took 39 ms on a lab keyframe; the whole :meth:`CoarseSurface.of` takes 5.5 ms).
    """
    # Moments about the cloud's mean: about a far sensor origin the second moments would
    # cancel the spread they hold.
    origin = points.mean(axis=0)
    centroids, cell = voxel_cells(points, reach / _MOMENT_CELLS)
    local = points - origin
    m = len(centroids)
    # Per cell: the count, the sum of the points and the sums of their products xx, xy, xz, yy,
    # yz, zz.
    pairs = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))
    columns = [np.ones(len(points)), *local.T, *(local[:, a] * local[:, b] for a, b in pairs)]
    sums = np.empty((m, 10))
    for j, column in enumerate(columns):
        sums[:, j] = np.bincount(cell, column, m)
    idx, _ = hybrid(centroids, centres, reach, _NORMAL_CAP, workers)
    ball = _sum_rows(sums, idx)
    total = ball[:, 0]
    mean = ball[:, 1:4] / np.maximum(total, 1.0)[:, None]
    covariance = np.empty((len(centres), 3, 3))
    for j, (a, b) in enumerate(pairs):
        covariance[:, a, b] = covariance[:, b, a] = ball[:, 4 + j] - total * mean[:, a] * mean[:, b]
    return normals_from_covariances(covariance, workers)[0], total


@numba.njit(cache=True)
def _sum_rows(rows, idx):
    """(K, C) row sums of ``rows`` (M, C) over each line of ``idx`` (K, L), up to its first -1
    (a gathered (K, L, C) copy cost more than the search)."""
    out = np.zeros((idx.shape[0], rows.shape[1]))
    for k in range(idx.shape[0]):
        for j in idx[k]:
            if j < 0:
                break
            out[k] += rows[j]
    return out


def surface_degeneracy(
    source_points: NDArray[np.float64],
    target_points: PointCloud | ArrayLike | CoarseSurface,
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
        (M, 3) cloud in its own frame (m; a PointCloud's normals are not used), or its
        :class:`CoarseSurface` made once.
    T_target_source
        (4, 4) the registration's result.
    radius
        Radius of the clouds (m); the sampling cell is :data:`SAMPLE_FRACTION` of it (a given
        coarse surface keeps its own).
    health
        ``lost_condition`` (degenerate above it) and ``ok_condition`` (the free directions are
        those whose :func:`aligned_information` is below ``1 / ok_condition`` of the best).
    workers
        Threads for the neighbour searches.

    Returns
    -------
    Degeneracy

    Raises
    ------
    InputError
        ``T_target_source`` not a 4x4 rigid transform, ``radius`` not a positive length, or
        an empty cloud.
    """
    T_target_source = se3.as_transform(T_target_source, "T_target_source")
    try:
        radius = float(radius)
    except (TypeError, ValueError):
        radius = float("nan")
    if not (np.isfinite(radius) and radius > 0):
        raise InputError(f"radius must be a positive finite number of metres, got {radius:g}")
    surface = target_points
    if not isinstance(surface, CoarseSurface):
        surface = CoarseSurface.of(target_points, radius, workers)
    voxel = surface.voxel
    source_points = as_points(source_points, "source points")
    src = se3.transform_points(T_target_source, voxel_cells(source_points, voxel)[0])
    # A rigid motion moves the centroid and keeps the radius: no need to move every point.
    centroid = se3.transform_points(T_target_source, source_points.mean(axis=0)[None])[0]
    # Points all at one place have no radius to scale rotations by: the given one stands in.
    r = rms_radius(source_points) or radius
    rows = np.zeros((0, 6))
    if surface.rows is not None:
        # The target's samples the frame overlaps, each as often as a frame cell matches it.
        _, t, _ = find_correspondences(surface.index, src, _GATE_VOXELS * voxel, workers)
        rows = surface.rows[t]
    information, directions = aligned_information(rows @ normalising_map(centroid, r))
    best = information.max()
    condition = float(best / information.min()) if information.min() > 0 else float("inf")
    free = np.zeros((6, 0))
    if not condition <= health.lost_condition:
        free = directions[:, information <= best / health.ok_condition]
    return Degeneracy(condition, health.lost_condition, free, centroid, r)
