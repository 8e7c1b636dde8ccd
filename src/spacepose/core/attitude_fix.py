"""Coarse target pose from recognised rectangles; the fix of the 4-fold ambiguity (methods.md §2.3).

The eigenvectors of a rectangle's distribution matrix fix its axes only up to sign, which leaves
four right-handed plane frames, related by 180° turns about the plane's x, y and z axes. Of these
the one whose difference quaternion with a prediction has scalar part nearest ±1 is kept
(Yu et al. 2019, §2.3). Without a prediction the normal is taken towards the sensor, which leaves
the 180° turn about the normal open; two or more rectangles in one frame settle it, because only
one choice makes them agree on the target's attitude.

Lost in space (no prediction at all): :func:`attitude_hypotheses` lists every pose the
rectangles of a frame allow, each rectangle taken as each catalogue face of its size with both
sign choices that show the face to the sensor; :mod:`spacepose.core.lost_in_space` scores them
against the target model.

Frames: ``sensor`` (the points' frame), ``plane`` (x short side, y long side, z normal) and
``model`` (the target's nominal body frame B' in which the catalogue is written).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from spacepose.core import se3
from spacepose.core.rectangle_measurement import RectangleMeasurement
from spacepose.core.rectangles import CatalogueEntry
from spacepose.errors import InputError

# The plane-frame turns of the 4-fold ambiguity: identity and 180° about x, y and z.
FOUR_FOLD_FLIPS = np.array(
    [np.diag([1.0, 1.0, 1.0]), np.diag([1.0, -1.0, -1.0]), np.diag([-1.0, 1.0, -1.0]),
     np.diag([-1.0, -1.0, 1.0])]
)  # fmt: skip
# The two of them that keep the normal (plane z) where it is.
_NORMAL_KEEPING_FLIPS = FOUR_FOLD_FLIPS[[0, 3]]


def _rotation(R: ArrayLike, name: str) -> NDArray[np.float64]:
    T = np.eye(4)
    R = np.asarray(R, dtype=np.float64)
    if R.shape != (3, 3):
        raise InputError(f"{name} must be a 3x3 rotation matrix, got shape {R.shape}")
    T[:3, :3] = R
    return se3.as_transform(T, name)[:3, :3]


def _nearest_flip(
    R_measured: NDArray[np.float64], R_reference: NDArray[np.float64], flips: NDArray[np.float64]
) -> tuple[NDArray[np.float64], float]:
    """The flipped frame ``R_measured · F`` closest to ``R_reference`` and its angle (rad)."""
    candidates = R_measured @ flips
    # |scalar| of the difference quaternion q_ref⁻¹ ⊗ q_candidate: 1 for the same attitude.
    diff = Rotation.from_matrix(R_reference).inv() * Rotation.from_matrix(candidates)
    w = np.abs(diff.as_quat()[:, 3])
    k = int(np.argmax(w))
    return candidates[k], float(2.0 * np.arccos(min(w[k], 1.0)))


def fix_four_fold(
    R_sensor_plane_measured: ArrayLike, R_sensor_plane_predicted: ArrayLike
) -> NDArray[np.float64]:
    """The one of the four sign-ambiguous plane frames nearest a prediction.

    Parameters
    ----------
    R_sensor_plane_measured
        (3, 3) measured plane frame in the sensor frame (columns: short side, long side, normal).
    R_sensor_plane_predicted
        (3, 3) predicted plane frame, e.g. the filter's ``R_sensor_model · R_model_plane``.

    Returns
    -------
    (3, 3) ``R_sensor_plane_measured · F`` with F the identity or a 180° turn about x, y or z,
    whichever gives the difference quaternion with the largest |scalar part|.
    """
    R_meas = _rotation(R_sensor_plane_measured, "R_sensor_plane_measured")
    R_pred = _rotation(R_sensor_plane_predicted, "R_sensor_plane_predicted")
    return _nearest_flip(R_meas, R_pred, FOUR_FOLD_FLIPS)[0]


def _pose(R_sensor_plane: NDArray[np.float64], m: RectangleMeasurement, e: CatalogueEntry):
    """``T_sensor_model`` from a plane frame: the rectangle's centre maps onto its centroid."""
    R_sensor_model = R_sensor_plane @ e.rotation.T
    return se3.make_transform(R_sensor_model, m.centroid - R_sensor_model @ e.centre)


