"""Depth image files: 16-bit PNG / TIFF and float EXR depth maps, their intrinsics file, TUM
RGB-D's list.

A depth folder holds one image per frame (``.png``, ``.tif``, ``.tiff``; 16-bit integers or
32-bit floats, one channel, decoded by Pillow; ``.exr``, a renderer's float depth channel,
:mod:`spacepose.tools.exr_io`; or ``.npy``, an (H, W) integer (16-bit or wider) or float array
as renderers and simulators save them, NaN or inf for no return) and an
intrinsics file (``intrinsics.yaml``, ``.yml`` or ``.json``: the fields of
:class:`spacepose.core.depth.DepthCamera`, or ROS's ``camera_info`` YAML, or Open3D's pinhole
JSON; :func:`read_intrinsics`), or one given explicitly. Frames are the images sorted by
name, with ``timestamps.txt`` when present, or, in TUM RGB-D's layout, the ``timestamp path``
lines of ``depth.txt`` (``#`` comments ignored; the paths relative to the folder).
"""

from __future__ import annotations

import functools
import io
import re
import struct
import warnings
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray
from PIL import Image, UnidentifiedImageError

from spacepose.core.cloud import PointCloud
from spacepose.core.config import read_mapping, validate_config
from spacepose.core.depth import (
    DepthCamera,
    check_distortion_model,
    depth_to_cloud,
    distort,
    matrix_fields,
    pixel_rays,
)
from spacepose.errors import ConfigError, FileFormatError, InputError, SpaceposeWarning
from spacepose.tools.cloud_io import DEPTH_SUFFIXES, warn_if_not_metres, warn_if_too_near
from spacepose.tools.exr_io import EXR_SUFFIX, exr_size, read_exr_depth, write_exr_depth
from spacepose.tools.npy_io import load_npy, npy_shape
from spacepose.tools.text_io import check_timing, not_a_file, read_text

