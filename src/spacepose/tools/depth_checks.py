"""The checks every depth map passes before it is tracked: its unit, its far plane, its lens and
odd pixels, each refused or warned of naming the map (:func:`~spacepose.tools.depth_io.depth_cloud`
calls them in order)."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from spacepose.core.cloud import MAX_ABS_COORDINATE, MM_MIN_EXTENT, PointCloud, check_scale
from spacepose.core.depth import DepthCamera
from spacepose.errors import InputError, SpaceposeWarning
from spacepose.tools.cloud_io import warn_if_not_metres, warn_if_too_near
from spacepose.tools.intrinsics_io import principal_point_problem

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


def check_depth_unit(cloud: PointCloud, source: str | Path, remedy: str) -> None:
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


def warn_if_short_focal(cloud: PointCloud, camera: DepthCamera, source: str | Path) -> bool:
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


def warn_if_odd_pixels(values: NDArray, camera: DepthCamera, source: str | Path) -> None:
    """Warn of what a map that back-projects reads oddly: depths below zero among the others
    (read as no return, as a map all below zero is refused), and, with intrinsics that give no
    size, a principal point swapped or a fifth of the image or more from its centre
    (:func:`~spacepose.tools.intrinsics_io.principal_point_problem`: intrinsics of another
    resolution put every ray off without a word; intrinsics with a size are checked once, by
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
    problem = principal_point_problem(camera, width, height)
    if problem is not None:
        warnings.warn(SpaceposeWarning(problem, source), stacklevel=4)


def refuse_z_buffer(values: NDArray, camera: DepthCamera, source: str | Path) -> None:
    """Refuse a float map that is a renderer's normalised depth buffer, not distances: every
    value in (0, 1] and at least :data:`_FAR_PLANE_SHARE` of them exactly 1, the buffer's far
    plane. An OpenGL z-buffer of the lab run at 1.2 m (near 0.1 m, far 100 m) holds 0.92–0.93
    where the target is and 1 elsewhere: read as metres it was a wall 1 m away with a shallow
    relief before it, tracked without a word. A map in metres whose far plane is 1 m says so
    with ``max_depth`` in the intrinsics, which skips this check.

    Raises
    ------
    InputError
        Naming ``source``, the values' range and the share at 1.
    """
    if camera.max_depth is not None or not np.issubdtype(np.asarray(values).dtype, np.floating):
        return
    v = np.asarray(values, dtype=np.float64)
    hit = v[np.isfinite(v) & (v > 0)]
    if len(hit) == 0 or hit.max() != 1.0:
        return
    at_one = int(np.count_nonzero(hit == 1.0))
    if at_one < _FAR_PLANE_SHARE * len(hit):
        return
    raise InputError(
        f"every value lies in ({hit.min():.3g}, 1] and {100 * at_one / len(hit):.0f} % are "
        "exactly 1: a renderer's normalised depth buffer, not distances (convert it with the "
        "render's near and far planes; a map in metres with a far plane at 1 m sets max_depth "
        "in the intrinsics)",
        source,
    )


def without_far_plane(values: NDArray, camera: DepthCamera, source: str | Path) -> DepthCamera:
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


def why_no_return(values: NDArray, camera: DepthCamera, path: str | Path) -> InputError | None:
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
    if len(returns) and np.max(returns) > MAX_ABS_COORDINATE:
        # The cloud's own error blamed the frame ("points reach |coordinate| 1.5e+303") for a
        # depth_scale of 1e300.
        scale = camera.metres_per_unit(values.dtype)
        given = "given" if camera.depth_scale is not None else "the default for its type"
        return InputError(
            f"depths reach {np.max(returns):.3g} m at a depth_scale of {scale:g} m per stored "
            f"unit ({given}), beyond {MAX_ABS_COORDINATE:.3g} m: a wrong depth_scale?",
            path,
        )
    if camera.max_depth is None or len(returns) == 0 or np.min(returns) < camera.max_depth:
        return None
    return InputError(
        f"every return lies at or beyond max_depth {camera.max_depth:g} m (the nearest at "
        f"{np.min(returns):.4g} m): a far plane in other units than metres?",
        path,
    )
