"""Tracking input and output: frames from a run folder, a folder of point cloud files or depth
images, or a ROS bag; the estimated trajectory, per-frame health table and effective config
written beside each other, row by row as the run goes.

:func:`open_frames` recognises, in this order: a ROS 1 / ROS 2 bag
(:mod:`spacepose.tools.bag_io`); a run folder (written by ``spacepose simulate``, recognised by
its ``scenario.json``); a depth image folder (:mod:`spacepose.tools.depth_io`: it holds an
intrinsics file or TUM RGB-D's ``depth.txt``, or an intrinsics file is given); any other folder
is read as one point cloud file per frame (``.ply``, ``.pcd``, ``.xyz``, ``.txt``, ``.csv``,
``.npy``, ``.npz``). Files are sorted by name, with timestamps from ``timestamps.txt`` (one
number per line) when present, else the frame index.

A frame that cannot be read (missing, zero-byte, truncated or corrupt file, an undecodable bag
message) or holds no usable point is yielded without a cloud and with the reason, so the
tracker reports it ``lost`` and the run goes on.
"""

from __future__ import annotations

import csv
import dataclasses
import json
import warnings
from collections import Counter
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from functools import partial
from pathlib import Path
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from spacepose.core.cloud import PointCloud
from spacepose.core.config import dump_config, load_config, validate_config
from spacepose.core.depth import DepthCamera
from spacepose.core.motion import order_problem
from spacepose.core.track_result import STAGES, lost_result
from spacepose.core.tracker import Tracker, TrackerConfig, TrackResult
from spacepose.core.trajectory import Trajectory
from spacepose.errors import InputError, SpaceposeWarning
from spacepose.tools import depth_io
from spacepose.tools.cloud_io import read_cloud
from spacepose.tools.outputs import check_spares_inputs, check_writable
from spacepose.tools.text_io import read_text
from spacepose.tools.trajectory_io import tum_lines

HEALTH_COLUMNS: tuple[str, ...] = (
    "frame",
    "timestamp",
    "status",
    "fitness",
    "rmse",
    "iterations",
    "time_ms",
    "sig_rx",
    "sig_ry",
    "sig_rz",
    "sig_tx",
    "sig_ty",
    "sig_tz",
    "reasons",
)
CLOUD_SUFFIXES: tuple[str, ...] = (".ply", ".pcd", ".xyz", ".txt", ".csv", ".npy", ".npz")
TIMESTAMPS_FILE = "timestamps.txt"
# Tables spacepose writes beside its outputs: an output written into a folder of frames is no
# frame of the next run over it.
_OWN_TABLES = (".health.csv", ".candidates.csv")


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
        Reads one file into a PointCloud, sensor frame (default: :func:`read_cloud`); any
        :class:`~spacepose.errors.InputError` it raises makes the frame lost, with the reason.
    """

    paths: tuple[Path, ...]
    timestamps: NDArray[np.float64]
    model_path: Path | None = None
    loader: Callable[[Path], PointCloud] = read_cloud

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
        The path does not exist, is not a folder or bag, holds no frame, a bag topic cannot be
        chosen, a depth folder has no intrinsics, or ``timestamps.txt`` does not hold one finite
        number per frame.
    ConfigError
        The intrinsics file is invalid.
    """
    from spacepose.tools.bag_io import is_bag, open_bag  # bag_io builds on this module

    root = Path(path)
    if not root.exists():
        raise InputError("does not exist", root)
    camera = None if intrinsics is None else depth_io.read_intrinsics(intrinsics)
    if is_bag(root):
        return open_bag(root, topic, camera)
    if topic is not None:
        raise InputError(f"--topic {topic} applies to a ROS bag, and this is not one", root)
    if not root.is_dir():
        raise InputError("not a folder of frames (or a run folder, or a ROS bag)", root)
    if (root / "scenario.json").is_file():
        return _open_run(root)
    if camera is not None or depth_io.is_depth_folder(root):
        return _open_depth_folder(root, camera)
    paths = tuple(
        p
        for p in depth_io.frame_entries(root, CLOUD_SUFFIXES)
        if p.name != TIMESTAMPS_FILE and not p.name.endswith(_OWN_TABLES)
    )
    if not paths and depth_io.frame_entries(root, depth_io.DEPTH_SUFFIXES):
        # Images without intrinsics: say what is missing, not that there is nothing.
        return _open_depth_folder(root, None)
    if not paths:
        raise InputError(f"no frame files ({', '.join(CLOUD_SUFFIXES)}) in the folder", root)
    return FrameSequence(paths, _folder_timestamps(root, len(paths)))


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
    names = (SCENARIO, GROUNDTRUTH, TRUTH, MODEL_CLOUD, "model.obj", TIMESTAMPS_FILE)
    files += [root / name for name in (*names, depth_io.TUM_DEPTH_LIST, *depth_io.INTRINSICS_FILES)]
    if not hasattr(frames, "paths"):  # a bag folder: its metadata and storage files
        files += [p for p in root.iterdir() if p.is_file()]
    return files


