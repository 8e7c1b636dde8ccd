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

from spacepose.core.cloud import MM_MIN_EXTENT, PointCloud, check_scale
from spacepose.core.depth import DepthCamera, depth_to_cloud
from spacepose.errors import FileFormatError, InputError, SpaceposeWarning
from spacepose.tools.cloud_io import DEPTH_SUFFIXES, warn_if_not_metres, warn_if_too_near
from spacepose.tools.exr_io import EXR_SUFFIX, exr_size, read_exr_depth, write_exr_depth
from spacepose.tools.intrinsics_io import lens_problem, principal_point_problem
from spacepose.tools.npy_io import load_npy, npy_shape
from spacepose.tools.text_io import not_a_file

# A float depth map's pixels this many times its nearest depths are a renderer's far plane (a
# target 1 m away before a wall 1 km behind it is 1,000 times; Blender's background, 1e10 m).
_FAR_PLANE_RATIO = 1e4
# Share of a map's returns one far-plane value holds at least (a render's background: most).
_FAR_PLANE_SHARE = 0.01
# Depths no sensor returns, even read as millimetres (100 km): a far plane whatever the rest
# (a render of the background alone is all 1e10 m).
_BEYOND_ANY_SENSOR_M = 1e8
# Depths (m) no ToF camera or flash LiDAR returns: nearer than a millimetre (the nearest
# of them range from a few centimetres; a depth_scale of 1e-8 put a scene 1.2 m away at 12 µm)
# or farther than 100 km (the farthest, a rendezvous LiDAR's, a few km; 1000 put it at
# 1,200 km). Such a map is in another unit than depth_scale says, and was reported as points
# on a line or a degenerate surface instead; between these and the ranges of real sensors it
# is only warned of (warn_if_depth_units), as a scene may be.
_NEAREST_DEPTH_M = 1e-3
_FARTHEST_DEPTH_M = 1e5
# Returns whose depths are compared with them: about this many, evenly strided.
_DEPTH_SAMPLE = 4096
# What Pillow raises on a corrupt file besides OSError: a TIFF that lost its size tags ends in
# TypeError ("Missing dimensions"), others in struct, index or key errors of their parsers.
_DECODE_ERRORS = (
    OSError, SyntaxError, ValueError, TypeError, IndexError, KeyError, EOFError, struct.error
)  # fmt: skip
# Pillow modes of one-channel depth maps: 16-bit unsigned (three byte orders), 32-bit int, float.
_DEPTH_MODES = ("I;16", "I;16L", "I;16B", "I", "F")


