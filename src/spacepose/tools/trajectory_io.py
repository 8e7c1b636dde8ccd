"""Trajectory files: TUM (``t tx ty tz qx qy qz qw``) and KITTI (3×4 row-major per line).

TUM is the project's exchange format (methods.md §0); it is what ``evo_ape tum ref est`` reads.
Quaternions are scalar-last, as in scipy. Values are written with 17 significant digits so a
write/read round trip reproduces the poses to float64 precision.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from spacepose.core import se3
from spacepose.core.trajectory import Trajectory
from spacepose.errors import FileFormatError, InputError, SpaceposeWarning
from spacepose.tools.cloud_io import warn_not_unit
from spacepose.tools.outputs import check_writable
from spacepose.tools.text_io import as_path, read_text

# Largest |‖q‖ − 1| of a quaternion read without a warning.
_QUATERNION_TOLERANCE = 1e-3
# Largest max |RᵀR − I| of a KITTI rotation block read as its nearest rotation without a
# warning (6 digits leave ~1e-6), and with one (4 decimals leave up to ~1e-3, the tolerance
# of a TUM quaternion's length); beyond that no rounding explains it: refused.
_ROUNDING_TOLERANCE = 1e-4
_KITTI_TOLERANCE = 1e-3

_TUM_COLUMNS = 8
_KITTI_COLUMNS = 12
_FMT = "%.17g"


def _read_rows(path: Path, width: int, kind: str) -> tuple[NDArray[np.float64], NDArray[np.int64]]:
    """Numeric rows of a whitespace-separated file, skipping blank lines and ``#`` comments.

    Returns the (M, width) values and the 1-based line number of each row, so errors found later
    (e.g. a zero quaternion) can name the line.
    """
    text = read_text(path, f"{kind} file")
    tokens: list[list[str]] = []
    numbers: list[int] = []
    for lineno, line in enumerate(text.splitlines(), start=1):
        body = line.split("#", 1)[0].replace(",", " ").split()
        if not body:
            continue
        if len(body) != width:
            raise FileFormatError(
                f"line {lineno}: expected {width} values for {kind}, got {len(body)}", path
            )
        if any("_" in token for token in body):
            # numpy reads Python's digit separators: 0_5 was 5 s. (Of the values only: a
            # comment after them may name T_sensor_target.)
            raise FileFormatError(f"line {lineno}: not a number in {body}", path)
        tokens.append(body)
        numbers.append(lineno)
    if not tokens:
        raise FileFormatError(f"no {kind} poses in file", path)
    try:
        values = np.array(tokens, dtype=np.float64)
    except ValueError:
        values = None
    if values is None or not np.all(np.isfinite(values)):
        # Only on failure: find the first offending line for the message.
        for body, lineno in zip(tokens, numbers, strict=True):
            try:
                row = np.array(body, dtype=np.float64)
            except ValueError:
                raise FileFormatError(f"line {lineno}: not a number in {body}", path) from None
            if not np.all(np.isfinite(row)):
                raise FileFormatError(f"line {lineno}: non-finite value", path)
    return values, np.asarray(numbers)


def _trajectory(
    path: Path, timestamps: ArrayLike, poses: NDArray[np.float64], lines: NDArray[np.int64]
) -> Trajectory:
    try:
        return Trajectory(timestamps, poses, source=str(path))
    except InputError as exc:
        # Translate "pose k" into the file's line number.
        msg = exc.reason
        if msg.startswith("pose "):
            k = int(msg.split()[1])
            msg = f"line {lines[k]}: {msg}"
        raise FileFormatError(msg, path) from None


def read_tum(path: str | Path) -> Trajectory:
    """Read a TUM trajectory file.

    Parameters
    ----------
    path
        Text file, one pose per line: ``timestamp tx ty tz qx qy qz qw`` (quaternion
        scalar-last, normalised on reading); blank lines and ``#`` comments are skipped.

    Returns
    -------
    Trajectory with ``poses[k]`` the 4×4 transform of line k (e.g. ``T_sensor_target``).

    Raises
    ------
    FileFormatError
        Missing file, wrong number of columns, non-numeric or non-finite value, or zero
        quaternion; the message names the file and line.
    """
    path = as_path(path)
    rows, lines = _read_rows(path, _TUM_COLUMNS, "TUM")
    quat = rows[:, 4:8]
    # Lengths of rows scaled by their largest component: the square of a component of 1e200
    # overflowed (numpy's bare warning, an inf length and a pose refused as "not a rigid
    # transform"), though its direction is a rotation as any other length's.
    largest = np.max(np.abs(quat), axis=1)
    quat = quat / np.where(largest > 0, largest, 1.0)[:, None]
    with np.errstate(over="ignore"):
        norms = largest * np.linalg.norm(quat, axis=1)
    bad = norms < 1e-12
    if bad.any():
        raise FileFormatError(f"line {lines[np.argmax(bad)]}: zero quaternion", path)
    # Text rounding leaves a unit quaternion within about 1e-6 of unit length; one far from it
    # is more likely columns in another order, or a corrupt file, than a rotation.
    off = np.flatnonzero(np.abs(norms - 1.0) > _QUATERNION_TOLERANCE)
    if len(off):
        k = off[0]
        warn_not_unit(len(off), "quaternions", f"line {lines[k]}", norms[k], "rotations", path)
    poses = np.zeros((len(rows), 4, 4))
    poses[:, :3, :3] = Rotation.from_quat(quat).as_matrix()
    poses[:, :3, 3] = rows[:, 1:4]
    poses[:, 3, 3] = 1.0
    return _trajectory(path, rows[:, 0], poses, lines)


def tum_lines(traj: Trajectory) -> str:
    """The TUM lines of ``traj`` (quaternion with ``qw >= 0``), each ending in a newline."""
    quat = Rotation.from_matrix(traj.poses[:, :3, :3]).as_quat()
    # One sign per rotation, so the same poses always produce the same bytes.
    quat[quat[:, 3] < 0] *= -1.0
    table = np.column_stack([traj.timestamps, traj.positions, quat])
    # No header line: one line per pose, as evo and the TUM tools expect.
    return "".join(" ".join(_FMT % v for v in row) + "\n" for row in table)


def write_tum(path: str | Path, traj: Trajectory) -> Path:
    """Write ``traj`` as a TUM file (see :func:`tum_lines`); returns the path."""
    path = as_path(path)
    if not isinstance(traj, Trajectory):
        raise InputError(f"traj must be a Trajectory, got {type(traj).__name__}", path)
    check_writable(path)  # a folder by that name ended in a bare IsADirectoryError
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(tum_lines(traj))
    return path


def read_kitti(path: str | Path, timestamps: ArrayLike | None = None) -> Trajectory:
    """Read a KITTI pose file: 12 numbers per line, the top 3×4 block of the pose, row-major.

    Parameters
    ----------
    path
        The pose file.
    timestamps
        (N,) times of the poses; KITTI files carry none, so ``0, 1, 2, ...`` when omitted.

    Raises
    ------
    FileFormatError
        As :func:`read_tum`, or when a 3×3 block is not a rotation (``RᵀR`` off the identity
        by more than 1e-3, or a reflection; the message says by how much), or the number of
        timestamps does not match the number of poses.

    Warns
    -----
    SpaceposeWarning
        Rotation blocks off orthonormal by more than 1e-4 (rounded to 4 decimals) and up to
        1e-3, read as their nearest rotations; the message names the first one's line.
    """
    path = as_path(path)
    rows, lines = _read_rows(path, _KITTI_COLUMNS, "KITTI")
    poses = np.zeros((len(rows), 4, 4))
    poses[:, :3, :] = rows.reshape(-1, 3, 4)
    poses[:, 3, 3] = 1.0
    R = poses[:, :3, :3]
    off = _off_orthonormal(R)
    far = np.flatnonzero((off > _KITTI_TOLERANCE) | (np.linalg.det(R) <= 0))
    if len(far):
        k = int(far[0])
        try:  # as_transform says how far off, as `register --init` does
            se3.as_transform(poses[k], f"pose {k} is not a rigid transform: its")
        except InputError as exc:
            raise FileFormatError(
                f"line {lines[k]}: {exc.reason}; up to {_KITTI_TOLERANCE:g} is read as rounding",
                path,
            ) from None
    rounded = np.flatnonzero(off > _ROUNDING_TOLERANCE)
    if len(rounded):
        k = int(rounded[0])
        problem = (
            f"{len(rounded)} rotation blocks are off orthonormal (line {lines[k]}: RᵀR off the "
            f"identity by {off[k]:.2g}, over {_ROUNDING_TOLERANCE:g}: too few digits written?); "
            "read as their nearest rotations"
        )
        warnings.warn(SpaceposeWarning(problem, path), stacklevel=2)
    poses[:, :3, :3] = nearest_rotations(R, _KITTI_TOLERANCE)
    t = np.arange(len(rows), dtype=np.float64) if timestamps is None else timestamps
    return _trajectory(path, t, poses, lines)


def nearest_rotations(R: NDArray[np.float64], tolerance: float = 1e-4) -> NDArray[np.float64]:
    """Project near-rotations (N, 3, 3) onto SO(3); leave the others for validation to reject.

    KITTI files are often printed with 6-7 significant digits, and a hand-written transform
    with 4 (``0.8660`` for cos 30°), which leaves ``RᵀR`` off the identity by up to ~1e-4:
    re-orthonormalising (SVD, nearest in Frobenius norm) keeps such files readable without
    accepting matrices that are not rotations at all. ``tolerance`` is the largest
    max |RᵀR − I| projected.
    """
    U, _, Vt = np.linalg.svd(R)
    projected = U @ Vt
    close = (_off_orthonormal(R) <= tolerance) & (np.linalg.det(projected) > 0)
    return np.where(close[:, None, None], projected, R)


def _off_orthonormal(R: NDArray[np.float64]) -> NDArray[np.float64]:
    """(N,) max |RᵀR − I| of each of the (N, 3, 3) blocks ``R``."""
    return np.abs(np.einsum("nji,njk->nik", R, R) - np.eye(3)).max(axis=(1, 2))


def write_kitti(path: str | Path, traj: Trajectory) -> Path:
    """Write ``traj`` as a KITTI pose file (timestamps are not stored); returns the path."""
    path = as_path(path)
    if not isinstance(traj, Trajectory):
        raise InputError(f"traj must be a Trajectory, got {type(traj).__name__}", path)
    check_writable(path)  # a folder by that name ended in a bare IsADirectoryError
    path.parent.mkdir(parents=True, exist_ok=True)
    np.savetxt(path, traj.poses[:, :3, :].reshape(-1, 12), fmt=_FMT)
    return path


def read_trajectory(path: str | Path) -> Trajectory:
    """Read a TUM or KITTI file, telling them apart by :func:`trajectory_format`; a KITTI
    file's poses are timed by their frame numbers ``0, 1, 2, ...``."""
    return read_tum(path) if trajectory_format(path) == "tum" else read_kitti(path)


def trajectory_format(path: str | Path) -> str:
    """``"tum"`` or ``"kitti"``: ``.kitti`` is KITTI and ``.tum`` is TUM; for any other
    extension the number of values on the first data line decides (8: TUM, 12: KITTI).

    Raises
    ------
    FileFormatError
        Another number of values.
    """
    path = as_path(path)
    suffix = path.suffix.lower()
    if suffix in (".tum", ".kitti"):
        return suffix[1:]
    lines = read_text(path, "trajectory file").splitlines()
    rows = (line.split("#", 1)[0].replace(",", " ").split() for line in lines)
    first = next((row for row in rows if row), [])
    if len(first) in (_TUM_COLUMNS, _KITTI_COLUMNS):
        return "tum" if len(first) == _TUM_COLUMNS else "kitti"
    raise FileFormatError(
        f"not a trajectory file: first data line has {len(first)} values "
        f"(TUM has {_TUM_COLUMNS}, KITTI {_KITTI_COLUMNS})",
        path,
    )
