"""Point cloud files: PLY, PCD, plain text (xyz/txt/csv) and numpy (npy/npz).

The format is chosen by the file extension. Each reader returns a
:class:`~spacepose.core.cloud.PointCloud` (normals included when the file has them) whose
``source`` is the file name; each failure raises :class:`~spacepose.errors.FileFormatError` (or
:class:`~spacepose.errors.InputError` for data that parse but are unusable, e.g. only NaN rows),
always naming the file.
"""

from __future__ import annotations

import io
import re
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import BinaryIO

import numpy as np
import plyfile
from numpy.typing import ArrayLike, NDArray

from spacepose.core.cloud import PointCloud, check_scale
from spacepose.errors import FileFormatError, InputError, SpaceposeWarning
from spacepose.tools.npy_io import as_float64, read_npy, read_npz, write_npy, write_npz
from spacepose.tools.outputs import check_writable
from spacepose.tools.pcd_io import read_pcd_table, write_pcd
from spacepose.tools.text_io import not_a_file

_XYZ = ("x", "y", "z")
_PLY_NORMALS = ("nx", "ny", "nz")
_FLOAT32_MAX = float(np.finfo(np.float32).max)
_PCD_NORMALS = ("normal_x", "normal_y", "normal_z")
_TEXT_SUFFIXES = (".xyz", ".txt", ".csv")
# Widest scene (m) a cloud in millimetres can span: 100 km, past any ToF camera or LiDAR.
_FARTHEST_M = 1e5
# Narrowest span (m) a cloud of a surface can have: a micrometre, a thousandth of the finest
# range resolution of any ToF camera or LiDAR; points closer together are one return.
_NARROWEST_M = 1e-6
# Significant digits that round-trip a value of the given precision through text.
_DIGITS = {"float32": 9, "float64": 17}
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
    path = Path(path)
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
    if not (np.isfinite(scale) and scale > 0):
        raise InputError(f"scale must be a positive number, got {scale}", path)
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


_RESCALE = "scale the file by 0.001 (read_cloud(..., scale=1e-3))"


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