def coarse_target_pose(
    measurement: RectangleMeasurement,
    entry: CatalogueEntry,
    predicted_R_sensor_model: ArrayLike | None = None,
) -> NDArray[np.float64]:
    """Target pose ``T_sensor_model`` (4, 4) from one recognised rectangle.

    ``R_sensor_model = R_sensor_plane · R_model_planeᵀ`` and the translation puts the entry's
    centre (model frame) on the measured centroid (sensor frame). With a predicted attitude the
    plane frame is first passed through :func:`fix_four_fold`; without one the measurement's
    normal-towards-the-sensor choice stands (a 180° turn about the normal stays possible).
    """
    R_sensor_plane = measurement.R_sensor_plane
    if predicted_R_sensor_model is not None:
        R_pred = _rotation(predicted_R_sensor_model, "predicted_R_sensor_model")
        R_sensor_plane = fix_four_fold(R_sensor_plane, R_pred @ entry.rotation)
    return _pose(R_sensor_plane, measurement, entry)


def consistent_rectangles(
    rectangles: Sequence[tuple[RectangleMeasurement, CatalogueEntry]],
    predicted_R_sensor_model: ArrayLike | None = None,
) -> NDArray[np.float64]:
    """One target pose ``T_sensor_model`` (4, 4) from several rectangles seen in one frame.

    Parameters
    ----------
    rectangles
        Pairs (measurement, the catalogue entry it was recognised as), at least one.
    predicted_R_sensor_model
        Optional (3, 3) predicted attitude. With it, each rectangle is fixed against it. Without
        it, each rectangle keeps its normal towards the sensor and the remaining 180° turn about
        the normal is chosen jointly: for both choices of the most populated rectangle, every
        other rectangle takes its nearer choice, and the pair of choices with the smaller total
        disagreement (rad) wins.

    Returns
    -------
    The attitudes averaged on SO(3) (``Rotation.mean``) weighted by point counts, and the
    translation that best places every rectangle centre on its centroid under that attitude.
    """
    if len(rectangles) == 0:
        raise InputError("consistent_rectangles needs at least one (measurement, entry) pair")
    pairs = sorted(rectangles, key=lambda p: -p[0].n_points)
    if predicted_R_sensor_model is not None:
        R_pred = _rotation(predicted_R_sensor_model, "predicted_R_sensor_model")
        frames = [fix_four_fold(m.R_sensor_plane, R_pred @ e.rotation) for m, e in pairs]
    else:
        best_cost, frames = np.inf, []
        m0, e0 = pairs[0]
        for flip in _NORMAL_KEEPING_FLIPS:
            R0 = m0.R_sensor_plane @ flip
            R_sensor_model = R0 @ e0.rotation.T
            chosen, cost = [R0], 0.0
            for m, e in pairs[1:]:
                R, angle = _nearest_flip(
                    m.R_sensor_plane, R_sensor_model @ e.rotation, _NORMAL_KEEPING_FLIPS
                )
                chosen.append(R)
                cost += angle
            if cost < best_cost:
                best_cost, frames = cost, chosen
    weights = np.array([m.n_points for m, _ in pairs], dtype=np.float64)
    R_models = np.stack([R @ e.rotation.T for R, (_, e) in zip(frames, pairs, strict=True)])
    R_sensor_model = Rotation.from_matrix(R_models).mean(weights=weights).as_matrix()
    offsets = np.stack([m.centroid - R_sensor_model @ e.centre for m, e in pairs])
    return se3.make_transform(R_sensor_model, weights @ offsets / weights.sum())


@dataclass(frozen=True, eq=False)
class PoseHypothesis:
    """One target pose the rectangles of a frame allow, and which face each rectangle is in it.

    Attributes
    ----------
    T_sensor_model
        (4, 4) target pose, model frame B' into the sensor frame.
    assignment
        ``(index, name)`` per rectangle the pose explains: the rectangle's index in the list
        given to :func:`attitude_hypotheses` and the catalogue face it is under this pose.
    """

    T_sensor_model: NDArray[np.float64]
    assignment: tuple[tuple[int, str], ...]