# A depth folder's frames may also be NumPy arrays; elsewhere a ``.npy`` is a point cloud.
FOLDER_DEPTH_SUFFIXES: tuple[str, ...] = (*DEPTH_SUFFIXES, ".npy")
INTRINSICS_FILES: tuple[str, ...] = ("intrinsics.yaml", "intrinsics.yml", "intrinsics.json")
TUM_DEPTH_LIST = "depth.txt"
# Samples along each ray from the principal point to an edge pixel at which the distortion's
# Jacobian must stay positive (a fold between them maps two directions to one pixel), and the
# step (normalised image units) of its central differences.
_FOLD_SAMPLES = 64
_JACOBIAN_STEP = 1e-6
# A float depth map's pixels this many times its nearest depths are a renderer's far plane (a
# target 1 m away before a wall 1 km behind it is 1,000 times; Blender's background, 1e10 m).
_FAR_PLANE_RATIO = 1e4
# Share of a map's returns one far-plane value holds at least (a render's background: most).
_FAR_PLANE_SHARE = 0.01
# Depths no sensor returns, even read as millimetres (100 km): a far plane whatever the rest
# (a render of the background alone is all 1e10 m).
_BEYOND_ANY_SENSOR_M = 1e8
# A principal point this share of the image from its centre is another resolution's (half the
# resolution's puts it a quarter out; lenses put theirs within a few per cent of the centre).
_OFF_CENTRE = 0.2
# A pincushion that draws the image's edge to less than half its pinhole radius is no lens's:
# a ToF lens bends its corners by a few per cent, a fisheye's barrel the other way.
_FARTHEST_PINCUSHION = 2.0
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
        raise FileFormatError(
            f"a depth map must be one channel of 16-bit integers or 32-bit floats, "
            f"got Pillow mode {mode!r}",
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
        No pixel has a return, the size differs from the intrinsics', or the lens distortion
        folds the image.

    Warns
    -----
    SpaceposeWarning
        The points look like millimetres (a wrong ``depth_scale``), or lie nearer than
        :data:`~spacepose.tools.cloud_io.NEAREST_RANGE_M` (metres read as millimetres), naming
        the file.
    """
    values = read_depth_image(path)
    remedy = f"check depth_scale in the intrinsics ({camera.depth_scale:g} m per stored unit)"
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
        The lens distortion folds the image (:func:`lens_problem`, checked at the map's size:
        intrinsics without one were not checked, and frames came out with their corners'
        rays through the opposite side), the size differs from the intrinsics', no pixel has
        a return (named: every depth negative, or beyond ``max_depth``).

    Warns
    -----
    SpaceposeWarning
        The points are in another unit (:func:`warn_if_depth_units`), a far plane is read as
        no return (:func:`_without_far_plane`), some depths are negative, or the principal
        point of intrinsics without a size is a fifth of the image from its centre.
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
    _warn_if_odd_pixels(values, camera, source)
    warn_if_depth_units(cloud, source, remedy)
    return cloud


def _warn_if_odd_pixels(values: NDArray, camera: DepthCamera, source: str | Path) -> None:
    """Warn of what a map that back-projects reads oddly: depths below zero among the others
    (read as no return, as a map all below zero is refused), and, with intrinsics that give no
    size, a principal point a fifth of the image or more from its centre (intrinsics of
    another resolution put every ray off without a word)."""
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
    off_x = abs(camera.cx - 0.5 * (width - 1)) / width
    off_y = abs(camera.cy - 0.5 * (height - 1)) / height
    if max(off_x, off_y) >= _OFF_CENTRE:
        problem = (
            f"the principal point lies far from the image's centre: intrinsics of another "
            f"resolution? (({camera.cx:g}, {camera.cy:g}) in a {width}x{height} image; give "
            "width and height in the intrinsics to check them)"
        )
        warnings.warn(SpaceposeWarning(problem, source), stacklevel=4)


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
    z = np.asarray(values, dtype=np.float64) * camera.depth_scale
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
        z = values.astype(np.float64) * camera.depth_scale
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


def read_intrinsics(path: str | Path) -> DepthCamera:
    """Read an intrinsics file (YAML or JSON) in one of three layouts:

    - ours: the fields of :class:`DepthCamera`;
    - ROS's ``camera_info`` YAML (``camera_calibration``'s output): ``camera_matrix``,
      ``distortion_model``, ``distortion_coefficients``, ``image_width``, ``image_height``;
    - Open3D's ``PinholeCameraIntrinsic`` JSON: ``intrinsic_matrix`` (9 numbers, column by
      column), ``width``, ``height``.

    A foreign layout may carry our other fields beside it (``depth_scale``, ``depth_kind``,
    ``max_depth``); without them, 16-bit values are millimetres along the boresight, as ROS
    and Open3D take them. Their other keys (``camera_name``, the rectification and projection
    matrices) are not used.

    Raises
    ------
    ConfigError
        Unreadable file, unknown key or one that is no name, a value out of range, or a matrix
        that is not a pinhole camera's.
    """
    data = read_mapping(path) or {}
    try:
        named = [k for k in data if not isinstance(k, str)]
        if named:
            # YAML reads "1: 0.1" (a key that lost its letters) as a number: pydantic's
            # TypeError "keywords must be strings" escaped as a traceback.
            kinds = {"int": "a number", "float": "a number", "bool": "a yes/no", "NoneType": "null"}
            kind = kinds.get(type(named[0]).__name__, f"a {type(named[0]).__name__}")
            raise InputError(f"key {named[0]!r} is not a field name: YAML reads it as {kind}")
        if "camera_matrix" in data and "intrinsic_matrix" in data:
            # One would be used and the other ignored without a word.
            raise InputError(
                "holds both camera_matrix (ROS) and intrinsic_matrix (Open3D): keep one"
            )
        data = _ros_fields(data) if "camera_matrix" in data else data
        data = _open3d_fields(data) if "intrinsic_matrix" in data else data
        data = _flat_fields(data) if "distortion_model" in data else data
    except InputError as exc:
        raise ConfigError(f"{path}: {exc}") from None
    return validate_config(DepthCamera, data, path)


# Keys of ROS's camera_info YAML that describe stereo rectification, not the depth image.
_ROS_UNUSED = ("camera_name", "rectification_matrix", "projection_matrix")
# Our fields that the foreign layouts' matrices give (ROS's also the image size, when given).
_OPEN3D_GIVES = ("fx", "fy", "cx", "cy")
_ROS_GIVES = (*_OPEN3D_GIVES, "k1", "k2", "k3", "k4", "k5", "k6", "p1", "p2")


def _ros_fields(data: dict) -> dict:
    """Our fields from ROS's ``camera_info`` YAML layout (and any of ours beside it)."""
    rest = {k: v for k, v in data.items() if k not in _ROS_UNUSED}
    K = _matrix_data(rest.pop("camera_matrix"), "camera_matrix")
    D = _matrix_data(
        rest.pop("distortion_coefficients", None) or {"data": []},
        "distortion_coefficients",
        size_checked=True,
    )
    model = rest.pop("distortion_model", None)
    size = {"width": rest.pop("image_width", None), "height": rest.pop("image_height", None)}
    size = {k: v for k, v in size.items() if v}
    given = (*_ROS_GIVES, *size)
    return (
        matrix_fields(K, D, model)
        | size
        | _not_given_twice(rest, given, "the ROS camera_info layout")
    )


