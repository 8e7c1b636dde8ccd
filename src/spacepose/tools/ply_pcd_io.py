"""PLY and PCD point clouds: the x y z (and normal) columns of a PLY's vertex element or a PCD's
fields, read and written.

A PLY header whose counts the body cannot hold, or a body with rows beyond them, is refused
before anything is read; the PCD header is checked by :mod:`spacepose.tools.pcd_io`. Every
failure is one :class:`~spacepose.errors.FileFormatError` naming the file. The column names
(:data:`XYZ`, :data:`PLY_NORMALS`, :data:`PCD_NORMALS`) and the digits that round-trip a
precision through text (:data:`DIGITS`) are shared with :mod:`spacepose.tools.text_cloud_io`;
:mod:`spacepose.tools.cloud_io` chooses these by extension.
"""

from __future__ import annotations

import io
import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import BinaryIO

import numpy as np
import plyfile
from numpy.typing import NDArray

from spacepose.errors import FileFormatError, SpaceposeWarning
from spacepose.tools.npy_io import as_float64
from spacepose.tools.pcd_io import read_pcd_table, write_pcd

# Column names of the coordinates, and of the normals as PLY (and text headers) and PCD name them.
XYZ = ("x", "y", "z")
PLY_NORMALS = ("nx", "ny", "nz")
PCD_NORMALS = ("normal_x", "normal_y", "normal_z")
# Significant digits that round-trip a value of the given precision through text.
DIGITS = {"float32": 9, "float64": 17}


# --------------------------------------------------------------------------------------------
# PLY


def read_ply(path: Path) -> tuple[NDArray[np.float64], NDArray[np.float64] | None]:
    """(N, 3) points and (N, 3) normals or None of a PLY file's ``vertex`` element.

    Raises
    ------
    FileFormatError
        A bad, truncated or miscounted file (rows beyond or short of the header's counts), no
        ``vertex`` element, no x/y/z properties, or a list property where a number goes.

    Warns
    -----
    SpaceposeWarning
        The file names some of ``nx ny nz`` but not all: its normals are read as absent.
    """
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
            with warnings.catch_warnings():
                # An ASCII value beyond its declared type is cast with numpy's warning alone
                # (1e300 as a float: inf, and the cloud then read as having no finite point)
                # or refused with an OverflowError (300 as a uchar).
                warnings.simplefilter("error", RuntimeWarning)
                ply = plyfile.PlyData.read(source, mmap=False)
    except (RuntimeWarning, OverflowError) as exc:
        problem = f"a value does not fit its declared PLY type ({exc})"
        raise FileFormatError(problem, path) from None
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
    return _columns(data, names, XYZ, PLY_NORMALS, path, "PLY vertex")


def ply_has_faces(path: Path) -> bool:
    """Whether a PLY file's header declares a non-empty ``face`` element (a mesh, not a
    cloud); False for a file whose header does not parse (:func:`read_ply` says why)."""
    try:
        with path.open("rb") as fh:
            header = plyfile.PlyData._parse_header(fh)
    except (plyfile.PlyParseError, UnicodeDecodeError, OSError, ValueError):
        return False
    return any(e.name == "face" and e.count > 0 for e in header.elements)


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


def write_ply(
    path: Path,
    points: NDArray[np.float64],
    normals: NDArray[np.float64] | None,
    binary: bool,
    dtype: np.dtype,
) -> None:
    """Points (and normals) as the ``vertex`` element of a little-endian binary or ASCII PLY
    file of ``dtype`` properties ``x y z`` (and ``nx ny nz``)."""
    names = XYZ if normals is None else XYZ + PLY_NORMALS
    values = points if normals is None else np.hstack([points, normals])
    # plyfile writes no timestamp or comment, so the bytes depend on the data only.
    element = plyfile.PlyElement.describe(_structured(values, names, dtype), "vertex")
    plyfile.PlyData([element], text=not binary, byte_order="<").write(str(path))


# --------------------------------------------------------------------------------------------
# PCD (Point Cloud Library v0.7): the header checks live in pcd_io


def read_pcd_cloud(path: Path) -> tuple[NDArray[np.float64], NDArray[np.float64] | None]:
    """(N, 3) points and (N, 3) normals or None of a PCD file's fields.

    Raises
    ------
    FileFormatError
        What :func:`~spacepose.tools.pcd_io.read_pcd_table` refuses, or no x/y/z fields.

    Warns
    -----
    SpaceposeWarning
        The file names some of ``normal_x normal_y normal_z`` but not all: its normals are
        read as absent.
    """
    table = read_pcd_table(path)
    return _columns(table, tuple(table), XYZ, PCD_NORMALS, path, "PCD")


def write_pcd_cloud(
    path: Path,
    points: NDArray[np.float64],
    normals: NDArray[np.float64] | None,
    binary: bool,
    dtype: np.dtype,
) -> None:
    """Points (and normals) as a binary or ASCII PCD file of ``dtype`` fields ``x y z`` (and
    ``normal_x normal_y normal_z``); ASCII values carry :data:`DIGITS` significant digits."""
    names = XYZ if normals is None else XYZ + PCD_NORMALS
    values = points if normals is None else np.hstack([points, normals])
    write_pcd(path, values, names, binary, f"%.{DIGITS[dtype.name]}g", dtype)


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
        warn_part_of_normals(names, normal_names, path)
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


def warn_part_of_normals(names: Sequence[str], normal_names: tuple[str, ...], path: Path) -> None:
    """Warn, naming ``path``, of a file naming some of the three normal components but not
    all: the normals it meant to give were dropped without a word (the points read alone).

    Parameters
    ----------
    names
        The columns (properties, fields, header names) the file has.
    normal_names
        The three names of a normal's components in the file's format.
    path
        The file, named in the warning.

    Warns
    -----
    SpaceposeWarning
        Attributed to the caller of :func:`~spacepose.tools.cloud_io.read_cloud`: it is called
        by a reader's helper, two frames below ``read_cloud``.
    """
    given = [n for n in normal_names if n in names]
    if given and len(given) < len(normal_names):
        missing = [n for n in normal_names if n not in names]
        problem = (
            f"normals read as absent: {', '.join(given)} without {', '.join(missing)} (a "
            "normal needs all three)"
        )
        warnings.warn(SpaceposeWarning(problem, path), stacklevel=5)