def read_depth_image(path: str | Path) -> NDArray:
    """Decode one depth image: (H, W) stored values (uint16, int32 or float32; float32 from an
    ``.exr``; any integer or float type from a ``.npy`` array).

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
        return read_exr_depth(path)
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


def read_depth_cloud(path: str | Path, camera: DepthCamera, stride: int = 1) -> PointCloud:
    """One call: a depth image file to the PointCloud of its returns, sensor frame
    (:func:`depth_cloud`).

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
    values = read_depth_image(path)
    scale = camera.metres_per_unit(values.dtype)
    given = "" if camera.depth_scale is not None else ", by the image's type"
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
        a return (named: every depth negative, or beyond ``max_depth``), or the depths lie
        nearer than a millimetre or farther than 100 km (:func:`_check_depth_unit`: a
        ``depth_scale`` of another unit).

    Warns
    -----
    SpaceposeWarning
        The points are in another unit (:func:`warn_if_depth_units`), a far plane is read as
        no return (:func:`_without_far_plane`), some depths are negative, or the principal
        point of intrinsics without a size looks swapped or is a fifth of the image from its
        centre.
    """
    height, width = np.shape(values)[:2]
    camera = _without_far_plane(values, camera, source)
    if (camera.width or width, camera.height or height) == (width, height):
        problem, _ = lens_problem(camera, height, width)  # another size is refused below
        if problem is not None:
            raise InputError(problem, source)
    try:
        cloud = depth_to_cloud(values, camera, stride, source=str(source))
    except InputError as exc:
        raise _why_no_return(values, camera, source) or exc from None
    _check_depth_unit(cloud, source, remedy)
    _warn_if_odd_pixels(values, camera, source)
    if not _warn_if_short_focal(cloud, camera, source):
        warn_if_depth_units(cloud, source, remedy)
    return cloud


def _check_depth_unit(cloud: PointCloud, source: str | Path, remedy: str) -> None:
    """Refuse a map whose depths no depth sensor returns (even its farthest returns nearer
    than :data:`_NEAREST_DEPTH_M`, or its nearest beyond :data:`_FARTHEST_DEPTH_M`): its
    values times the unit read them in (``remedy``, which names it) are not metres.

    Raises
    ------
    InputError
        Naming ``source``, the depth in metres and ``remedy``.
    """
    depth = cloud.points[:: max(1, len(cloud) // _DEPTH_SAMPLE), 2]
    depth = depth[depth > 0.0]
    if not len(depth):
        return
    # The nearest returns against the far limit, the farthest against the near one: a render's
    # Earth 400 km behind a target 25 m away is far, and its target is not.
    nearest, farthest = np.percentile(depth, [1.0, 99.0])
    if nearest > _FARTHEST_DEPTH_M:
        where = f"the nearest 1 % of the returns lie beyond {nearest:.3g} m, farther"
    elif farthest < _NEAREST_DEPTH_M:
        where = f"the farthest 1 % of the returns lie within {farthest:.3g} m, nearer"
    else:
        return
    raise InputError(
        f"{where} than any ToF camera or flash LiDAR ranges: the depths are in another unit? "
        f"{remedy}",
        source,
    )


def _warn_if_short_focal(cloud: PointCloud, camera: DepthCamera, source: str | Path) -> bool:
    """Warn, and say so, when the points spread as millimetres do but their depths are metres:
    the rays fan out too wide, from focal lengths far too short (``fx: 1`` was reported as a
    map in millimetres, its advice to check ``depth_scale``)."""
    check = check_scale(cloud.points)
    depth = float(np.median(cloud.points[:, 2]))
    if not check.millimetres or abs(depth) >= MM_MIN_EXTENT:
        return False
    problem = (
        f"the points spread {check.extent:.3g} m across at a median depth of {depth:.3g} m: "
        f"focal lengths of {camera.fx:g} and {camera.fy:g} px fan the rays out too wide "
        "(check fx and fy in the intrinsics)"
    )
    warnings.warn(SpaceposeWarning(problem, source), stacklevel=4)
    return True


def _warn_if_odd_pixels(values: NDArray, camera: DepthCamera, source: str | Path) -> None:
    """Warn of what a map that back-projects reads oddly: depths below zero among the others
    (read as no return, as a map all below zero is refused), and, with intrinsics that give no
    size, a principal point swapped or a fifth of the image or more from its centre
    (:func:`off_centre_problem`: intrinsics of another resolution put every ray off without a
    word; intrinsics with a size are checked once, by
    :func:`~spacepose.tools.intrinsics_io.check_camera`)."""
    height, width = np.shape(values)[:2]
    if np.issubdtype(np.asarray(values).dtype, np.signedinteger) or np.issubdtype(
        np.asarray(values).dtype, np.floating
    ):
        negative = int(np.count_nonzero(np.asarray(values) < 0))
        if negative:
            problem = f"pixels of negative depth read as no return ({negative} of {width * height})"
            warnings.warn(SpaceposeWarning(problem, source), stacklevel=4)
    if camera.width is not None:
        return
    problem = off_centre_problem(camera, width, height)
    if problem is not None:
        warnings.warn(SpaceposeWarning(problem, source), stacklevel=4)


def off_centre_problem(camera: DepthCamera, width: int, height: int) -> str | None:
    """Why ``camera``'s principal point looks wrong for a ``width`` × ``height`` image: cx and
    cy swapped, or a fifth of the image or more from its centre (another resolution's), or None
    (:func:`~spacepose.tools.intrinsics_io.principal_point_problem`)."""
    return principal_point_problem(camera, width, height)


def _without_far_plane(values: NDArray, camera: DepthCamera, source: str | Path) -> DepthCamera:
    """``camera`` with a ``max_depth`` below a renderer's far plane, when it has none and the map
    holds one: depths past :data:`_BEYOND_ANY_SENSOR_M`, or one value shared by at least
    :data:`_FAR_PLANE_SHARE` of the returns and :data:`_FAR_PLANE_RATIO` times the nearest
    (1st percentile) or more. Blender writes 1e10 m where nothing is hit, most of a render's
    pixels: read as points 1e10 m out, they spread the cloud over 1e10 m and moved the lab run's
    poses by 0.2 mm. One shared value, not every depth past a ratio: a sensor's spurious returns
    near it (a per cent of pixels at a millimetre) would otherwise cut its real far ones. Said
    once a map, with the depth found.

    Raises
    ------
    InputError
        Every pixel at the far plane (a render of the background alone).
    """
    if camera.max_depth is not None or not np.issubdtype(np.asarray(values).dtype, np.floating):
        return camera
    z = np.asarray(values, dtype=np.float64) * camera.metres_per_unit(np.asarray(values).dtype)
    hit = z[np.isfinite(z) & (z > 0)]
    if len(hit) == 0:
        return camera
    top = float(hit.max())
    if top >= _BEYOND_ANY_SENSOR_M:
        cut = _BEYOND_ANY_SENSOR_M
    elif top < _FAR_PLANE_RATIO * float(hit.min()):  # every map of a sensor (1.2 ms, 1280x720)
        return camera
    elif np.count_nonzero(hit == top) >= _FAR_PLANE_SHARE * len(
        hit
    ) and top >= _FAR_PLANE_RATIO * float(np.percentile(hit, 1)):
        cut = top
    else:
        return camera
    far = hit >= cut
    if far.all():  # a render of the background alone: "beyond max_depth" would blame the user
        raise InputError(
            f"no return: every pixel lies at {hit.min():.3g} m or more, a renderer's far plane "
            "(the target out of view?)",
            source,
        )
    warnings.warn(
        SpaceposeWarning(
            f"a renderer's far plane, read as no return ({int(far.sum())} pixels at "
            f"{hit[far].min():.3g} m or more, over {_FAR_PLANE_RATIO:g} times the nearest "
            "depths; set max_depth in the intrinsics to say so)",
            source,
        ),
        stacklevel=3,
    )
    return camera.model_copy(update={"max_depth": cut})


def warn_if_depth_units(cloud: PointCloud, source: str | Path, remedy: str) -> None:
    """Warn (naming ``source``) when a depth map's points look like millimetres or lie nearer
    than any depth camera ranges: the map's unit is not the one it was read in; ``remedy``
    says which setting gave it."""
    # A millimetre map read with depth_scale 1 is a scene 1000 times too large, tracked as such.
    warn_if_not_metres(cloud, source, remedy)
    # A map in metres read as millimetres (a float TIFF with depth_scale 0.001) is a scene 1000
    # times too small.
    warn_if_too_near(cloud, source, f"depth camera ranges: metres read as smaller units? {remedy}")


def _why_no_return(values: NDArray, camera: DepthCamera, path: str | Path) -> InputError | None:
    """The error of a map without a return that says why, when its values do (None when they
    do not): "no return (every pixel zero or invalid)" blamed the pixels for a map of negative
    depths (a renderer's camera looking down -z, as OpenGL's) or for the intrinsics' far
    plane."""
    with np.errstate(invalid="ignore", over="ignore"):
        z = values.astype(np.float64) * camera.metres_per_unit(values.dtype)
        finite = np.isfinite(z) & (z != 0)
        if np.issubdtype(values.dtype, np.integer):  # the type's largest value: no return
            finite &= values != np.iinfo(values.dtype).max
    if np.any(finite) and np.all(z[finite] < 0):
        return InputError(
            f"every depth is negative (median {np.median(z[finite]):.4g} m): depths along -z, "
            "as an OpenGL camera's? they are distances in front of the sensor, positive",
            path,
        )
    returns = z[finite & (z > 0)]
    if camera.max_depth is None or len(returns) == 0 or np.min(returns) < camera.max_depth:
        return None
    return InputError(
        f"every return lies at or beyond max_depth {camera.max_depth:g} m (the nearest at "
        f"{np.min(returns):.4g} m): a far plane in other units than metres?",
        path,
    )
