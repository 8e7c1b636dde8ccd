"""A PLY file read with its header's counts checked against its body (plyfile parses it).

A header whose counts the body cannot hold, a body with rows beyond them, a row cut short or a
value beyond its declared type is one :class:`~spacepose.errors.FileFormatError` naming the
file: the point cloud reader (:mod:`spacepose.tools.ply_pcd_io`) and the mesh reader
(:mod:`spacepose.core.sim.mesh_files`, whose trimesh took a face list shorter than its count, or
a file cut before its last faces, without a word) share it.
"""

from __future__ import annotations

import io
import warnings
from pathlib import Path
from typing import BinaryIO

import numpy as np
import plyfile

from spacepose.errors import FileFormatError


def read_checked_ply(path: Path) -> plyfile.PlyData:
    """Every element of the PLY file ``path``, its body checked against its header.

    Raises
    ------
    FileFormatError
        A bad, truncated or miscounted file (rows beyond or short of the header's counts, a
        list row shorter or longer than its count), a header that is not ASCII, or a value
        beyond its declared type.
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
    return ply


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
