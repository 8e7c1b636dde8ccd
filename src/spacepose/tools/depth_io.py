"""Depth image files: 16-bit PNG / TIFF and float EXR depth maps, read into the point clouds of
their returns.

A depth image is ``.png``, ``.tif`` or ``.tiff`` (16-bit integers or 32-bit floats, one
channel, decoded by Pillow), ``.exr`` (a renderer's float depth channel,
:mod:`spacepose.tools.exr_io`) or ``.npy`` (an (H, W) integer (16-bit or wider) or float array
as renderers and simulators save them, NaN or inf for no return). Its camera comes from an
intrinsics file (:mod:`spacepose.tools.intrinsics_io`); a folder of them, one image per frame,
is read by :mod:`spacepose.tools.depth_folder`.
"""

from __future__ import annotations

import io
import struct
import warnings
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray
from PIL import Image, UnidentifiedImageError

from spacepose.core.cloud import PointCloud
from spacepose.core.depth import DepthCamera, depth_to_cloud
from spacepose.errors import FileFormatError, InputError, SpaceposeWarning
from spacepose.tools.cloud_io import DEPTH_SUFFIXES
from spacepose.tools.depth_checks import (
    check_depth_unit,
    refuse_z_buffer,
    warn_if_depth_units,
    warn_if_odd_pixels,
    warn_if_short_focal,
    why_no_return,
    without_far_plane,
)
from spacepose.tools.exr_io import EXR_SUFFIX, exr_size, read_exr_depth, write_exr_depth
from spacepose.tools.intrinsics_io import lens_problem
from spacepose.tools.npy_io import load_npy, npy_shape
from spacepose.tools.text_io import not_a_file

# What Pillow raises on a corrupt file besides OSError: a TIFF that lost its size tags ends in
# TypeError ("Missing dimensions"), others in struct, index or key errors of their parsers.
_DECODE_ERRORS = (
    OSError, SyntaxError, ValueError, TypeError, IndexError, KeyError, EOFError, struct.error
)  # fmt: skip
# Pillow modes of one-channel depth maps: 16-bit unsigned (three byte orders), 32-bit int, float.
_DEPTH_MODES = ("I;16", "I;16L", "I;16B", "I", "F")


def read_depth_image(path: str | Path, kind_given: bool = False) -> NDArray:
    """Decode one depth image: (H, W) stored values (uint16, int32 or float32; float32 from an
    ``.exr``; any integer or float type from a ``.npy`` array). ``kind_given``: the intrinsics
    say which depth the map holds (:func:`~spacepose.tools.exr_io.read_exr_depth`).

    Raises
    ------
    FileFormatError
        Missing, unreadable, corrupt or truncated file, or an image that is not one channel of
        16-bit integers or 32-bit floats (an 8-bit or colour image is not a depth map), or a
        ``.npy`` that is not a 2-D numeric array of more than 8 bits.
    """
    path = Path(path)
    if path.exists() and not path.is_file():  # a folder, or a pipe Pillow would wait on
        raise FileFormatError(not_a_file(path), path)
    if path.suffix.lower() == EXR_SUFFIX:
        return read_exr_depth(path, kind_given)
    if path.suffix.lower() == ".npy":
        values = load_npy(path)
        if values.ndim != 2 or values.dtype.kind not in "fiu":
            raise FileFormatError(
                f"a depth map must be a 2-D integer or float array, got {values.dtype} "
                f"{values.shape}",
                path,
            )
        if values.dtype.kind in "iu" and values.dtype.itemsize == 1:
            # As an 8-bit PNG: 256 levels are a picture of depth, not depths (0-255 mm).
            raise FileFormatError(
                f"a depth map of 8-bit integers ({values.dtype}) is an image of depth, not "
                "depths: save the 16-bit or float values",
                path,
            )
        return values
    return _image_values(path, path)


def decode_depth_image(data: bytes, source: str) -> NDArray:
    """Decode one depth image held in memory (a PNG or TIFF in a bag message), checked as
    :func:`read_depth_image` checks a file.

    Parameters
    ----------
    data
        The encoded image.
    source
        What holds it (a bag's message), named in errors and warnings.

    Returns
    -------
    (H, W) stored values (uint16, int32 or float32).

    Raises
    ------
    FileFormatError
        Not an image, corrupt or truncated, or not one channel of 16-bit integers or 32-bit
        floats.
    """
    return _image_values(io.BytesIO(data), source)


# PNG colour types (the IHDR chunk's byte 25) by name.
_PNG_COLOURS = {0: "grey", 2: "RGB", 3: "palette", 4: "grey + alpha", 6: "RGBA"}