def _flat_fields(data: dict) -> dict:
    """Our layout with ROS's ``distortion_model`` beside it: the model our ``k1``..``k6``,
    ``p1``, ``p2`` are (:data:`~spacepose.core.depth.DISTORTION_MODELS`), or any model with no
    coefficient given (as :func:`~spacepose.core.depth.matrix_fields` takes it)."""
    rest = dict(data)
    model = rest.pop("distortion_model")
    check_distortion_model(model, any(rest.get(n) for n in _ROS_GIVES[4:]))
    return rest


def _not_given_twice(rest: dict, given: tuple[str, ...], layout: str) -> dict:
    """``rest`` (our fields beside a foreign layout), refused when it repeats one the layout
    gives: one of the two would win without a word (a focal length of another camera)."""
    twice = [k for k in given if k in rest]
    if twice:
        raise InputError(f"{', '.join(twice)} given twice, by {layout} and on its own: keep one")
    return rest


def _open3d_fields(data: dict) -> dict:
    """Our fields from Open3D's ``PinholeCameraIntrinsic`` JSON (the matrix column-major)."""
    rest = dict(data)
    values = rest.pop("intrinsic_matrix")
    try:
        K = np.asarray(values, dtype=np.float64).reshape(3, 3).T
    except (TypeError, ValueError):
        raise InputError("intrinsic_matrix must be 9 numbers, column by column") from None
    return matrix_fields(K) | _not_given_twice(rest, _OPEN3D_GIVES, "intrinsic_matrix")


def _matrix_data(entry: object, name: str, size_checked: bool = False) -> list:
    """A ROS YAML matrix's numbers: ``{rows, cols, data}`` or a bare list; with
    ``size_checked``, refused when ``data`` does not hold ``rows x cols`` numbers."""
    if isinstance(entry, dict):
        if "data" not in entry:
            raise InputError(f"{name} has no data")
        rows, cols, data = entry.get("rows"), entry.get("cols"), entry["data"]
        # A list cut short (5 coefficients announced, 1 given) read as k1 alone without a word;
        # the camera matrix's own count (9) is checked by matrix_fields.
        sized = all(isinstance(v, int) and not isinstance(v, bool) for v in (rows, cols))
        if sized and size_checked and isinstance(data, list) and rows * cols != len(data):
            raise InputError(
                f"{name} announces rows {rows} x cols {cols} = {rows * cols} numbers, "
                f"its data holds {len(data)}"
            )
        entry = data
    if not isinstance(entry, list):
        # numpy would read a lone number as a list of one (distortion k1 = that number).
        raise InputError(f"{name} must be a list of numbers or {{rows, cols, data}}, got {entry!r}")
    return entry


