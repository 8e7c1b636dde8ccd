"""Point cloud files: PLY, PCD, plain text (xyz/txt/csv) and numpy (npy/npz).

The format is chosen by the file extension. Each reader returns a
:class:`~spacepose.core.cloud.PointCloud` (normals included when the file has them) whose
``source`` is the file name; each failure raises :class:`~spacepose.errors.FileFormatError` (or
:class:`~spacepose.errors.InputError` for data that parse but are unusable, e.g. only NaN rows),
always naming the file.

The formats themselves are read and written by :mod:`spacepose.tools.ply_pcd_io`,
:mod:`spacepose.tools.text_cloud_io` and :mod:`spacepose.tools.npy_io`; here are the checks
every format shares: infinite coordinates, normals of zero or other than unit length, and
coordinates in another unit than metres (:func:`warn_if_not_metres`, :func:`warn_if_too_near`).
"""

from __future__ import annotations

import warnings
from collections.abc import Callable
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from spacepose.core.cloud import PointCloud, check_scale
from spacepose.core.scale import point_spacing
from spacepose.core.se3 import check_real
from spacepose.errors import FileFormatError, InputError, SpaceposeWarning
from spacepose.tools.npy_io import read_npy, read_npz, write_npy, write_npz
from spacepose.tools.outputs import check_writable
from spacepose.tools.ply_pcd_io import (
    DIGITS,
    ply_has_faces,
    read_pcd_cloud,
    read_ply,
    write_pcd_cloud,
    write_ply,
)
from spacepose.tools.text_cloud_io import read_text_cloud, write_text_cloud
from spacepose.tools.text_io import as_path, not_a_file

_FLOAT32_MAX = float(np.finfo(np.float32).max)
# Largest move of a point by float32's rounding, as a share of the cloud's point spacing, that
# the default precision accepts: a lab frame at 1.2 m moves by 1e-7 m, 1e-5 of its spacing; the
# same frame 7,000 km out (an Earth-centred frame) by 0.25 m, and came back flat.
_FLOAT32_SHARE = 0.01
_TEXT_SUFFIXES = (".xyz", ".txt", ".csv")
# The cloud formats that are not text (an output of text under one of them is refused).
BINARY_CLOUD_SUFFIXES: tuple[str, ...] = (".ply", ".pcd", ".npy", ".npz")
# Widest scene (m) a cloud in millimetres can span: 100 km, past any ToF camera or LiDAR.
_FARTHEST_M = 1e5
# Narrowest span (m) a cloud of a surface can have: a micrometre, a thousandth of the finest
# range resolution of any ToF camera or LiDAR; points closer together are one return.
_NARROWEST_M = 1e-6
# No sensor ranges nearer (m): returns closer than this in the median are a unit error.
NEAREST_RANGE_M = 0.02
# Returns whose median range is compared with it: about this many, evenly strided.
_RANGE_SAMPLE = 4096


# --------------------------------------------------------------------------------------------
# Public API


# Depth images (16-bit or float, one channel): read by spacepose.tools.depth_io with a camera's
# intrinsics, never as clouds; named here so that a cloud reader can say what one is.
DEPTH_SUFFIXES: tuple[str, ...] = (".png", ".tif", ".tiff", ".exr")


