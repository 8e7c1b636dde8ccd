"""PCD files (Point Cloud Library format v0.7): the header checked field by field, ASCII and binary.

:func:`read_pcd_table` returns the single-valued fields as named float64 columns, after checking
that the header is complete and self-consistent (FIELDS, SIZE, TYPE and COUNT of one length and
non-empty, POINTS a non-negative integer equal to WIDTH × HEIGHT) and that the body holds exactly
the points the header announces. Every failure is one :class:`~spacepose.errors.FileFormatError`
naming the file. :func:`write_pcd` writes what Open3D and PCL read.
"""

from __future__ import annotations

import io
import warnings
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from spacepose.errors import FileFormatError, SpaceposeWarning
from spacepose.tools.npy_io import as_float64

# Largest point record numpy can describe (its dtype sizes are C ints).
_MAX_RECORD = 2**31 - 1

_PCD_TYPES = {("F", 4): "f4", ("F", 8): "f8"} | {
    (kind, size): f"{code}{size}"
    for kind, code in (("I", "i"), ("U", "u"))
    for size in (1, 2, 4, 8)
}


def read_pcd_table(path: Path) -> dict[str, NDArray[np.float64]]:
    """The (N,) columns of every single-valued field of a PCD file, by field name.

    Raises
    ------
    FileFormatError
        Missing or empty header lines, lengths that differ, a negative or non-integer count,
        POINTS that disagrees with WIDTH × HEIGHT, a body with more or fewer values than the
        header announces, an unsupported DATA encoding, or a VIEWPOINT that is not 7 finite
        numbers (one that is not the origin is warned about).
    """
    raw = path.read_bytes()
    header, body = _split_header(raw, path)
    fields, sizes, counts, n_points = _check_header(header, path)
    _check_viewpoint(header, path)
    formats = []
    for name, kind, size, count in zip(fields, header["TYPE"], sizes, counts, strict=True):
        code = _PCD_TYPES.get((kind.upper(), size))
        if code is None:
            raise FileFormatError(f"PCD field {name!r} has unknown TYPE {kind} SIZE {size}", path)
        formats.append((code, count))
    mode = header["DATA"][0].lower() if header["DATA"] else ""
    if mode == "binary":
        record = sum(size * count for size, count in zip(sizes, counts, strict=True))
        if len(body) != n_points * record:
            what = "truncated" if len(body) < n_points * record else "inconsistent"
            raise FileFormatError(
                f"{what} binary PCD: POINTS {n_points} of {record} bytes need "
                f"{n_points * record} bytes of data, file has {len(body)}",
                path,
            )
        if record > _MAX_RECORD:
            raise FileFormatError(
                f"binary PCD: SIZE x COUNT make a point of {record} bytes (COUNT too large)", path
            )
        # Field names may repeat (e.g. the "_" padding field), so read into positional names.
        dt = np.dtype([(f"f{i}", "<" + code, (count,)) for i, (code, count) in enumerate(formats)])
        data = np.frombuffer(body, dtype=dt, count=n_points)
        table = np.column_stack([as_float64(data[f"f{i}"]) for i in range(len(fields))])
    elif mode == "ascii":
        width = sum(counts)
        try:
            text = body.decode("ascii")
            tokens = np.array(text.split(), dtype=np.float64)
        except (UnicodeDecodeError, ValueError):
            raise FileFormatError("ASCII PCD body holds a non-number", path) from None
        if len(tokens) != n_points * width:
            what = "truncated" if len(tokens) < n_points * width else "inconsistent"
            raise FileFormatError(
                f"{what} ASCII PCD: POINTS {n_points} of {width} values need "
                f"{n_points * width} numbers, the body has {len(tokens)}",
                path,
            )
        _check_ascii_rows(text, width, path)
        table = tokens.reshape(n_points, width)
    elif mode == "binary_compressed":
        raise FileFormatError(
            "PCD DATA binary_compressed (LZF) is not supported; save as binary or ascii", path
        )
    else:
        raise FileFormatError(f"PCD DATA {mode!r} is not ascii or binary", path)
    single = [name for name, count in zip(fields, counts, strict=True) if count == 1]
    if not {"x", "y", "z"} <= set(single):
        listed = ", ".join(f"{n} (COUNT {c})" for n, c in zip(fields, counts, strict=True))
        raise FileFormatError(f"PCD has no x, y and z fields of COUNT 1 (FIELDS: {listed})", path)
    # Column index of each single-valued field in the flattened table.
    offsets = np.cumsum([0, *counts[:-1]])
    return {
        name: table[:, int(off)]
        for name, off, count in zip(fields, offsets, counts, strict=True)
        if count == 1
    }


def _check_ascii_rows(text: str, width: int, path: Path) -> None:
    """Refuse an ASCII body whose points are not one a line of ``width`` values, as PCL does:
    counted whole, a row of 2 values and one of 4 were read as two points of 3, each holding
    the other's coordinates, without a word."""
    rows = (line for line in text.splitlines() if line.strip())
    for k, row in enumerate(rows):
        if len(values := row.split()) != width:
            raise FileFormatError(
                f"ASCII PCD point {k} holds {len(values)} values on its line, where FIELDS and "
                f"COUNT make {width}: one point a line (a row cut short or run together?)",
                path,
            )


