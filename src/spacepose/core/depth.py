"""Depth images to points: the pinhole camera with OpenCV's distortion model, back-projection.

A depth image holds, per pixel ``(u, v)`` (column, row; pixel centres at integer coordinates),
the depth ``z`` along the boresight in stored units (``z = value · depth_scale`` metres), or with
``depth_kind = "range"`` the distance along the pixel's ray, as flash LiDARs and some renderers
write it. A zero, negative or non-finite value is "no return", and so is an integer image's
largest value (65535 in 16 bits: the no-return or saturation code of many cameras and a
renderer's empty background) and any depth at or beyond ``max_depth``. The sensor frame is z along
the boresight, x right, y down, so a pixel's point is ``(x_n·z, y_n·z, z)`` with ``(x_n, y_n)``
the undistorted normalised image coordinates of the pixel; a range ``r`` gives
``z = r / √(1 + x_n² + y_n²)``.

The lens distortion and its inverse are :mod:`spacepose.core.lens`'s: back-projection inverts
the distortion per pixel, and a pixel whose inverse does not converge is no return.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import Field

from spacepose.core.cloud import PointCloud, as_points
from spacepose.core.config import StageConfig, stage_config
from spacepose.core.lens import distort, undistort
from spacepose.errors import InputError

# Metres per stored value of an integer depth image whose scale is not given.
MILLIMETRE = 0.001
# Share of an image's pixels whose distortion may fail to invert before the camera is refused.
_MOST_PIXELS = 0.5


class DepthCamera(StageConfig):
    """Intrinsics of a depth camera (pinhole, OpenCV distortion) and the unit of its values.

    ``depth_scale`` is metres per stored unit: 0.001 for millimetres (ROS ``16UC1``), 1 for
    float images in metres (ROS ``32FC1``), 0.0002 for TUM RGB-D's 5000 units per metre. Left
    out, it follows the image's type (:meth:`metres_per_unit`): integer images are read as
    millimetres, float ones (a renderer's EXR, a float TIFF) as metres.
    ``width`` and ``height``, when given, are checked against every image. ``depth_kind`` says
    whether a value is the depth along the boresight (``z``: OpenCV, ROS, Kinect-style cameras)
    or the range along the pixel's ray (``range``); read as the wrong kind, a flat wall bends.
    """

    # Below a pixel a pinhole sees more than a half-space across two pixels; above 1e6 pixels
    # a 1280-pixel image spans 0.07°, a telescope's view: either is a unit mistake (fx 1e300
    # put every point at one place, 1e-300 overflowed the coordinates).
    fx: float = Field(ge=1, le=1e6, description="Focal length along x (columns), pixels.")
    fy: float = Field(ge=1, le=1e6, description="Focal length along y (rows), pixels.")
    cx: float = Field(description="Principal point, column (pixel centres at integers).")
    cy: float = Field(description="Principal point, row.")
    depth_scale: float | None = Field(
        None,
        gt=0,
        description="Metres per stored depth unit; left out: 0.001 (integer images), 1 (float).",
    )
    k1: float = 0.0
    k2: float = 0.0
    k3: float = 0.0
    k4: float = 0.0
    k5: float = 0.0
    k6: float = 0.0
    p1: float = 0.0
    p2: float = 0.0
    width: int | None = Field(None, ge=1, description="Image columns, checked when given.")
    height: int | None = Field(None, ge=1, description="Image rows, checked when given.")
    depth_kind: Literal["z", "range"] = Field(
        "z", description="z: depth along the boresight; range: distance along the pixel's ray."
    )
    max_depth: float | None = Field(
        None, gt=0, description="Depths (m) at or beyond this are no return: a far clip plane."
    )

    def metres_per_unit(self, dtype: np.dtype) -> float:
        """Metres per stored value of an image of ``dtype``: ``depth_scale``, or, left out, the
        convention of the type (float: metres; integer: millimetres). A float map in metres
        read as millimetres tracked a scene a thousand times too small, ``ok``."""
        if self.depth_scale is not None:
            return self.depth_scale
        return 1.0 if np.issubdtype(dtype, np.floating) else MILLIMETRE

    @property
    def distorted(self) -> bool:
        """Whether any distortion coefficient is non-zero."""
        return any((self.k1, self.k2, self.k3, self.k4, self.k5, self.k6, self.p1, self.p2))


def _whole(name: str, value: int, minimum: int, source: str | None = None) -> int:
    """``value`` as an int, or an InputError unless it is a whole number >= ``minimum``."""
    try:
        whole = not isinstance(value, bool) and float(value).is_integer() and value >= minimum
    except (TypeError, ValueError, OverflowError):
        whole = False
    if not whole:
        raise InputError(f"{name} must be a whole number >= {minimum}, got {value!r}", source)
    return int(value)


def pixel_rays(camera: DepthCamera, height: int, width: int) -> NDArray[np.float64]:
    """Undistorted normalised coordinates ``(x_n, y_n)`` of every pixel, (H, W, 2).

    Read-only and cached per camera and image size: every frame of a sequence shares them.
    NaN where the distortion cannot be inverted.

    Raises
    ------
    InputError
        ``height`` or ``width`` is not a whole number >= 1 (0 gave numpy's "mean of empty
        slice" warnings, 2.5 rays of a 3-pixel row), or most pixels cannot be undistorted.
    """
    camera = stage_config(camera, DepthCamera, "camera")
    height = _whole("pixel_rays: height", height, 1)
    width = _whole("pixel_rays: width", width, 1)
    return _pixel_rays(camera, height, width)


@functools.lru_cache(maxsize=8)
def _pixel_rays(camera: DepthCamera, height: int, width: int) -> NDArray[np.float64]:
    u = (np.arange(width, dtype=np.float64) - camera.cx) / camera.fx
    v = (np.arange(height, dtype=np.float64) - camera.cy) / camera.fy
    xd, yd = np.meshgrid(u, v)
    rays = np.stack(undistort(camera, xd, yd) if camera.distorted else (xd, yd), axis=-1)
    lost = float(np.mean(np.isnan(rays[..., 0])))
    if lost > _MOST_PIXELS:
        # A lens folds its image beyond a corner at most: coefficients that fold most of it
        # are a unit or sign mistake, and every frame would come out all but empty.
        raise InputError(
            f"the camera's distortion cannot be inverted at {100 * lost:.0f} % of its "
            f"{width}x{height} pixels (k1..k6 {camera.k1:g} {camera.k2:g} {camera.k3:g} "
            f"{camera.k4:g} {camera.k5:g} {camera.k6:g}, p1 p2 {camera.p1:g} {camera.p2:g})"
        )
    rays.setflags(write=False)
    return rays


@dataclass(frozen=True, eq=False)
class OrganisedCloud:
    """Points on the pixel grid of a depth image.

    Attributes
    ----------
    points
        (H, W, 3) metres, sensor frame; NaN rows where the pixel has no return.
    valid
        (H, W) True where the pixel has a return.
    """

    points: NDArray[np.float64]
    valid: NDArray[np.bool_]

    def cloud(self, stride: int = 1, source: str | None = None) -> PointCloud:
        """The returns as a PointCloud, row-major (row, then column).

        Parameters
        ----------
        stride
            Keep every ``stride``-th row and column (organised downsampling).
        source
            Name for error messages.

        Raises
        ------
        InputError
            ``stride`` is not a whole number >= 1 (1.5 or NaN ended in a TypeError about slice
            indices), or no pixel has a return.
        """
        stride = _whole("stride", stride, 1, source)
        points = self.points[::stride, ::stride]
        valid = self.valid[::stride, ::stride]
        if not valid.any():
            raise InputError("depth image has no return (every pixel zero or invalid)", source)
        return PointCloud(points[valid], source=source)


def backproject(depth: ArrayLike, camera: DepthCamera, source: str | None = None) -> OrganisedCloud:
    """Back-project a depth image into the sensor frame.

    Parameters
    ----------
    depth
        (H, W) stored depth values (any numeric dtype); metres are ``value · depth_scale``.
        Zero, negative and non-finite values are no return, and so are an integer dtype's
        largest value and depths at or beyond ``camera.max_depth``.
    camera
        Intrinsics and depth scale.
    source
        Name for error messages.

    Returns
    -------
    OrganisedCloud
        (H, W, 3) points, sensor frame (z boresight, x right, y down).

    Raises
    ------
    InputError
        ``depth`` is not 2-D, its size differs from the camera's ``width``/``height``, or the
        principal point lies outside it.
    """
    camera = stage_config(camera, DepthCamera, "camera")
    values = np.asarray(depth)
    if values.ndim != 2 or not (
        np.issubdtype(values.dtype, np.integer) or np.issubdtype(values.dtype, np.floating)
    ):
        raise InputError(
            f"a depth image must be one numeric channel, got shape {values.shape} of "
            f"{values.dtype}",
            source,
        )
    height, width = values.shape
    if (camera.width or width, camera.height or height) != (width, height):
        raise InputError(
            f"image is {width}x{height}, the intrinsics say {camera.width}x{camera.height}", source
        )
    if not (-0.5 <= camera.cx <= width - 0.5 and -0.5 <= camera.cy <= height - 0.5):
        # Intrinsics of another resolution (or camera): every ray would be off.
        raise InputError(
            f"the principal point ({camera.cx:g}, {camera.cy:g}) lies outside the "
            f"{width}x{height} image: intrinsics of another resolution?",
            source,
        )
    z = values.astype(np.float64) * camera.metres_per_unit(values.dtype)
    try:
        rays = pixel_rays(camera, height, width)
    except InputError as exc:
        raise InputError(exc.reason, source) from None
    with np.errstate(invalid="ignore"):
        valid = (z > 0) & np.isfinite(z) & np.isfinite(rays[..., 0])
        if np.issubdtype(values.dtype, np.integer):
            valid &= values != np.iinfo(values.dtype).max
        if camera.max_depth is not None:
            valid &= z < camera.max_depth
        if camera.depth_kind == "range":
            z = z / np.sqrt(1.0 + rays[..., 0] ** 2 + rays[..., 1] ** 2)
    z = np.where(valid, z, np.nan)
    points = np.stack([rays[..., 0] * z, rays[..., 1] * z, z], axis=-1)
    return OrganisedCloud(points, valid)


def depth_to_cloud(
    depth: ArrayLike, camera: DepthCamera, stride: int = 1, source: str | None = None
) -> PointCloud:
    """One call: a depth image (H, W) to the PointCloud of its returns, sensor frame.

    See :func:`backproject` and :meth:`OrganisedCloud.cloud`.
    """
    return backproject(depth, camera, source).cloud(stride, source)


def render_depth(
    points: ArrayLike, camera: DepthCamera, height: int, width: int
) -> NDArray[np.float64]:
    """Z-buffer points into a depth image: the inverse of :func:`backproject`.

    Each point in front of the camera goes to its nearest pixel (distortion applied); where
    several land on one pixel the nearest depth wins.

    Parameters
    ----------
    points
        (N, 3) metres, sensor frame (z boresight, x right, y down).
    camera
        Intrinsics (``depth_scale`` is not used: the image is in metres).
    height, width
        Image size, pixels.

    Returns
    -------
    (H, W) depth ``z`` in metres, 0 where no point lands.

    Raises
    ------
    InputError
        Points not a finite (N, 3) array, or ``height`` / ``width`` not a whole number >= 1
        (-1 ended in numpy's 'negative dimensions', 60.5 in a TypeError, 0 gave an empty image).
    """
    camera = stage_config(camera, DepthCamera, "camera")
    height = _whole("height", height, 1)
    width = _whole("width", width, 1)
    pts = as_points(points)
    pts = pts[pts[:, 2] > 0]
    xd, yd = distort(camera, pts[:, 0] / pts[:, 2], pts[:, 1] / pts[:, 2])
    u = np.rint(camera.fx * xd + camera.cx)
    v = np.rint(camera.fy * yd + camera.cy)
    inside = (u >= 0) & (u < width) & (v >= 0) & (v < height)
    image = np.full((height, width), np.inf)
    np.minimum.at(image, (v[inside].astype(np.intp), u[inside].astype(np.intp)), pts[inside, 2])
    image[np.isinf(image)] = 0.0
    return image