def read_cloud(path: str | Path, *, scale: float = 1.0) -> PointCloud:
    """Read a point cloud file, choosing the format by extension.

    Parameters
    ----------
    path
        ``.ply`` (ASCII or binary; ``x y z`` and optional ``nx ny nz`` vertex properties),
        ``.pcd`` (``ascii`` or ``binary``; optional ``normal_x normal_y normal_z``),
        ``.xyz``/``.txt``/``.csv`` (3 or 6 columns, whitespace- or comma-separated; a header
        line is allowed), ``.npy`` ((N, 3) or (N, 6) array) or ``.npz`` (``points``, optional
        ``normals``).
    scale
        Factor applied to the coordinates: ``1e-3`` reads a file in millimetres as metres.

    Returns
    -------
    PointCloud in the frame the file's coordinates are in, in metres (times ``scale``); rows
    with NaN are dropped, and rows with inf too, with a warning.

    Warns
    -----
    SpaceposeWarning
        When the coordinates, read with ``scale = 1``, look like millimetres
        (:func:`spacepose.core.cloud.check_scale`): the message names the file, its extent and
        its point spacing.

    Raises
    ------
    FileFormatError
        Unknown extension, missing file (or a folder, a pipe), a read the system refuses,
        truncated file, bad header or no x/y/z data.
    InputError
        The file holds no finite point.
    """
    path = as_path(path)
    if path.is_dir():
        raise FileFormatError("a folder, not a point cloud file", path)
    reader = _READERS.get(path.suffix.lower())
    if reader is None and path.suffix.lower() in DEPTH_SUFFIXES:
        # "Unknown extension" left the user to guess what to do with a depth image.
        raise FileFormatError(
            f"a depth image where a point cloud ({', '.join(sorted(_READERS))}) goes: "
            "back-project it with its camera's intrinsics first "
            "(spacepose.tools.depth_io.read_depth_cloud, then write_cloud to a .ply)",
            path,
        )
    if reader is None:
        raise FileFormatError(
            f"unknown point cloud extension {path.suffix!r}; use one of "
            f"{', '.join(sorted(_READERS))}",
            path,
        )
    problem = not_a_file(path)
    if problem is not None:
        raise FileFormatError(problem, path)
    # Text or None ended in numpy's TypeError, and True read as a scale of 1.
    number = isinstance(scale, int | float | np.integer | np.floating)
    if isinstance(scale, bool) or not number or not (np.isfinite(scale) and scale > 0):
        raise InputError(f"scale must be a positive number, got {scale!r}", path)
    try:
        points, normals = reader(path)
    except OSError as exc:  # refused by the system: this file fails (a frame is lost), not the run
        raise FileFormatError(f"cannot read: {exc.strerror or exc}", path) from None
    if normals is not None:
        normals = _unit_normals(normals, path, points)
    cloud = PointCloud(points * scale, normals, source=str(path))
    if cloud.n_dropped:
        _warn_if_infinite(points, path)
    if scale == 1.0:
        warn_if_not_metres(cloud, path)
    return cloud


def _warn_if_infinite(points: NDArray[np.float64], path: Path) -> None:
    """Warn of rows dropped for an infinite coordinate: NaN is how a sensor writes "no return",
    but inf (or a number past float64, ``1e400``) is a corrupt value, and was dropped unsaid."""
    infinite = int(np.count_nonzero(np.isinf(points).any(axis=1)))
    if infinite:
        warnings.warn(
            SpaceposeWarning(
                f"{infinite} of {len(points)} rows with an infinite coordinate dropped (NaN is "
                "no return; inf a corrupt value?)",
                path,
            ),
            stacklevel=3,
        )


_RESCALE = "write its coordinates times 0.001 (in Python: read_cloud(..., scale=1e-3))"


