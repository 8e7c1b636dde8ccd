"""Two rigid bodies in one object: a support moving otherwise, split off by motion (§5.8).

The first frame's object is everything connected to the nearest cluster
(:mod:`spacepose.core.segmentation`). A support touching the target (a turntable's post, disc and
plinth; a docking fixture) is part of it, and when it moves otherwise (a slide carries it while
the target turns or tumbles) no single rigid motion fits both: registration settles on a
compromise that point-to-plane residuals barely reject, because each surface slides along
itself. Against a nearby keyframe the residuals may carry structure or a part pull the pose
(:mod:`spacepose.core.residual_structure`, :mod:`spacepose.core.part_influence`), or not: the
two have hardly parted. On the few frames the tracker looks (:mod:`spacepose.core.support`),
:func:`split_trial` looks for a second rigid motion against the first keyframe:

1. the points the compromise leaves unexplained (point-to-plane residual beyond three residual
   σ, or no surface within reach) are registered alone from it, with a redescending kernel of
   adaptive scale (a wide basin), unless the second motion is known (a support standing still
   before a still sensor: the identity), which is then held;
2. a two-model EM over parts of the frame (cubes of a quarter of its RMS radius): each motion
   (the first only, when the second is known) is refitted, with the kernel at the sensor's σ,
   on the parts it explains clearly better than the other (capped squared residuals below
   :data:`FIT_RATIO` of the other's). Parts both explain (a surface sliding along itself) are
   left out of both fits, or they would hold the compromise in place;
3. each part goes to the motion that explains it better. The split stands when each body holds
   :data:`MIN_BODY_SHARE` of the points and fits its own motion clearly better than the other's.
   A frame of one rigid body, even with noise correlated over patches, has one motion that
   explains nearly every part.

Which body is the target: the one that turns, i.e. the one a pure shift in the sensor frame
explains worse (capped residuals, so that a turn its surfaces cannot show counts for nothing).
A support carried by a slide, a wall, a fixture translate or stand still in the sensor frame
while the target turns or tumbles, so a split whose support turns is not one. Surfaces
symmetric about the turn (a turntable's disc and post) fit both motions and stay with the
target. :class:`spacepose.core.clutter_body.ClutterBody` then follows the support with its own
constant-velocity motion, so that its points can be left out of every later frame.

Frames: a *reference* is a keyframe's sensor frame; ``T_ref_frame`` maps the current frame's
sensor coordinates into it (``T_target_source`` of a registration onto the keyframe).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree

from spacepose.core import se3
from spacepose.core.cloud import PointCloud, as_points
from spacepose.core.correspondences import find_correspondences
from spacepose.core.health import normalised_condition
from spacepose.core.icp import ICPConfig, icp
from spacepose.core.icp_systems import point_to_plane_system
from spacepose.core.keyframes import PreparedCloud
from spacepose.core.scale import rms_radius
from spacepose.core.voxel import voxel_cells
from spacepose.errors import InputError, SpaceposeError

# Each body must hold at least this share of the frame's points (a turntable's post and disc
# under a large target: 14 %), and the target twice it: on noisy frames a small patch that a
# second motion fits by chance turns as a target would.
MIN_BODY_SHARE = 0.1
# Residuals are capped at this many σ: beyond, a point is unexplained, however far.
EXPLAINED_SIGMAS = 3.0
# A part belongs to a motion's fit when its capped squared residuals under it are below this
# share of those under the other; a split stands when each body fits its own motion so.
FIT_RATIO = 0.5
# Parts of the assignment: cubes of this fraction of the frame's RMS radius, each part a
# surface patch large enough to tell two motions apart, small enough to lie on one body.
CELLS_PER_RADIUS = 4.0
_TINY = 1e-300
# Gauss-Newton steps of the pure-shift fit (linear in the shift: two or three settle it).
_SHIFT_ITERATIONS = 5
# Rounds of the two-model EM (assignment, then both refits); the labels settle in two or three.
_EM_ROUNDS = 4


@dataclass(frozen=True)
class MotionSplit:
    """A frame whose points follow two rigid motions relative to a reference.

    Attributes
    ----------
    T_ref_frame
        (4, 4) the target body's motion: frame sensor coordinates into the reference's.
    T_ref_frame_support
        (4, 4) the other body's motion.
    frame_target
        (N,) True for the frame points that follow the target's motion.
    ref_target, ref_support
        (M,) True for the reference points on the target body, and on the support (a point
        the frame does not come near is on neither).
    shares
        Shares of the frame's points assigned to the target and to the support.
    """

    T_ref_frame: NDArray[np.float64]
    T_ref_frame_support: NDArray[np.float64]
    frame_target: NDArray[np.bool_]
    ref_target: NDArray[np.bool_]
    ref_support: NDArray[np.bool_]
    shares: tuple[float, float]


@dataclass(frozen=True)
class SplitTrial:
    """What a motion split found (:func:`split_trial`).

    Attributes
    ----------
    split
        The split, or None when one motion explains the frame.
    support_apart
        With the support's motion given: its body already fits that motion clearly better than
        the target's, while the target's part does not yet fit its own clearly better (a still
        support under a target that has turned little since the reference).
    """

    split: MotionSplit | None
    support_apart: bool = False


def checked_registration_inputs(
    points: PointCloud | ArrayLike,
    ref: PreparedCloud | PointCloud,
    T_ref_frame: ArrayLike,
    what: str,
    lengths: dict[str, float],
) -> tuple[NDArray[np.float64], PreparedCloud, NDArray[np.float64]]:
    """A frame's points (N, 3), its reference (prepared, with normals) and ``T_ref_frame``
    (4, 4), checked for ``what`` uses them, with its ``lengths`` (m) positive.

    Raises
    ------
    InputError
        Points that are not finite (N, 3), a reference without normals, a transform that is not
        rigid, or a length that is not positive.
    """
    for name, value in lengths.items():
        if not (np.isfinite(value) and value > 0):
            raise InputError(f"{what}: {name} must be a positive length in metres, got {value}")
    points = as_points(points, "frame points")
    if isinstance(ref, PointCloud):
        ref = PreparedCloud(ref)
    if not ref.cloud.has_normals:
        raise InputError(f"the reference of {what} needs normals", ref.cloud.source)
    return points, ref, se3.as_transform(T_ref_frame, "T_ref_frame")


def plane_residuals(
    ref: PreparedCloud,
    points: NDArray[np.float64],
    T_ref_frame: NDArray[np.float64],
    gate: float,
    workers: int = -1,
) -> NDArray[np.float64]:
    """(N,) absolute point-to-plane residual of each frame point onto its nearest reference
    point within ``gate`` (m); inf where none is. ``ref`` needs normals."""
    moved, s, t, _ = nearest_within(ref, points, T_ref_frame, gate, workers)
    r = np.full(len(points), np.inf)
    q = ref.cloud
    r[s] = np.abs(np.einsum("ij,ij->i", moved[s] - q.points[t], q.normals[t]))
    return r


def nearest_within(
    ref: PreparedCloud,
    points: NDArray[np.float64],
    T_ref_frame: NDArray[np.float64],
    gate: float,
    workers: int,
) -> tuple[NDArray[np.float64], NDArray[np.intp], NDArray[np.intp], NDArray[np.float64]]:
    """The frame points moved into the reference, and the pairs within ``gate`` (m) of their
    nearest reference point: frame indices, reference indices, squared distances."""
    moved = se3.transform_points(T_ref_frame, points)
    return moved, *find_correspondences(ref.tree, moved, gate, workers)


def split_trial(
    points: PointCloud | ArrayLike,
    ref: PreparedCloud | PointCloud,
    T_ref_frame: ArrayLike,
    sigma: float,
    reach: float,
    near: float,
    workers: int = -1,
    second: ArrayLike | None = None,
    max_condition: float = 1e3,
) -> SplitTrial:
    """Look for a second rigid motion among a frame's points (module docstring).

    Parameters
    ----------
    points
        (N, 3) the frame's prepared points (array or cloud), its sensor frame.
    ref
        The reference with normals (a keyframe's prepared cloud, or a cloud), its own sensor
        frame.
    T_ref_frame
        (4, 4) the one-motion registration of the frame onto the reference.
    sigma
        Point-to-plane residual σ of the sensor at this scale (m).
    reach
        Farthest a point may sit from the reference surface and still pair (m): the reach of
        the motion the split may find.
    near
        Distance (m) within which a moved frame point shows a reference point seen: about the
        point spacing.
    workers
        Threads of the searches.
    second
        (4, 4) the second motion (``T_ref_frame`` of the support) when it is known: held, only
        the first is refitted. None: fitted to the points the one-motion registration leaves
        unexplained (step 1). The identity is a support standing still before a sensor that
        stands still too.
    max_condition
        Largest normalised condition number of the target body's information under its own
        motion (the tracker passes its health's ``ok_condition``): the target is tracked alone
        after a split, and a part that cannot constrain its motion is no target.

    Returns
    -------
    SplitTrial
        Its ``split`` is None when one motion explains the frame (or a second cannot be
        fitted).

    Raises
    ------
    InputError
        A reference without normals, non-finite points, or a length that is not positive.
    """
    points, ref, T_ref_frame = checked_registration_inputs(
        points, ref, T_ref_frame, "a motion split", {"sigma": sigma, "reach": reach, "near": near}
    )
    cap = EXPLAINED_SIGMAS * sigma
    # The kernel's scale is the sensor's σ, not the residuals' spread: a compromise between two
    # motions has a wide spread, and an adaptive scale would keep it.
    config = ICPConfig(
        method="point_to_plane",
        max_correspondence_distance=reach,
        robust_kernel="geman_mcclure",
        robust_scale=sigma,
    )
    _, cell = voxel_cells(points, rms_radius(points) / CELLS_PER_RADIUS)

    def cell_costs(T: NDArray[np.float64]) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        r2 = np.minimum(plane_residuals(ref, points, T, reach, workers), cap) ** 2
        return r2, np.bincount(cell, r2)

    T_a = T_ref_frame
    unexplained = cell_costs(T_a)[0] >= cap**2
    # A body may be half explained by the compromise: half its share is enough to start from.
    if unexplained.sum() < 0.5 * MIN_BODY_SHARE * len(points):
        return SplitTrial(None)
    if second is not None:
        T_b = se3.as_transform(second, "second")
    else:
        # The second motion may lie far from the compromise: its first fit takes the adaptive
        # scale (wide basin), the rounds after it the sensor's.
        wide = config.model_copy(update={"robust_scale": None})
        T_b = _fit(points[unexplained], ref, T_a, wide, workers)
    for _ in range(_EM_ROUNDS):
        (_, c_a), (_, c_b) = cell_costs(T_a), cell_costs(T_b)
        # Each motion is refitted on the parts it explains clearly better: parts both explain
        # (a surface sliding along itself) would hold a compromise in place.
        T_a = _fit(points[(c_a < FIT_RATIO * c_b)[cell]], ref, T_a, config, workers)
        if second is None:
            T_b = _fit(points[(c_b < FIT_RATIO * c_a)[cell]], ref, T_b, config, workers)
    (r_a, c_a), (r_b, c_b) = cell_costs(T_a), cell_costs(T_b)
    on_b = (c_b < c_a)[cell]
    share_b = float(on_b.mean())
    if min(share_b, 1.0 - share_b) < MIN_BODY_SHARE:
        return SplitTrial(None)
    # Each body's points must fit its own motion clearly better than the other's.
    fit_a = r_a[~on_b].sum() / max(r_b[~on_b].sum(), _TINY)
    fit_b = r_b[on_b].sum() / max(r_a[on_b].sum(), _TINY)
    if max(fit_a, fit_b) > FIT_RATIO:
        # A support whose motion is known can part from a slow target before the target's
        # part does: the caller looks again on the next frame.
        return SplitTrial(None, second is not None and fit_b <= FIT_RATIO)
    frame_target, shares = ~on_b, (1.0 - share_b, share_b)
    # The points each body's motion explains: what shows the reference's points seen.
    shown = (~on_b & (r_a < cap**2), on_b & (r_b < cap**2))
    # The target is the body that turns: the one a pure shift explains worse (in its capped
    # residuals, so that a turn the surfaces cannot show, a plane spinning in itself, counts
    # for nothing).
    rigid = (r_a[~on_b].mean(), r_b[on_b].mean())
    shift = (
        _shift_cost(ref, points[~on_b], T_a, cap, reach, workers),
        _shift_cost(ref, points[on_b], T_b, cap, reach, workers),
    )
    # A known second motion is the support's by hypothesis: a target that slides without
    # turning over a still table shows no turn either, and the test would pick by noise.
    if second is None and shift[1] - rigid[1] > shift[0] - rigid[0]:
        T_a, T_b, frame_target, shares, shown = T_b, T_a, on_b, shares[::-1], shown[::-1]
        rigid, shift = rigid[::-1], shift[::-1]
    # The support moves without turning (a slide carries it, or it stands still): a pure shift
    # explains it nearly as well as a rigid motion. A part of a tumbling target that the
    # frame's new views set apart does not.
    if rigid[1] < FIT_RATIO * shift[1] or shares[0] < 2.0 * MIN_BODY_SHARE:
        return SplitTrial(None)
    # The target is tracked alone after the split, and its motion was refitted on its part
    # alone: a part that does not constrain it (a flat end) lets the refit run off, and every
    # other part then fits the support's motion better (a rigid spacecraft at 25 m split into
    # a "still" 75 % and an end whose refit ran 0.7-1.2 m off, condition 1.6e4-1.8e4;
    # methods.md §5.8, step 4).
    moved = se3.transform_points(T_a, points[frame_target])
    if _condition(ref, moved, cap, reach, workers) > max_condition:
        return SplitTrial(None)
    labels = _reference_labels(ref, points, shown, (T_a, T_b), near, workers)
    return SplitTrial(MotionSplit(T_a, T_b, frame_target, *labels, shares))


def _fit(
    points: NDArray[np.float64],
    ref: PreparedCloud,
    T_init: NDArray[np.float64],
    config: ICPConfig,
    workers: int = -1,
) -> NDArray[np.float64]:
    """``T_ref_frame`` of ``points`` registered from ``T_init``; ``T_init`` itself when they do
    not constrain a motion (too few, or one plane)."""
    try:
        result = icp(points, ref.cloud, T_init, config, workers=workers, target_tree=ref.tree)
    except SpaceposeError:
        return T_init
    return result.T_target_source


def _condition(
    ref: PreparedCloud, moved: NDArray[np.float64], cap: float, reach: float, workers: int
) -> float:
    """Normalised condition number (:func:`~spacepose.core.health.normalised_condition`) of
    the point-to-plane information of ``moved`` (N, 3, the reference's frame) over its pairs
    within ``reach`` that the motion explains (residual below ``cap``); inf with fewer than
    seven."""
    s, t, _ = find_correspondences(ref.tree, moved, reach, workers)
    p, q, n = moved[s], ref.cloud.points[t], ref.cloud.normals[t]
    explained = np.abs(np.einsum("ij,ij->i", p - q, n)) < cap
    if explained.sum() < 7:
        return float("inf")
    p = p[explained]
    H, _, _ = point_to_plane_system(p, q[explained], n[explained])
    return normalised_condition(H, p.mean(axis=0), rms_radius(p))


def _shift_cost(
    ref: PreparedCloud,
    points: NDArray[np.float64],
    T_ref_frame: NDArray[np.float64],
    cap: float,
    reach: float,
    workers: int,
) -> float:
    """Mean capped squared point-to-plane residual of ``points`` under the best pure shift
    (no turn in the sensor frame), found by Gauss-Newton from the shift ``T_ref_frame`` gives
    their centroid."""
    # The shift the motion gives the body's centroid: T's own shift is that of the sensor
    # origin, metres away from a body turning about its own axis (a turntable's disc).
    centroid = points.mean(axis=0)
    t = se3.transform_points(T_ref_frame, centroid[None])[0] - centroid
    q = ref.cloud
    for _ in range(_SHIFT_ITERATIONS):
        moved = points + t
        s, j, _ = find_correspondences(ref.tree, moved, reach, workers)
        n = q.normals[j]
        r = np.einsum("ij,ij->i", moved[s] - q.points[j], n)
        # Pairs beyond the cap do not pull (a redescending kernel at its simplest).
        w = (np.abs(r) < cap).astype(np.float64)
        A = np.einsum("i,ij,ik->jk", w, n, n)
        if np.linalg.matrix_rank(A) < 3:
            break
        t -= np.linalg.solve(A, n.T @ (w * r))
    T = np.eye(4)
    T[:3, 3] = t
    r = np.minimum(plane_residuals(ref, points, T, reach, workers), cap)
    return float(np.mean(r**2))


def _reference_labels(
    ref: PreparedCloud,
    points: NDArray[np.float64],
    shown: tuple[NDArray[np.bool_], NDArray[np.bool_]],
    motions: tuple[NDArray[np.float64], NDArray[np.float64]],
    near: float,
    workers: int,
) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
    """(M,) masks of the reference points on the target and on the support: each goes with
    the body whose explained frame points (``shown``, moved by its motion) lie nearer, if
    within ``near`` (m); a reference point neither comes near (the wall, stray pixels, a face
    turned away since) goes with neither."""
    q = ref.cloud.points
    d_target, d_support = (
        _nearest_distance(se3.transform_points(T, points[mask]), q, near, workers)
        for T, mask in zip(motions, shown, strict=True)
    )
    target = (d_target <= d_support) & (d_target <= near)
    return target, ~target & (d_support <= near)


def _nearest_distance(
    points: NDArray[np.float64], queries: NDArray[np.float64], bound: float, workers: int
) -> NDArray[np.float64]:
    """(M,) distance of each query to the nearest of ``points`` within ``bound`` (m); inf
    beyond, or when there are no points."""
    if len(points) == 0:
        return np.full(len(queries), np.inf)
    d, _ = cKDTree(points).query(queries, distance_upper_bound=bound, workers=workers)
    return d
