"""The lens: OpenCV's distortion model of a pinhole camera, its inverse, and its coefficients.

Distortion follows OpenCV's rational model (``k1…k6``, ``p1``, ``p2``; plumb-bob is the special
case ``k4 = k5 = k6 = 0``): an undistorted normalised point ``(x, y)`` is seen at

    x_d = x·c(r²) + 2·p1·x·y + p2·(r² + 2x²),   y_d = y·c(r²) + p1·(r² + 2y²) + 2·p2·x·y,
    c(r²) = (1 + k1·r² + k2·r⁴ + k3·r⁶) / (1 + k4·r² + k5·r⁴ + k6·r⁶),

and a pixel is ``(fx·x_d + cx, fy·y_d + cy)``. :func:`undistort` inverts this by Newton's method
per point (vectorised over the image); a point whose inverse does not converge is NaN, a pixel
:mod:`spacepose.core.depth` then reads as no return. :func:`matrix_fields` reads a camera matrix
and OpenCV's distortion coefficients, as ROS ``CameraInfo`` and calibration files hold them.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike, NDArray

from spacepose.errors import InputError

if TYPE_CHECKING:
    from spacepose.core.depth import DepthCamera

# Newton's method on the distortion model: iterations, and the residual (normalised image units,
# about 1e-6 pixel for a 500-pixel focal length) below which a pixel's inverse counts as found.
_NEWTON_ITERATIONS = 50
_NEWTON_TOLERANCE = 1e-12
_ACCEPT_RESIDUAL = 1e-9

# OpenCV's distortion coefficients in their order (plumb-bob gives the first five).
_OPENCV_DISTORTION = ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6")
#: ROS's names of the distortion models whose coefficients those are.
DISTORTION_MODELS = ("plumb_bob", "rational_polynomial")


def check_distortion_model(model: str | None, has_coefficients: bool) -> None:
    """Refuse a distortion model other than :data:`DISTORTION_MODELS` (or none) that comes
    with coefficients: they would be read as another model's.

    Raises
    ------
    InputError
        Naming the model and the supported ones.
    """
    if has_coefficients and model not in (None, *DISTORTION_MODELS):
        supported = ", ".join(DISTORTION_MODELS)
        raise InputError(f"distortion model {model!r} is not supported ({supported})")


def matrix_fields(
    K: ArrayLike, D: ArrayLike = (), distortion_model: str | None = None
) -> dict[str, float]:
    """The :class:`~spacepose.core.depth.DepthCamera` fields of a camera matrix and OpenCV
    distortion coefficients, as ROS ``CameraInfo`` and calibration files hold them.

    Parameters
    ----------
    K
        The 3×3 camera matrix ``[[fx, 0, cx], [0, fy, cy], [0, 0, 1]]``, nested or 9 numbers
        row by row.
    D
        Distortion coefficients in OpenCV's order ``k1, k2, p1, p2[, k3[, k4, k5, k6]]``.
    distortion_model
        ROS's name of the model (``plumb_bob`` or ``rational_polynomial``); another name is
        accepted only with every coefficient zero.

    Returns
    -------
    dict
        ``fx, fy, cx, cy`` and the non-zero distortion coefficients.

    Raises
    ------
    InputError
        ``K`` not 9 finite numbers, a zero focal length, a skew or bottom row this model does
        not have, more than 8 coefficients, or non-zero coefficients of another model.
    """
    try:
        k = np.asarray(K, dtype=np.float64).ravel()
        d = np.asarray(D, dtype=np.float64).ravel()
    except (TypeError, ValueError):
        raise InputError("the camera matrix and distortion must be numbers") from None
    if k.size != 9:
        raise InputError(f"a camera matrix needs 9 numbers, got {k.size}")
    if not np.all(np.isfinite(k)):
        raise InputError(f"the camera matrix holds non-finite numbers: {k.tolist()}")
    if k[0] <= 0 or k[4] <= 0:
        raise InputError(f"the camera matrix has no focal length (fx {k[0]:g}, fy {k[4]:g})")
    # A skewed or projective matrix is not a pinhole with square pixel axes.
    if k[1] != 0 or k[3] != 0 or np.any(k[6:] != (0.0, 0.0, 1.0)):
        raise InputError("the camera matrix must be [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]")
    if d.size > len(_OPENCV_DISTORTION):
        raise InputError(f"expected at most 8 distortion coefficients, got {d.size}")
    if not np.all(np.isfinite(d)):
        # A YAML null reads as NaN.
        raise InputError(f"the distortion coefficients hold non-finite numbers: {d.tolist()}")
    check_distortion_model(distortion_model, bool(np.any(d)))
    fields = {"fx": k[0], "fy": k[4], "cx": k[2], "cy": k[5]}
    return fields | {n: float(v) for n, v in zip(_OPENCV_DISTORTION, d, strict=False) if v}


def _radial(camera: DepthCamera, r2: NDArray) -> tuple[NDArray, NDArray]:
    """The radial factor ``c(r²)`` of the distortion model and its derivative ``dc/d(r²)``."""
    c = camera
    num = 1 + r2 * (c.k1 + r2 * (c.k2 + r2 * c.k3))
    den = 1 + r2 * (c.k4 + r2 * (c.k5 + r2 * c.k6))
    dnum = c.k1 + r2 * (2 * c.k2 + 3 * c.k3 * r2)
    dden = c.k4 + r2 * (2 * c.k5 + 3 * c.k6 * r2)
    return num / den, (dnum * den - num * dden) / (den * den)


def distort(camera: DepthCamera, x: ArrayLike, y: ArrayLike) -> tuple[NDArray, NDArray]:
    """Apply the distortion model to undistorted normalised image coordinates.

    Parameters
    ----------
    camera
        The camera.
    x, y
        Undistorted normalised coordinates (any equal shapes), sensor frame ``X/Z``, ``Y/Z``.

    Returns
    -------
    x_d, y_d
        Distorted normalised coordinates, same shape.

    Raises
    ------
    InputError
        ``x`` and ``y`` have different shapes (numpy's broadcast error before).
    """
    x, y = _coordinates("distort", "x", x, "y", y)
    p1, p2 = camera.p1, camera.p2
    r2 = x * x + y * y
    radial, _ = _radial(camera, r2)
    xd = x * radial + 2 * p1 * x * y + p2 * (r2 + 2 * x * x)
    yd = y * radial + p1 * (r2 + 2 * y * y) + 2 * p2 * x * y
    return xd, yd


def undistort(camera: DepthCamera, xd: ArrayLike, yd: ArrayLike) -> tuple[NDArray, NDArray]:
    """Invert :func:`distort` by Newton's method (analytic 2×2 Jacobian), element-wise.

    Parameters
    ----------
    camera
        The camera.
    xd, yd
        Distorted normalised coordinates (equal shapes).

    Returns
    -------
    x, y
        Undistorted normalised coordinates; NaN where the inverse was not found to 1e-9
        (normalised units), e.g. beyond the fold of a strong barrel distortion.

    Raises
    ------
    InputError
        ``xd`` and ``yd`` have different shapes.
    """
    xd, yd = _coordinates("undistort", "xd", xd, "yd", yd)
    p1, p2 = camera.p1, camera.p2
    x, y = xd.copy(), yd.copy()
    # Where the inverse fails the iterates overflow or divide by zero: they end as NaN, the
    # documented result, not as warnings.
    with np.errstate(all="ignore"):
        for _ in range(_NEWTON_ITERATIONS):
            fx_, fy_ = distort(camera, x, y)
            radial, dradial = _radial(camera, x * x + y * y)
            j11 = radial + 2 * x * x * dradial + 2 * p1 * y + 6 * p2 * x
            j12 = 2 * x * y * dradial + 2 * p1 * x + 2 * p2 * y  # the Jacobian is symmetric
            j22 = radial + 2 * y * y * dradial + 6 * p1 * y + 2 * p2 * x
            det = j11 * j22 - j12 * j12
            step_x = (j22 * (fx_ - xd) - j12 * (fy_ - yd)) / det
            step_y = (j11 * (fy_ - yd) - j12 * (fx_ - xd)) / det
            x, y = x - step_x, y - step_y
            if np.nanmax(np.abs(step_x) + np.abs(step_y), initial=0.0) <= _NEWTON_TOLERANCE:
                break
        xr, yr = distort(camera, x, y)
        bad = ~(np.hypot(xr - xd, yr - yd) <= _ACCEPT_RESIDUAL)
    return np.where(bad, np.nan, x), np.where(bad, np.nan, y)


def _coordinates(
    caller: str, x_name: str, x: ArrayLike, y_name: str, y: ArrayLike
) -> tuple[NDArray, NDArray]:
    """``x`` and ``y`` as float arrays of one shape; InputError naming both shapes otherwise."""
    xa, ya = np.asarray(x, dtype=np.float64), np.asarray(y, dtype=np.float64)
    if xa.shape != ya.shape:
        raise InputError(
            f"{caller}: {x_name} and {y_name} must have the same shape, got {xa.shape} and "
            f"{ya.shape}"
        )
    return xa, ya