def _unit_normals(
    normals: NDArray[np.float64], path: Path, points: NDArray[np.float64]
) -> NDArray[np.float64] | None:
    """A file's normals as unit vectors, or None: one of zero length has no direction, and a
    file with such normals (a point type with normal fields no step filled, as PCL's
    PointNormal left at zero) has its normals left out, with a warning, to be estimated; so has
    one with NaN or inf normals at finite ``points`` (PCL's normal estimation where a point has
    too few neighbours), which dropped those points without a word (every point, when no
    normal was filled: the file was refused); one of another length is read as its direction,
    with a warning (a registration weighs a point-to-plane residual by its normal's length)."""
    # Lengths of rows scaled by their largest component: a normal of 1e300 is a direction too,
    # and its square must not overflow (numpy's bare warning, and an inf length kept it as is).
    largest = np.max(np.abs(normals), axis=1)
    finite = np.isfinite(largest)
    unfilled = np.flatnonzero(~finite & np.isfinite(points).all(axis=1))
    if len(unfilled):
        problem = (
            f"{len(unfilled)} of {len(normals)} normals are NaN or inf at finite points (first "
            f"at point {unfilled[0]}), which would drop those points: the file's normals are "
            "left out and estimated"
        )
        warnings.warn(SpaceposeWarning(problem, path), stacklevel=3)
        return None
    scaled = normals / np.where(finite & (largest > 0), largest, 1.0)[:, None]
    unit_length = np.linalg.norm(scaled, axis=1)
    with np.errstate(over="ignore"):
        length = largest * unit_length
    zero = np.flatnonzero(finite & (length < 1e-6))
    if len(zero):
        problem = (
            f"{len(zero)} normals have zero length (first at point {zero[0]}): a normal needs a "
            "direction; the file's normals are left out and estimated"
        )
        warnings.warn(SpaceposeWarning(problem, path), stacklevel=3)
        return None
    off = np.flatnonzero(finite & (np.abs(length - 1.0) > 1e-3))
    if len(off):
        k = off[0]
        warn_not_unit(len(off), "normals", f"point {k}", length[k], "directions", path)
        normals = normals.copy()
        normals[off] = scaled[off] / unit_length[off, None]
    return normals


def warn_not_unit(
    count: int, things: str, first: str, length: float, read_as: str, path: Path
) -> None:
    """Warn (naming ``path``) that ``count`` ``things`` of a file are not of unit length, the
    first at ``first`` with ``length``, and are read as their ``read_as``."""
    problem = (
        f"{count} {things} are not of unit length ({first}: {length:.4g}); read as their {read_as}"
    )
    warnings.warn(SpaceposeWarning(problem, path), stacklevel=4)


def warn_if_not_metres(cloud: PointCloud, source: str | Path, remedy: str = _RESCALE) -> None:
    """Warn (:class:`SpaceposeWarning`, naming ``source``) when a cloud's coordinates look like
    millimetres, span more than any sensor sees even in millimetres, or less than any
    resolves (:data:`_NARROWEST_M`); ``remedy`` says what to change (for a file of points,
    its scale)."""
    check = check_scale(cloud.points)
    if len(cloud) > 1 and 0.0 < check.extent < _NARROWEST_M:
        # planes took 70,000 such points for one plane of 0 x 0 m, without a word.
        problem = (
            f"coordinates span {check.extent:.3g} m, closer together than any sensor resolves: "
            "corrupt values, or another unit?"
        )
        warnings.warn(SpaceposeWarning(problem, source), stacklevel=3)
        return
    if not check.millimetres:
        return
    from spacepose.core.reach import within_reach

    near = within_reach(cloud.points)
    if not near.all() and near.sum() > 1 and not check_scale(cloud.points[near]).millimetres:
        # A far background (a rendered Earth in 99 % of the view) set the spacing; the near
        # surfaces are in metres.
        return
    if check.extent * 1e-3 > _FARTHEST_M:
        problem = (
            f"coordinates span {check.extent:.3g} m, beyond any sensor's reach even read "
            "as millimetres: corrupt values, or another unit?"
        )
    else:
        problem = (
            f"coordinates look like millimetres ({check.extent:.0f} m across, median point "
            f"spacing {check.spacing:.2f} m); spacepose works in metres: {remedy}"
        )
    warnings.warn(SpaceposeWarning(problem, source), stacklevel=3)


# Surface samples of a mesh given as a model (as many as a simulated run's model.ply holds).
MODEL_SAMPLES = 20_000


