"""Plain text point clouds (``.xyz``, ``.txt``, ``.csv``): 3 or 6 columns, whitespace- or
comma-separated, with an optional header line naming them.

A header names x y z (and nx ny nz or normal_x normal_y normal_z) in any order among other
columns; without one, columns 4-6 that look like colours are refused rather than read as
normals. A row that breaks the table is named by its line, with what is wrong in it (a ';'
separator, decimal commas, an empty field, a word, a column too many). Every failure is one
:class:`~spacepose.errors.FileFormatError` naming the file. :mod:`spacepose.tools.cloud_io`
chooses these by extension.
"""

from __future__ import annotations

import io
import re
import warnings
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from spacepose.errors import FileFormatError
from spacepose.tools.ply_pcd_io import DIGITS, PCD_NORMALS, PLY_NORMALS, XYZ, warn_part_of_normals


def read_text_cloud(path: Path) -> tuple[NDArray[np.float64], NDArray[np.float64] | None]:
    """(N, 3) points and (N, 3) normals or None of a text file of 3 or 6 columns, or of the
    columns its header line names; ``#`` comments and blank lines are skipped.

    Raises
    ------
    FileFormatError
        Not UTF-8, no rows, a first line that is neither numbers nor a header naming x, y and
        z, a row that breaks the table (named by its line), a column count other than 3 or 6
        without a header, or columns 4-6 that look like colours.

    Warns
    -----
    SpaceposeWarning
        The header names some of a normal's three components but not all: the normals are
        read as absent.
    """
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
    # ';' too: a row of "0.1;0.2;0.3" is a row with the wrong separator, not a header. A name
    # between separators may hold a space (CloudCompare's "//X,Y,Z,Scalar field").
    separated = re.split(r"[,;]", lines[first]) if re.search(r"[,;]", lines[first]) else None
    head = lines[first].split() if separated is None else [t.strip() for t in separated]
    head = [t for t in head if t]
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
    none above 255, most rows not of unit length, and pointing many ways or grey (r = g = b on
    every row, not all black). A curved surface's normals point into every octant somewhere;
    a plane's (long normals of one plate) all one way, and those are read as their directions
    (so is one colour for every point: nothing tells it from such normals)."""
    if not (np.all(values >= 0.0) and np.all(values <= 255.0)):
        return False
    lengths = np.linalg.norm(values, axis=1)
    if np.mean(np.abs(lengths - 1.0) > 1e-3) <= 0.5:
        return False
    some = lengths > 0  # black is a colour, and no direction
    if not some.any():
        return False  # all zero: no direction, and no colour either (normals left unfilled)
    if np.all(values == values[:, :1]):
        return True  # grey: read as normals along (1, 1, 1), "not of unit length"
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
    if set(XYZ) & set(names):
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
    if not set(XYZ) <= set(names):
        raise FileFormatError(f"the header {header} does not name x, y and z columns", path)
    twice = sorted({n for n in names if names.count(n) > 1} & {*XYZ, *PLY_NORMALS, *PCD_NORMALS})
    if twice:  # which of the two is the coordinate? Taking the first would be a guess.
        raise FileFormatError(f"the header {header} names {', '.join(twice)} twice", path)
    xyz = table[:, [names.index(c) for c in XYZ]]
    for normal_names in (PLY_NORMALS, PCD_NORMALS):
        if set(normal_names) <= set(names):
            return xyz, table[:, [names.index(c) for c in normal_names]]
    for normal_names in (PLY_NORMALS, PCD_NORMALS):
        warn_part_of_normals(names, normal_names, path)
    return xyz, None


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
        # The first row sets the separator for all: "1,2,3" then "4 5 6" read as one field.
        if delimiter is not None and "," not in data and len(data.split()) > 1:
            return f"line {i}: fields separated by blanks where the first row's are by commas"
        if delimiter is None and "," in data:
            return f"line {i}: fields separated by commas where the first row's are by blanks"
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


def write_text_cloud(
    path: Path,
    points: NDArray[np.float64],
    normals: NDArray[np.float64] | None,
    binary: bool,
    dtype: np.dtype,
) -> None:
    """Points (and normals) as rows of :data:`~spacepose.tools.ply_pcd_io.DIGITS` significant
    digits: comma-separated under a header line ``x,y,z[,nx,ny,nz]`` for ``.csv``, blank-
    separated without one otherwise (``binary`` unused)."""
    values = points if normals is None else np.hstack([points, normals])
    csv = path.suffix.lower() == ".csv"
    names = XYZ if normals is None else XYZ + PLY_NORMALS
    np.savetxt(
        path,
        values.astype(dtype),
        fmt=f"%.{DIGITS[dtype.name]}g",
        delimiter="," if csv else " ",
        header=",".join(names) if csv else "",
        comments="",
    )


def _is_number(token: str) -> bool:
    try:
        float(token)
    except ValueError:
        return False
    return True