def _split_header(raw: bytes, path: Path) -> tuple[dict[str, list[str]], bytes]:
    """Header lines by upper-case key, and the bytes after the DATA line."""
    header: dict[str, list[str]] = {}
    stream = io.BytesIO(raw)
    while True:
        line = stream.readline()
        if not line:
            raise FileFormatError("PCD header has no DATA line (truncated or not a PCD)", path)
        text = line.decode("ascii", errors="replace").strip()
        if not text or text.startswith("#"):
            continue
        key, *values = text.split()
        header[key.upper()] = values
        if key.upper() == "DATA":
            return header, raw[stream.tell() :]


def _check_header(
    header: dict[str, list[str]], path: Path
) -> tuple[list[str], list[int], list[int], int]:
    """FIELDS, SIZE and COUNT (as integers) and the number of points, checked."""
    missing = [k for k in ("FIELDS", "SIZE", "TYPE", "DATA") if k not in header]
    if missing:
        raise FileFormatError(f"PCD header lacks {', '.join(missing)}", path)
    fields = header["FIELDS"]
    # "_" pads a record and may repeat; a coordinate or any other field named twice would leave
    # the reader to pick one copy silently.
    twice = sorted({f for f in fields if f != "_" and fields.count(f) > 1})
    if twice:
        raise FileFormatError(f"PCD header names field {twice[0]!r} twice", path)
    listed = {k: header[k] for k in ("FIELDS", "SIZE", "TYPE", "COUNT") if k in header}
    empty = [k for k, v in listed.items() if not v]
    if empty:
        raise FileFormatError(f"PCD header {'/'.join(empty)} is empty", path)
    if len({len(v) for v in listed.values()}) != 1:
        lengths = ", ".join(f"{k} {len(v)}" for k, v in listed.items())
        raise FileFormatError(f"PCD header lists differ in length ({lengths})", path)
    sizes = _integers(header, "SIZE", path)
    counts = _integers(header, "COUNT", path) if "COUNT" in header else [1] * len(fields)
    width = _integers(header, "WIDTH", path)[0] if "WIDTH" in header else None
    height = _integers(header, "HEIGHT", path)[0] if "HEIGHT" in header else 1
    points = _integers(header, "POINTS", path)[0] if "POINTS" in header else None
    if points is None and width is None:
        raise FileFormatError("PCD header has neither POINTS nor WIDTH", path)
    if width is not None and points is not None and width * height != points:
        raise FileFormatError(
            f"PCD header POINTS {points} disagrees with WIDTH {width} x HEIGHT {height}", path
        )
    if any(v < 1 for v in sizes + counts):
        raise FileFormatError("PCD header SIZE and COUNT must be positive", path)
    return fields, sizes, counts, width * height if points is None else points


def _check_viewpoint(header: dict[str, list[str]], path: Path) -> None:
    """Refuse a VIEWPOINT that is not 7 finite numbers; warn of one that is not the origin.

    PCL's VIEWPOINT (``tx ty tz qw qx qy qz``) is where the sensor was in the points' frame.
    The points are read as stored (as Open3D reads them), but spacepose takes them for the
    sensor's frame: a sensor elsewhere is said, not left to turn every pose silently.

    Raises
    ------
    FileFormatError
        VIEWPOINT is not 7 finite numbers.
    """
    if "VIEWPOINT" not in header:
        return
    text = " ".join(header["VIEWPOINT"])
    try:
        values = np.array([float(v) for v in header["VIEWPOINT"]])
    except ValueError:
        values = np.array([])
    if values.shape != (7,) or not np.isfinite(values).all():
        raise FileFormatError(
            f"PCD header VIEWPOINT must be 7 numbers (tx ty tz qw qx qy qz), got {text!r}", path
        )
    q = values[3:]
    norm = float(np.linalg.norm(q))
    # An all-zero quaternion (some writers' "none") turns nothing; q and -q are one rotation.
    turned = norm > 0 and 1.0 - abs(q[0]) / norm > 1e-9
    if np.any(values[:3] != 0) or turned:
        warnings.warn(
            SpaceposeWarning(
                f"PCD VIEWPOINT {text} puts the sensor away from the points' origin: the "
                "points are read as stored, in that frame, not the sensor's (move them into "
                "the sensor's frame first)",
                path,
            ),
            stacklevel=4,
        )


def _integers(header: dict[str, list[str]], key: str, path: Path) -> list[int]:
    """The values of one header line as non-negative integers."""
    try:
        values = [int(v) for v in header[key]]
    except ValueError:
        raise FileFormatError(f"PCD header {key} is not an integer: {header[key]}", path) from None
    if not values:
        raise FileFormatError(f"PCD header {key} is empty", path)
    if min(values) < 0:
        raise FileFormatError(f"PCD header {key} is negative: {' '.join(header[key])}", path)
    return values


def write_pcd(
    path: Path,
    values: NDArray[np.float64],
    names: tuple[str, ...],
    binary: bool,
    fmt: str,
    dtype: np.dtype,
) -> None:
    """Write the (N, K) ``values`` as K float fields ``names``, binary or ASCII (``fmt``)."""
    n, k = values.shape
    header = (
        "# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\n"
        f"FIELDS {' '.join(names)}\nSIZE {' '.join([str(dtype.itemsize)] * k)}\n"
        f"TYPE {' '.join(['F'] * k)}\nCOUNT {' '.join(['1'] * k)}\n"
        f"WIDTH {n}\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS {n}\n"
        f"DATA {'binary' if binary else 'ascii'}\n"
    )
    if binary:
        body = np.ascontiguousarray(values, dtype=dtype.newbyteorder("<")).tobytes()
    else:
        buf = io.StringIO()
        np.savetxt(buf, values.astype(dtype), fmt=fmt)
        body = buf.getvalue().encode("ascii")
    path.write_bytes(header.encode("ascii") + body)