def read_model(path: str | Path) -> PointCloud:
    """A reference model for ``track``/``navigate --model``: a point cloud file
    (:func:`read_cloud`), or a mesh (OBJ, STL, GLB, glTF, OFF, or a PLY with faces) sampled on
    its surface with outward normals (:data:`MODEL_SAMPLES` points, seed 0), in the file's own
    frame. A mesh PLY used to be read as its vertices alone, without a word: a box is eight
    corners, and every frame was lost ("the model has 21 points at the frame's voxel")."""
    from spacepose.core.sim.mesh_files import MESH_SUFFIXES, load_mesh
    from spacepose.core.sim.targets import sample_surface

    path = as_path(path)
    problem = not_a_file(path)
    if problem is not None:
        # Before the PLY header is looked at: a pipe named model.ply blocked that read for ever.
        raise FileFormatError(f"cannot read the model: {problem}", path)
    suffix = path.suffix.lower()
    mesh = suffix in MESH_SUFFIXES and (suffix != ".ply" or ply_has_faces(path))
    if not mesh:
        return read_cloud(path)
    model = sample_surface(load_mesh(path, center=False), MODEL_SAMPLES, seed=0)
    warn_if_not_metres(model, path)
    # Named, as a cloud file is: the tracker's warnings about the model name it.
    return PointCloud(model.points, model.normals, source=str(path))


def read_sensor_cloud(path: str | Path) -> PointCloud:
    """:func:`read_cloud` of a cloud in a sensor's frame, without the rows a driver writes at
    the sensor's origin for a pixel or beam with no return (an organised ToF frame holds one
    for every dark pixel): taken as points, 300,000 of them at one place took ``planes`` 161 s
    and gave every length a zero point spacing. A single row at the origin stays (a model's
    vertex may lie there); two or more go, with one warning saying how many."""
    cloud = read_cloud(path)
    at_origin = ~cloud.points.any(axis=1)
    count = int(at_origin.sum())
    if count < 2:
        return cloud
    if count == len(cloud):
        raise InputError(f"all {count} points lie at the sensor's origin: no return", path)
    warnings.warn(
        SpaceposeWarning(
            f"{count} of {len(cloud)} points lie at the sensor's origin (0, 0, 0), a driver's "
            "mark of no return: left out",
            path,
        ),
        stacklevel=2,
    )
    return cloud.select(np.flatnonzero(~at_origin))