def _png_kind(file: Path | io.BytesIO) -> str | None:
    """ "a 16-bit grey + alpha PNG" and the like from a PNG's header; None for another file."""
    if isinstance(file, io.BytesIO):
        head = file.getvalue()[:26]
    else:
        with file.open("rb") as fh:
            head = fh.read(26)
    if len(head) < 26 or not head.startswith(b"\x89PNG\r\n\x1a\n") or head[12:16] != b"IHDR":
        return None
    article = "an" if head[24] in (8, 11, 18) else "a"
    return f"{article} {head[24]}-bit {_PNG_COLOURS.get(head[25], 'unknown colour type')} PNG"


def _image_values(file: Path | io.BytesIO, source: str | Path) -> NDArray:
    """One decoded depth image, refused unless one page of one 16-bit or float channel."""
    # Pillow warns of what it skips in a damaged file (a line each, naming no file): kept
    # back, they are said once, naming the image, when it decodes; its error says the rest.
    with warnings.catch_warnings(record=True) as skipped:
        warnings.simplefilter("always")
        values, mode, pages = _decode(file, source)
    if pages != 1:  # a stack would be read as its first page, the rest dropped
        raise FileFormatError(
            f"holds {pages} images; a depth map is one (one file a frame)", source
        )
    if mode not in _DEPTH_MODES or values.ndim != 2:
        # Pillow decodes a 16-bit grey + alpha PNG as 8-bit RGBA: the file's header says what
        # it holds.
        got = _png_kind(file) or f"Pillow mode {mode!r}"
        raise FileFormatError(
            f"a depth map must be one channel of 16-bit integers or 32-bit floats, got {got}",
            source,
        )
    said = list(dict.fromkeys(" ".join(str(w.message).split()) for w in skipped))
    if said:
        more = f" (and {len(said) - 2} more)" if len(said) > 2 else ""
        problem = f"decoded despite Pillow's warnings: {'; '.join(said[:2])}{more}"
        warnings.warn(SpaceposeWarning(problem, source), stacklevel=3)
    return values


def _decode(file: Path | io.BytesIO, source: str | Path) -> tuple[NDArray, str, int]:
    """An image's values, Pillow mode and page count (``file`` a path or the bytes).

    Raises
    ------
    FileFormatError
        Missing, not an image, too large, or corrupt.
    """
    try:
        with Image.open(file) as image:
            pages = getattr(image, "n_frames", 1)
            image.load()
            return np.array(image), image.mode, pages
    except FileNotFoundError:
        raise FileFormatError("file not found", source) from None
    except UnidentifiedImageError:
        raise FileFormatError("not an image Pillow can decode", source) from None
    except Image.DecompressionBombError as exc:  # a header claiming more pixels than any camera
        raise FileFormatError(f"refused: {exc}", source) from None
    except _DECODE_ERRORS as exc:
        raise FileFormatError(f"cannot decode the image: {exc}", source) from None


def image_size(path: str | Path) -> tuple[int, int] | None:
    """(width, height) of an image from its header (nothing decoded), None if unreadable."""
    if not Path(path).is_file():  # a pipe would block the header read
        return None
    if Path(path).suffix.lower() == ".npy":
        shape = npy_shape(Path(path))
        return None if shape is None or len(shape) != 2 else (shape[1], shape[0])
    if Path(path).suffix.lower() == EXR_SUFFIX:
        return exr_size(Path(path))
    try:
        with warnings.catch_warnings():  # the frame's own read says what is wrong with it
            warnings.simplefilter("ignore")
            with Image.open(path) as image:
                return image.size
    except (*_DECODE_ERRORS, Image.DecompressionBombError):
        return None


def write_depth_image(path: str | Path, depth_m: ArrayLike, depth_scale: float = 0.001) -> Path:
    """Write a depth image (metres, 0 = no return) as 16-bit units of ``depth_scale`` metres
    (PNG or TIFF by suffix), or as 32-bit float metres for a ``.tif``/``.tiff`` when
    ``depth_scale`` is 1, or as float32 units of ``depth_scale`` in an ``.exr``.

    Raises
    ------
    InputError
        Not 2-D, negative or non-finite depths, a depth of 65535 units or more (65535 is
        no return), or an unknown suffix.
    """
    path = Path(path)
    depth = np.asarray(depth_m, dtype=np.float64)
    if path.suffix.lower() not in DEPTH_SUFFIXES:
        raise InputError(f"depth images are {', '.join(DEPTH_SUFFIXES)}", path)
    if depth.ndim != 2 or not np.all(np.isfinite(depth)) or np.any(depth < 0):
        raise InputError("a depth image must be 2-D, finite and non-negative (metres)", path)
    if path.suffix.lower() == EXR_SUFFIX:
        values = (depth / depth_scale).astype(np.float32)  # a renderer's float depths
    elif depth_scale == 1.0 and path.suffix.lower() != ".png":
        values = depth.astype(np.float32)
    else:
        units = np.rint(depth / depth_scale)
        # 65535 is read back as no return (:func:`~spacepose.core.depth.backproject`).
        if units.max(initial=0.0) >= np.iinfo(np.uint16).max:
            raise InputError(
                f"depth {depth.max():.4g} m reaches 65535 units of {depth_scale} m, "
                "the no-return code",
                path,
            )
        values = units.astype(np.uint16)
    path.parent.mkdir(parents=True, exist_ok=True)
    if path.suffix.lower() == EXR_SUFFIX:
        write_exr_depth(path, values)
    else:
        Image.fromarray(values).save(path)
    return path


