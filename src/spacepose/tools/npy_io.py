"""NumPy point files: ``.npy`` (an (N, 3) or (N, 6) array) and ``.npz`` (``points``, optional
``normals``), read without ever unpickling and written byte for byte the same for the same data;
and the plain ``.npy`` reading that depth maps stored as arrays share (:func:`load_npy`).

A file that does not start with NumPy's (or zip's) signature is refused as such: ``np.load``
would take it for a pickle and answer with advice to load it unsafely. Every failure is one
:class:`~spacepose.errors.FileFormatError` naming the file. :mod:`spacepose.tools.cloud_io`
chooses these by extension.
"""

from __future__ import annotations

import zipfile
from pathlib import Path
from tokenize import TokenError

import numpy as np
from numpy.typing import NDArray

from spacepose.errors import FileFormatError

NPY_MAGIC = b"\x93NUMPY"
ZIP_MAGIC = b"PK"
# What numpy's parsing of a corrupt header raises besides ValueError: tokenize's TokenError (an
# unclosed bracket in the header's dict) escaped as a traceback.
_BAD_HEADER = (SyntaxError, TokenError)


def as_float64(values: NDArray) -> NDArray[np.float64]:
    """``values`` as float64. A float32 signalling NaN (a corrupt or foreign writer's bits)
    stays NaN, a point dropped as any NaN row is, without numpy's bare "invalid value
    encountered in cast" warning, which named no file."""
    with np.errstate(invalid="ignore"):
        return np.asarray(values).astype(np.float64)


def _check_magic(path: Path, magic: bytes, problem: str) -> None:
    """Refuse a file that does not start with ``magic``: numpy reads anything else as a pickle
    and answers with advice to load it unsafely."""
    with path.open("rb") as fh:
        if fh.read(len(magic)) != magic:
            raise FileFormatError(problem, path)


def _numpy_problem(exc: ValueError, kind: str) -> str:
    """The problem of a ``np.load`` ValueError, without numpy's advice to allow pickles."""
    if "pickle" in str(exc).lower():
        return f"{kind} holds Python objects (pickled data), not a numeric array; not loaded"
    return f"bad or truncated {kind}: {exc}"


def _check_size(path: Path) -> None:
    """Refuse a ``.npy`` whose header describes more data than the file holds, before
    ``np.load`` allocates what the header says (a shape of 10¹¹ rows asks for terabytes)."""
    with path.open("rb") as fh:
        version = np.lib.format.read_magic(fh)
        read_header = (
            np.lib.format.read_array_header_1_0
            if version == (1, 0)
            else np.lib.format.read_array_header_2_0
        )
        shape, _, dtype = read_header(fh, max_header_size=100_000)
        start = fh.tell()
    if dtype.hasobject:
        return  # refused by np.load without pickles
    needed = start + int(np.prod(shape, dtype=object)) * dtype.itemsize
    size = path.stat().st_size
    if size < needed:
        raise FileFormatError(
            f"truncated .npy: its header says {dtype} {shape} ({needed:,} bytes), "
            f"the file has {size:,}",
            path,
        )


def load_npy(path: Path) -> NDArray:
    """The array of a ``.npy`` file, as stored (never unpickled).

    Raises
    ------
    FileFormatError
        Missing, not a ``.npy`` file, pickled objects, or a bad or truncated array.
    """
    try:
        _check_magic(path, NPY_MAGIC, "not a .npy file (no NumPy header)")
    except FileNotFoundError:
        raise FileFormatError("file not found", path) from None
    except OSError as exc:  # a folder, a read refused: this file fails, not the run
        raise FileFormatError(f"cannot read: {exc.strerror or exc}", path) from None
    try:
        _check_size(path)
        return np.load(path, allow_pickle=False)
    except FileFormatError:
        raise
    except ValueError as exc:
        raise FileFormatError(_numpy_problem(exc, ".npy"), path) from None
    except _BAD_HEADER:
        raise FileFormatError("bad .npy header: its description does not parse", path) from None
    except (OSError, EOFError) as exc:
        raise FileFormatError(f"bad or truncated .npy: {exc}", path) from None


