"""PLY and PCD point clouds: the x y z (and normal) columns of a PLY's vertex element or a PCD's
fields, read and written.

A PLY header whose counts the body cannot hold, or a body with rows beyond them, is refused
before anything is read (:mod:`spacepose.core.ply_checks`, which the mesh reader shares); the
PCD header is checked by :mod:`spacepose.tools.pcd_io`. Every
failure is one :class:`~spacepose.errors.FileFormatError` naming the file. The column names
(:data:`XYZ`, :data:`PLY_NORMALS`, :data:`PCD_NORMALS`) and the digits that round-trip a
precision through text (:data:`DIGITS`) are shared with :mod:`spacepose.tools.text_cloud_io`;
:mod:`spacepose.tools.cloud_io` chooses these by extension.
"""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import plyfile
from numpy.typing import NDArray

from spacepose.core.ply_checks import read_checked_ply
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
    ply = read_checked_ply(path)
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
