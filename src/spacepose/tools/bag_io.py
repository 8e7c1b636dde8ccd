"""ROS 1 and ROS 2 bags as frames, through ``rosbags`` (no ROS installation needed).

A bag is a ``.bag`` file (ROS 1) or a ROS 2 bag folder (``metadata.yaml`` with its ``.db3`` or
``.mcap`` file; the storage file itself is accepted too). One topic gives the frames:

- ``sensor_msgs/PointCloud2`` (:mod:`spacepose.tools.ros_pointcloud`): the ``x``, ``y``, ``z``
  fields, at any offset, of any numeric datatype, either byte order, with row padding; NaN
  points (``is_dense`` false) are dropped;
- ``sensor_msgs/Image`` depth (``16UC1``/``mono16`` in millimetres, ``32FC1`` in metres) or
  ``sensor_msgs/CompressedImage`` depth (:mod:`spacepose.tools.ros_depth`), back-projected with
  the intrinsics of the bag's ``sensor_msgs/CameraInfo`` (the topic beside the raw image's,
  else the bag's only one; its first message: :mod:`spacepose.tools.bag_camera`) or of an
  intrinsics file. A compressed topic whose first message is no depth map (a JPEG colour
  stream) is no frame topic.

A frame's time is its header stamp (seconds), or the bag's record time when the topic's first
messages are all stamped zero (a driver that leaves stamps unset: :mod:`spacepose.tools.bag_clock`;
said with a warning). An explicit ``depth_scale`` of given intrinsics wins over the encoding's.
A message that cannot be decoded becomes a frame without a cloud and the reason why; so does
every message from a corrupt stretch of the bag on (a chunk that does not decompress ends what
can be read), with a NaN time.
"""

from __future__ import annotations

import struct
import warnings
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from spacepose.core.cloud import PointCloud
from spacepose.core.depth import DepthCamera
from spacepose.errors import FileFormatError, InputError, SpaceposeWarning
from spacepose.tools.bag_camera import bag_camera
from spacepose.tools.bag_clock import stamp_seconds, topic_clock, warn_record_times
from spacepose.tools.bag_messages import bag_messages
from spacepose.tools.cloud_io import warn_if_not_metres
from spacepose.tools.depth_io import depth_cloud
from spacepose.tools.frames import FrameInput, warn_if_kilometres
from spacepose.tools.ros_depth import COMPRESSED_IMAGE, IMAGE, depth_values, is_depth_format
from spacepose.tools.ros_pointcloud import POINTCLOUD2, pointcloud2_points

BAG_SUFFIXES: tuple[str, ...] = (".bag", ".db3", ".mcap")
# The first line of every ROS 1 bag (format 2.0, the only one rosbags reads).
_ROSBAG1_MAGIC = b"#ROSBAG V2.0\n"


def is_bag(path: str | Path) -> bool:
    """Whether ``path`` is a ROS 1 bag file, a ROS 2 bag folder or a ROS 2 storage file."""
    path = Path(path)
    if path.is_dir():
        return (path / "metadata.yaml").is_file()
    return path.is_file() and path.suffix.lower() in BAG_SUFFIXES


def _bag_root(path: Path) -> Path:
    """What ``AnyReader`` opens: the ``.bag`` file, or the ROS 2 folder of a storage file."""
    if path.suffix.lower() in (".db3", ".mcap") and (path.parent / "metadata.yaml").is_file():
        return path.parent
    return path


def _not_a_bag(root: Path) -> str | None:
    """Why ``root`` is no bag at all, before ``rosbags`` words it (a random file named .bag
    gave "'utf-8' codec can't decode byte 0x9d", an empty metadata.yaml "'NoneType' object is
    not subscriptable"), or None."""
    try:
        if root.is_dir():
            if not (root / "metadata.yaml").read_text(errors="replace").strip():
                return "not a ROS 2 bag: its metadata.yaml is empty"
            return None
        if root.suffix.lower() == ".bag" and root.stat().st_size > 0:
            with root.open("rb") as fh:
                head = fh.read(len(_ROSBAG1_MAGIC))
            if head != _ROSBAG1_MAGIC:
                return f"not a ROS 1 bag: it begins with {head[:8]!r}, not {_ROSBAG1_MAGIC!r}"
    except OSError:
        return None  # unreadable: the reader's own error says so
    return None


