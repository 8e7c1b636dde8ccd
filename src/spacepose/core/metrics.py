"""Pose error metrics: Li's per-axis table (Li §3.2.2, Eq. 10) and evo-compatible ATE.

Two error definitions are used on purpose (methods.md §0):

* The per-axis table follows Li Eq. 10: ``ΔT = T_est · T_gt⁻¹``; the translation errors are the
  components of ``Δt`` and the rotation errors are ``ΔR`` as ZYX Euler angles (yaw, pitch, roll).
  Note that ``Δt = t_est − ΔR t_gt`` is not the position difference when ``ΔR ≠ I``.
* The ATE numbers match ``evo_ape`` without alignment: translation RMSE over
  ``‖t_est − t_gt‖`` (evo's ``translation_part``) and RMSE of the rotation angle of ``ΔR``
  (evo's ``rotation_angle_deg``; the angle of ``R_est R_gtᵀ`` equals that of ``R_estᵀ R_gt``).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from spacepose.core import se3
from spacepose.core.cloud import MAX_ABS_COORDINATE
from spacepose.core.trajectory import Trajectory
from spacepose.errors import InputError

#: Row names of the per-axis table, in the order of Li's Table 2.
TRANSLATION_AXES = ("x", "y", "z")
ROTATION_AXES = ("pitch", "yaw", "roll")

#: Default tolerance (s) for pairing an estimated pose with a ground-truth pose.
TIMESTAMP_TOLERANCE = 1e-6


def pose_errors(
    T_est: ArrayLike, T_gt: ArrayLike
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Per-frame pose errors ``ΔT = T_est · T_gt⁻¹`` (Li Eq. 10).

    Parameters
    ----------
    T_est, T_gt
        (N, 4, 4) or (4, 4) estimated and true poses mapping the same frames (e.g.
        ``T_sensor_target``).

    Returns
    -------
    translation
        (N, 3) ``Δt`` in metres, in the frame the poses map into.
    euler_zyx
        (N, 3) ``ΔR`` as intrinsic ZYX Euler angles in radians, ordered (yaw, pitch, roll) as
        scipy's ``as_euler("ZYX")`` returns them.
    """
    est, gt = _pose_stacks(T_est, T_gt)
    delta = est @ se3.invert(gt)
    return delta[:, :3, 3], Rotation.from_matrix(delta[:, :3, :3]).as_euler("ZYX")


