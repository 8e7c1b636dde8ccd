"""Tracking a sequence of frames into files: the tracker config from a file and the command
line, the outputs' paths (``EST.tum``, ``EST.health.csv``,
``EST.config.json``, ``EST.scale.json``) and :func:`track_folder`, which writes them row by row
as the run goes, from any input :func:`~spacepose.tools.frames.open_frames` opens (the tables'
rows: :mod:`spacepose.tools.track_tables`).
"""

from __future__ import annotations

import csv
import dataclasses
import json
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, TextIO

import numpy as np

from spacepose.core.config import dump_config, read_mapping, validate_config
from spacepose.core.track_result import STAGES, lost_result
from spacepose.core.tracker import Tracker, TrackerConfig, TrackResult
from spacepose.core.trajectory import Trajectory
from spacepose.errors import ConfigError, InputError, Interrupted, SpaceposeWarning
from spacepose.tools.cloud_io import read_model
from spacepose.tools.frames import CLOUD_SUFFIXES, FrameInput, Frames, input_files, open_frames
from spacepose.tools.outputs import (
    check_not_anothers,
    check_spares_inputs,
    check_text_name,
    check_writable,
    companion,
)
from spacepose.tools.track_tables import (
    COVARIANCE_COLUMNS,
    HEALTH_COLUMNS,
    covariance_row,
    health_row,
    open_table,
)
from spacepose.tools.trajectory_io import tum_lines


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
    data: dict[str, Any] = {}
    if path is not None:
        raw = read_mapping(path)
        _refuse_navigation_keys(raw, path)
        data = validate_config(TrackerConfig, raw, path).model_dump()
    if method is not None:
        data["method"] = method
    if mls is not None:
        data["use_mls"] = mls
    if background:
        data["use_background_removal"] = True
    return validate_config(TrackerConfig, data, path)


def _refuse_navigation_keys(raw: Any, path: str | Path) -> None:
    """Refuse a tracker config holding navigate's settings and none of the tracker's: a
    navigate config of one or two keys (``ekf:``) was refused as "ekf: Extra inputs are not
    permitted", which did not say whose key it is."""
    from spacepose.core.fused_navigation import FusionConfig
    from spacepose.core.nav_config import NavigationConfig

    if not isinstance(raw, dict) or not raw:
        return
    keys = [str(k) for k in raw]
    if any(k in TrackerConfig.model_fields for k in keys):
        return
    theirs = [
        k for k in keys if k in NavigationConfig.model_fields or k in FusionConfig.model_fields
    ]
    if theirs:
        named = ", ".join(theirs[:4])
        whose = "is a navigate setting" if len(theirs) == 1 else "are navigate settings"
        raise ConfigError(
            f"{path}: {named} {whose}, not the tracker's: a navigate config given to track?"
        )


def output_paths(out: str | Path) -> tuple[Path, Path, Path, Path, Path]:
    """``EST.tum`` -> (``EST.tum``, ``EST.health.csv``, ``EST.config.json``,
    ``EST.scale.json``, ``EST.cov.csv``); an ``EST`` not named ``.tum`` keeps its whole name
    (``est_0.25`` -> ``est_0.25.health.csv``)."""
    out = Path(out)
    suffixes = (".health.csv", ".config.json", ".scale.json", ".cov.csv")
    health, config, scale, cov = (companion(out, ".tum", s) for s in suffixes)
    return out, health, config, scale, cov


@dataclasses.dataclass(frozen=True)
class _Row:
    """A frame's result as :func:`track_folder` writes it: ``where`` names its file in the
    summary's first lost frame; an untracked frame (out of time order) has no TUM line."""

    result: TrackResult
    where: str
    tracked: bool


def _lost_hint(model_size_ratio: float) -> str:
    """What a model-based run that lost every frame adds to its reason when its first frame is
    twice the model's size or more (``model_size_ratio``, the model's over the frame's, half or
    less: :attr:`~spacepose.core.tracker.Tracker.model_size_ratio`): frames in feet against a
    model in metres (3.3 times) lost every frame as "fitness 0.11 < 0.3", in inches as "the
    model has 16 points at the frame's voxel", and nothing named the units."""
    if not model_size_ratio <= 0.5:
        return ""
    return (
        f"; the first frame is {1.0 / model_size_ratio:.3g} times the model's size (RMS "
        "radius): frames and model in different units (feet are 3.28 times metres, inches "
        "39.4)?"
    )


