"""Camera intrinsics from a bag: a ``sensor_msgs/CameraInfo`` as a :class:`DepthCamera`, and
the CameraInfo that goes with a depth image topic.

A CameraInfo gives ROS 1 ``K``/``D`` or ROS 2 ``k``/``d``, with ``plumb_bob`` or
``rational_polynomial`` distortion, for the full-resolution sensor; its ``binning_x``,
``binning_y`` and ``roi`` say how the image was cut from it and binned, and are applied
(:func:`camera_from_info`). An image topic's is the one beside it (same namespace; a
compressed topic's raw image's), else the bag's only one, which is then warned about
(:func:`bag_camera`); intrinsics given beside it must agree with it. :mod:`spacepose.tools.bag_io`
reads the depth frames.
"""

from __future__ import annotations

import math
import warnings
from pathlib import Path
from typing import Any

from spacepose.core.depth import DepthCamera
from spacepose.core.lens import matrix_fields
from spacepose.errors import FileFormatError, InputError, SpaceposeError, SpaceposeWarning
from spacepose.tools.bag_messages import bag_messages
from spacepose.tools.intrinsics_io import check_camera
from spacepose.tools.ros_depth import raw_topic

CAMERA_INFO = "sensor_msgs/msg/CameraInfo"
# The fields given intrinsics and a CameraInfo must agree on: the lens (the size is compared
# when both give one). The rest (depth_scale, depth_kind, max_depth) only a file gives.
_LENS_FIELDS = ("fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4", "k5", "k6", "p1", "p2")
# Relative difference below which two calibrations' numbers are one (a YAML file rounding
# the bag's float64 K to 10 digits).
_SAME = 1e-9