def _pose_stacks(
    T_est: ArrayLike, T_gt: ArrayLike
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Matching non-empty (N, 4, 4) stacks of rigid transforms ((4, 4): N = 1).

    Raises
    ------
    InputError
        Not numbers, shapes that differ or are not (N, 4, 4), non-finite entries, or a pose
        that is not a rigid transform (a scaled or reflected rotation would give errors of a
        transform that is not a pose).
    """
    se3.check_real(T_est, "estimated poses")
    se3.check_real(T_gt, "true poses")
    try:
        est = np.asarray(T_est, dtype=np.float64)
        gt = np.asarray(T_gt, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError("poses must be (N, 4, 4) arrays of numbers") from None
    est = est[None] if est.ndim == 2 else est
    gt = gt[None] if gt.ndim == 2 else gt
    if est.shape != gt.shape or est.ndim != 3 or est.shape[1:] != (4, 4) or len(est) == 0:
        raise InputError(
            f"pose errors need matching non-empty (N, 4, 4) stacks, got {est.shape} and {gt.shape}"
        )
    for name, T in (("estimated", est), ("true", gt)):
        if not np.isfinite(T).all():
            raise InputError(f"{name} poses have non-finite entries")
        # As a Trajectory refuses them: the squared errors overflowed to inf and NaN.
        far = np.abs(T[:, :3, 3]).max(axis=1) > MAX_ABS_COORDINATE
        if far.any():
            raise InputError(
                f"{name} pose {int(np.argmax(far))} has a translation beyond "
                f"{MAX_ABS_COORDINATE:.0e} m"
            )
        off = se3.non_rigid(T)
        if off.any():
            raise InputError(f"{name} pose {int(np.argmax(off))} is not a rigid transform")
    return est, gt


def associate(
    est_timestamps: ArrayLike,
    gt_timestamps: ArrayLike,
    tolerance: float = TIMESTAMP_TOLERANCE,
) -> tuple[NDArray[np.intp], NDArray[np.intp]]:
    """Pair every estimated timestamp with the nearest ground-truth timestamp.

    Parameters
    ----------
    est_timestamps, gt_timestamps
        (N,) and (M,) times in seconds.
    tolerance
        Largest accepted time difference, seconds.

    Returns
    -------
    Index arrays ``(i_est, i_gt)`` of equal length N, ``i_est = arange(N)``.

    Raises
    ------
    InputError
        If any estimated timestamp has no ground truth within ``tolerance`` (every estimate must
        be evaluated, so none is silently skipped), or timestamps that are not finite 1-D
        numbers.
    """
    se3.check_real(est_timestamps, "estimated timestamps")
    se3.check_real(gt_timestamps, "ground-truth timestamps")
    try:
        t_est = np.asarray(est_timestamps, dtype=np.float64)
        t_gt = np.asarray(gt_timestamps, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError("timestamps must be numbers (seconds)") from None
    if t_est.ndim != 1 or t_gt.ndim != 1 or len(t_gt) == 0:
        raise InputError(f"timestamps must be 1-D, got {t_est.shape} and {t_gt.shape}")
    if not (np.isfinite(t_est).all() and np.isfinite(t_gt).all()):
        raise InputError("timestamps must be finite")
    number = isinstance(tolerance, int | float | np.integer | np.floating)
    if isinstance(tolerance, bool) or not number or not tolerance >= 0:
        # Text or None ended in a TypeError of the comparison.
        raise InputError(f"tolerance must be a number of seconds >= 0, got {tolerance!r}")
    order = np.argsort(t_gt, kind="stable")
    sorted_gt = t_gt[order]
    right = np.clip(np.searchsorted(sorted_gt, t_est), 0, len(sorted_gt) - 1)
    left = np.clip(right - 1, 0, len(sorted_gt) - 1)
    take_left = np.abs(sorted_gt[left] - t_est) <= np.abs(sorted_gt[right] - t_est)
    nearest = np.where(take_left, left, right)
    gap = np.abs(sorted_gt[nearest] - t_est)
    unmatched = gap > tolerance
    if unmatched.any():
        first = int(np.argmax(unmatched))
        raise InputError(
            f"{int(unmatched.sum())} of {len(t_est)} estimated timestamps have no ground truth "
            f"within {tolerance:g} s (first: t = {float(t_est[first])!r}, nearest ground truth "
            f"{gap[first]:.3g} s away)"
        )
    return np.arange(len(t_est)), order[nearest]


@dataclass(frozen=True, eq=False)
class ErrorTable:
    """Per-axis pose error statistics over a trajectory (Li's Table 2) plus evo's ATE.

    Attributes
    ----------
    translation_mean_mm, translation_std_mm
        (3,) mean and standard deviation (ddof 0) of ``|Δt|`` per axis x, y, z, millimetres.
    rotation_mean_deg, rotation_std_deg
        (3,) the same for the Euler angle errors, ordered pitch, yaw, roll, degrees.
    ate_translation_rmse
        RMSE of ``‖t_est − t_gt‖``, metres (evo ``translation_part``).
    ate_rotation_rmse
        RMSE of the rotation angle of ``ΔR``, degrees (evo ``rotation_angle_deg``).
    n
        Number of frames compared.
    """

    translation_mean_mm: NDArray[np.float64]
    translation_std_mm: NDArray[np.float64]
    rotation_mean_deg: NDArray[np.float64]
    rotation_std_deg: NDArray[np.float64]
    ate_translation_rmse: float
    ate_rotation_rmse: float
    n: int

    def rows(self) -> list[tuple[str, str, float, float]]:
        """Table rows ``(axis, unit, mean, std)``: x, y, z in mm then pitch, yaw, roll in deg."""
        trans = [
            (axis, "mm", float(m), float(s))
            for axis, m, s in zip(
                TRANSLATION_AXES, self.translation_mean_mm, self.translation_std_mm, strict=True
            )
        ]
        rot = [
            (axis, "deg", float(m), float(s))
            for axis, m, s in zip(
                ROTATION_AXES, self.rotation_mean_deg, self.rotation_std_deg, strict=True
            )
        ]
        return trans + rot

    def to_dict(self) -> dict[str, Any]:
        """JSON-ready mapping with keys named like the attributes.

        ``{"n", "mean": {"x_mm", "y_mm", "z_mm", "pitch_deg", "yaw_deg", "roll_deg"},
        "std": {...same keys...}, "ate_translation_rmse" (m), "ate_rotation_rmse" (deg)}``.
        """
        rows = self.rows()
        return {
            "n": self.n,
            "mean": {f"{axis}_{unit}": mean for axis, unit, mean, _ in rows},
            "std": {f"{axis}_{unit}": std for axis, unit, _, std in rows},
            "ate_translation_rmse": float(self.ate_translation_rmse),
            "ate_rotation_rmse": float(self.ate_rotation_rmse),
        }


def error_table(T_est: ArrayLike, T_gt: ArrayLike) -> ErrorTable:
    """Statistics of paired poses (N, 4, 4) already associated frame by frame."""
    est, gt = _pose_stacks(T_est, T_gt)
    dt, euler = pose_errors(est, gt)
    trans_mm = np.abs(dt) * 1e3
    # as_euler("ZYX") gives (yaw, pitch, roll); the table lists pitch, yaw, roll.
    rot_deg = np.degrees(np.abs(euler[:, [1, 0, 2]]))
    position_error = np.linalg.norm(est[:, :3, 3] - gt[:, :3, 3], axis=1)
    angle = Rotation.from_matrix(est[:, :3, :3] @ np.swapaxes(gt[:, :3, :3], 1, 2)).magnitude()
    return ErrorTable(
        translation_mean_mm=trans_mm.mean(axis=0),
        translation_std_mm=trans_mm.std(axis=0),
        rotation_mean_deg=rot_deg.mean(axis=0),
        rotation_std_deg=rot_deg.std(axis=0),
        ate_translation_rmse=float(np.sqrt(np.mean(position_error**2))),
        ate_rotation_rmse=float(np.degrees(np.sqrt(np.mean(angle**2)))),
        n=len(est),
    )


def evaluate(
    est: Trajectory,
    gt: Trajectory,
    rebase_first: bool = False,
    align_by: Literal["timestamp", "index"] = "timestamp",
    tolerance: float = TIMESTAMP_TOLERANCE,
) -> ErrorTable:
    """Compare an estimated trajectory with ground truth.

    Parameters
    ----------
    est, gt
        Estimated and true poses of the same frames (e.g. ``T_sensor_target``).
    rebase_first
        Express both trajectories relative to their first associated pose, the earliest in
        time (methods.md §0, model-free tracking), so a constant offset of the whole estimate
        is not counted.
    align_by
        ``"timestamp"``: pair each estimate with the ground truth within ``tolerance`` seconds
        (ground truth may have extra frames); ``"index"``: pair pose k with pose k (the two must
        have the same length).
    tolerance
        Time tolerance for ``"timestamp"`` pairing, seconds.

    Raises
    ------
    InputError
        If an estimate has no matching ground truth, or the lengths differ for ``"index"``.
    """
    for name, traj in (("est", est), ("gt", gt)):
        if not isinstance(traj, Trajectory):
            raise InputError(f"{name} must be a Trajectory, got {type(traj).__name__}")
    if align_by == "timestamp":
        i_est, i_gt = associate(est.timestamps, gt.timestamps, tolerance)
    elif align_by == "index":
        if len(est) != len(gt):
            raise InputError(
                f"align_by='index' needs equal lengths, got {len(est)} estimated and "
                f"{len(gt)} ground-truth poses"
            )
        i_est = i_gt = np.arange(len(est))
    else:
        raise InputError(f"align_by must be 'timestamp' or 'index', got {align_by!r}")
    T_est, T_gt = est.poses[i_est], gt.poses[i_gt]
    if rebase_first:
        # The earliest pair, not the first row: a file written in another order (rows in
        # reverse) was rebased on its last pose without a word.
        first = int(np.argmin(est.timestamps[i_est])) if align_by == "timestamp" else 0
        T_est = T_est @ se3.invert(T_est[first])
        T_gt = T_gt @ se3.invert(T_gt[first])
    return error_table(T_est, T_gt)


#: Navigation state groups scored against truth: (name, columns, scale to display unit, unit).
NAV_GROUPS: tuple[tuple[str, tuple[str, str, str], float, str], ...] = (
    ("position", ("rho_x", "rho_y", "rho_z"), 1e3, "mm"),
    ("velocity", ("v_x", "v_y", "v_z"), 1e3, "mm/s"),
    ("angular rate", ("w_x", "w_y", "w_z"), float(np.degrees(1.0)), "deg/s"),
    ("inertia ratios", ("k_x", "k_y", "k_z"), 1.0, "-"),
    ("centre-of-mass offset", ("com_x", "com_y", "com_z"), 1e3, "mm"),
)


@dataclass(frozen=True)
class NavigationErrors:
    """Navigation errors per state group against truth, in display units.

    Attributes
    ----------
    t
        (N,) time, s.
    groups
        Group name -> (unit, columns (3,), error (N, 3), sigma (N, 3)); ``attitude`` is the
        rotation vector δθ in B with ``R_true = R_est · exp(δθ)``, in degrees.
    """

    t: NDArray[np.float64]
    groups: dict[str, tuple[str, tuple[str, ...], NDArray[np.float64], NDArray[np.float64]]]

    def rms(self, start_fraction: float = 0.5) -> dict[str, list[float]]:
        """Per-axis RMS of each group over the frames after ``start_fraction`` of the run
        (frames before the filter started, NaN, are left out)."""
        first = int(len(self.t) * start_fraction)
        return {
            name: np.sqrt(np.nanmean(err[first:] ** 2, axis=0)).tolist()
            for name, (_, _, err, _) in self.groups.items()
        }


def navigation_errors(
    nav: dict[str, NDArray[np.float64]], truth: dict[str, NDArray[np.float64]]
) -> NavigationErrors:
    """Compare a NAV table with the simulator's truth table, frame by frame.

    Parameters
    ----------
    nav
        Column name -> (N,) values, with the NAV.csv state columns and their ``sig_`` columns
        (``sig_att_x/y/z`` for the attitude, radians).
    truth
        Column name -> (M,) values with the truth.csv columns; the first min(N, M) rows pair.
    """
    if not (isinstance(nav, Mapping) and isinstance(truth, Mapping)):
        raise InputError(
            "navigation_errors needs two tables of columns (name -> values), got "
            f"{type(nav).__name__} and {type(truth).__name__}"
        )
    quaternion = ["t", "qx", "qy", "qz", "qw"]
    state = [c for _, cols, _, _ in NAV_GROUPS for c in cols]
    sigmas = [f"sig_{c}" for c in state] + [f"sig_att_{a}" for a in "xyz"]
    missing = [c for c in quaternion + state + sigmas if c not in nav]
    missing += [f"truth {c}" for c in quaternion + state if c not in truth]
    if missing:
        raise InputError(f"navigation table lacks columns {missing}")
    nav = {c: _column(nav[c], c) for c in quaternion + state + sigmas}
    truth = {c: _column(truth[c], f"truth {c}") for c in quaternion + state}
    n = min(len(nav["t"]), len(truth["t"]))
    q_est = np.stack([nav[c][:n] for c in ("qx", "qy", "qz", "qw")], axis=1)
    q_true = np.stack([truth[c][:n] for c in ("qx", "qy", "qz", "qw")], axis=1)
    started = np.all(np.isfinite(q_est), axis=1)
    zero = started & (~np.any(q_est, axis=1) | ~np.any(q_true, axis=1))
    if zero.any():
        raise InputError(f"navigation table row {int(np.argmax(zero))}: a quaternion of zeros")
    att = np.full((n, 3), np.nan)
    att[started] = (
        Rotation.from_quat(q_est[started]).inv() * Rotation.from_quat(q_true[started])
    ).as_rotvec()
    groups = {
        "attitude": (
            "deg",
            ("att_x", "att_y", "att_z"),
            np.degrees(att),
            np.degrees(np.stack([nav[f"sig_att_{a}"][:n] for a in "xyz"], axis=1)),
        )
    }
    for name, cols, scale, unit in NAV_GROUPS:
        err = np.stack([scale * (nav[c][:n] - truth[c][:n]) for c in cols], axis=1)
        sig = np.stack([scale * nav[f"sig_{c}"][:n] for c in cols], axis=1)
        groups[name] = (unit, cols, err, sig)
    return NavigationErrors(np.asarray(nav["t"][:n], dtype=np.float64), groups)


def _column(values: ArrayLike, name: str) -> NDArray[np.float64]:
    """A table's column as (N,) float64, or the package's error naming it."""
    se3.check_real(values, f"navigation column {name}")
    try:
        column = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError):
        raise InputError(f"navigation column {name} must be numbers") from None
    if column.ndim != 1:
        raise InputError(f"navigation column {name} must be (N,) values, got shape {column.shape}")
    return column