def check_camera(camera: DepthCamera, source: str | Path) -> None:
    """Refuse a camera that cannot make its images' points: its principal point outside the
    image, or a distortion that does not map the image one-to-one onto directions
    (:func:`lens_problem`); warn of one that narrows its view beyond any lens. Each was found
    frame by frame (every frame lost, or back-projected wrong without a word), naming the
    image rather than the intrinsics at fault.

    Parameters
    ----------
    camera
        The camera; nothing is checked without its image size.
    source
        Its intrinsics file (or bag topic), named in the message.

    Raises
    ------
    ConfigError
        ``source: problem``.

    Warns
    -----
    SpaceposeWarning
        The distortion pulls some pixel's direction to less than half its pinhole radius.
    """
    width, height = camera.width, camera.height
    if width is None or height is None:
        return
    if not (-0.5 <= camera.cx <= width - 0.5 and -0.5 <= camera.cy <= height - 0.5):
        raise ConfigError(
            f"{source}: the principal point ({camera.cx:g}, {camera.cy:g}) lies outside the "
            f"{width}x{height} image: intrinsics of another resolution?"
        )
    problem, caution = lens_problem(camera, height, width)
    if problem is not None:
        raise ConfigError(f"{source}: {problem}")
    if caution is not None:
        warnings.warn(SpaceposeWarning(caution, source), stacklevel=3)


@functools.lru_cache(maxsize=8)
def lens_problem(camera: DepthCamera, height: int, width: int) -> tuple[str | None, str | None]:
    """Why ``camera``'s distortion cannot be undone over its ``width`` x ``height`` image (or
    None), and what looks wrong with it though it can (or None).

    The model must be one-to-one over the image: every pixel undistorted, and no fold
    between the principal point and any pixel (the map's Jacobian positive along the rays to
    the edge pixels and at every pixel). Past a fold a pixel was given the direction of the
    far side (k1 = -0.5 on a 640-pixel, fx 500 image put the corners' rays through the
    opposite corner), or none: the frame lost its edges, or its shape, without a word.
    """
    if not camera.distorted:
        return None, None
    coefficients = (
        f"k1..k6 {camera.k1:g} {camera.k2:g} {camera.k3:g} {camera.k4:g} {camera.k5:g} "
        f"{camera.k6:g}, p1 p2 {camera.p1:g} {camera.p2:g}"
    )
    try:
        rays = pixel_rays(camera, height, width)
    except InputError as exc:  # most of the image folded away
        return exc.reason, None
    edge = np.concatenate([rays[0], rays[-1], rays[:, 0], rays[:, -1]])
    along = np.linspace(0.0, 1.0, _FOLD_SAMPLES + 1)[1:, None, None] * edge[None]
    xd, yd = distort(camera, along[..., 0], along[..., 1])
    # Where each sample and each pixel is seen, in pixels from the principal point.
    reach = np.hypot(camera.fx * xd, camera.fy * yd)
    v, u = np.mgrid[:height, :width]
    pixel_reach = np.hypot(u - camera.cx, v - camera.cy)
    folded = _jacobian_det(camera, along) <= 0  # samples of a NaN ray are its pixel's
    folded_pixels = ~(_jacobian_det(camera, rays) > 0)  # NaN rays included
    if np.any(folded) or np.any(folded_pixels):
        # Where each ray is last seen before its first fold (past it, it may come back inward).
        rays_folded = np.any(folded, axis=0)
        before = np.maximum(np.argmax(folded, axis=0) - 1, 0)
        first = reach[before, np.arange(folded.shape[1])][rays_folded]
        fold = min(
            np.min(first, initial=np.inf), np.min(pixel_reach[folded_pixels], initial=np.inf)
        )
        lost = int(np.sum(~np.isfinite(rays[..., 0])))
        return (
            f"the lens distortion ({coefficients}) is not one-to-one over the {width}x{height} "
            f"image: it folds back about {fold:.0f} pixels from the principal point, and "
            f"pixels beyond see another direction or none ({lost} cannot be undistorted); "
            "coefficients of another convention or camera?",
            None,
        )
    pinhole = np.hypot((u - camera.cx) / camera.fx, (v - camera.cy) / camera.fy)
    with np.errstate(divide="ignore", invalid="ignore"):  # the principal point's pixel: 0 / 0
        narrowing = pinhole / np.hypot(rays[..., 0], rays[..., 1])
    worst = float(np.nanmax(narrowing, initial=1.0))
    if worst <= _FARTHEST_PINCUSHION:
        return None, None
    return None, (
        f"the lens distortion ({coefficients}) draws pixels to {1 / worst:.2g} of their pinhole "
        f"distance from the principal point, narrowing the {width}x{height} image's view "
        "beyond any lens: coefficients of another convention or camera?"
    )