def _folder_timestamps(root: Path, n_frames: int) -> NDArray[np.float64]:
    """``timestamps.txt`` of a folder when present, else the frame indices."""
    stamps_path = root / TIMESTAMPS_FILE
    # Not only a regular file: a folder or a broken link by that name is an error, not frame
    # indices taken without a word.
    if stamps_path.exists() or stamps_path.is_symlink():
        return read_timestamps(stamps_path, n_frames)
    return np.arange(n_frames, dtype=np.float64)


def _open_depth_folder(root: Path, camera: DepthCamera | None) -> FrameSequence:
    """Depth images (sorted, or listed by ``depth.txt``) back-projected with ``camera`` or the
    folder's intrinsics file."""
    if camera is None:
        found = depth_io.find_intrinsics(root)
        if found is None:
            raise InputError(
                f"depth images need intrinsics: put {depth_io.INTRINSICS_FILES[0]} (fx, fy, cx, "
                "cy, depth_scale) in the folder or give --intrinsics",
                root,
            )
        camera = depth_io.read_intrinsics(found)
    if (root / depth_io.TUM_DEPTH_LIST).is_file():
        paths, timestamps = depth_io.read_tum_depth_list(root / depth_io.TUM_DEPTH_LIST)
    else:
        paths = depth_io.depth_files(root)
        timestamps = _folder_timestamps(root, len(paths))
    # Cloud-only formats: text files beside depth images are lists (TUM's rgb.txt), and a
    # .npy may be a depth map.
    clouds = depth_io.frame_entries(root, (".ply", ".pcd", ".npz"))
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
    loader = partial(depth_io.read_depth_cloud, camera=_sized(camera, paths))
    return FrameSequence(paths, timestamps, loader=loader)


def _sized(camera: DepthCamera, paths: Sequence[Path]) -> DepthCamera:
    """``camera`` with the sequence's image size where its intrinsics give none: the size most
    of its images have (read from their headers). One camera makes every frame, and an image
    of another size (a frame of another stream) would be back-projected with the wrong
    principal point without a word."""
    if camera.width is not None and camera.height is not None:
        return camera
    sizes = Counter(size for size in map(depth_io.image_size, paths) if size is not None)
    if not sizes:
        return camera  # each frame's own error is reported when it is read
    (width, height), _ = sizes.most_common(1)[0]
    size = {"width": width, "height": height}
    return camera.model_copy(update={k: v for k, v in size.items() if getattr(camera, k) is None})


def read_timestamps(path: str | Path, n_frames: int) -> NDArray[np.float64]:
    """Read ``timestamps.txt``: one number per line (blank lines and ``#`` comments ignored).

    Raises
    ------
    InputError
        A line is not a single finite number, the count differs from ``n_frames``, or the
        timestamps do not increase.
    """
    path = Path(path)
    values: list[float] = []
    for lineno, line in enumerate(read_text(path, "timestamps").splitlines(), start=1):
        body = line.split("#", 1)[0].strip()
        if not body:
            continue
        try:
            value = float(body)
        except ValueError:
            raise InputError(f"line {lineno}: not a timestamp: {body!r}", path) from None
        if not np.isfinite(value):
            raise InputError(f"line {lineno}: timestamp is not finite", path)
        values.append(value)
    if len(values) != n_frames:
        raise InputError(f"{len(values)} timestamps for {n_frames} frame files", path)
    stamps = np.asarray(values, dtype=np.float64)
    problem = order_problem(stamps)
    if problem is not None:
        raise InputError(problem, path)
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


