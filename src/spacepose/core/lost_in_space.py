"""Lost-in-space start of the navigation: which target pose the first frames show, if any.

The rectangles of a frame, each matched to the catalogue faces of its size, allow a handful of
poses (:func:`spacepose.core.attitude_fix.attitude_hypotheses`: assignments × the sign choices
of the plane frames). Each is scored by how much of the frame and of the target it explains
(:func:`explained_share`):

* with the target's surface samples (a model in B' with outward normals): the share of the
  frame's points lying on the model surface under the pose, averaged with the share of the
  model samples the pose shows the sensor (front-facing, not hidden behind a nearer part, in
  the field of view) that have a measured point nearby. The first catches a part where the
  model has none (the wing on the wrong side); the second a part the model puts in view that
  the frame lacks (an antenna panel on the hidden side);
* without a model: the share of the rectangles' points whose rectangle the pose explains as a
  catalogue face at its predicted place (:func:`spacepose.core.attitude_fix.explained_rectangles`).

Poses whose scores lie within ``ambiguity_margin`` of the best are equally good: a symmetric
target (or a view hiding what breaks the symmetry) leaves several, and the navigator keeps them
all until the data tell them apart instead of picking one.

Every distance is derived from the data: the inlier radius is ``inlier_spacings`` sample spacings
(the median nearest-neighbour distance of the model samples, or of the frame's points) plus
``inlier_sigmas`` range σ.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import Annotated

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import Field
from scipy.spatial import cKDTree

from spacepose.core import se3
from spacepose.core.attitude_fix import explained_rectangles
from spacepose.core.cloud import PointCloud
from spacepose.core.config import StageConfig, validate_config
from spacepose.core.icp import ICPConfig, icp
from spacepose.core.normals import NormalsConfig, estimate_normals
from spacepose.core.rectangle_measurement import RectangleMeasurement
from spacepose.core.rectangles import CatalogueEntry
from spacepose.core.scale import point_spacing
from spacepose.errors import InputError, RegistrationError

__all__ = [
    "FrameEvidence",
    "LostInSpaceConfig",
    "ModelSurface",
    "equally_good",
    "explained_share",
    "refine_on_model",
    "visible_samples",
]


# A field of view side: a cone of 0 or 180 deg or more sees nothing or has no tangent.
_Angle = Annotated[float, Field(gt=0, lt=180)]


class LostInSpaceConfig(StageConfig):
    """Settings of the lost-in-space start and of the bank of candidate filters."""

    inlier_spacings: float = Field(
        1.5,
        gt=0,
        description="Inlier radius in sample spacings (median nearest-neighbour "
        "distance of the samples searched).",
    )
    inlier_sigmas: float = Field(3.0, ge=0, description="Inlier radius: range σ's added.")
    zbuffer_spacings: float = Field(
        2.0,
        gt=0,
        description="Side of the visibility buffer's cells in angular spacings of "
        "the frame's points (cells must hold a model sample of every surface they see).",
    )
    start_margin: float = Field(
        0.1,
        gt=0,
        lt=1,
        description="At the start, hypotheses whose explained share lies within this of the "
        "best one's each start a candidate filter: one frame alone never decides.",
    )
    ambiguity_margin: float = Field(
        0.008,
        gt=0,
        lt=1,
        description="A candidate is dropped once the median of its shortfalls from the best "
        "share over the last decide_frames frames exceeds this (and it was behind in each). "
        "Measured on the orbit run (16 frames, every 37th): the half-turn twin of the default "
        "target falls 0.008-0.19 behind (median 0.037); the twins of the symmetric target "
        "0.000-0.002.",
    )
    decide_frames: int = Field(
        5,
        ge=1,
        description="Frames of scores a candidate is judged on: it is dropped when it "
        "was behind the best in each of them, by a median shortfall above ambiguity_margin.",
    )
    min_explained: float = Field(
        0.98,
        gt=0,
        le=1,
        description="A frame counts towards a decision only if its best candidate explains "
        "at least this share: a poorer frame (part of the target out of view, a refinement "
        "that slid) cannot tell candidates apart.",
    )
    max_candidates: int = Field(4, ge=1, description="Largest number of candidate filters.")
    refine_iterations: int = Field(
        15,
        ge=0,
        description="Point-to-plane ICP iterations refining each hypothesis on the "
        "model before it is scored (0: none).",
    )
    refine_gate_spacings: float = Field(
        4.0,
        gt=0,
        description="ICP correspondence gate in spacings of the frame's points: it "
        "must cover the coarse pose's error at the far end of the target (1° at 7 m is 12 cm).",
    )
    max_incidence_deg: float = Field(
        75.0,
        gt=0,
        lt=90,
        description="Model surfaces seen at a larger incidence are not expected in the frame "
        "(their pixels lie r·δ / cos θ apart, and a range sensor's return fades).",
    )
    same_pose_deg: float = Field(
        5.0, gt=0, description="Attitudes closer than this (deg) are one candidate."
    )
    fov_deg: tuple[_Angle, _Angle] | None = Field(
        None,
        description="Sensor field of view (horizontal, vertical), deg: model samples "
        "outside it are not expected in the frame. None: no limit.",
    )


def with_sensor_fov(config: LostInSpaceConfig, fov: object, source: str) -> LostInSpaceConfig:
    """``config`` with a scenario's ``sensor_fov_deg``, validated as the field is.

    Raises
    ------
    ConfigError
        ``source: sensor_fov_deg: invalid lost in space config: ...``: not two angles in
        (0, 180) deg (null, text, a negative or non-finite angle).
    """
    data = config.model_dump() | {"fov_deg": fov}
    return validate_config(LostInSpaceConfig, data, f"{source}: sensor_fov_deg")


def _spacing(tree: cKDTree) -> float:
    """Median nearest-neighbour distance (m) of a tree's own points, to the nearest other
    place when over half of them are repeated (0 made every gate 0)."""
    return point_spacing(tree.data, samples=len(tree.data))


@dataclass(frozen=True, eq=False)
class ModelSurface:
    """Surface samples of the target in its model frame B', with outward normals.

    Attributes
    ----------
    points, normals
        (M, 3) samples and unit outward normals, model frame (m).
    tree
        KD-tree of ``points``.
    spacing
        Median nearest-neighbour distance of the samples (m).
    """

    points: NDArray[np.float64]
    normals: NDArray[np.float64]
    tree: cKDTree
    spacing: float

    @classmethod
    def from_cloud(cls, cloud: PointCloud) -> ModelSurface:
        """From a model cloud (a run's ``model.ply``); normals estimated when it has none,
        turned away from its centroid (a bare point cloud as ``--model`` was refused).

        Raises
        ------
        InputError
            Fewer than 2 points (or too few to estimate normals on).
        """
        if len(cloud) < 2:
            raise InputError("the target model needs surface samples with normals", cloud.source)
        if cloud.normals is None:
            centroid = cloud.points.mean(axis=0)
            inward = estimate_normals(cloud, NormalsConfig(), viewpoint=centroid)
            cloud = inward.with_normals(-inward.normals)
        points = np.array(cloud.points, dtype=np.float64)
        tree = cKDTree(points)
        return cls(points, np.array(cloud.normals, dtype=np.float64), tree, _spacing(tree))


@dataclass(frozen=True, eq=False)
class FrameEvidence:
    """What one frame offers to score a pose: its points and its candidate rectangles.

    Attributes
    ----------
    points
        (N, 3) measured points, sensor frame (m).
    tree
        KD-tree of ``points``.
    spacing
        Median nearest-neighbour distance of the points (m).
    angular_step
        ``spacing`` over the median range (rad): the angular pixel pitch of the frame.
    rectangles
        Whole rectangles of the frame with the catalogue faces their sides allow (those that
        allow none are left out).
    sigma
        Range noise σ (m).
    """

    points: NDArray[np.float64]
    tree: cKDTree
    spacing: float
    angular_step: float
    rectangles: tuple[tuple[RectangleMeasurement, tuple[CatalogueEntry, ...]], ...]
    sigma: float

    @classmethod
    def build(
        cls,
        points: ArrayLike,
        rectangles: Sequence[tuple[RectangleMeasurement, Sequence[CatalogueEntry]]],
        sigma: float,
    ) -> FrameEvidence:
        """From a frame's (N, 3) points (N >= 2), its rectangles and the range σ (m)."""
        pts = np.array(points, dtype=np.float64)
        if pts.ndim != 2 or pts.shape[1] != 3 or len(pts) < 2:
            raise InputError(f"a frame needs at least 2 points (N, 3), got shape {pts.shape}")
        tree = cKDTree(pts)
        spacing = _spacing(tree)
        step = spacing / max(float(np.median(np.linalg.norm(pts, axis=1))), 1e-300)
        rects = tuple((m, tuple(c)) for m, c in rectangles if len(c))
        return cls(pts, tree, spacing, step, rects, float(sigma))


def visible_samples(
    T_sensor_model: NDArray[np.float64],
    frame: FrameEvidence,
    model: ModelSurface,
    config: LostInSpaceConfig = LostInSpaceConfig(),
) -> NDArray[np.bool_]:
    """Which model samples (M,) a pose shows the sensor: facing it, ahead of it, in the field of
    view and not hidden behind a nearer part (a z-buffer of angular cells of
    ``zbuffer_spacings`` of the frame's pixel pitch; within a cell a sample is seen if it lies
    within the inlier radius of the nearest one, plus the depth its own surface spans across
    the cell, ``w tan θ`` for a cell w wide at incidence θ). Surfaces seen at more than
    ``max_incidence_deg`` are not expected to return points."""
    R, t = T_sensor_model[:3, :3], T_sensor_model[:3, 3]
    q = model.points @ R.T + t
    cos = _incidence_cosine(T_sensor_model, model)
    keep = (cos > np.cos(np.deg2rad(config.max_incidence_deg))) & (q[:, 2] > 0.0)
    if config.fov_deg is not None:
        half = np.tan(np.deg2rad(np.asarray(config.fov_deg)) / 2.0)
        with np.errstate(divide="ignore", invalid="ignore"):
            angles = np.abs(q[:, :2] / q[:, 2:3])
        keep &= np.all(angles <= half, axis=1)
    idx = np.flatnonzero(keep)
    if len(idx) == 0:
        return keep
    q = q[idx]
    cell = config.zbuffer_spacings * frame.angular_step
    ij = np.floor(q[:, :2] / q[:, 2:3] / cell).astype(np.int64)
    _, cells = np.unique(ij, axis=0, return_inverse=True)
    r = np.linalg.norm(q, axis=1)
    nearest = np.full(cells.max() + 1, np.inf)
    np.minimum.at(nearest, cells, r)
    c = cos[idx]
    slope = cell * r * np.sqrt(1.0 - c**2) / c
    keep[idx] = r <= nearest[cells] + _radius_on_frame(frame, config) + slope
    return keep


def _incidence_cosine(T_sensor_model: NDArray[np.float64], model: ModelSurface) -> NDArray:
    """``cos θ`` (M,) between each sample's outward normal and the ray back to the sensor."""
    R, t = T_sensor_model[:3, :3], T_sensor_model[:3, 3]
    q = model.points @ R.T + t
    return -np.einsum("ij,ij->i", model.normals @ R.T, q) / np.linalg.norm(q, axis=1)


def _radius_on_frame(frame: FrameEvidence, config: LostInSpaceConfig) -> float:
    return config.inlier_spacings * frame.spacing + config.inlier_sigmas * frame.sigma


def _model_share(
    T_sensor_model: NDArray[np.float64],
    frame: FrameEvidence,
    model: ModelSurface,
    config: LostInSpaceConfig,
) -> tuple[float, float]:
    """Share of the frame's points on the model, share of the visible model samples observed."""
    R, t = T_sensor_model[:3, :3], T_sensor_model[:3, 3]
    radius_on_model = config.inlier_spacings * model.spacing + config.inlier_sigmas * frame.sigma
    d, _ = model.tree.query((frame.points - t) @ R, distance_upper_bound=radius_on_model)
    data_share = float(np.mean(np.isfinite(d)))
    seen = visible_samples(T_sensor_model, frame, model, config)
    if not np.any(seen):
        return data_share, 0.0
    q = model.points[seen] @ R.T + t
    # The pixels of a surface at incidence θ lie r·δ / cos θ apart along its tilt.
    pitch = (
        frame.angular_step
        * np.linalg.norm(q, axis=1)
        / _incidence_cosine(T_sensor_model, model)[seen]
    )
    radius = (
        config.inlier_spacings * np.maximum(pitch, frame.spacing)
        + config.inlier_sigmas * frame.sigma
    )
    d, _ = frame.tree.query(q)
    return data_share, float(np.mean(d <= radius))


def refine_on_model(
    T_sensor_model: ArrayLike,
    frame: FrameEvidence,
    model: ModelSurface,
    config: LostInSpaceConfig = LostInSpaceConfig(),
) -> NDArray[np.float64]:
    """A hypothesis (4, 4) refined by point-to-plane ICP of the frame's points on the model.

    The coarse pose from one rectangle is off by a degree or more, which moves the far end of a
    large target by more than the inlier radius; refined, every hypothesis is scored at its best.
    A registration that fails (too few correspondences) leaves the pose as it was.
    """
    T = se3.as_transform(T_sensor_model, "T_sensor_model")
    if config.refine_iterations == 0:
        return T
    icp_config = ICPConfig(
        method="point_to_plane",
        max_correspondence_distance=config.refine_gate_spacings * frame.spacing,
        max_iterations=config.refine_iterations,
    )
    target = PointCloud(model.points, model.normals, source="target model")
    try:
        result = icp(frame.points, target, se3.invert(T), icp_config, target_tree=model.tree)
    except (RegistrationError, InputError):
        return T
    return se3.invert(result.T_target_source)


def explained_share(
    T_sensor_model: ArrayLike,
    frame: FrameEvidence,
    model: ModelSurface | None,
    config: LostInSpaceConfig = LostInSpaceConfig(),
) -> float:
    """How well a pose explains a frame, in [0, 1] (see the module notes).

    Parameters
    ----------
    T_sensor_model
        (4, 4) candidate pose, model frame B' into the sensor frame.
    frame
        The frame's points and rectangles.
    model
        The target's surface samples; None scores by the rectangles alone.
    config
        Inlier radii, visibility cells and field of view.
    """
    T = np.asarray(T_sensor_model, dtype=np.float64)
    if model is not None:
        return float(np.mean(_model_share(T, frame, model, config)))
    weights = np.array([m.n_points for m, _ in frame.rectangles], dtype=np.float64)
    if weights.sum() == 0:
        return 0.0
    explained = [i for i, _ in explained_rectangles(T, frame.rectangles)]
    return float(weights[explained].sum() / weights.sum())


def equally_good(scores: ArrayLike, margin: float) -> NDArray[np.intp]:
    """Indices of the scores within ``margin`` of the best, best first (ties: lower index)."""
    s = np.asarray(scores, dtype=np.float64)
    if s.size == 0:
        return np.arange(0)
    order = np.argsort(-s, kind="stable")
    return order[s[order] >= s[order[0]] - margin]
