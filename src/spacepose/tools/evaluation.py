"""Score a trajectory file against a ground-truth file, saying what the numbers may hide.

:func:`compare_trajectory_files` reads both files (TUM or KITTI), pairs the poses by timestamp,
computes the error table (:func:`spacepose.core.metrics.evaluate`) and warns, naming the file,
when the comparison is suspect rather than wrong:

- the files hold different numbers of poses (only the estimated ones are scored);
- several estimates share one ground-truth pose (repeated timestamps);
- the estimate starts at the identity, as a model-free track does (frame 0 defines the target
  frame), while the ground truth does not, and ``rebase_first`` is off: the errors are then
  dominated by the first pose's offset.

Its JSON form states its units in every key (``_mm``, ``_deg``) and in a ``units`` entry.
"""

from __future__ import annotations

import csv
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from spacepose.core import se3
from spacepose.core.metrics import TIMESTAMP_TOLERANCE, ErrorTable, associate, evaluate
from spacepose.core.trajectory import Trajectory
from spacepose.errors import InputError, SpaceposeWarning
from spacepose.tools.text_io import as_path
from spacepose.tools.trajectory_io import read_trajectory, trajectory_format

# A pose counts as the identity (a model-free track's first pose) within this much rotation
# (rad) and translation (in the file's units): far below any real offset, far above rounding.
_IDENTITY_TOLERANCE = 1e-9
# Median distances of paired absolute poses differing by this factor or more are taken for a
# unit mismatch (cm 100, inch 39.4, mm 1000): a tracking error, even a lost track, rarely moves
# a pose that far from where its truth lies.
_UNIT_FACTOR = 30.0
# Rebased poses are motions, and a nearly static truth against an estimate's noise can differ
# by any factor: there only a unit's own factor (mm 1000, cm 100, inch 39.37, or their
# inverses) within this ratio counts, and only when both turn alike (within 2x: a unit does
# not touch rotations).
_UNIT_FACTORS = (1000.0, 100.0, 1.0 / 0.0254)
_UNIT_MATCH = 1.25