# --------------------------------------------------------------------------------------------
# Tracking a folder


def tracker_config(
    path: str | Path | None = None,
    *,
    method: str | None = None,
    mls: bool | None = None,
    background: bool = False,
) -> TrackerConfig:
    """The tracker config from an optional file, with command-line overrides applied.

    ``method`` and ``mls`` override the file when given; ``background`` switches background
    removal on.

    Raises
    ------
    ConfigError
        Unreadable or invalid file, or an override out of range (e.g. an unknown method).
    """
    data: dict[str, Any] = {} if path is None else load_config(TrackerConfig, path).model_dump()
    if method is not None:
        data["method"] = method
    if mls is not None:
        data["use_mls"] = mls
    if background:
        data["use_background_removal"] = True
    return validate_config(TrackerConfig, data, path)


def health_row(result: TrackResult) -> dict[str, object]:
    """One row of :data:`HEALTH_COLUMNS` (σ in rad and m, RMSE in m, time in ms; the reasons a
    frame is not ``ok`` joined by ``; ``)."""
    return {
        "frame": result.index,
        "timestamp": repr(result.timestamp),
        "status": result.status,
        "fitness": f"{result.fitness:.6g}",
        "rmse": f"{result.rmse:.6g}",
        "iterations": result.iterations,
        "time_ms": f"{result.time_ms.get('total', float('nan')):.3f}",
        **{c: f"{v:.6g}" for c, v in zip(HEALTH_COLUMNS[7:13], result.sigma, strict=True)},
        "reasons": "; ".join(result.reasons),
    }


def write_health_csv(path: str | Path, results: Sequence[TrackResult]) -> Path:
    """Write the per-frame health table (:data:`HEALTH_COLUMNS`) as CSV."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=HEALTH_COLUMNS)
        writer.writeheader()
        writer.writerows(health_row(r) for r in results)
    return path


def output_paths(out: str | Path) -> tuple[Path, Path, Path, Path]:
    """``EST.tum`` -> (``EST.tum``, ``EST.health.csv``, ``EST.config.json``,
    ``EST.scale.json``)."""
    out = Path(out)
    stem = out.with_suffix("")
    return (
        out,
        Path(f"{stem}.health.csv"),
        Path(f"{stem}.config.json"),
        Path(f"{stem}.scale.json"),
    )


def _out_of_order(frame: FrameInput, last_time: float) -> TrackResult:
    """The ``lost`` result of a frame whose time does not come after the frame before's."""
    what = "repeats" if frame.timestamp == last_time else "does not come after"
    reason = f"timestamp {frame.timestamp} {what} the last tracked one ({last_time}): not tracked"
    return lost_result(frame.index, frame.timestamp, None, (reason,), dict.fromkeys(STAGES, 0.0))


def check_output(out: str | Path) -> None:
    """Refuse an output location that cannot be written, before any work is done: each of the
    four output files (:func:`~spacepose.tools.outputs.check_writable`).

    Raises
    ------
    InputError
        An output is an existing folder, a parent is a regular file, or a file cannot be
        written there.
    """
    if Path(out).name in ("", ".", ".."):
        raise InputError(f"--out needs a file name such as EST.tum, got {str(out)!r}")
    check_writable(*output_paths(out))


