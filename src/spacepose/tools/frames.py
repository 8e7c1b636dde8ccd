"""Tracking input: frames from a run folder, a folder of point cloud files or depth images, or a
ROS bag (their outputs: :mod:`spacepose.tools.tracking_io`).

:func:`open_frames` recognises, in this order: a ROS 1 / ROS 2 bag
(:mod:`spacepose.tools.bag_io`); a run folder (written by ``spacepose simulate``, recognised by
its ``scenario.json``); a depth image folder (:mod:`spacepose.tools.depth_folder`: it holds an
intrinsics file or TUM RGB-D's ``depth.txt``, or an intrinsics file is given); any other folder
is read as one point cloud file per frame (``.ply``, ``.pcd``, ``.xyz``, ``.txt``, ``.csv``,
``.npy``, ``.npz``). Files are sorted by name, with timestamps from ``timestamps.txt`` (one
number per line) when present, else the frame index.

A frame that cannot be read (missing, zero-byte, truncated or corrupt file, an undecodable bag
message) or holds no usable point is yielded without a cloud and with the reason, so the
tracker reports it ``lost`` and the run goes on.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Protocol

import numpy as np
from numpy.typing import NDArray

from spacepose.core.cloud import PointCloud
from spacepose.core.depth import DepthCamera
from spacepose.errors import InputError, SpaceposeWarning
from spacepose.tools import depth_folder, depth_io, intrinsics_io
from spacepose.tools.cloud_io import DEPTH_SUFFIXES, read_cloud, warn_if_too_near
from spacepose.tools.text_io import check_timing, data_number, not_a_file, read_text

CLOUD_SUFFIXES: tuple[str, ...] = (".ply", ".pcd", ".xyz", ".txt", ".csv", ".npy", ".npz")
TIMESTAMPS_FILE = "timestamps.txt"
# Tables spacepose writes beside its outputs: an output written into a folder of frames is no
# frame of the next run over it.
_OWN_TABLES = (".health.csv", ".cov.csv", ".candidates.csv")
# A run folder's frames are point clouds in metres: intrinsics given for them are a mistake,
# not a no-op (as for a bag's PointCloud2 topic).
_RUN_INTRINSICS = (
    "intrinsics apply to depth images, and this is a run folder of point clouds: leave out "
    "--intrinsics"
)


@dataclass(frozen=True)
class FrameInput:
    """One input frame.

    Attributes
    ----------
    index
        Position of the frame in the sequence (0-based).
    timestamp
        Seconds.
    cloud
        The points in the sensor frame, or ``None`` when the frame holds no usable point.
    source
        The file (or bag message) the frame came from.
    error
        Why ``cloud`` is None (the read error, naming the source); None when it is not.
    """

    index: int
    timestamp: float
    cloud: PointCloud | None
    source: str
    error: str | None = None


def read_frame_cloud(path: Path) -> PointCloud:
    """One frame's point cloud file (:func:`read_cloud`), sensor frame, warned about when its
    points lie nearer the sensor than any sensor ranges
    (:func:`~spacepose.tools.cloud_io.warn_if_too_near`): a file in kilometres, an orbit
    simulator's unit, was tracked as a scene a thousandth of its size without a word."""
    cloud = read_cloud(path)
    warn_if_kilometres(cloud, path)
    return cloud


# Recordings no reader here decodes, and the way to frames that one does.
_RECORDINGS = {
    ".mkv": "an Azure Kinect recording? extract its depth track to 16-bit PNGs (Open3D's "
    "AzureKinectMKVReader, or k4arecorder's tools) with an intrinsics.yaml",
    ".pcap": "a LiDAR packet capture: convert its scans to .pcd or .ply frames with the sensor's "
    "SDK (a folder of one file a frame)",
    ".pcapng": "a LiDAR packet capture: convert its scans to .pcd or .ply frames with the "
    "sensor's SDK (a folder of one file a frame)",
    ".oni": "an OpenNI recording: export its depth frames to 16-bit PNGs with an intrinsics.yaml",
}


