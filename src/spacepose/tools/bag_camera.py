"""Camera intrinsics from a bag: a ``sensor_msgs/CameraInfo`` as a :class:`DepthCamera`, and
the CameraInfo that goes with a depth image topic.

A CameraInfo gives ROS 1 ``K``/``D`` or ROS 2 ``k``/``d``, with ``plumb_bob`` or
``rational_polynomial`` distortion (:func:`camera_from_info`). An image topic's is the one
beside it (same namespace; a compressed topic's raw image's), else the bag's only one, which is
then warned about (:func:`bag_camera`). :mod:`spacepose.tools.bag_io` reads the depth frames.
"""

from __future__ import annotations

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


def camera_from_info(msg: Any, depth_scale: float) -> DepthCamera:
    """A :class:`DepthCamera` from a ``sensor_msgs/CameraInfo`` (ROS 1 ``K``/``D`` or ROS 2
    ``k``/``d``; ``plumb_bob`` or ``rational_polynomial`` distortion).

    Raises
    ------
    FileFormatError
        Another distortion model with non-zero coefficients, or a zero focal length.
    """
    K = msg.k if hasattr(msg, "k") else msg.K
    D = msg.d if hasattr(msg, "d") else msg.D
    try:
        fields = matrix_fields(K, D, msg.distortion_model)
    except InputError as exc:
        raise FileFormatError(f"CameraInfo: {exc}") from None
    size = {"width": msg.width or None, "height": msg.height or None}
    return DepthCamera(depth_scale=depth_scale, **fields, **size)


def bag_camera(reader: Any, image_topic: str, path: Path) -> DepthCamera:
    """The camera of the first CameraInfo beside ``image_topic`` (same namespace; a compressed
    topic's raw image's), else of the bag's only one.

    Parameters
    ----------
    reader
        An open ``rosbags`` AnyReader on the bag.
    image_topic
        The depth image topic.
    path
        The bag, named in errors and warnings.

    Raises
    ------
    InputError
        No CameraInfo beside the topic and not exactly one in the bag, a CameraInfo topic
        without a message, or a CameraInfo that :func:`camera_from_info` refuses.
    ConfigError
        A camera that cannot make its images' points
        (:func:`~spacepose.tools.intrinsics_io.check_camera`).

    Warns
    -----
    SpaceposeWarning
        No CameraInfo beside the topic: the bag's only one is used. Pointed at the caller of
        :func:`~spacepose.tools.bag_io.open_bag`.
    """
    infos = [c for c in reader.connections if c.msgtype == CAMERA_INFO]
    namespace = raw_topic(image_topic).rsplit("/", 1)[0]
    beside = [c for c in infos if c.topic.rsplit("/", 1)[0] == namespace]
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
    for conn, _, raw in bag_messages(reader, chosen, path):
        try:
            camera = camera_from_info(reader.deserialize(raw, conn.msgtype), depth_scale=1.0)
        except SpaceposeError as exc:  # say which bag and topic hold the bad CameraInfo
            raise InputError(f"CameraInfo on {conn.topic}: {exc}", path) from None
        check_camera(camera, f"{path}: CameraInfo on {conn.topic}")
        return camera
    raise InputError(f"CameraInfo topic {chosen[0].topic} has no message", path)
