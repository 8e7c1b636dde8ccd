"""Tracking input and output: frames from a run folder or a folder of point cloud files; the
estimated trajectory, per-frame health table and effective config written beside each other.

A run folder (written by ``spacepose simulate``, read by :func:`spacepose.tools.runs.read_run`)
is recognised by its ``scenario.json``. Any other folder is read as one point cloud file per
frame (``.ply``, ``.pcd``, ``.xyz``, ``.txt``, ``.csv``, ``.npy``, ``.npz``), sorted by file name,
with timestamps from ``timestamps.txt`` (one number per line) when present, else the frame index.

A frame file that parses but holds no usable point (an empty cloud, only NaN rows) is yielded as
an empty frame so the tracker can report it as lost; a file that cannot be parsed is an error.
"""

from __future__ import annotations

import csv
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from spacepose.core.cloud import PointCloud
from spacepose.core.config import dump_config, load_config, validate_config
from spacepose.core.tracker import Tracker, TrackerConfig, TrackResult
from spacepose.core.trajectory import Trajectory
from spacepose.errors import FileFormatError, InputError
from spacepose.tools.cloud_io import read_cloud
from spacepose.tools.trajectory_io import write_tum

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
)
CLOUD_SUFFIXES: tuple[str, ...] = (".ply", ".pcd", ".xyz", ".txt", ".csv", ".npy", ".npz")
TIMESTAMPS_FILE = "timestamps.txt"


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
        The points in the sensor frame, or ``None`` when the file holds no usable point.
    source
        The file the frame came from.
    """

    index: int
    timestamp: float
    cloud: PointCloud | None
    source: str


@dataclass(frozen=True)
class FrameSequence:
    """A sized, re-iterable sequence of input frames (files are read lazily, one at a time).

    Attributes
    ----------
    paths
        One file per frame, in order.
    timestamps
        (N,) seconds, one per frame.
    model_path
        The reference model cloud of a run folder (``model.ply``), else ``None``.
    """

    paths: tuple[Path, ...]
    timestamps: NDArray[np.float64]
    model_path: Path | None = None

    def __len__(self) -> int:
        return len(self.paths)

    def __iter__(self) -> Iterator[FrameInput]:
        for i, (path, t) in enumerate(zip(self.paths, self.timestamps, strict=True)):
            yield FrameInput(i, float(t), read_frame(path), str(path))


def read_frame(path: str | Path) -> PointCloud | None:
    """Read one frame file; ``None`` for a well-formed file with no finite point.

    Raises
    ------
    FileFormatError
        The file cannot be parsed (corrupt, truncated, unknown extension, missing).
    """
    try:
        return read_cloud(path)
    except FileFormatError:
        raise
    except InputError:
        # Parsed but empty / all-NaN: a frame the tracker must report as lost, not a crash.
        return None


def open_frames(path: str | Path) -> FrameSequence:
    """Open a run folder or a folder of frame files (see the module docstring).

    Raises
    ------
    InputError
        The path is not a folder, holds no frame file, or ``timestamps.txt`` does not hold one
        finite number per frame.
    """
    root = Path(path)
    if not root.exists():
        raise InputError("does not exist", root)
    if not root.is_dir():
        raise InputError("not a folder of frames (or a run folder)", root)
    if (root / "scenario.json").is_file():
        return _open_run(root)
    paths = tuple(
        sorted(
            p
            for p in root.iterdir()
            if p.is_file() and p.suffix.lower() in CLOUD_SUFFIXES and p.name != TIMESTAMPS_FILE
        )
    )
    if not paths:
        raise InputError(f"no frame files ({', '.join(CLOUD_SUFFIXES)}) in the folder", root)
    stamps_path = root / TIMESTAMPS_FILE
    if stamps_path.is_file():
        timestamps = read_timestamps(stamps_path, len(paths))
    else:
        timestamps = np.arange(len(paths), dtype=np.float64)
    return FrameSequence(paths, timestamps)


def read_timestamps(path: str | Path, n_frames: int) -> NDArray[np.float64]:
    """Read ``timestamps.txt``: one number per line (blank lines and ``#`` comments ignored).

    Raises
    ------
    InputError
        A line is not a single finite number, the count differs from ``n_frames``, or the
        timestamps decrease.
    """
    path = Path(path)
    values: list[float] = []
    for lineno, line in enumerate(path.read_text().splitlines(), start=1):
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
    if np.any(np.diff(stamps) < 0):
        raise InputError("timestamps decrease", path)
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


def health_rows(results: Sequence[TrackResult]) -> list[dict[str, object]]:
    """One row per frame with :data:`HEALTH_COLUMNS` (σ in rad and m, RMSE in m, time in ms)."""
    rows = []
    for r in results:
        sig = r.sigma
        rows.append(
            {
                "frame": r.index,
                "timestamp": repr(r.timestamp),
                "status": r.status,
                "fitness": f"{r.fitness:.6g}",
                "rmse": f"{r.rmse:.6g}",
                "iterations": r.iterations,
                "time_ms": f"{r.time_ms.get('total', float('nan')):.3f}",
                **{c: f"{v:.6g}" for c, v in zip(HEALTH_COLUMNS[7:], sig, strict=True)},
            }
        )
    return rows


def write_health_csv(path: str | Path, results: Sequence[TrackResult]) -> Path:
    """Write the per-frame health table (:data:`HEALTH_COLUMNS`) as CSV."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", newline="") as fh:
        writer = csv.DictWriter(fh, fieldnames=HEALTH_COLUMNS)
        writer.writeheader()
        writer.writerows(health_rows(results))
    return path