def warn_if_kilometres(cloud: PointCloud, source: str | Path) -> None:
    """Warn (naming ``source``) when a sensor-frame cloud's points lie nearer the sensor than
    any sensor ranges (:func:`~spacepose.tools.cloud_io.warn_if_too_near`): coordinates in
    kilometres, read as metres; or when nearly all of them lie behind its image plane
    (:func:`warn_if_behind`)."""
    warn_if_too_near(cloud, source, "sensor ranges: coordinates in kilometres? they are metres")
    warn_if_behind(cloud, source)


def warn_if_behind(cloud: PointCloud, source: str | Path) -> None:
    """Warn (naming ``source``) when 90 % or more of a sensor-frame cloud's returns lie at
    z <= 0: spacepose's sensor looks along +z (x right, y down, as OpenCV). Frames rendered in
    OpenGL's convention (looking along -z) tracked without a word, in that frame: 84° off
    the camera's. A strided sample, as for the ranges."""
    sample = cloud.points[:: max(1, len(cloud) // 4096)]
    sample = sample[sample.any(axis=1)]  # rows at the origin are no returns
    if len(sample) and np.mean(sample[:, 2] <= 0.0) >= 0.9:
        problem = (
            "nearly all returns lie behind the sensor (z <= 0); its frame looks along +z (x "
            "right, y down, as OpenCV): a cloud in another convention (OpenGL looks along -z) "
            "is tracked in that frame"
        )
        warnings.warn(SpaceposeWarning(problem, source), stacklevel=3)


class Frames(Protocol):
    """What :func:`open_frames` returns: a sized, re-iterable sequence of frames."""

    model_path: Path | None

    def __len__(self) -> int: ...

    def __iter__(self) -> Iterator[FrameInput]: ...


@dataclass(frozen=True)
class FrameSequence:
    """Frames from one file each (files are read lazily, one at a time).

    Attributes
    ----------
    paths
        One file per frame, in order.
    timestamps
        (N,) seconds, one per frame.
    model_path
        The reference model cloud of a run folder (``model.ply``), else ``None``.
    loader
        Reads one file into a PointCloud, sensor frame (default: :func:`read_frame_cloud`); any
        :class:`~spacepose.errors.InputError` it raises makes the frame lost, with the reason.
    """

    paths: tuple[Path, ...]
    timestamps: NDArray[np.float64]
    model_path: Path | None = None
    loader: Callable[[Path], PointCloud] = read_frame_cloud

    def __len__(self) -> int:
        return len(self.paths)

    def __iter__(self) -> Iterator[FrameInput]:
        for i, (path, t) in enumerate(zip(self.paths, self.timestamps, strict=True)):
            cloud, error = None, None
            try:
                cloud = self.loader(path)
            except InputError as exc:  # FileFormatError included: the frame is lost, not the run
                error = str(exc)
            yield FrameInput(i, float(t), cloud, str(path), error)


def open_frames(
    path: str | Path, intrinsics: str | Path | None = None, topic: str | None = None
) -> Frames:
    """Open a bag, a run folder, a depth image folder or a folder of cloud files (see the
    module docstring).

    Parameters
    ----------
    path
        The input.
    intrinsics
        Intrinsics file (YAML/JSON, :class:`spacepose.core.depth.DepthCamera`) for depth images;
        by default the folder's own ``intrinsics.yaml``/``.yml``/``.json`` (for a bag: its
        CameraInfo).
    topic
        The bag topic to read (bags only).

    Raises
    ------
    InputError
        The path does not exist, is not a folder or bag, holds no frame, is a run folder without
        its scenario.json or given intrinsics, a bag topic cannot be chosen, a depth folder has
        no intrinsics or intrinsics given that differ from its own file, or both a
        ``depth.txt`` and a ``timestamps.txt``, or ``timestamps.txt`` does not hold one finite
        number per frame.
    ConfigError
        The intrinsics file is invalid, or its principal point lies outside the images or its
        lens distortion folds them (:func:`~spacepose.tools.intrinsics_io.check_camera`).
    """
    from spacepose.tools.bag_io import is_bag, open_bag  # bag_io builds on this module

    root = Path(path)
    if not root.exists():
        raise InputError("does not exist", root)
    if intrinsics is not None and root.is_dir() and (root / "scenario.json").is_file():
        # Refused before the file is read: a wrong file given (a .ply) was reported as a
        # config "not UTF-8", about a file the run would never have read.
        raise InputError(_RUN_INTRINSICS, root)
    camera = None if intrinsics is None else intrinsics_io.read_intrinsics(intrinsics)
    if is_bag(root):
        if camera is not None:  # sized by the file; else checked at each image's size
            intrinsics_io.check_camera(camera, intrinsics)
        return open_bag(root, topic, camera, intrinsics)
    if topic is not None:
        raise InputError(f"--topic {topic} applies to a ROS bag, and this is not one", root)
    if not root.is_dir():
        known = _RECORDINGS.get(root.suffix.lower())
        what = f"; {known}" if known else ""
        raise InputError(f"not a folder of frames (or a run folder, or a ROS bag){what}", root)
    if (root / "scenario.json").is_file():
        return _open_run(root)
    if (root / "frames").is_dir():
        # A run folder that lost its scenario: its own files (model.ply) would be tracked as
        # the frames, and frames/ left out without a word.
        raise InputError(
            "has a frames/ folder but no scenario.json: restore the run's scenario.json, "
            "or give the frames/ folder itself",
            root,
        )
    if camera is not None or depth_folder.is_depth_folder(root):
        _check_holds_depth_images(root, given=camera is not None)
        return _open_depth_folder(root, *depth_folder.folder_camera(root, intrinsics, camera))
    stamps = _timestamps_path(root)
    paths = tuple(
        p
        for p in depth_folder.frame_entries(root, CLOUD_SUFFIXES)
        if p != stamps and not p.name.endswith(_OWN_TABLES)
    )
    if not paths and depth_folder.frame_entries(root, DEPTH_SUFFIXES):
        # Images without intrinsics: say what is missing, not that there is nothing.
        return _open_depth_folder(root, None)
    if not paths:
        storage = sorted(p.name for p in root.iterdir() if p.suffix.lower() in (".db3", ".mcap"))
        if storage:  # a ROS 2 recording that did not finish writes its metadata.yaml last
            raise InputError(
                f"holds {storage[0]} but no metadata.yaml: a ROS 2 bag whose recording did not "
                "finish? (`ros2 bag reindex` writes it)",
                root,
            )
        raise InputError(f"no frame files ({', '.join(CLOUD_SUFFIXES)}) in the folder", root)
    return FrameSequence(paths, _folder_timestamps(root, len(paths)))


def _check_holds_depth_images(root: Path, given: bool) -> None:
    """Refuse a folder read as depth images (intrinsics ``given``, or its own intrinsics file)
    whose frames are point clouds: "no depth images in the folder" did not say what made it a
    depth folder, beside the clouds the user sees.

    Raises
    ------
    InputError
        The folder holds no depth image and some point cloud files.
    """
    # TUM RGB-D's depth.txt lists images in a subfolder: the list decides, not the files here.
    if (root / depth_folder.TUM_DEPTH_LIST).is_file() or depth_folder.frame_entries(
        root, depth_folder.FOLDER_DEPTH_SUFFIXES
    ):
        return
    # Text files beside depth images are lists (TUM's rgb.txt), not clouds.
    clouds = depth_folder.frame_entries(root, (".ply", ".pcd", ".npz", ".xyz", ".csv"))
    if not clouds:
        return
    names = ", ".join(p.name for p in clouds[:2]) + (", ..." if len(clouds) > 2 else "")
    if given:
        why, remedy = "intrinsics apply to depth images", "leave out --intrinsics"
    else:
        found = intrinsics_io.find_intrinsics(root)
        name = found.name if found is not None else intrinsics_io.INTRINSICS_FILES[0]
        why = f"its {name} makes it a folder of depth images"
        remedy = f"move {name} out"
    raise InputError(f"{why}, and its frames are point clouds ({names}): {remedy}", root)


def input_files(path: str | Path, frames: Frames) -> list[Path]:
    """The files reading ``path`` through ``frames`` (:func:`open_frames`) takes from: the
    input itself when a file, each frame file, and a folder's description (its run files,
    timestamps, depth list and intrinsics; every file of a bag folder). Not all need exist.
    An output must not be one of them (:func:`~spacepose.tools.outputs.check_spares_inputs`).
    """
    from spacepose.tools.runs import GROUNDTRUTH, MODEL_CLOUD, SCENARIO, TRUTH

    root = Path(path)
    if not root.is_dir():
        return [root]
    files = [*getattr(frames, "paths", ()), *([frames.model_path] if frames.model_path else [])]
    names = (SCENARIO, GROUNDTRUTH, TRUTH, MODEL_CLOUD, "model.obj")
    files += [
        root / name
        for name in (*names, depth_folder.TUM_DEPTH_LIST, *intrinsics_io.INTRINSICS_FILES)
    ]
    files.append(_timestamps_path(root))
    if not hasattr(frames, "paths"):  # a bag folder: its metadata and storage files
        files += [p for p in root.iterdir() if p.is_file()]
    return files


def untimed_folder(path: str | Path) -> bool:
    """Whether ``path`` is a folder of frame files or depth images that does not time them (no
    ``timestamps.txt``, no TUM ``depth.txt``): its frames are then one second apart."""
    from spacepose.tools.bag_io import is_bag  # bag_io builds on this module

    root = Path(path)
    if not root.is_dir() or is_bag(root) or (root / "scenario.json").is_file():
        return False
    stamps = _timestamps_path(root)
    listed = (root / depth_folder.TUM_DEPTH_LIST).is_file()
    return not (stamps.exists() or stamps.is_symlink() or listed)


def _folder_timestamps(root: Path, n_frames: int) -> NDArray[np.float64]:
    """``timestamps.txt`` of a folder when present, else the frame indices."""
    stamps_path = _timestamps_path(root)
    # Not only a regular file: a folder or a broken link by that name is an error, not frame
    # indices taken without a word.
    if stamps_path.exists() or stamps_path.is_symlink():
        return read_timestamps(stamps_path, n_frames)
    return np.arange(n_frames, dtype=np.float64)


def _timestamps_path(root: Path) -> Path:
    """A folder's ``timestamps.txt``, its name in any case (``Timestamps.txt``, as a
    case-blind file system keeps it): spelt otherwise it was tracked as a frame, and the times
    replaced by frame numbers without a word. ``root / timestamps.txt`` when there is none.

    Raises
    ------
    InputError
        The folder holds two, in different cases.
    """
    found = sorted(p for p in root.iterdir() if p.name.lower() == TIMESTAMPS_FILE)
    if len(found) > 1:
        raise InputError(f"holds {' and '.join(p.name for p in found)}: keep one", root)
    return found[0] if found else root / TIMESTAMPS_FILE


def _open_depth_folder(
    root: Path, camera: DepthCamera | None, source: Path | None = None
) -> FrameSequence:
    """Depth images (sorted, or listed by ``depth.txt``) back-projected with ``camera``, read
    from ``source`` (see :func:`~spacepose.tools.depth_folder.folder_camera`), checked at their
    size (:func:`~spacepose.tools.intrinsics_io.check_camera`)."""
    if camera is None:
        for name in intrinsics_io.INTRINSICS_FILES:
            problem = not_a_file(root / name)
            if (root / name).exists() and problem is not None:
                # Found by its name, yet no file to read: said so, not "put it in the folder".
                raise InputError(f"depth images need intrinsics: {name} is {problem}", root)
        raise InputError(
            f"depth images need intrinsics: put {intrinsics_io.INTRINSICS_FILES[0]} (fx, fy, cx, "
            "cy, depth_scale) in the folder or give --intrinsics",
            root,
        )
    unit_from = None
    if (root / depth_folder.TUM_DEPTH_LIST).is_file():
        stamps = _timestamps_path(root)
        if stamps.exists():
            # Each times the frames: the list won and timestamps.txt was left without a word.
            raise InputError(
                f"holds {depth_folder.TUM_DEPTH_LIST} and {stamps.name}, and each times the "
                "frames: keep one",
                root,
            )
        paths, timestamps = depth_folder.read_tum_depth_list(root / depth_folder.TUM_DEPTH_LIST)
        unlisted = depth_folder.unlisted_images(paths)
        if unlisted:
            problem = (
                f"{len(unlisted)} depth image(s) beside the listed ones are not in "
                f"{depth_folder.TUM_DEPTH_LIST} and are not read (the first: {unlisted[0].name})"
            )
            warnings.warn(
                SpaceposeWarning(problem, root / depth_folder.TUM_DEPTH_LIST), stacklevel=3
            )
        if camera.depth_scale is None and depth_folder.integer_depths(paths):
            # TUM RGB-D's layout, and its unit for 16-bit images: 5000 per metre (read as
            # millimetres, every translation came out 5 times too long, ok). Float images
            # stay metres: at 5000 per metre a float TIFF in metres was read 5000 times too
            # near, every frame lost and blamed on a depth_scale the intrinsics did not hold.
            camera = camera.model_copy(update={"depth_scale": depth_folder.TUM_DEPTH_SCALE})
            unit_from = f"TUM RGB-D's {depth_folder.TUM_DEPTH_LIST} layout, 5000 per metre"
    else:
        paths = depth_folder.depth_files(root)
        timestamps = _folder_timestamps(root, len(paths))
    # Cloud-only formats: text files beside depth images are lists (TUM's rgb.txt), and a
    # .npy may be a depth map.
    clouds = depth_folder.frame_entries(root, (".ply", ".pcd", ".npz"))
    if clouds:  # read as depth images, the folder's cloud files are no frames
        names = ", ".join(p.name for p in clouds[:3]) + (", ..." if len(clouds) > 3 else "")
        warnings.warn(
            SpaceposeWarning(
                f"a depth-image folder: its {len(clouds)} point cloud file(s) ({names}) are not "
                "read as frames",
                root,
            ),
            stacklevel=3,
        )
    sized = depth_folder.sized_camera(camera, paths, source)
    # Checked at the size the intrinsics give, or else the images': the frames' own check looks
    # for a size the intrinsics lack, and the folder gave one (a principal point of another
    # resolution, or swapped, is warned of here, once).
    intrinsics_io.check_camera(sized, source)
    camera = sized
    loader = partial(depth_io.read_depth_cloud, camera=camera, unit_from=unit_from)
    return FrameSequence(paths, timestamps, loader=loader)


def read_timestamps(path: str | Path, n_frames: int) -> NDArray[np.float64]:
    """Read ``timestamps.txt``: one number per line (blank lines and ``#`` comments ignored).

    Raises
    ------
    InputError
        A line is not a single finite number, the count differs from ``n_frames``, or the
        timestamps do not increase or are not seconds
        (:func:`~spacepose.tools.text_io.check_timing`, which warns of frames slower than
        any ToF camera or flash LiDAR).
    """
    path = Path(path)
    values: list[float] = []
    for lineno, line in enumerate(read_text(path, "timestamps").splitlines(), start=1):
        body = line.split("#", 1)[0].strip()
        if not body:
            continue
        try:
            value = data_number(body)
        except ValueError:
            raise InputError(f"line {lineno}: not a timestamp: {body!r}", path) from None
        if not np.isfinite(value):
            raise InputError(f"line {lineno}: timestamp is not finite", path)
        values.append(value)
    if len(values) != n_frames:
        raise InputError(f"{len(values)} timestamps for {n_frames} frame files", path)
    stamps = np.asarray(values, dtype=np.float64)
    check_timing(stamps, path)
    return stamps


def _open_run(root: Path) -> FrameSequence:
    """Frames, timestamps and model of a simulator run folder, through ``read_run``."""
    from spacepose.tools.runs import read_run

    run = read_run(root)
    model = root / "model.ply"
    return FrameSequence(
        tuple(Path(p) for p in run.frame_paths),
        np.asarray(run.timestamps, dtype=np.float64),
        model if model.is_file() else None,
    )