def warn_if_too_near(cloud: PointCloud, source: str | Path, problem: str) -> None:
    """Warn (:class:`SpaceposeWarning`, naming ``source``) when a sensor-frame cloud's returns
    lie nearer the sensor than any sensor ranges (:data:`NEAREST_RANGE_M`, median): a scene
    in another unit, which preprocessing then loses as a few points or tracks a thousandth of
    its size; ``problem`` says which unit and what to check.

    A strided sample says as much as the whole frame: the median range of 900k points cost
    32 ms, of this sample 0.1 ms.
    """
    sample = cloud.points[:: max(1, len(cloud) // _RANGE_SAMPLE)]
    ranges = np.linalg.norm(sample, axis=1)
    # Rows at the sensor's origin are no returns (dropped before tracking), not near ones.
    ranges = ranges[ranges > 0.0]
    if not len(ranges):
        return
    nearest = float(np.median(ranges))
    if nearest < NEAREST_RANGE_M:
        where = f"the returns lie {1e3 * nearest:.3g} mm from the sensor (median), nearer than"
        warnings.warn(SpaceposeWarning(f"{where} any {problem}", source), stacklevel=3)


def write_cloud(
    path: str | Path,
    cloud: PointCloud | ArrayLike,
    *,
    binary: bool = True,
    dtype: str | np.dtype | type | None = None,
) -> Path:
    """Write a point cloud, choosing the format by extension (see :func:`read_cloud`).

    Parameters
    ----------
    path
        Output file; its parent directory is created.
    cloud
        A PointCloud (normals written when present; its per-point ``sigma`` is not written in
        any format, with a warning, as no reader here reads it back) or an (N, 3) / (N, 6)
        array of points and optional normals; an array goes through :class:`PointCloud`, so
        rows with NaN are dropped and an all-NaN array raises.
    binary
        Binary encoding for PLY (little-endian) and PCD; ignored by the other formats.
    dtype
        ``"float32"`` or ``"float64"`` (or numpy's ``np.float32``, ``np.dtype("float64")``):
        the stored precision (text formats print enough digits to round-trip it). None:
        float32 unless its rounding would move a point by more than a hundredth of the cloud's
        point spacing (coordinates far from the origin), then float64.

    Returns
    -------
    The path written. The same data always give the same bytes.

    Warns
    -----
    SpaceposeWarning
        ``cloud`` carries per-point ``sigma``, which the file leaves out (once a call).
    """
    path = as_path(path)
    if not isinstance(binary, bool | np.bool_):
        raise InputError(f"binary must be True or False, got {binary!r}", path)
    # numpy's own spellings (np.float32, np.dtype("float64")) name the same precision.
    named = dtype
    if isinstance(dtype, np.dtype) or (isinstance(dtype, type) and issubclass(dtype, np.generic)):
        named = np.dtype(dtype).name
    if dtype is not None and (not isinstance(named, str) or named not in DIGITS):
        raise InputError(f"dtype must be 'float32' or 'float64', got {dtype!r}", path)
    writer = _WRITERS.get(path.suffix.lower())
    if writer is None:
        raise FileFormatError(
            f"unknown point cloud extension {path.suffix!r}; use one of "
            f"{', '.join(sorted(_WRITERS))}",
            path,
        )
    if not isinstance(cloud, PointCloud):
        check_real(cloud, "cloud", str(path))
        try:
            arr = np.asarray(cloud, dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise InputError(f"cloud is not numeric: {exc}", path) from None
        if arr.ndim != 2 or arr.shape[1] not in (3, 6):
            raise InputError(f"cloud array must be (N, 3) or (N, 6), got {arr.shape}", path)
        cloud = PointCloud(arr[:, :3], arr[:, 3:] if arr.shape[1] == 6 else None, source=str(path))
    if named != "float64":
        problem = _float32_problem(cloud.points)
        if problem and dtype is not None:
            raise InputError(f"{problem}: write them with dtype='float64'", path)
        named = "float64" if problem else "float32"
    # A folder by the file's name (or a file where its folder goes) ended in a bare
    # IsADirectoryError / FileExistsError.
    check_writable(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    writer(path, cloud.points, cloud.normals, binary, np.dtype(named))
    if cloud.sigma is not None:
        # Dropped without a word before: a cloud written and read back lost its noise model.
        warnings.warn(
            SpaceposeWarning(
                f"per-point sigma is not written ({len(cloud.sigma)} values): the cloud formats "
                "here store points and normals only",
                path,
            ),
            stacklevel=2,
        )
    return path


def _float32_problem(points: NDArray[np.float64]) -> str:
    """Why float32 cannot hold ``points`` (N, 3), or "" when it can: beyond its range, or
    rounded by more than :data:`_FLOAT32_SHARE` of the point spacing."""
    if not len(points):
        return ""
    peak = float(np.abs(points).max())
    if peak > _FLOAT32_MAX:
        # Stored as inf (numpy's overflow warning alone), the file read back without them.
        return f"points reach |coordinate| {peak:.3g}, beyond float32's {_FLOAT32_MAX:.3g}"
    moved = float(np.abs(points.astype(np.float32).astype(np.float64) - points).max())
    if moved == 0.0 or len(points) < 2 or np.all(points == points[0]):
        return ""
    spacing = point_spacing(points)
    if moved <= _FLOAT32_SHARE * spacing:
        return ""
    return (
        f"float32 moves points at |coordinate| up to {peak:.3g} by {moved:.3g} m, "
        f"{moved / spacing:.2g} of their spacing {spacing:.3g} m"
    )


Reader = Callable[[Path], tuple[NDArray[np.float64], NDArray[np.float64] | None]]
Writer = Callable[[Path, NDArray[np.float64], NDArray[np.float64] | None, bool, np.dtype], None]

_READERS: dict[str, Reader] = {
    ".ply": read_ply,
    ".pcd": read_pcd_cloud,
    ".npy": read_npy,
    ".npz": read_npz,
} | dict.fromkeys(_TEXT_SUFFIXES, read_text_cloud)
_WRITERS: dict[str, Writer] = {
    ".ply": write_ply,
    ".pcd": write_pcd_cloud,
    ".npy": write_npy,
    ".npz": write_npz,
} | dict.fromkeys(_TEXT_SUFFIXES, write_text_cloud)