def _write_rows(files: tuple[TextIO, TextIO, TextIO], rows: Sequence[_Row], header: bool) -> None:
    """Append ``rows`` to the trajectory, health and covariance files (the tables' headers
    first when ``header``), flushed."""
    tum_fh, health_fh, cov_fh = files
    writer = csv.DictWriter(health_fh, fieldnames=HEALTH_COLUMNS)
    covariances = csv.DictWriter(cov_fh, fieldnames=COVARIANCE_COLUMNS)
    if header:
        writer.writeheader()
        covariances.writeheader()
    for row in rows:
        r = row.result
        if row.tracked:
            tum_fh.write(tum_lines(Trajectory([r.timestamp], [r.T_sensor_target])))
        writer.writerow(health_row(r))
        covariances.writerow(covariance_row(r))
    for fh in files:
        fh.flush()


def _out_of_order(frame: FrameInput, last_time: float) -> TrackResult:
    """The ``lost`` result of a frame whose time does not come after the frame before's."""
    what = "repeats" if frame.timestamp == last_time else "does not come after"
    reason = f"timestamp {frame.timestamp} {what} the last tracked one ({last_time}): not tracked"
    return lost_result(frame.index, frame.timestamp, None, (reason,), dict.fromkeys(STAGES, 0.0))


def check_output(out: str | Path) -> None:
    """Refuse an output location that cannot be written, before any work is done: each of the
    five output files (:func:`~spacepose.tools.outputs.check_writable`).

    Raises
    ------
    InputError
        An output is an existing folder, a parent is a regular file, or a file cannot be
        written there; or the trajectory is named ``.kitti``.
    """
    if Path(out).name in ("", ".", ".."):
        raise InputError(f"--out needs a file name such as EST.tum, got {str(out)!r}")
    if Path(out).suffix.lower() == ".kitti":
        # The trajectory is TUM; named .kitti, evaluate (and evo) read it as KITTI and fail.
        raise InputError(
            "track writes a TUM trajectory (timestamp tx ty tz qx qy qz qw), and a .kitti file "
            "is read as KITTI (12 numbers a line, no times): name it .tum",
            out,
        )
    check_writable(*output_paths(out))
    check_not_anothers(out, ".tum", ".csv", "navigate", _is_navigation_table)


def _is_navigation_table(path: Path) -> bool:
    """Whether ``path`` starts with the header navigate writes."""
    from spacepose.core.nav_result import NAV_COLUMNS

    try:
        with path.open(encoding="utf-8", errors="replace") as fh:
            return fh.readline().strip() == ",".join(NAV_COLUMNS)
    except OSError:
        return False