@dataclass(frozen=True)
class TrajectoryComparison:
    """The error table of an estimate against ground truth, and what to be wary of.

    Attributes
    ----------
    table
        Per-axis errors (mm, deg) and ATE RMSE of the paired poses.
    n_estimated, n_ground_truth
        Poses in each file (lost frames included; ``table.n`` counts those scored).
    rebase_first
        Whether both were expressed relative to their first paired pose.
    warnings
        One sentence per suspect point (also issued as :class:`SpaceposeWarning`).
    """

    table: ErrorTable
    n_estimated: int
    n_ground_truth: int
    rebase_first: bool
    warnings: tuple[str, ...]

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready mapping; every length in mm and every angle in degrees, as its key says.

        ``{"units", "n", "n_estimated", "n_ground_truth", "rebase_first", "mean": {"x_mm", ...,
        "roll_deg"}, "std": {...}, "ate_translation_rmse_mm", "ate_rotation_rmse_deg",
        "warnings"}``.
        """
        rows = self.table.rows()
        return {
            "units": {"translation": "mm", "rotation": "deg"},
            "n": self.table.n,
            "n_estimated": self.n_estimated,
            "n_ground_truth": self.n_ground_truth,
            "rebase_first": self.rebase_first,
            "mean": {f"{axis}_{unit}": mean for axis, unit, mean, _ in rows},
            "std": {f"{axis}_{unit}": std for axis, unit, _, std in rows},
            "ate_translation_rmse_mm": 1e3 * float(self.table.ate_translation_rmse),
            "ate_rotation_rmse_deg": float(self.table.ate_rotation_rmse),
            "warnings": list(self.warnings),
        }


# Rotations this far apart (median, deg) with a reading that brings them within the second
# are quaternions written in another order: no tracker is wrong by 60° on most frames and
# right to a few degrees once w is moved.
_MISREAD_TURN_DEG = 60.0
_REREAD_TURN_DEG = 5.0
# The statuses EST.health.csv holds (spacepose.core.track_result).
_STATUSES: tuple[str, ...] = ("ok", "degraded", "lost")


def compare_trajectory_files(
    est_path: str | Path,
    gt_path: str | Path,
    rebase_first: bool = False,
    tolerance: float = TIMESTAMP_TOLERANCE,
    gt_sensor_poses: bool = False,
) -> TrajectoryComparison:
    """Read, pair by timestamp and score ``est_path`` against ``gt_path``.

    Parameters
    ----------
    est_path, gt_path
        Trajectories (TUM or KITTI) of the same pose, e.g. ``T_sensor_target``, metres.
    rebase_first
        Express both relative to their first paired pose (model-free tracking, methods.md §0).
    gt_sensor_poses
        ``gt_path`` holds the sensor's pose in a world frame, ``T_world_sensor`` (TUM RGB-D's
        ``groundtruth.txt``, most SLAM datasets): scored as its inverses, ``T_sensor_world``,
        the pose of a still scene (the target) in the sensor frame, which the estimate holds.
    tolerance
        Largest time difference of a pair, seconds.

    Raises
    ------
    InputError
        An estimate without a ground-truth pose within ``tolerance``, or with one pose alone
        to score rebased (zero by construction), naming ``est_path``; a ground truth with two
        poses at one time, naming ``gt_path``.

    Warns
    -----
    SpaceposeWarning
        Lost frames left out (``EST.health.csv`` beside the estimate), estimated poses outside
        the ground truth's span left out, different lengths,
        repeated pairings, a model-free
        estimate compared as it is, or
        poses whose distances (from the origin, or rebased from the first) differ by a unit's
        factor (mm against m).
    """
    est_path, gt_path = as_path(est_path, "est_path"), as_path(gt_path, "gt_path")
    with warnings.catch_warnings(record=True) as read:  # kept for the result too (--json)
        warnings.simplefilter("always")
        est, gt = read_trajectory(est_path), read_trajectory(gt_path)
    for caught in read:
        warnings.warn_explicit(caught.message, caught.category, caught.filename, caught.lineno)
    read_notes = [str(caught.message) for caught in read]
    if gt_sensor_poses:
        gt = Trajectory(gt.timestamps, se3.invert(gt.poses), gt.source)
    _check_one_truth_per_time(gt.timestamps, gt_path)
    _check_frame_numbers((est_path, est), (gt_path, gt))
    # Counted as read: less the lost frames, "1 poses against 3" read as a file of 1 pose.
    n_read = len(est)
    est, _, lost_note = without_lost_frames(est_path, est)
    est, outside_note = within_truth_span(est, gt, tolerance, gt_path.name)
    try:
        _, i_gt = associate(est.timestamps, gt.timestamps, tolerance)
        table = evaluate(est, gt, rebase_first=rebase_first, tolerance=tolerance)
    except InputError as exc:
        # The poses left out first are said: "5 of 5 estimated timestamps" of a 6-row file.
        before = "" if outside_note is None else f"{outside_note}; "
        raise InputError(f"against {gt_path.name}: {before}{exc.reason}", est_path) from None
    notes = [note for note in (lost_note, outside_note) if note is not None]
    offset = clock_offset(est.timestamps, gt.timestamps[i_gt], gt_path.name)
    if offset is not None:
        notes.append(offset)
    order = quaternion_order(est.poses, gt.poses[i_gt], gt_path.name, rebase_first)
    if order is not None:
        notes.append(order)
    if n_read != len(gt) and outside_note is None:  # the note says what is scored already
        scored = "estimated ones" if len(est) == n_read else "estimated ones not lost"
        notes.append(
            f"{n_read} poses against {len(gt)} in {gt_path.name}: only the {len(est)} "
            f"{scored} are scored"
        )
    shared = shared_pairings(i_gt)
    if shared is not None:
        notes.append(shared)
    alone = lone_rebased_pose(len(est), rebase_first)
    if alone is not None:
        # Zero by construction: an exit code of 0 passed a track with one pose on the truth's
        # times (an estimate in nanoseconds against a truth in seconds) as a perfect one.
        raise InputError("; ".join([*notes, alone]), est_path)
    if (
        not rebase_first
        and starts_at_identity(est.poses[0])
        and not starts_at_identity(gt.poses[i_gt[0]])
    ):
        notes.append(
            "the first pose is the identity (a model-free track: frame 0 defines the target "
            f"frame) but {gt_path.name}'s is not, so every error includes that offset; "
            "compare with --rebase-first (rebase_first=True)"
        )
    else:
        notes.extend(unit_mismatch(est.poses, gt.poses[i_gt], gt_path.name, rebase_first))
    for note in notes:
        warnings.warn(SpaceposeWarning(note, est_path), stacklevel=2)
    return TrajectoryComparison(table, n_read, len(gt), rebase_first, (*read_notes, *notes))


def clock_offset(t_est: np.ndarray, t_gt: np.ndarray, gt_name: str) -> str | None:
    """The note for estimates all paired with truths one same time away (a clock offset that
    a wide ``--max-dt`` let through: the scores compare poses that far apart in time), or
    None. ``t_est`` and ``t_gt`` (N,) are the paired times."""
    gap = t_gt - t_est
    if len(gap) < 3 or np.ptp(gap) > TIMESTAMP_TOLERANCE or abs(gap[0]) <= TIMESTAMP_TOLERANCE:
        return None
    return (
        f"every estimate is paired with a pose of {gt_name} {gap[0]:+.6g} s from it: a clock "
        "offset between the two files? the errors compare poses that far apart in time"
    )


def quaternion_order(
    est: np.ndarray, gt: np.ndarray, gt_name: str, rebase_first: bool
) -> str | None:
    """The note for rotations that agree once one file's quaternions are read w first (a
    common mix-up: TUM writes ``qx qy qz qw``), or None; ``est`` and ``gt`` (N, 4, 4) paired.

    A truth written w first scored 160° of rotation error beside 0.17 mm of translation."""
    as_written = _median_turn_deg(est, gt, rebase_first)
    if as_written < _MISREAD_TURN_DEG:
        return None
    for name, a, b in (("the estimate", _w_first(est), gt), (gt_name, est, _w_first(gt))):
        read_w_first = _median_turn_deg(a, b, rebase_first)
        if read_w_first < _REREAD_TURN_DEG:
            return (
                f"rotations {as_written:.0f}° apart (median) agree within {read_w_first:.2g}° "
                f"when {name}'s quaternions are read w first: TUM's order is qx qy qz qw"
            )
    return None


def _w_first(poses: np.ndarray) -> np.ndarray:
    """``poses`` (N, 4, 4) whose rotations were read from quaternions written ``w x y z`` as
    if they were ``x y z w``: the rotations those quaternions meant."""
    from scipy.spatial.transform import Rotation

    read = Rotation.from_matrix(poses[:, :3, :3]).as_quat()  # (x, y, z, w) as read
    out = poses.copy()
    out[:, :3, :3] = Rotation.from_quat(np.roll(read, -1, axis=1)).as_matrix()
    return out


def _median_turn_deg(a: np.ndarray, b: np.ndarray, rebase_first: bool) -> float:
    """Median angle (deg) of ``a_k b_k⁻¹`` (each rebased on its first when ``rebase_first``)."""
    Ra, Rb = a[:, :3, :3], b[:, :3, :3]
    if rebase_first:
        Ra = Ra @ Ra[0].T
        Rb = Rb @ Rb[0].T
    cos = (np.einsum("nij,nij->n", Ra, Rb) - 1.0) / 2.0
    return float(np.degrees(np.median(np.arccos(np.clip(cos, -1.0, 1.0)))))


def shared_pairings(i_gt: np.ndarray) -> str | None:
    """The note for estimates paired with a ground-truth pose another estimate is paired with
    too (repeated timestamps), ``i_gt`` (N,) their ground-truth indices; None when none is."""
    shared = len(i_gt) - len(np.unique(i_gt))
    if not shared:
        return None
    return (
        f"{shared} estimate(s) share a ground-truth pose with another (repeated timestamps, "
        "or a --max-dt wider than the spacing of the truth)"
    )


def lone_rebased_pose(count: int, rebase_first: bool) -> str | None:
    """The note for ``count`` scored poses rebased on the first when there is one: rebased
    on itself it is the identity on both sides, a perfect score of any estimate; else None."""
    if not (rebase_first and count == 1):
        return None
    return (
        "one pose scored: rebased on itself it is the identity in both files, so every error "
        "is zero whatever the estimate; nothing is measured"
    )


def _check_one_truth_per_time(timestamps: np.ndarray, path: Path) -> None:
    """Refuse a ground truth with two poses at one time (within :data:`TIMESTAMP_TOLERANCE`,
    whatever the pairing's tolerance): an estimate there would be scored against whichever the
    pairing met first, without a word. Poses apart in time are not ambiguous however close
    (a 100 Hz motion-capture truth paired within 20 ms): the nearest is taken.

    Raises
    ------
    InputError
        Naming the file and the time.
    """
    t = np.sort(np.asarray(timestamps, dtype=np.float64))
    close = np.flatnonzero(np.diff(t) <= TIMESTAMP_TOLERANCE)
    if close.size:
        # As a float: numpy's repr put "np.float64(...)" in the message.
        raise InputError(
            f"two ground-truth poses at t = {float(t[close[0]])!r}: which one is the truth? "
            "(one pose a time)",
            path,
        )


def _check_frame_numbers(*files: tuple[Path, Trajectory]) -> None:
    """Refuse a KITTI file against a TUM file whose times are not frame numbers.

    KITTI carries no times: its poses are timed 0, 1, 2, ... (frame numbers). Against a 2 Hz
    TUM file (0, 0.5, 1, ...) its k-th pose met the truth at t = k s, frame 2k, and was
    scored against it without a word.

    Raises
    ------
    InputError
        One file is KITTI and the other's times are not whole numbers, naming the other.
    """
    kitti = [path for path, _ in files if trajectory_format(path) == "kitti"]
    if len(kitti) != 1:
        return  # both timed alike (both frame numbers, or both clocks)
    path, traj = next((p, t) for p, t in files if p != kitti[0])
    t = traj.timestamps
    off = np.flatnonzero(np.abs(t - np.round(t)) > TIMESTAMP_TOLERANCE)
    if len(off):
        raise InputError(
            f"its times are not frame numbers (t = {t[off[0]]:.9g} s), and {kitti[0].name} is "
            "KITTI, timed by frame number (0, 1, 2, ...) as it holds no times: give both as "
            "KITTI, or both as TUM with their times",
            path,
        )


def within_truth_span(
    est: Trajectory, gt: Trajectory, tolerance: float, gt_name: str
) -> tuple[Trajectory, str | None]:
    """The poses of ``est`` within ``tolerance`` of the span of the ground truth's times, and
    a note of how many fell outside (a ground truth that ends before the estimate scores the
    overlap); all of them, with no note, when none or every one does (nothing to score: the
    pairing then says why)."""
    valid = isinstance(tolerance, int | float | np.integer | np.floating)
    if isinstance(tolerance, bool) or not valid or not tolerance >= 0:
        return est, None  # the pairing refuses it, saying why
    t = est.timestamps
    inside = (t >= gt.timestamps.min() - tolerance) & (t <= gt.timestamps.max() + tolerance)
    if inside.all() or not inside.any():
        return est, None
    note = (
        f"{int((~inside).sum())} of {len(t)} estimated poses lie outside {gt_name}'s times "
        f"({gt.timestamps.min():.6g}..{gt.timestamps.max():.6g} s): left out"
    )
    return Trajectory(t[inside], est.poses[inside], est.source), note


def without_lost_frames(
    est_path: Path, est: Trajectory
) -> tuple[Trajectory, np.ndarray | None, str | None]:
    """The estimate read from ``est_path`` without the poses :func:`lost_frames` marks (all
    of them kept when every frame is lost: nothing else can be scored), the mask and its
    note."""
    lost, note = lost_frames(est_path, est)
    if lost is None or lost.all():
        return est, lost, note
    return Trajectory(est.timestamps[~lost], est.poses[~lost]), lost, note


def lost_frames(est_path: Path, est: Trajectory) -> tuple[np.ndarray | None, str | None]:
    """Which of the poses ``est`` of ``est_path`` its tracker's health table
    (``EST.health.csv`` beside it, one row a pose, at the pose's time) marks ``lost``
    ((len(est),) bool; None without a usable table or a lost frame), and a note saying what
    is left out or why nothing is.

    A lost frame's pose in ``EST.tum`` is the motion model's prediction, written so that no
    frame goes missing, not a measurement: scored, it counts the tracker's guess as its
    error."""
    from spacepose.tools.tracking_io import output_paths  # the tracker's own file names

    health = output_paths(est_path)[1]
    if not health.is_file():
        return None, None
    try:
        with health.open(newline="") as fh:
            rows = list(csv.DictReader(fh))
    except (OSError, UnicodeDecodeError, csv.Error):
        return None, f"{health.name} is unreadable: lost frames, if any, are scored"
    unused = f"{health.name} {{}}: lost frames, if any, are scored"
    if rows and "status" not in rows[0]:
        # Another delimiter or a renamed column: every frame read as not lost, silently.
        return None, unused.format("has no status column")
    if len(rows) != len(est):
        return None, unused.format(f"has {len(rows)} rows for {len(est)} poses")
    off = _other_times(rows, est.timestamps)
    if off is not None:
        # Another run's table: its lost flags were laid on other frames without a word.
        k, t = off
        return None, unused.format(
            f"row {k + 1} is at t = {t:.9g} s, pose {k} at {est.timestamps[k]:.9g} s"
        )
    # Read as the tracker writes them; another word (LOST, failed) left that frame scored
    # without a word.
    statuses = [(row["status"] or "").strip().lower() for row in rows]
    other = next((k for k, v in enumerate(statuses) if v not in _STATUSES), None)
    if other is not None:
        word = rows[other]["status"]
        return None, unused.format(
            f"row {other + 1} has status {word!r}, not one of {', '.join(_STATUSES)}"
        )
    lost = np.array([v == "lost" for v in statuses])
    if not lost.any():
        return None, None
    if lost.all():
        return lost, f"every frame is lost in {health.name}: the scores are of predictions"
    return lost, (
        f"{int(lost.sum())} frame(s) lost in {health.name} left out (their poses are the "
        "motion model's predictions)"
    )


def _other_times(rows: list[dict[str, str]], timestamps: np.ndarray) -> tuple[int, float] | None:
    """The first health row (index, time) whose ``timestamp`` is not its pose's, or None
    (a table without readable times is paired by row, as the tracker writes it)."""
    try:
        times = np.array([float(row["timestamp"]) for row in rows])
    except (KeyError, TypeError, ValueError):
        return None
    # Not "> tolerance": a NaN time compares False and its row was paired by position.
    off = np.flatnonzero(~(np.abs(times - timestamps) <= TIMESTAMP_TOLERANCE))
    return None if not len(off) else (int(off[0]), float(times[off[0]]))


def unit_mismatch(
    est: np.ndarray, gt: np.ndarray, gt_name: str, rebase_first: bool = False
) -> list[str]:
    """A note when the paired poses' distances (N, 4, 4 each) differ by a factor a unit would
    explain (a trajectory in millimetres against one in metres scores errors of the whole
    distance), else nothing. Absolute poses are measured from the origin. With
    ``rebase_first`` each pose is measured from its trajectory's first: then the factor must
    be a unit's, and the two must turn alike."""
    where = "from the origin"
    if rebase_first:
        # Rebased as the scores are (T_k T_0⁻¹): rebased the other way (T_0⁻¹ T_k) a target
        # turning in place at range moves from its first pose by far less than its
        # model-free track does, and a track in millimetres came out 3,000 times as far, no
        # unit's factor, and was not flagged.
        est, gt = (T[1:] @ np.linalg.inv(T[0]) for T in (est, gt))
        where = "from its first pose"
    if len(est) == 0:
        return []
    d_est, d_gt = (float(np.median(np.linalg.norm(T[:, :3, 3], axis=1))) for T in (est, gt))
    if d_est <= 0.0 or d_gt <= 0.0 or 1.0 / _UNIT_FACTOR < d_est / d_gt < _UNIT_FACTOR:
        return []
    if rebase_first and not _a_unit_apart(est, gt, d_est / d_gt):
        return []
    return [
        f"its poses lie {d_est:.4g} (median distance) {where} and {gt_name}'s "
        f"{d_gt:.4g}, {d_est / d_gt:.3g} times as far: are both in metres?"
    ]


def _a_unit_apart(est: np.ndarray, gt: np.ndarray, ratio: float) -> bool:
    """Whether motions (N, 4, 4 each) whose distances differ by ``ratio`` turn alike and
    ``ratio`` is a unit's factor."""
    angles = [
        float(
            np.median(np.arccos(np.clip((np.trace(T[:, :3, :3], axis1=1, axis2=2) - 1) / 2, -1, 1)))
        )
        for T in (est, gt)
    ]
    if min(angles) <= 0.0 or max(angles) > 2.0 * min(angles):
        return False
    factor = max(ratio, 1.0 / ratio)
    return any(1.0 / _UNIT_MATCH < factor / unit < _UNIT_MATCH for unit in _UNIT_FACTORS)


def starts_at_identity(T_first: np.ndarray) -> bool:
    """Whether a first pose (4, 4) is the identity, as a model-free estimate's (methods.md §0)."""
    return bool(np.allclose(T_first, np.eye(4), rtol=0.0, atol=_IDENTITY_TOLERANCE))