def _jacobian_det(camera: DepthCamera, points: NDArray[np.float64]) -> NDArray[np.float64]:
    """The determinant of :func:`distort`'s Jacobian at (..., 2) normalised points (central
    differences; NaN where a point is NaN)."""
    x, y, h = points[..., 0], points[..., 1], _JACOBIAN_STEP
    with np.errstate(all="ignore"):
        x1, y1 = distort(camera, x + h, y)
        x0, y0 = distort(camera, x - h, y)
        x3, y3 = distort(camera, x, y + h)
        x2, y2 = distort(camera, x, y - h)
        return ((x1 - x0) * (y3 - y2) - (x3 - x2) * (y1 - y0)) / (4 * h * h)


def find_intrinsics(root: str | Path) -> Path | None:
    """The intrinsics file in a folder (see :data:`INTRINSICS_FILES`), or None.

    Raises
    ------
    InputError
        The folder holds more than one.
    """
    found = [Path(root) / name for name in INTRINSICS_FILES if (Path(root) / name).is_file()]
    if len(found) > 1:
        # Which one a reader takes would be a rule of ours the user cannot see.
        raise InputError(
            f"holds {len(found)} intrinsics files ({', '.join(p.name for p in found)}): keep one",
            root,
        )
    return found[0] if found else None


def folder_camera(
    root: Path, intrinsics: str | Path | None, camera: DepthCamera | None
) -> tuple[DepthCamera | None, Path | None]:
    """The camera of a depth folder (or of a depth image's folder) and its file: ``camera``
    read from the ``intrinsics`` given, else the folder's own intrinsics file (None, None
    without either). Every reader of depth images takes its camera here, so a given file and
    the folder's own are weighed alike (a depth folder's frames, ``register``'s images).

    Raises
    ------
    InputError
        Both are there and differ: the given file won without a word, the folder's own
        calibration (the one recorded with its images) ignored. As for two intrinsics files
        in one folder, the user keeps one.
    ConfigError
        An intrinsics file is invalid.
    """
    given = None if intrinsics is None else Path(intrinsics)
    found = find_intrinsics(root)
    if found is None:
        return camera, given
    try:
        own = read_intrinsics(found)
    except ConfigError as exc:
        if camera is None:
            raise
        # The user gave intrinsics, perhaps for this very reason: say why theirs are refused.
        raise InputError(
            f"--intrinsics {intrinsics} is given beside the folder's {found.name}, which "
            f"cannot be read ({exc}): keep one",
            root,
        ) from None
    if camera is None:
        return own, found
    differ = [
        f"{name} {getattr(camera, name)} vs {getattr(own, name)}"
        for name in type(own).model_fields
        if getattr(camera, name) != getattr(own, name)
    ]
    if differ:
        raise InputError(
            f"--intrinsics {intrinsics} and the folder's {found.name} differ "
            f"({', '.join(differ[:3])}{', ...' if len(differ) > 3 else ''}): keep one "
            f"(move {found.name} out, or leave out --intrinsics)",
            root,
        )
    return camera, given


def is_depth_folder(root: str | Path) -> bool:
    """Whether a folder is read as depth images: it holds ``depth.txt`` or an intrinsics file."""
    return (Path(root) / TUM_DEPTH_LIST).is_file() or find_intrinsics(root) is not None


def _name_order(path: Path) -> tuple[tuple[int | str, ...], str]:
    """Sort key of a frame's name: its runs of digits by value (``frame5`` before
    ``frame10``), but those after a dot, a fraction's digits, as text (``1.25`` before
    ``1.5``); the same order as the names' where the numbers are zero-padded. Names of equal
    value (``frame1``, ``frame01``) follow as text, so the order never rests on the folder's."""
    chunks: list[int | str] = re.split(r"(\d+)", path.name)
    for i in range(1, len(chunks), 2):
        if not str(chunks[i - 1]).endswith("."):
            chunks[i] = int(chunks[i])
    return tuple(chunks), path.name