def npy_shape(path: Path) -> tuple[int, ...] | None:
    """The shape of a ``.npy`` array from its header (nothing loaded), None if unreadable."""
    if not path.is_file():  # a pipe would block the header read
        return None
    try:
        _check_magic(path, NPY_MAGIC, "")
        return tuple(np.load(path, mmap_mode="r", allow_pickle=False).shape)
    except (OSError, ValueError, EOFError, FileFormatError, *_BAD_HEADER):
        return None


def read_npy(path: Path) -> tuple[NDArray[np.float64], NDArray[np.float64] | None]:
    """(N, 3) points and (N, 3) normals or None of a numeric (N, 3) / (N, 6) ``.npy`` array."""
    arr = load_npy(path)
    if arr.ndim != 2 or arr.shape[1] not in (3, 6) or arr.dtype.kind not in "fiu":
        raise FileFormatError(
            f".npy must hold a numeric (N, 3) or (N, 6) array, got {arr.dtype} {arr.shape}", path
        )
    arr = as_float64(arr)
    return arr[:, :3], (arr[:, 3:] if arr.shape[1] == 6 else None)


def read_npz(path: Path) -> tuple[NDArray[np.float64], NDArray[np.float64] | None]:
    """(N, 3) ``points`` and (N, 3) ``normals`` or None of a ``.npz`` archive."""
    _check_magic(path, ZIP_MAGIC, "not a .npz archive (no zip header)")
    try:
        # Opened here, not by np.load: numpy leaves its own handle open when the archive is
        # corrupt (a ResourceWarning at exit, for every bad file a folder holds).
        with path.open("rb") as fh, np.load(fh, allow_pickle=False) as npz:
            if "points" not in npz.files:
                raise FileFormatError(f".npz has no 'points' array (keys: {npz.files})", path)
            points = npz["points"]
            normals = npz["normals"] if "normals" in npz.files else None
    except FileFormatError:
        raise
    except ValueError as exc:
        raise FileFormatError(_numpy_problem(exc, ".npz"), path) from None
    except Exception as exc:  # zipfile/zlib errors of a corrupt archive have no common base
        raise FileFormatError(f"bad or truncated .npz: {exc}", path) from None
    for name, arr in (("points", points), ("normals", normals)):
        if arr is not None and not isinstance(arr, np.ndarray):
            # numpy hands a member without the .npy header back as its bytes: an
            # AttributeError traceback on .ndim.
            raise FileFormatError(f".npz '{name}' is no .npy array (no NumPy header)", path)
        if arr is not None and (arr.ndim != 2 or arr.shape[1] != 3 or arr.dtype.kind not in "fiu"):
            raise FileFormatError(f".npz '{name}' must be numeric (N, 3), got {arr.shape}", path)
    if normals is not None and len(normals) != len(points):
        raise FileFormatError(
            f".npz has {len(normals)} normals for {len(points)} points: one a point", path
        )
    return as_float64(points), None if normals is None else as_float64(normals)


def write_npy(
    path: Path,
    points: NDArray[np.float64],
    normals: NDArray[np.float64] | None,
    binary: bool,
    dtype: np.dtype,
) -> None:
    """Points (and normals) as one (N, 3) / (N, 6) array of ``dtype`` (``binary`` unused)."""
    values = points if normals is None else np.hstack([points, normals])
    np.save(path, values.astype(dtype))


def write_npz(
    path: Path,
    points: NDArray[np.float64],
    normals: NDArray[np.float64] | None,
    binary: bool,
    dtype: np.dtype,
) -> None:
    """``points`` (and ``normals``) of ``dtype`` in an uncompressed, date-free archive."""
    arrays = {"points": points.astype(dtype)}
    if normals is not None:
        arrays["normals"] = normals.astype(dtype)
    # np.savez stamps each member with the current time; a fixed date keeps the bytes
    # a function of the data only.
    with zipfile.ZipFile(path, "w", compression=zipfile.ZIP_STORED) as zf:
        for name, arr in arrays.items():
            info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            with zf.open(info, "w") as fh:
                np.lib.format.write_array(fh, arr, allow_pickle=False)