def track_folder(
    input: str | Path,
    out: str | Path,
    config: TrackerConfig = TrackerConfig(),
    model: str | Path | None = None,
    workers: int = -1,
    progress: Callable[[int, int, str], None] | None = None,
    *,
    intrinsics: str | Path | None = None,
    topic: str | None = None,
) -> dict[str, Any]:
    """Track every frame of an input and write the trajectory, health table, config and scale.

    The output location is checked and the input opened before tracking starts; the
    trajectory and health rows are written (and flushed) frame by frame, so an interrupted run
    keeps every frame done. A frame that cannot be read is reported ``lost`` with its reason.

    Parameters
    ----------
    input
        A bag, run folder, depth image folder or folder of frame files (see
        :func:`open_frames`).
    out
        The TUM trajectory to write (one line per input frame, methods.md §0, but for a frame
        whose time does not come after the last tracked one's); ``.health.csv``,
        ``.config.json`` and (once a frame has set the scale) ``.scale.json``, the lengths
        derived from the first frame, are written beside it with the same stem.
    config
        Tracker config (written out as the effective config).
    model
        Optional reference model cloud file (model-based tracking).
    workers
        Threads for neighbour searches.
    progress
        Called after each frame with (frames done, total, status).
    intrinsics, topic
        Depth image intrinsics file and bag topic (see :func:`open_frames`).

    Returns
    -------
    Summary: frames, ok / degraded / lost counts, the first lost frame and its reasons (None
    when none is lost), mean time per frame (ms), output paths.
    """
    check_output(out)
    frames = open_frames(input, intrinsics=intrinsics, topic=topic)
    given = [p for p in (model, intrinsics) if p is not None]
    check_spares_inputs(output_paths(out), [*input_files(input, frames), *given])
    model_cloud = None if model is None else read_cloud(model)
    tum, health, config_path, scale_path = output_paths(out)
    tracker = Tracker(config, model_cloud, workers)
    dump_config(config, config_path)  # creates the folder
    scale_path.unlink(missing_ok=True)  # a former run's lengths are not this run's
    statuses: list[str] = []
    times: list[float] = []
    first_lost = None
    written_scale = None
    with tum.open("w") as tum_fh, health.open("w", newline="") as health_fh:
        writer = csv.DictWriter(health_fh, fieldnames=HEALTH_COLUMNS)
        writer.writeheader()
        last_time = -np.inf
        for frame in frames:
            if not frame.timestamp > last_time:
                # A bag's header stamps, read as the frames come: a repeat or a step back is
                # this frame's fault, not the run's; the trajectory skips it (TUM times rise).
                result = _out_of_order(frame, last_time)
                tracker.continue_at(frame.index + 1)
            else:
                result = tracker.track_frame(frame.cloud, frame.timestamp)
                last_time = frame.timestamp
                tum_fh.write(tum_lines(Trajectory([result.timestamp], [result.T_sensor_target])))
            if frame.error is not None:  # the read error says more than the tracker's "no points"
                result = dataclasses.replace(result, reasons=(frame.error,))
            writer.writerow(health_row(result))
            tum_fh.flush()
            health_fh.flush()
            if tracker.scale is not None and tracker.scale is not written_scale:
                # The lengths derived from the first usable frame, as soon as it sets them (an
                # interrupted run keeps them), and again when the whole scene becomes the
                # target: what a new sensor's user checks.
                written_scale = tracker.scale
                lengths = tracker.scale.to_dict() | tracker.lengths.to_dict()
                scale_path.write_text(json.dumps(lengths, indent=2) + "\n")
            statuses.append(result.status)
            times.append(result.time_ms["total"])
            if result.status == "lost" and first_lost is None:
                first_lost = f"frame {len(statuses) - 1}: {'; '.join(result.reasons)}"
            if progress is not None:
                progress(len(statuses), len(frames), result.status)
    return {
        "frames": len(statuses),
        "ok": statuses.count("ok"),
        "degraded": statuses.count("degraded"),
        "lost": statuses.count("lost"),
        "first_lost": first_lost,
        "mean_time_ms": float(np.mean(times)) if times else float("nan"),
        "trajectory": str(tum),
        "health": str(health),
        "config": str(config_path),
        "scale": str(scale_path) if tracker.scale is not None else None,
    }