def read_depth_cloud(
    path: str | Path, camera: DepthCamera, stride: int = 1, unit_from: str | None = None
) -> PointCloud:
    """One call: a depth image file to the PointCloud of its returns, sensor frame
    (:func:`depth_cloud`). ``unit_from``: what set ``camera.depth_scale`` when the intrinsics
    did not (a folder's layout), as errors and warnings name it.

    Raises
    ------
    FileFormatError
        The image cannot be decoded (see :func:`read_depth_image`).
    InputError
        No pixel has a return, the size differs from the intrinsics', the lens distortion
        folds the image, or the depths lie nearer than a millimetre or beyond 100 km
        (a wrong ``depth_scale``, named with the depth).

    Warns
    -----
    SpaceposeWarning
        The points look like millimetres (a wrong ``depth_scale``), or lie nearer than
        :data:`~spacepose.tools.cloud_io.NEAREST_RANGE_M` (metres read as millimetres), naming
        the file.
    """
    values = read_depth_image(path, "depth_kind" in camera.model_fields_set)
    scale = camera.metres_per_unit(values.dtype)
    given = "" if camera.depth_scale is not None else ", by the image's type"
    given = f", by {unit_from}" if unit_from is not None else given
    remedy = f"check depth_scale in the intrinsics ({scale:g} m per stored unit{given})"
    return depth_cloud(values, camera, path, remedy, stride)


def depth_cloud(
    values: NDArray, camera: DepthCamera, source: str | Path, remedy: str, stride: int = 1
) -> PointCloud:
    """The PointCloud of a depth map's returns (:func:`~spacepose.core.depth.depth_to_cloud`),
    checked as every depth frame is, whatever its container (a file, a bag message).

    Parameters
    ----------
    values
        (H, W) stored depth values.
    camera
        Its intrinsics.
    source
        The file or message, named in errors and warnings.
    remedy
        Which setting gave the values' unit, for the warnings.
    stride
        Keep every ``stride``-th pixel along rows and columns.

    Raises
    ------
    InputError
        The lens distortion folds the image
        (:func:`~spacepose.tools.intrinsics_io.lens_problem`, checked at the map's size:
        intrinsics without one were not checked, and frames came out with their corners'
        rays through the opposite side), the size differs from the intrinsics', no pixel has
        a return (named: every depth negative, or beyond ``max_depth``), the map is a
        normalised depth buffer (:func:`~spacepose.tools.depth_checks.refuse_z_buffer`), or
        the depths lie nearer than a millimetre or farther than 100 km
        (:func:`~spacepose.tools.depth_checks.check_depth_unit`: a ``depth_scale`` of another
        unit).

    Warns
    -----
    SpaceposeWarning
        The points are in another unit
        (:func:`~spacepose.tools.depth_checks.warn_if_depth_units`), a far plane is read as
        no return (:func:`~spacepose.tools.depth_checks.without_far_plane`), some depths are
        negative, or the principal point of intrinsics without a size looks swapped or is a
        fifth of the image from its centre.
    """
    height, width = np.shape(values)[:2]
    refuse_z_buffer(values, camera, source)
    camera = without_far_plane(values, camera, source)
    if (camera.width or width, camera.height or height) == (width, height):
        problem, _ = lens_problem(camera, height, width)  # another size is refused below
        if problem is not None:
            raise InputError(problem, source)
    try:
        cloud = depth_to_cloud(values, camera, stride, source=str(source))
    except InputError as exc:
        raise why_no_return(values, camera, source) or exc from None
    check_depth_unit(cloud, source, remedy)
    warn_if_odd_pixels(values, camera, source)
    if not warn_if_short_focal(cloud, camera, source):
        warn_if_depth_units(cloud, source, remedy)
    return cloud