@contextmanager
def _open_reader(path: Path) -> Iterator[Any]:
    """An open ``rosbags`` AnyReader on the bag, closed on exit."""
    from rosbags.highlevel import AnyReader, AnyReaderError

    root = _bag_root(path)
    problem = _not_a_bag(root)
    if problem is not None:
        raise FileFormatError(problem, path)
    try:
        reader = AnyReader([root])
        reader.open()
    except (AnyReaderError, OSError, ValueError, KeyError) as exc:
        raise FileFormatError(f"cannot open the bag: {exc}", path) from None
    except (TypeError, MemoryError):
        # rosbags' own slips on a damaged MCAP: an end right after its magic bytes (ord() of
        # nothing), a record length of 2**62 allocated as it stands; each a traceback.
        problem = "truncated or corrupt (cut short, or a record longer than the file)"
        raise FileFormatError(f"cannot open the bag: {problem}", path) from None
    try:
        yield reader
    finally:
        reader.close()


@dataclass(frozen=True)
class BagFrames:
    """The frames of one bag topic (read lazily, in record order).

    Attributes
    ----------
    path
        The bag.
    topic, msgtype
        The frame topic and its message type.
    count
        Number of messages (frames) on the topic, as the bag's index or metadata counts them
        (every message is read, and a count that differs is warned about).
    camera
        Intrinsics for a depth Image topic (None for PointCloud2); its ``depth_scale`` None
        (a CameraInfo's) takes each image encoding's.
    clock
        The largest of the topic's first header stamps (s); None when they are all zero, and
        the frame times are then the record times
        (:func:`~spacepose.tools.bag_clock.topic_clock`).
    """

    path: Path
    topic: str
    msgtype: str
    count: int
    camera: DepthCamera | None = None
    clock: float | None = 0.0
    model_path: Path | None = None

    def __len__(self) -> int:
        return self.count

    def __iter__(self) -> Iterator[FrameInput]:
        from rosbags.highlevel import AnyReaderError
        from rosbags.serde import SerdeError

        index = 0
        with _open_reader(self.path) as reader:
            connections = [c for c in reader.connections if c.topic == self.topic]
            messages = reader.messages(connections)
            while True:
                try:
                    conn, time_ns, raw = next(messages)
                except StopIteration:
                    break
                except Exception as exc:  # whatever rosbags meets in a bad chunk
                    # A corrupt chunk ends the stream (a compressed block that does not
                    # decompress, a damaged record): the frames from here on cannot be read.
                    problem = " ".join(str(exc).split()) or type(exc).__name__
                    error = f"cannot read the bag from message #{index} on: {problem}"
                    for k in range(index, max(self.count, index + 1)):
                        source = f"{self.path}:{self.topic}#{k}"
                        yield FrameInput(k, float("nan"), None, source, error)
                    return
                source = f"{self.path}:{self.topic}#{index}"
                cloud, error, timestamp = None, None, time_ns * 1e-9
                try:
                    msg = reader.deserialize(raw, conn.msgtype)
                    timestamp = stamp_seconds(msg, time_ns, self.clock)
                    cloud = self._cloud(msg, source)
                    if self.msgtype == POINTCLOUD2:
                        # As a folder's cloud files, each frame: a driver in millimetres or
                        # kilometres, or a corrupt message's 1e9 m (the first alone was checked).
                        warn_if_not_metres(cloud, source)
                        warn_if_kilometres(cloud, source)
                except InputError as exc:
                    error = exc.reason
                except (
                    AnyReaderError,  # rosbags' own wrapping of a message it cannot decode
                    SerdeError,
                    ValueError,
                    IndexError,
                    TypeError,
                    struct.error,
                ) as exc:
                    error = f"cannot decode the message: {exc}"
                yield FrameInput(index, timestamp, cloud, source, error)
                index += 1
        if index != self.count:  # a crashed recording's metadata.yaml, say: all were read
            warnings.warn(
                SpaceposeWarning(
                    f"the bag counts {self.count} messages on {self.topic} and holds {index}: "
                    f"all {index} read",
                    self.path,
                ),
                stacklevel=2,
            )

    def _cloud(self, msg: Any, source: str) -> PointCloud:
        if self.msgtype == POINTCLOUD2:
            return PointCloud(pointcloud2_points(msg), source=source)
        values, scale = depth_values(msg, self.msgtype, source)
        camera = self.camera
        assert camera is not None  # open_bag gives every Image topic a camera
        encoding = msg.format if self.msgtype == COMPRESSED_IMAGE else msg.encoding
        remedy = f"the {encoding} encoding is {scale:g} m per unit"
        if camera.depth_scale is None:
            camera = camera.model_copy(update={"depth_scale": scale})
        else:
            # The user's, as for a folder: a driver in quarter-millimetres was read as the
            # encoding's millimetres, 4 times too far, ok.
            remedy = (
                f"check depth_scale in the intrinsics ({camera.depth_scale:g} m per stored "
                f"unit; {remedy})"
            )
        # Checked as a depth folder's images are: the lens at the image's size, the units.
        return depth_cloud(values, camera, source, remedy)