def warn_if_too_near(cloud: PointCloud, source: str | Path, problem: str) -> None:
    """Warn (:class:`SpaceposeWarning`, naming ``source``) when a sensor-frame cloud's returns
    lie nearer the sensor than any sensor ranges (:data:`NEAREST_RANGE_M`, median): a scene
    in another unit, which preprocessing then loses as a few points or tracks a thousandth of
    its size; ``problem`` says which unit and what to check.

    A strided sample says as much as the whole frame: the median range of 900k points cost
    32 ms, of this sample 0.1 ms.
    """
    sample = cloud.points[:: max(1, len(cloud) // _RANGE_SAMPLE)]
    nearest = float(np.median(np.linalg.norm(sample, axis=1)))
    if nearest < NEAREST_RANGE_M:
        where = f"the returns lie {1e3 * nearest:.3g} mm from the sensor (median), nearer than"
        warnings.warn(SpaceposeWarning(f"{where} any {problem}", source), stacklevel=3)


def write_cloud(
    path: str | Path,
    cloud: PointCloud | ArrayLike,
    *,
    binary: bool = True,
    dtype: str = "float32",
) -> Path:
    """Write a point cloud, choosing the format by extension (see :func:`read_cloud`).

    Parameters
    ----------
    path
        Output file; its parent directory is created.
    cloud
        A PointCloud (normals written when present) or an (N, 3) / (N, 6) array of points and
        optional normals; an array goes through :class:`PointCloud`, so rows with NaN are
        dropped and an all-NaN array raises.
    binary
        Binary encoding for PLY (little-endian) and PCD; ignored by the other formats.
    dtype
        ``"float32"`` or ``"float64"``: the stored precision (text formats print enough digits
        to round-trip it).

    Returns
    -------
    The path written. The same data always give the same bytes.
    """
    path = Path(path)
    if dtype not in _DIGITS:
        raise InputError(f"dtype must be 'float32' or 'float64', got {dtype!r}", path)
    writer = _WRITERS.get(path.suffix.lower())
    if writer is None:
        raise FileFormatError(
            f"unknown point cloud extension {path.suffix!r}; use one of "
            f"{', '.join(sorted(_WRITERS))}",
            path,
        )
    if not isinstance(cloud, PointCloud):
        arr = np.asarray(cloud, dtype=np.float64)
        if arr.ndim != 2 or arr.shape[1] not in (3, 6):
            raise InputError(f"cloud array must be (N, 3) or (N, 6), got {arr.shape}", path)
        cloud = PointCloud(arr[:, :3], arr[:, 3:] if arr.shape[1] == 6 else None, source=str(path))
    if dtype == "float32":
        # Beyond float32's range a coordinate was stored as inf (numpy's overflow warning
        # alone), and the file read back with those points dropped.
        peak, largest = float(max(cloud.points.max(), -cloud.points.min())), _FLOAT32_MAX
        if peak > largest:
            raise InputError(
                f"points reach |coordinate| {peak:.3g}, beyond float32's {largest:.3g}: write "
                "them with dtype='float64'",
                path,
            )
    # A folder by the file's name (or a file where its folder goes) ended in a bare
    # IsADirectoryError / FileExistsError.
    check_writable(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    writer(path, cloud.points, cloud.normals, binary, np.dtype(dtype))
    return path


# --------------------------------------------------------------------------------------------
# PLY


def _read_ply(path: Path) -> tuple[NDArray[np.float64], NDArray[np.float64] | None]:
    try:
        with path.open("rb") as fh:
            header = plyfile.PlyData._parse_header(fh)
            body_bytes = path.stat().st_size - fh.tell()
            _check_ply_counts(header, body_bytes)
            _check_ply_rest(header, fh, body_bytes)
            fh.seek(0)
            # plyfile reads an ASCII body through a text wrapper it leaves open on the file,
            # which warns when collected: it gets the bytes instead (an ASCII cloud is small).
            source = io.BytesIO(fh.read()) if header.text else fh
            ply = plyfile.PlyData.read(source, mmap=False)
    except plyfile.PlyParseError as exc:
        raise FileFormatError(f"bad or truncated PLY: {exc}", path) from None
    except UnicodeDecodeError:
        raise FileFormatError("not a PLY file: its header is not ASCII text", path) from None
    except (OSError, ValueError) as exc:
        raise FileFormatError(f"cannot read PLY: {exc}", path) from None
    if "vertex" not in ply:
        raise FileFormatError("PLY has no 'vertex' element", path)
    data = ply["vertex"].data
    names = data.dtype.names or ()
    return _columns(data, names, _XYZ, _PLY_NORMALS, path, "PLY vertex")


def _check_ply_counts(header: plyfile.PlyData, body_bytes: int) -> None:
    """Refuse a header whose element counts the body cannot hold, before anything is
    allocated: a corrupt count of 10¹² vertices would otherwise ask for terabytes.

    Each row takes at least its fixed-size properties' bytes (a list's count) in binary, and a
    character and a separator per property in ASCII.

    Raises
    ------
    plyfile.PlyParseError
        A negative count, or rows promised beyond what ``body_bytes`` can hold.
    """
    for element in header.elements:
        if element.count < 0:
            raise plyfile.PlyParseError(
                f"the header counts {element.count:,} '{element.name}' rows: a count is >= 0"
            )
        if header.text:
            row = 2 * len(element.properties)
        else:
            row = sum(
                np.dtype(getattr(p, "len_dtype", None) or p.val_dtype).itemsize
                for p in element.properties
            )
        if element.count * row > body_bytes:
            raise plyfile.PlyParseError(
                f"the header promises {element.count:,} '{element.name}' rows, more than the "
                f"file's {body_bytes:,} bytes of data can hold"
            )


def _check_ply_rest(header: plyfile.PlyData, fh: BinaryIO, body_bytes: int) -> None:
    """Refuse a body holding whole rows beyond the header's counts: read by the counts, they
    would be dropped without a word (a count written before the last rows were).

    Binary bodies of fixed-size rows are measured by their size (less than a row of trailing
    bytes is let through); ASCII bodies (``fh`` at the body) by their non-blank lines.

    Raises
    ------
    plyfile.PlyParseError
        Rows beyond the header's counts.
    """
    counts = sum(element.count for element in header.elements)
    if header.text:
        rows = sum(1 for line in fh if line.strip())
        if rows > counts:
            raise plyfile.PlyParseError(
                f"the file holds {rows:,} rows but its header counts {counts:,}: the rest "
                "would be dropped"
            )
        return
    if not header.elements or any(
        hasattr(p, "len_dtype") for e in header.elements for p in e.properties
    ):
        return  # rows of lists vary in size
    sizes = [sum(np.dtype(p.val_dtype).itemsize for p in e.properties) for e in header.elements]
    extra = body_bytes - sum(e.count * n for e, n in zip(header.elements, sizes, strict=True))
    if sizes[-1] and extra >= sizes[-1]:
        raise plyfile.PlyParseError(
            f"the file holds {extra:,} bytes of data beyond its header's counts (at least "
            f"{extra // sizes[-1]:,} more rows): they would be dropped"
        )


def _write_ply(
    path: Path,
    points: NDArray[np.float64],
    normals: NDArray[np.float64] | None,
    binary: bool,
    dtype: np.dtype,
) -> None:
    names = _XYZ if normals is None else _XYZ + _PLY_NORMALS
    values = points if normals is None else np.hstack([points, normals])
    # plyfile writes no timestamp or comment, so the bytes depend on the data only.
    element = plyfile.PlyElement.describe(_structured(values, names, dtype), "vertex")
    plyfile.PlyData([element], text=not binary, byte_order="<").write(str(path))


# --------------------------------------------------------------------------------------------
# PCD (Point Cloud Library v0.7): the header checks live in pcd_io


def _read_pcd(path: Path) -> tuple[NDArray[np.float64], NDArray[np.float64] | None]:
    table = read_pcd_table(path)
    return _columns(table, tuple(table), _XYZ, _PCD_NORMALS, path, "PCD")


def _write_pcd(
    path: Path,
    points: NDArray[np.float64],
    normals: NDArray[np.float64] | None,
    binary: bool,
    dtype: np.dtype,
) -> None:
    names = _XYZ if normals is None else _XYZ + _PCD_NORMALS
    values = points if normals is None else np.hstack([points, normals])
    write_pcd(path, values, names, binary, f"%.{_DIGITS[dtype.name]}g", dtype)


# --------------------------------------------------------------------------------------------
# Plain text and numpy


def _read_text(path: Path) -> tuple[NDArray[np.float64], NDArray[np.float64] | None]:
    try:
        # utf-8-sig drops a byte-order mark, which would otherwise hide the first row's number.
        text = path.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError as exc:
        byte = exc.object[exc.start]
        raise FileFormatError(
            f"not UTF-8 text (byte 0x{byte:02x} at offset {exc.start}): binary content, or "
            "text in another encoding",
            path,
        ) from None
    lines = text.splitlines()
    first = next(
        (i for i, ln in enumerate(lines) if ln.strip() and not ln.lstrip().startswith("#")), None
    )
    if first is None:
        raise FileFormatError("no point rows in text file", path)
    delimiter = "," if "," in lines[first] else None
    # ';' too: a row of "0.1;0.2;0.3" is a row with the wrong separator, not a header.
    head = lines[first].replace(",", " ").replace(";", " ").split()
    # A header line names its columns ("x,y,z", CloudCompare's "//X,Y,Z"); a row with a number
    # in it is a row, however malformed its first field ("0x1 2 3" was taken for a header).
    header = not any(_is_number(token) for token in head)
    if header:
        _check_header(head, first + 1, path)
    skip = first + 1 if header else 0
    try:
        with warnings.catch_warnings():
            # A header without rows: numpy warns naming its buffer; the error below names the file.
            warnings.filterwarnings("ignore", "loadtxt: input contained no data", UserWarning)
            table = np.loadtxt(
                io.StringIO(text), delimiter=delimiter, comments="#", skiprows=skip, ndmin=2
            )
    except ValueError:
        raise FileFormatError(_first_bad_line(lines[skip:], skip, delimiter), path) from None
    if table.shape[0] == 0:
        raise FileFormatError("no point rows in text file", path)
    if header:
        return _named_columns(table, head, path)
    if table.shape[1] not in (3, 6):
        raise FileFormatError(
            f"expected 3 (x y z) or 6 (x y z nx ny nz) columns, got {table.shape[1]}", path
        )
    if table.shape[1] == 6 and _colours(table[:, 3:]):
        # x y z r g b is as common a layout as x y z nx ny nz: its colours were read as
        # normals "not of unit length" and used as the surface's directions.
        raise FileFormatError(
            "columns 4-6 look like colours (none negative or above 255, not unit vectors, "
            "pointing every way), not normals nx ny nz: name the columns in a header line "
            "(x y z r g b, or x y z nx ny nz), or write x y z alone",
            path,
        )
    return table[:, :3], (table[:, 3:] if table.shape[1] == 6 else None)


def _colours(values: NDArray[np.float64]) -> bool:
    """Whether three columns (N, 3) read as normals are colours: no component negative and
    none above 255, most rows not of unit length, and pointing many ways. A curved surface's
    normals point into every octant somewhere; a plane's (long normals of one plate) all one
    way, and those are read as their directions."""
    if not (np.all(values >= 0.0) and np.all(values <= 255.0)):
        return False
    lengths = np.linalg.norm(values, axis=1)
    if np.mean(np.abs(lengths - 1.0) > 1e-3) <= 0.5:
        return False
    some = lengths > 0  # black is a colour, and no direction
    if not some.any():
        return False  # all zero: no direction, and no colour either (normals left unfilled)
    directions = values[some] / lengths[some, None]
    mean = directions.mean(axis=0)
    if not np.any(mean):
        return False
    apart = directions @ (mean / np.linalg.norm(mean)) < np.cos(np.radians(10.0))
    return bool(np.mean(apart) > 0.1)


def _check_header(head: list[str], line: int, path: Path) -> None:
    """Refuse a first line with no number that names none of x, y, z as a header.

    Such a line is a bad row, not a header: taken for one and skipped, the error pointed at
    the next line (every value quoted, ``"0.1","0.2","0.3"``; C's hexadecimal floats). A
    header naming some of x, y, z is left to :func:`_named_columns`.

    Raises
    ------
    FileFormatError
        ``line N: not numbers, and as a header it does not name x, y and z columns: [...]``.
    """
    names = [token.strip("/\"'").lower() for token in head]
    if set(_XYZ) & set(names):
        return
    hint = ""
    if all(_is_number(name) for name in names):
        hint = " (quoted numbers? write them without quotes)"
    elif all(_is_hex_float(token) for token in head):
        hint = " (hexadecimal floats? write them in decimal)"
    raise FileFormatError(
        f"line {line}: not numbers, and as a header it does not name x, y and z columns: "
        f"{head}{hint}",
        path,
    )


def _is_hex_float(token: str) -> bool:
    """Whether ``token`` is a float as ``float.hex()`` writes it (``0x1.8p+0``); a bare ``a``
    is a column's name, though ``float.fromhex`` reads it as 10."""
    if not token.lstrip("+-").lower().startswith("0x"):
        return False
    try:
        float.fromhex(token)
    except ValueError:
        return False
    return True


def _named_columns(
    table: NDArray[np.float64], header: list[str], path: Path
) -> tuple[NDArray[np.float64], NDArray[np.float64] | None]:
    """The x y z (and nx ny nz, when all three are named) columns a header line names, in
    whatever order and among whatever other columns (intensity, ring) it lists.

    Raises
    ------
    FileFormatError
        The header does not name x, y and z, names one of them (or a normal) twice, or names
        a different number of columns than the rows hold.
    """
    names = [token.strip("/\"'").lower() for token in header]
    if len(names) != table.shape[1]:
        raise FileFormatError(
            f"the header names {len(names)} columns {header}, the rows hold {table.shape[1]}", path
        )
    if not set(_XYZ) <= set(names):
        raise FileFormatError(f"the header {header} does not name x, y and z columns", path)
    twice = sorted({n for n in names if names.count(n) > 1} & {*_XYZ, *_PLY_NORMALS, *_PCD_NORMALS})
    if twice:  # which of the two is the coordinate? Taking the first would be a guess.
        raise FileFormatError(f"the header {header} names {', '.join(twice)} twice", path)
    xyz = table[:, [names.index(c) for c in _XYZ]]
    for normal_names in (_PLY_NORMALS, _PCD_NORMALS):
        if set(normal_names) <= set(names):
            return xyz, table[:, [names.index(c) for c in normal_names]]
    for normal_names in (_PLY_NORMALS, _PCD_NORMALS):
        _warn_part_of_normals(names, normal_names, path)
    return xyz, None


def _warn_part_of_normals(names: Sequence[str], normal_names: tuple[str, ...], path: Path) -> None:
    """Warn, naming ``path``, of a file naming some of the three normal components but not
    all: the normals it meant to give were dropped without a word (the points read alone)."""
    given = [n for n in normal_names if n in names]
    if given and len(given) < len(normal_names):
        missing = [n for n in normal_names if n not in names]
        problem = (
            f"normals read as absent: {', '.join(given)} without {', '.join(missing)} (a "
            "normal needs all three)"
        )
        warnings.warn(SpaceposeWarning(problem, path), stacklevel=5)


def _first_bad_line(lines: list[str], offset: int, delimiter: str | None) -> str:
    """Describe the first row that breaks a numeric table (only called once parsing failed)."""
    width = None
    for i, line in enumerate(lines, start=offset + 1):
        data = line.split("#", 1)[0]
        # A European locale's export: decimal commas, fields apart by ';' or blanks. Read by
        # the comma, "0,5 1,2" is 0 | 5 1 | 2, which said only "cannot parse".
        if ";" in data:
            return (
                f"line {i}: fields separated by ';' ({data.strip()[:40]!r}): separate them by "
                "blanks or commas, with decimal points"
            )
        if delimiter is not None and len(data.split()) > 1 and re.search(r"\d,\d", data):
            return (
                f"line {i}: commas and blanks both in {data.strip()[:40]!r}: decimal commas? "
                "write decimal points"
            )
        if delimiter is not None and data.strip() and "" in [f.strip() for f in data.split(",")]:
            return f"line {i}: an empty field between commas (a trailing or doubled ',')"
        row = data.replace(",", " ").split()
        if not row:
            continue
        # Python's float reads "1_000"; the table's parser does not.
        if not all(_is_number(t) and "_" not in t for t in row):
            return f"line {i}: not a number in {row}"
        if width is not None and len(row) != width:
            return f"line {i}: {len(row)} columns where earlier rows have {width}"
        width = len(row)
    return "cannot parse text point file"


def _write_text(
    path: Path,
    points: NDArray[np.float64],
    normals: NDArray[np.float64] | None,
    binary: bool,
    dtype: np.dtype,
) -> None:
    values = points if normals is None else np.hstack([points, normals])
    csv = path.suffix.lower() == ".csv"
    names = _XYZ if normals is None else _XYZ + _PLY_NORMALS
    np.savetxt(
        path,
        values.astype(dtype),
        fmt=f"%.{_DIGITS[dtype.name]}g",
        delimiter="," if csv else " ",
        header=",".join(names) if csv else "",
        comments="",
    )


# --------------------------------------------------------------------------------------------
# Helpers


def _structured(values: NDArray[np.float64], names: tuple[str, ...], dtype: np.dtype) -> np.ndarray:
    out = np.empty(len(values), dtype=[(n, dtype.newbyteorder("<")) for n in names])
    for j, name in enumerate(names):
        out[name] = values[:, j]
    return out


def _columns(
    data: np.ndarray | dict[str, NDArray[np.float64]],
    names: tuple[str, ...],
    xyz: tuple[str, ...],
    normal_names: tuple[str, ...],
    path: Path,
    what: str,
) -> tuple[NDArray[np.float64], NDArray[np.float64] | None]:
    """Stack the x/y/z (and, when all present, normal) columns of a record table."""
    if not all(n in names for n in xyz):
        raise FileFormatError(f"{what} has no x/y/z properties (found {list(names)})", path)
    points = np.column_stack([_scalar_column(data, n, path, what) for n in xyz])
    normals = None
    if all(n in names for n in normal_names):
        normals = np.column_stack([_scalar_column(data, n, path, what) for n in normal_names])
    else:
        _warn_part_of_normals(names, normal_names, path)
    return points, normals


def _scalar_column(
    data: np.ndarray | dict[str, NDArray[np.float64]], name: str, path: Path, what: str
) -> NDArray[np.float64]:
    """One property as an (N,) float64 column; a list property (one array per point) is refused."""
    try:
        # Signalling-NaN bit patterns (a file of the other byte order) are NaN rows, dropped and
        # counted with the cloud, and its span is warned about.
        column = as_float64(data[name])
    except (TypeError, ValueError):
        column = None
    if column is None or column.ndim != 1:
        raise FileFormatError(
            f"{what} property {name!r} is not one number per point (a list property?)", path
        )
    return column


def _is_number(token: str) -> bool:
    try:
        float(token)
    except ValueError:
        return False
    return True


Reader = Callable[[Path], tuple[NDArray[np.float64], NDArray[np.float64] | None]]
Writer = Callable[[Path, NDArray[np.float64], NDArray[np.float64] | None, bool, np.dtype], None]

_READERS: dict[str, Reader] = {
    ".ply": _read_ply,
    ".pcd": _read_pcd,
    ".npy": read_npy,
    ".npz": read_npz,
} | dict.fromkeys(_TEXT_SUFFIXES, _read_text)
_WRITERS: dict[str, Writer] = {
    ".ply": _write_ply,
    ".pcd": _write_pcd,
    ".npy": write_npy,
    ".npz": write_npz,
} | dict.fromkeys(_TEXT_SUFFIXES, _write_text)