def explained_rectangles(
    T_sensor_model: NDArray[np.float64],
    rectangles: Sequence[tuple[RectangleMeasurement, Sequence[CatalogueEntry]]],
    min_normal_cosine: float = 0.5,
) -> list[tuple[int, CatalogueEntry]]:
    """Which rectangles a pose explains, and as which catalogue face.

    A rectangle is explained by the candidate face whose outward normal, turned by the pose,
    lies within ``arccos(min_normal_cosine)`` of the measured normal and whose centre falls
    nearest the measured centroid, within half the face's long side (a length set by the face
    itself, so it scales with the target).

    Parameters
    ----------
    T_sensor_model
        (4, 4) candidate pose.
    rectangles
        Measurements (sensor frame) with the catalogue faces their sides allow.
    min_normal_cosine
        Smallest cosine between the predicted outward normal and the measured normal.

    Returns
    -------
    ``(index, entry)`` for every explained rectangle, in input order.
    """
    R, t = T_sensor_model[:3, :3], T_sensor_model[:3, 3]
    out = []
    for i, (m, entries) in enumerate(rectangles):
        best, best_d = None, np.inf
        for e in entries:
            if float((R @ e.rotation[:, 2]) @ m.normal) < min_normal_cosine:
                continue
            d = float(np.linalg.norm(R @ e.centre + t - m.centroid))
            if d <= 0.5 * e.b and d < best_d:
                best, best_d = e, d
        if best is not None:
            out.append((i, best))
    return out


def attitude_hypotheses(
    rectangles: Sequence[tuple[RectangleMeasurement, Sequence[CatalogueEntry]]],
    same_pose_deg: float = 5.0,
) -> list[PoseHypothesis]:
    """Every target pose the rectangles of one frame allow, with no prediction (lost in space).

    Each rectangle, as each catalogue face of its size, gives two poses: the plane frame's
    four sign choices less the two that would show the face from behind. Every other rectangle
    then joins the pose as the face it best fits (:func:`explained_rectangles`) and the pose is
    re-estimated from all of them (:func:`consistent_rectangles` with the anchor's attitude as
    the prediction). Poses whose attitudes lie within ``same_pose_deg`` and whose origins lie
    within half the smallest side of the catalogue faces involved are one hypothesis.

    Parameters
    ----------
    rectangles
        Whole rectangles of one frame (sensor frame) with the faces their sides allow
        (:func:`spacepose.core.rectangles.candidates`); rectangles without any are ignored.
    same_pose_deg
        Attitude difference (deg) below which two poses are merged.

    Returns
    -------
    The distinct hypotheses, those explaining the most points first.
    """
    usable = [(m, list(c)) for m, c in rectangles if len(c)]
    index = [i for i, (_, c) in enumerate(rectangles) if len(c)]
    scored: list[tuple[int, PoseHypothesis]] = []
    for m, entries in usable:
        for e in entries:
            # The measured normal faces the sensor, and so must the face's outward normal: of
            # the four sign choices only the two that keep the normal remain.
            for flip in _NORMAL_KEEPING_FLIPS:
                T0 = _pose(m.R_sensor_plane @ flip, m, e)
                found = explained_rectangles(T0, usable)
                pairs = [(usable[i][0], entry) for i, entry in found] or [(m, e)]
                T = consistent_rectangles(pairs, T0[:3, :3]) if found else T0
                names = tuple((index[i], entry.name) for i, entry in found)
                support = sum(usable[i][0].n_points for i, _ in found)
                scored.append((support, PoseHypothesis(T, names)))
    scored.sort(key=lambda item: -item[0])
    kept: list[PoseHypothesis] = []
    for _, h in scored:
        if not any(_same_pose(h, k, same_pose_deg, usable) for k in kept):
            kept.append(h)
    return kept


def _same_pose(
    h: PoseHypothesis,
    k: PoseHypothesis,
    same_pose_deg: float,
    usable: Sequence[tuple[RectangleMeasurement, Sequence[CatalogueEntry]]],
) -> bool:
    angle = Rotation.from_matrix(h.T_sensor_model[:3, :3] @ k.T_sensor_model[:3, :3].T).magnitude()
    smallest = min(e.a for _, entries in usable for e in entries)
    offset = np.linalg.norm(h.T_sensor_model[:3, 3] - k.T_sensor_model[:3, 3])
    return bool(np.rad2deg(angle) < same_pose_deg and offset < 0.5 * smallest)