def open_bag(
    path: str | Path,
    topic: str | None = None,
    camera: DepthCamera | None = None,
    intrinsics: str | Path | None = None,
) -> BagFrames:
    """Open the frames of a bag: the given topic, or its only PointCloud2 / Image topic.

    Parameters
    ----------
    path
        ROS 1 ``.bag`` file or ROS 2 bag folder.
    topic
        The frame topic; needed when the bag has several PointCloud2 / Image topics.
    camera
        Intrinsics for a depth Image topic: refused when the CameraInfo beside the topic
        differs (:func:`~spacepose.tools.bag_camera.agreed_camera`), else used, sized as it;
        their ``depth_scale``, if given, wins over the image encoding's.
    intrinsics
        The file ``camera`` was read from, named in errors.

    Raises
    ------
    InputError
        The topic is missing or not a frame type, several frame topics and none chosen, no
        frame topic at all, an Image topic without CameraInfo or intrinsics, intrinsics that
        differ from the CameraInfo beside the topic, or intrinsics for a PointCloud2 topic.
        The message lists the bag's frame topics.
    FileFormatError
        The bag cannot be opened.

    Warns
    -----
    SpaceposeWarning
        The topic's first messages carry no header stamp: the record times time every frame.
    """
    path = Path(path)
    with _open_reader(path) as reader:
        types = {c.topic: c.msgtype for c in reader.connections}
        candidates = {t: m for t, m in types.items() if m in (POINTCLOUD2, IMAGE, COMPRESSED_IMAGE)}
        # A compressed colour stream (JPEG) beside the depth one is no frame topic.
        pictures = _not_depth(reader, [t for t, m in candidates.items() if m == COMPRESSED_IMAGE])
        candidates = {t: m for t, m in candidates.items() if t not in pictures}
        listing = ", ".join(f"{t} ({m.rsplit('/', 1)[-1]})" for t, m in sorted(candidates.items()))
        listing = listing or "none"
        if topic is None:
            if not candidates:  # nothing to choose with --topic: say what the bag holds
                held = ", ".join(f"{t} ({m.rsplit('/', 1)[-1]})" for t, m in sorted(types.items()))
                left = "".join(
                    f"; {t} left out: its first message's format {form!r} names no depth encoding"
                    for t, form in sorted(pictures.items())
                )
                raise InputError(
                    f"no PointCloud2/Image topic: the bag holds no frame (its topics: "
                    f"{held or 'none'}){left}",
                    path,
                )
            if len(candidates) != 1:
                raise InputError(
                    f"{len(candidates)} PointCloud2/Image topics, choose one with --topic: "
                    f"{listing}",
                    path,
                )
            topic = next(iter(candidates))
        elif topic in pictures:
            raise InputError(
                f"topic {topic} carries {pictures[topic]!r} images, not depth maps; frame "
                f"topics: {listing}",
                path,
            )
        elif topic not in candidates:
            what = "not in the bag" if topic not in types else f"a {types[topic]}"
            raise InputError(f"topic {topic} is {what}; frame topics: {listing}", path)
        connections = [c for c in reader.connections if c.topic == topic]
        count = sum(c.msgcount for c in connections)
        if count <= 0:  # a metadata.yaml may count none (a crashed recording): count them
            count = sum(1 for _ in bag_messages(reader, connections, path))
        if count == 0:  # a topic declared but never published
            raise InputError(f"no messages on {topic}: the bag holds no frame", path)
        if candidates[topic] == POINTCLOUD2 and camera is not None:
            # Its points are metres already: intrinsics given for it are a mistake, not a no-op.
            raise InputError(
                f"intrinsics apply to depth images, and {topic} is a PointCloud2 (points in "
                "metres): leave out --intrinsics, or choose an Image topic",
                path,
            )
        if candidates[topic] != POINTCLOUD2:
            camera = bag_camera(reader, topic, path, camera, intrinsics)
        clock = topic_clock(reader, connections)
        if clock is None:
            warn_record_times(topic, path)
    return BagFrames(path, topic, candidates[topic], count, camera, clock=clock)


def _not_depth(reader: Any, topics: list[str]) -> dict[str, str]:
    """The format of each compressed image topic whose first message holds no depth map."""
    found = {}
    for topic in topics:
        connections = [c for c in reader.connections if c.topic == topic]
        try:
            first = next(iter(reader.messages(connections)), None)
            form = None if first is None else reader.deserialize(first[2], first[0].msgtype).format
        except Exception:  # a damaged message or chunk: the topic's frames will say why
            continue
        if form is not None and not is_depth_format(form):
            found[topic] = form
    return found