def camera_from_info(msg: Any, depth_scale: float | None = None) -> DepthCamera:
    """A :class:`DepthCamera` from a ``sensor_msgs/CameraInfo`` (ROS 1 ``K``/``D`` or ROS 2
    ``k``/``d``; ``plumb_bob`` or ``rational_polynomial`` distortion), for the image as sent.

    Under the ROS convention (``sensor_msgs/CameraInfo``, ``image_geometry``) ``K``, ``D``,
    ``width`` and ``height`` describe the full-resolution sensor, and the image is its ``roi``
    (all zero: the whole sensor) binned by ``binning_x`` x ``binning_y`` (0 or 1: none):
    ``fx' = fx / binning_x``, ``cx' = (cx - roi.x_offset) / binning_x`` (likewise y), the size
    the ROI's (or the sensor's) divided by the binning. The distortion, in normalised
    coordinates, stays. ``depth_scale`` None: the image's encoding gives it.

    Raises
    ------
    FileFormatError
        Another distortion model with non-zero coefficients, a zero focal length, or a ROI
        reaching past the sensor.
    """
    K = msg.k if hasattr(msg, "k") else msg.K
    D = msg.d if hasattr(msg, "d") else msg.D
    try:
        fields = matrix_fields(K, D, msg.distortion_model)
    except InputError as exc:
        raise FileFormatError(f"CameraInfo: {exc}") from None
    bin_x, bin_y = info_binning(msg)
    x0, y0, width, height = _roi(msg)
    if msg.width and msg.height and (x0 + width > msg.width or y0 + height > msg.height):
        raise FileFormatError(
            f"roi {width}x{height} at ({x0}, {y0}) reaches past the {msg.width}x{msg.height} sensor"
        )
    # image_geometry's PinholeCameraModel formulas, which calibrated drivers follow.
    fields |= {
        "fx": fields["fx"] / bin_x,
        "fy": fields["fy"] / bin_y,
        "cx": (fields["cx"] - x0) / bin_x,
        "cy": (fields["cy"] - y0) / bin_y,
    }
    size = {"width": width // bin_x or None, "height": height // bin_y or None}
    return DepthCamera(depth_scale=depth_scale, **fields, **size)


def info_binning(msg: Any) -> tuple[int, int]:
    """A CameraInfo's ``binning_x``, ``binning_y`` (0, "no binning" in ROS, read as 1)."""
    return max(int(getattr(msg, "binning_x", 0)), 1), max(int(getattr(msg, "binning_y", 0)), 1)


def _roi(msg: Any) -> tuple[int, int, int, int]:
    """A CameraInfo's ROI as x, y offsets, width, height: the whole sensor when all zero."""
    roi = getattr(msg, "roi", None)
    if roi is None or not (roi.x_offset or roi.y_offset or roi.width or roi.height):
        return 0, 0, msg.width, msg.height
    return roi.x_offset, roi.y_offset, roi.width, roi.height


def _reshaping(msg: Any) -> str:
    """What a CameraInfo's binning and ROI did to its camera, said in a refusal ("" if none)."""
    bin_x, bin_y = info_binning(msg)
    x0, y0, width, height = _roi(msg)
    said = [f"binning {bin_x}x{bin_y}"] if (bin_x, bin_y) != (1, 1) else []
    if (x0, y0, width, height) != (0, 0, msg.width, msg.height):
        said.append(f"roi {width}x{height} at ({x0}, {y0})")
    return f" ({' and '.join(said)} applied)" if said else ""


def bag_camera(
    reader: Any,
    image_topic: str,
    path: Path,
    given: DepthCamera | None = None,
    intrinsics: str | Path | None = None,
) -> DepthCamera:
    """The camera of the first CameraInfo beside ``image_topic`` (same namespace; a compressed
    topic's raw image's), else of the bag's only one; with ``given`` intrinsics, those,
    checked against the CameraInfo beside the topic (:func:`agreed_camera`).

    Parameters
    ----------
    reader
        An open ``rosbags`` AnyReader on the bag.
    image_topic
        The depth image topic.
    path
        The bag, named in errors and warnings.
    given
        Intrinsics given for the topic (an intrinsics file), or None. They stand alone when
        the bag holds no usable CameraInfo beside the topic (none, one without a message or
        one that cannot be read: an uncalibrated driver's zero ``K``), or only another
        namespace's (another camera's, perhaps).
    intrinsics
        The file ``given`` was read from, named in errors.

    Raises
    ------
    InputError
        Without ``given``: no CameraInfo beside the topic and not exactly one in the bag, a
        CameraInfo topic without a message, or a CameraInfo that :func:`camera_from_info`
        refuses. With it: a CameraInfo beside the topic that differs (:func:`agreed_camera`).
    ConfigError
        A camera that cannot make its images' points
        (:func:`~spacepose.tools.intrinsics_io.check_camera`).

    Warns
    -----
    SpaceposeWarning
        No CameraInfo beside the topic and no intrinsics given: the bag's only one is used.
        Pointed at the caller of :func:`~spacepose.tools.bag_io.open_bag`.
    """
    infos = [c for c in reader.connections if c.msgtype == CAMERA_INFO]
    namespace = raw_topic(image_topic).rsplit("/", 1)[0]
    beside = [c for c in infos if c.topic.rsplit("/", 1)[0] == namespace]
    if given is not None:
        if len({c.topic for c in beside}) != 1:  # none, or several: the file tells
            return given
        try:
            own, reshaped = _first_camera(reader, beside, path)
        except SpaceposeError:  # unreadable or uncalibrated: what the file was given for
            return given
        return agreed_camera(given, own, intrinsics, beside[0].topic + reshaped, path)
    chosen = beside or infos
    if not beside and len({c.topic for c in infos}) == 1:
        # The bag's only CameraInfo may be another camera's (a RealSense bag with the colour
        # camera's alone): used, and said.
        warnings.warn(
            SpaceposeWarning(
                f"no CameraInfo beside {raw_topic(image_topic)}; using {infos[0].topic} (give "
                "--intrinsics if that is another camera's)",
                path,
            ),
            stacklevel=3,
        )
    if len({c.topic for c in chosen}) != 1:
        found = ", ".join(sorted({c.topic for c in infos})) or "none"
        raise InputError(
            f"cannot tell the CameraInfo of {image_topic} (CameraInfo topics: {found}); "
            "give an intrinsics file",
            path,
        )
    return _first_camera(reader, chosen, path)[0]


def _first_camera(reader: Any, connections: list[Any], path: Path) -> tuple[DepthCamera, str]:
    """The checked camera of the first CameraInfo on ``connections`` (one topic), and what
    its binning and ROI did (:func:`_reshaping`)."""
    for conn, _, raw in bag_messages(reader, connections, path):
        try:
            msg = reader.deserialize(raw, conn.msgtype)
            camera = camera_from_info(msg)
        except SpaceposeError as exc:  # say which bag and topic hold the bad CameraInfo
            raise InputError(f"CameraInfo on {conn.topic}: {exc}", path) from None
        check_camera(camera, f"{path}: CameraInfo on {conn.topic}")
        return camera, _reshaping(msg)
    raise InputError(f"CameraInfo topic {connections[0].topic} has no message", path)


def agreed_camera(
    given: DepthCamera, own: DepthCamera, intrinsics: str | Path | None, where: str, path: Path
) -> DepthCamera:
    """``given`` intrinsics, sized as the bag's CameraInfo ``own`` when they give no size,
    refused unless they describe the same lens.

    As a depth folder's own intrinsics file beside ``--intrinsics``: the given file won
    without a word, the calibration recorded with the images ignored (another camera's fx
    tracked ``ok`` at 5 sigma). ``depth_scale``, ``depth_kind`` and ``max_depth``, which a
    CameraInfo does not hold, are the given file's.

    Parameters
    ----------
    given, own
        The given intrinsics and the CameraInfo's camera.
    intrinsics
        The file ``given`` was read from (None if unknown), and ``where`` the CameraInfo's
        topic (with what its binning and ROI did), named in the refusal.
    path
        The bag.

    Raises
    ------
    InputError
        The camera matrix, the distortion or the size differ: one line naming both.
    """
    differ = [
        f"{name} {getattr(given, name):.10g} vs {getattr(own, name):.10g}"
        for name in _LENS_FIELDS
        if not math.isclose(getattr(given, name), getattr(own, name), rel_tol=_SAME, abs_tol=_SAME)
    ]
    for name in ("width", "height"):
        ours, theirs = getattr(given, name), getattr(own, name)
        if ours is not None and theirs is not None and ours != theirs:
            differ.append(f"{name} {ours} vs {theirs}")
    if differ:
        named = "--intrinsics" if intrinsics is None else f"--intrinsics {intrinsics}"
        listed = ", ".join(differ[:3]) + (", ..." if len(differ) > 3 else "")
        raise InputError(
            f"{named} and the bag's CameraInfo on {where} differ ({listed}): keep one (leave "
            "out --intrinsics to use the bag's)",
            path,
        )
    size = {k: getattr(own, k) for k in ("width", "height") if getattr(given, k) is None}
    return given.model_copy(update=size) if size else given