def output_paths(out: str | Path) -> tuple[Path, Path, Path]:
    """``EST.tum`` -> (``EST.tum``, ``EST.health.csv``, ``EST.config.json``)."""
    out = Path(out)
    stem = out.with_suffix("")
    return out, Path(f"{stem}.health.csv"), Path(f"{stem}.config.json")


def track_folder(
    input: str | Path,
    out: str | Path,
    config: TrackerConfig = TrackerConfig(),
    model: str | Path | None = None,
    workers: int = -1,
    progress: Callable[[int, int, str], None] | None = None,
) -> dict[str, Any]:
    """Track every frame of a folder and write the trajectory, health table and config.

    Parameters
    ----------
    input
        A run folder or a folder of frame files (see :func:`open_frames`).
    out
        The TUM trajectory to write (one line per input frame, METHODS §0); ``.health.csv``
        and ``.config.json`` are written beside it with the same stem.
    config
        Tracker config (written out as the effective config).
    model
        Optional reference model cloud file (model-based tracking).
    workers
        Threads for neighbour searches.
    progress
        Called after each frame with (frames done, total, status).

    Returns
    -------
    Summary: frames, ok / degraded / lost counts, mean time per frame (ms), output paths.
    """
    frames = open_frames(input)
    model_cloud = None if model is None else read_cloud(model)
    tum, health, config_path = output_paths(out)
    dump_config(config, config_path)
    tracker = Tracker(config, model_cloud, workers)
    results = []
    for frame in frames:
        results.append(tracker.track_frame(frame.cloud, frame.timestamp))
        if progress is not None:
            progress(len(results), len(frames), results[-1].status)
    trajectory = Trajectory(
        np.array([r.timestamp for r in results]), np.array([r.T_sensor_target for r in results])
    )
    write_tum(tum, trajectory)
    write_health_csv(health, results)
    statuses = [r.status for r in results]
    return {
        "frames": len(results),
        "ok": statuses.count("ok"),
        "degraded": statuses.count("degraded"),
        "lost": statuses.count("lost"),
        "mean_time_ms": float(np.mean([r.time_ms["total"] for r in results])),
        "trajectory": str(tum),
        "health": str(health),
        "config": str(config_path),
    }