def frame_entries(root: Path, suffixes: tuple[str, ...]) -> tuple[Path, ...]:
    """A folder's entries named as frames (a suffix of ``suffixes``, any case), sorted by name
    with its numbers by value (:func:`_name_order`).

    Not only regular files: a folder or a broken link named as a frame is a frame that cannot
    be read (reported lost), not one to skip and shift the rest. Hidden entries (a leading
    dot: macOS's ``._000000.ply`` resource forks, editors' swap files) are not frames.

    Raises
    ------
    InputError
        Two entries share a name but for the suffix.
    """
    entries = tuple(
        sorted(
            (
                p
                for p in root.iterdir()
                if p.suffix.lower() in suffixes and not p.name.startswith(".")
            ),
            key=_name_order,
        )
    )
    # Two files of one frame name (000001.ply and 000001.npy) would both be tracked, and every
    # later frame numbered, and timed, one too far.
    seen: dict[str, Path] = {}
    for p in entries:
        if p.stem in seen:
            raise InputError(
                f"{seen[p.stem].name} and {p.name} are one frame name twice: keep one", root
            )
        seen[p.stem] = p
    return entries


def depth_files(root: str | Path) -> tuple[Path, ...]:
    """The depth images of a folder, sorted by name.

    Raises
    ------
    InputError
        The folder holds no image with a suffix of :data:`FOLDER_DEPTH_SUFFIXES`, or its
        first ``.npy`` is an (N, 3) or (N, 6) point array.
    """
    root = Path(root)
    paths = frame_entries(root, FOLDER_DEPTH_SUFFIXES)
    if not paths:
        raise InputError(
            f"no depth images ({', '.join(FOLDER_DEPTH_SUFFIXES)}) in the folder", root
        )
    arrays = [p for p in paths if p.suffix.lower() == ".npy"]
    shape = npy_shape(arrays[0]) if arrays else None
    if shape is not None and len(shape) == 2 and shape[1] in (3, 6):
        # No depth map is 3 or 6 pixels wide: these are point clouds, given intrinsics.
        raise InputError(
            f"{arrays[0].name} holds points, an {shape} array, not a depth map: a folder of "
            "point clouds needs no intrinsics",
            root,
        )
    return paths


def read_tum_depth_list(path: str | Path) -> tuple[tuple[Path, ...], NDArray[np.float64]]:
    """Read TUM RGB-D's ``depth.txt``: ``timestamp relative/path.png`` per line.

    Returns
    -------
    paths, timestamps
        The image paths (relative to the list's folder) and their (N,) times, seconds.

    Raises
    ------
    InputError
        Unreadable list, a line that is not ``number path``, an image listed twice, a
        non-finite or decreasing time,
        times that are not seconds (:func:`~spacepose.tools.text_io.check_timing`), or no
        line at all.
    """
    path = Path(path)
    text = read_text(path, "the depth list")
    paths: list[Path] = []
    stamps: list[float] = []
    listed: dict[Path, int] = {}  # each image's line
    for lineno, line in enumerate(text.splitlines(), start=1):
        body = line.split("#", 1)[0].strip()
        if not body:
            continue
        parts = body.split(maxsplit=1)
        try:
            stamp = float(parts[0])
        except ValueError:
            stamp = float("nan")
        if len(parts) != 2 or not np.isfinite(stamp):
            raise InputError(f"line {lineno}: expected 'timestamp path', got {body!r}", path)
        image = path.parent / parts[1]
        if image in listed:
            # One image tracked as two frames: a line pasted twice, or the wrong file named.
            raise InputError(
                f"line {lineno}: {parts[1]} is listed again (line {listed[image]}): one image is "
                "one frame",
                path,
            )
        listed[image] = lineno
        stamps.append(stamp)
        paths.append(image)
    if not paths:
        raise InputError("lists no depth image", path)
    timestamps = np.asarray(stamps, dtype=np.float64)
    check_timing(timestamps, path)
    return tuple(paths), timestamps