def check_not_a_frame(
    out: Path,
    frames: Frames,
    what: str = "a trajectory",
    fix: str = "name it .tum or write it elsewhere",
) -> None:
    """Refuse an output written among the frames under a frame file's suffix: the next run
    over the folder would read it as a frame (one more frame, lost), and a folder of depth
    images would be read as a folder of point-cloud files.

    Parameters
    ----------
    out
        The output file (``track``'s trajectory, ``navigate``'s NAV.csv).
    frames
        The frames the command reads.
    what, fix
        The output, and what to do about it, as the message says them.

    Raises
    ------
    InputError
        One line naming the output and the suffix to use.
    """
    if out.suffix.lower() not in CLOUD_SUFFIXES:
        return
    folders = {p.parent.resolve() for p in getattr(frames, "paths", ())}
    if out.parent.resolve() in folders:
        raise InputError(
            f"{what} named {out.suffix} among the frames would be read as a frame by "
            f"the next run over the folder: {fix}",
            out,
        )


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
    """Track every frame of an input and write the trajectory, health and covariance tables,
    config and scale.

    The output location is checked and the input opened before tracking starts; the
    trajectory and the tables' rows are written (and flushed) frame by frame, so an interrupted run
    keeps every frame done. A frame that cannot be read is reported ``lost`` with its reason.

    Parameters
    ----------
    input
        A bag, run folder, depth image folder or folder of frame files (see
        :func:`open_frames`).
    out
        The TUM trajectory to write (one line per input frame, methods.md §0, but for a frame
        whose time does not come after the last tracked one's); ``.health.csv``, ``.cov.csv``
        (:data:`COVARIANCE_COLUMNS`, a row a frame), ``.config.json`` and (once a frame has
        set the scale) ``.scale.json``, the lengths
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
    check_not_a_frame(Path(out), frames)
    check_text_name(out, "a TUM trajectory", "name it .tum")
    if Path(out).suffix.lower() != ".tum":
        # Tracked, scored by evaluate, but not found by report, which reads *.tum.
        problem = "not named .tum: spacepose report looks for tracks named *.tum only"
        warnings.warn(SpaceposeWarning(problem, out), stacklevel=2)
    model_cloud = None if model is None else read_model(model)
    tum, health, config_path, scale_path, cov_path = output_paths(out)
    tracker = Tracker(config, model_cloud, workers)
    dump_config(config, config_path)  # creates the folder
    scale_path.unlink(missing_ok=True)  # a former run's lengths are not this run's
    rows: list[_Row] = []
    times: list[float] = []
    with tum.open("w") as tum_fh, open_table(health) as health_fh, open_table(cov_path) as cov_fh:
        files = (tum_fh, health_fh, cov_fh)
        _write_rows(files, [], header=True)
        try:
            _track_frames(tracker, frames, files, rows, times, scale_path, progress)
        except KeyboardInterrupt:
            # Written again whole: an interrupt inside a write would leave half a row.
            _rewrite(files, rows)
            raise Interrupted(
                f"interrupted after {len(rows)} of {len(frames)} frames: the trajectory and its "
                "tables hold those frames",
                tum,
            ) from None
    statuses = [r.result.status for r in rows]
    first_lost = next(
        (
            f"frame {k}{r.where}: {'; '.join(r.result.reasons)}"
            for k, r in enumerate(rows)
            if r.result.status == "lost"
        ),
        None,
    )
    if first_lost is not None and statuses.count("lost") == len(statuses):
        first_lost += _lost_hint(tracker.model_size_ratio)
    return {
        "frames": len(statuses),
        "ok": statuses.count("ok"),
        "degraded": statuses.count("degraded"),
        "lost": statuses.count("lost"),
        "first_lost": first_lost,
        "mean_time_ms": float(np.mean(times)) if times else float("nan"),
        "trajectory": str(tum),
        "health": str(health),
        "covariance": str(cov_path),
        "config": str(config_path),
        "scale": str(scale_path) if tracker.scale is not None else None,
    }


def _track_frames(
    tracker: Tracker,
    frames: Frames,
    files: tuple[TextIO, TextIO, TextIO],
    rows: list[_Row],
    times: list[float],
    scale_path: Path,
    progress: Callable[[int, int, str], None] | None,
) -> None:
    """Track each frame and write its rows as it comes (``rows`` and ``times`` grow with them;
    :func:`track_folder`)."""
    written_scale = None
    last_time = -np.inf
    for frame in frames:
        tracked = frame.timestamp > last_time
        if not tracked:
            # A bag's header stamps, read as the frames come: a repeat or a step back is this
            # frame's fault, not the run's; the trajectory skips it (TUM times rise).
            result = _out_of_order(frame, last_time)
            tracker.continue_at(frame.index + 1)
            # Said as an unreadable frame is (the table alone held it).
            problem = f"frame lost: {result.reasons[0]}"
            warnings.warn(SpaceposeWarning(problem, frame.source), stacklevel=3)
        else:
            result = tracker.track_frame(frame.cloud, frame.timestamp)
            last_time = frame.timestamp
        if frame.error is not None:  # the read error says more than the tracker's "no points"
            result = dataclasses.replace(result, reasons=(frame.error,))
            # On stderr too, not in the table alone (the CLI counts repeats past three).
            problem = frame.error.removeprefix(f"{frame.source}: ")
            warnings.warn(
                SpaceposeWarning(f"not read, frame lost: {problem}", frame.source), stacklevel=3
            )
        # The tracker's reasons ("unusable frame: 1 point(s)") name no file; a read error does.
        where = "" if frame.error is not None else f", {frame.source}"
        rows.append(_Row(result, where, tracked))
        if result.revises:
            # Earlier frames' results revised (a model-free first frame replaced): the files are
            # written again, a few lines at the start of a run.
            new = {r.index: r for r in result.revises}
            rows[:] = [
                dataclasses.replace(r, result=new.get(r.result.index, r.result)) for r in rows
            ]
            _rewrite(files, rows)
        else:
            _write_rows(files, rows[-1:], header=False)
        if tracker.scale is not None and tracker.scale is not written_scale:
            # The lengths derived from the first usable frame, as soon as it sets them (an
            # interrupted run keeps them), and again when the whole scene becomes the target:
            # what a new sensor's user checks.
            written_scale = tracker.scale
            lengths = tracker.scale.to_dict() | tracker.lengths.to_dict()
            scale_path.write_text(json.dumps(lengths, indent=2) + "\n")
        times.append(result.time_ms["total"])
        if progress is not None:
            progress(len(rows), len(frames), result.status)


def _rewrite(files: tuple[TextIO, TextIO, TextIO], rows: Sequence[_Row]) -> None:
    """Write the three tables again from their first line."""
    for fh in files:
        fh.seek(0)
        fh.truncate()
    _write_rows(files, rows, header=True)
