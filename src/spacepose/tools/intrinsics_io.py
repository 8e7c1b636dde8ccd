"""Intrinsics files of depth cameras, and the checks that a camera can make its images' points.

An intrinsics file (``intrinsics.yaml``, ``.yml`` or ``.json``) holds the fields of
:class:`spacepose.core.depth.DepthCamera`, or ROS's ``camera_info`` YAML, or Open3D's pinhole
JSON (:func:`read_intrinsics`); a depth folder holds one (:func:`find_intrinsics`), or one is
given explicitly. A camera whose principal point lies outside its image, or whose lens
distortion folds it, is refused before any frame is read (:func:`check_camera`).
"""

from __future__ import annotations

import functools
import warnings
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from spacepose.core.config import holds_boolean, holds_text, read_mapping, validate_config
from spacepose.core.depth import DepthCamera, pixel_rays
from spacepose.core.lens import check_distortion_model, distort, matrix_fields
from spacepose.errors import ConfigError, InputError, SpaceposeWarning

INTRINSICS_FILES: tuple[str, ...] = ("intrinsics.yaml", "intrinsics.yml", "intrinsics.json")
# Samples along each ray from the principal point to an edge pixel at which the distortion's
# Jacobian must stay positive (a fold between them maps two directions to one pixel), and the
# step (normalised image units) of its central differences.
_FOLD_SAMPLES = 64
_JACOBIAN_STEP = 1e-6
# A pincushion that draws the image's edge to less than half its pinhole radius is no lens's:
# a ToF lens bends its corners by a few per cent, a fisheye's barrel the other way.
_FARTHEST_PINCUSHION = 2.0
# A principal point this share of the image from its centre is another resolution's (half the
# resolution's puts it a quarter out; lenses put theirs within a few per cent of the centre).
OFF_CENTRE = 0.2
# A principal point within this share of the image's larger side of the centre with cx and cy
# exchanged, when that centre lies twice as far from the true one, is a swapped one (lenses
# put theirs within a few per cent of the centre; cx 239.5, cy 319.5 in a 640x480 image, 13 %
# and 17 % of the image off, under OFF_CENTRE, tracked 264 mm off without a word). Images
# nearer square than that are left to OFF_CENTRE: their swapped centre is a lens's own.
_SWAPPED_CENTRE = 0.03


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
        rest.pop("distortion_coefficients", None) or {"data": []}, "distortion_coefficients"
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
    ``p1``, ``p2`` are (:data:`~spacepose.core.lens.DISTORTION_MODELS`), or any model with no
    coefficient given (as :func:`~spacepose.core.lens.matrix_fields` takes it)."""
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
    values = _numbers(rest.pop("intrinsic_matrix"), "intrinsic_matrix")
    try:
        K = np.asarray(values, dtype=np.float64).reshape(3, 3).T
    except (TypeError, ValueError):
        raise InputError("intrinsic_matrix must be 9 numbers, column by column") from None
    return matrix_fields(K) | _not_given_twice(rest, _OPEN3D_GIVES, "intrinsic_matrix")


def _matrix_data(entry: object, name: str) -> list:
    """A ROS YAML matrix's numbers: ``{rows, cols, data}`` (refused when ``data`` does not hold
    ``rows x cols`` numbers) or a bare list."""
    if isinstance(entry, dict):
        if "data" not in entry:
            raise InputError(f"{name} has no data")
        rows, cols, data = entry.get("rows"), entry.get("cols"), entry["data"]
        # A list cut short (5 coefficients announced, 1 given) read as k1 alone without a word,
        # and a camera matrix announced 2 x 3 with 9 numbers as the 3 x 3 its data makes.
        sized = all(isinstance(v, int) and not isinstance(v, bool) for v in (rows, cols))
        if sized and isinstance(data, list) and rows * cols != len(data):
            raise InputError(
                f"{name} announces rows {rows} x cols {cols} = {rows * cols} numbers, "
                f"its data holds {len(data)}"
            )
        entry = data
    if not isinstance(entry, list):
        # numpy would read a lone number as a list of one (distortion k1 = that number).
        raise InputError(f"{name} must be a list of numbers or {{rows, cols, data}}, got {entry!r}")
    return _numbers(entry, name)


def _numbers(values: object, name: str) -> object:
    """``values`` (a matrix's numbers), refused when they hold a yes/no or text: numpy read
    ``true`` as a focal length of 1 px and ``"200"`` as 200, where our own layout's fields
    refuse both."""
    if holds_boolean(values):
        raise InputError(f"{name} holds a yes/no where numbers go")
    if holds_text(values):
        raise InputError(f"{name} holds text where numbers go (a number is written unquoted)")
    return values


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
        The distortion pulls some pixel's direction to less than half its pinhole radius, or
        the principal point looks swapped or of another resolution
        (:func:`principal_point_problem`).
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
    odd = principal_point_problem(camera, width, height)
    if odd is not None:
        warnings.warn(SpaceposeWarning(odd, source), stacklevel=3)


def principal_point_problem(camera: DepthCamera, width: int, height: int) -> str | None:
    """Why ``camera``'s principal point looks wrong for a ``width`` x ``height`` image, or None:
    cx and cy swapped (each within :data:`_SWAPPED_CENTRE` of the image of the other's centre),
    or the point :data:`OFF_CENTRE` of the image or more from its centre (intrinsics of another
    resolution). A warning, not a refusal: a lens's own principal point may lie off centre."""
    centre_x, centre_y = 0.5 * (width - 1), 0.5 * (height - 1)
    near = _SWAPPED_CENTRE * max(width, height)
    # The swapped centre clear of the true one's neighbourhood, so no centred lens matches it.
    if (
        abs(width - height) / 2.0 > 2.0 * near
        and abs(camera.cx - centre_y) <= near
        and abs(camera.cy - centre_x) <= near
    ):
        return (
            f"the principal point ({camera.cx:g}, {camera.cy:g}) is the centre of a "
            f"{height}x{width} image, not of this {width}x{height} one: cx and cy swapped?"
        )
    off_x = abs(camera.cx - centre_x) / width
    off_y = abs(camera.cy - centre_y) / height
    if max(off_x, off_y) < OFF_CENTRE:
        return None
    # Intrinsics without a size were checked at the image's: giving one checks it at theirs.
    hint = "; give width and height in the intrinsics to check them" if camera.width is None else ""
    return (
        f"the principal point lies far from the image's centre: intrinsics of another "
        f"resolution? (({camera.cx:g}, {camera.cy:g}) in a {width}x{height} image{hint})"
    )


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
