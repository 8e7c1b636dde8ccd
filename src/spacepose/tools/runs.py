"""Run folders: what ``spacepose simulate`` writes and every evaluation reads (methods.md §3).

Layout of a run folder ``DIR``::

    DIR/frames/000000.ply ...   one binary PLY (float32 x y z) per frame, sensor frame
    DIR/groundtruth.tum         true T_sensor_target per frame (TUM)
    DIR/model.ply               target surface samples with normals, target frame
    DIR/model.obj               the target mesh, target frame
    DIR/scenario.json           every parameter, the seed, the package version
    DIR/truth.csv               orbit only: ρ, ρ̇, q_I_B, ω, k, Δ per frame

The same simulation (same seed) always produces the same bytes.
"""

from __future__ import annotations

import json
import warnings
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from spacepose.core.cloud import PointCloud
from spacepose.core.sim.scenarios import TRUTH_COLUMNS
from spacepose.core.sim.simulation import Simulation
from spacepose.core.sim.targets import Rectangle
from spacepose.core.structured_text import load_structured
from spacepose.core.tracker_config import TrackerConfig
from spacepose.core.trajectory import Trajectory
from spacepose.errors import FileFormatError, InputError, SpaceposeWarning
from spacepose.tools.cloud_io import read_cloud, write_cloud
from spacepose.tools.text_io import check_timing, read_text
from spacepose.tools.trajectory_io import read_tum, write_tum

# The tracker's default health.min_points: a frame of fewer points is lost.
_FEWEST_TRACKED = TrackerConfig().health.min_points

FRAMES_DIR = "frames"
GROUNDTRUTH = "groundtruth.tum"
MODEL_CLOUD = "model.ply"
MODEL_MESH = "model.obj"
SCENARIO = "scenario.json"
TRUTH = "truth.csv"


@dataclass(frozen=True, eq=False)
class Run:
    """A run folder opened for reading; frames are read from disk only when asked for.

    Attributes
    ----------
    path
        The run folder.
    scenario
        The contents of ``scenario.json``.
    groundtruth
        True ``T_sensor_target`` per frame.
    model
        Target surface samples with normals, target frame (``model.ply``); None when the
        folder has none.
    frame_paths
        One PLY per frame, in time order.
    truth
        Orbit runs: (N, 20) table with the columns of ``truth.csv``; None otherwise.
    """

    path: Path
    scenario: dict[str, Any]
    groundtruth: Trajectory
    model: PointCloud | None
    frame_paths: tuple[Path, ...]
    truth: NDArray[np.float64] | None = None

    def __len__(self) -> int:
        return len(self.frame_paths)

    @property
    def timestamps(self) -> NDArray[np.float64]:
        """(N,) frame times, seconds."""
        return self.groundtruth.timestamps

    @property
    def mesh_path(self) -> Path:
        """The target mesh file."""
        return self.path / MODEL_MESH

    @property
    def rectangles(self) -> list[Rectangle]:
        """The target's rectangle catalogue (empty for a mesh-file target)."""
        return [Rectangle.from_dict(r) for r in self.scenario.get("rectangles", [])]

    def frame(self, k: int) -> PointCloud:
        """Read frame ``k`` (sensor frame)."""
        return read_cloud(self.frame_paths[k])

    def frames(self) -> Iterator[PointCloud]:
        """Every frame in time order, read one at a time."""
        return (read_cloud(p) for p in self.frame_paths)


def check_run_out(out_dir: str | Path) -> None:
    """Refuse to write a run into a folder that holds something else: a run rewrites its
    ground truth, model and scenario and removes frame files it did not write, so only a new
    folder, one without files, or an earlier run (its scenario file), is safe to write into.

    Raises
    ------
    InputError
        One line naming the folder: it holds something else, or is (or lies under) a file.
    """
    out = Path(out_dir)
    # The nearest existing path decides whether the folder can be made: under a file it ended
    # in mkdir's "frames: Not a directory", naming neither the file nor the problem.
    existing = out
    while not existing.exists() and existing != existing.parent:
        existing = existing.parent
    if existing.exists() and not existing.is_dir():
        where = "is a file" if existing == out else f"lies under {existing}, a file"
        raise InputError(f"{where}: a run is written to a folder", out)
    # Empty folders alone hold nothing to lose (a run that failed on its first frame leaves
    # its frames folder): the first file found decides.
    holds = out.is_dir() and any(p.is_file() for p in out.rglob("*"))
    if holds and not (out / SCENARIO).is_file():
        raise InputError(
            f"not empty and not a spacepose run (no {SCENARIO}): a run would overwrite or "
            "remove what it holds; give a new or empty folder",
            out,
        )


def _earlier_results(out: Path) -> list[str]:
    """The files under an earlier run's folder ``out`` that simulate does not write (tracks,
    navigation tables, reports), by their paths in it."""
    if not (out / SCENARIO).is_file():
        return []
    own = {GROUNDTRUTH, MODEL_CLOUD, MODEL_MESH, SCENARIO, TRUTH}
    return sorted(
        str(p.relative_to(out))
        for p in out.rglob("*")
        if p.is_file()
        and p.name not in own
        and not (p.parent == out / FRAMES_DIR and p.name[:1].isdigit() and p.suffix == ".ply")
    )


def write_run(
    out_dir: str | Path,
    sim: Simulation,
    progress: Callable[[int], None] | None = None,
) -> Path:
    """Render every frame of ``sim`` and write the run folder ``out_dir``.

    Parameters
    ----------
    out_dir
        Created if needed; frame files left from an earlier, longer run there are removed so the
        folder describes this run only (a folder that is neither empty nor a run is refused:
        :func:`check_run_out`).
    sim
        The simulation (see :mod:`spacepose.core.sim`).
    progress
        Called with the frame index after each frame is written.

    Returns
    -------
    The folder written.
    """
    from spacepose import __version__

    check_run_out(out_dir)
    out = Path(out_dir)
    if earlier := _earlier_results(out):
        shown = ", ".join(earlier[:4]) + (
            f" and {len(earlier) - 4} more" if len(earlier) > 4 else ""
        )
        problem = (
            f"holds results of the run written there before ({shown}): they are not of the "
            "frames written now, and report would score them against the new truth"
        )
        warnings.warn(SpaceposeWarning(problem, out), stacklevel=2)
    if sim.truth is None:
        # An orbit run's truth left under a lab run: report scored its navigation against it.
        (out / TRUTH).unlink(missing_ok=True)
    frames_dir = out / FRAMES_DIR
    frames_dir.mkdir(parents=True, exist_ok=True)
    wanted = {_frame_name(k) for k in range(len(sim))}
    for stale in frames_dir.glob("[0-9]*.ply"):
        if stale.name not in wanted:
            stale.unlink()
    sparse = []
    for k in range(len(sim)):
        frame = sim.frame(k)
        write_cloud(frames_dir / _frame_name(k), frame.cloud.points, binary=True, dtype="float32")
        if len(frame.cloud) < _FEWEST_TRACKED:
            sparse.append((k, len(frame.cloud)))
        if progress is not None:
            progress(k)
    if sparse:  # such frames were written without a word, and every one is lost when tracked
        k, n = sparse[0]
        problem = (
            f"{len(sparse)} of {len(sim)} frames hold fewer than {_FEWEST_TRACKED} points (frame "
            f"{k}: {n}), the fewest a frame is tracked on: the target is too small or too far "
            "for the sensor"
        )
        warnings.warn(SpaceposeWarning(problem, frames_dir), stacklevel=2)
    write_tum(out / GROUNDTRUTH, sim.groundtruth)
    write_cloud(out / MODEL_CLOUD, sim.model_cloud(), binary=True, dtype="float32")
    sim.target.mesh.export(
        out / MODEL_MESH, file_type="obj", include_normals=False, include_texture=False
    )
    scenario = sim.scenario() | {"spacepose_version": __version__}
    (out / SCENARIO).write_text(json.dumps(scenario, indent=2, sort_keys=True) + "\n")
    if sim.truth is not None:
        np.savetxt(
            out / TRUTH,
            sim.truth,
            fmt="%.17g",
            delimiter=",",
            header=",".join(TRUTH_COLUMNS),
            comments="",
        )
    return out


def read_run(path: str | Path) -> Run:
    """Open a run folder written by :func:`write_run`.

    Raises
    ------
    InputError
        The folder does not exist, or a file of the layout (but the model's) is missing, the
        number of frames differs from the number of ground-truth poses, or their times do not
        rise or are not seconds (:func:`~spacepose.tools.text_io.check_timing`).
    FileFormatError
        ``scenario.json`` or ``truth.csv`` cannot be parsed (other files: see their readers).
    """
    root = Path(path)
    if not root.is_dir():
        raise InputError("run folder does not exist", root)
    # The model files are not needed: a run folder without them is tracked and navigated
    # model-free (navigate refused one "missing model.ply", where the README promised that).
    for name in (SCENARIO, GROUNDTRUTH, FRAMES_DIR):
        if not (root / name).exists():
            raise InputError(f"run folder is missing {name}", root)
    # read_text names the file whatever fails: a bare OSError ("Input/output error") did not.
    text = read_text(root / SCENARIO, "the run's scenario")
    try:
        scenario = load_structured(text, "json")
    except json.JSONDecodeError as exc:
        raise FileFormatError(f"not valid JSON: {exc}", root / SCENARIO) from None
    if not isinstance(scenario, dict):
        raise FileFormatError("must hold a JSON object", root / SCENARIO)
    groundtruth = read_tum(root / GROUNDTRUTH)
    # The run's frames are timed by it: they must rise and be seconds (an edited file in
    # milliseconds was navigated a thousand times too slow without a word).
    check_timing(groundtruth.timestamps, root / GROUNDTRUTH)
    frame_paths = _numbered_frames(root)
    _warn_of_timestamps(root)
    if len(frame_paths) != len(groundtruth):
        other = sorted({p.suffix for p in (root / FRAMES_DIR).glob("[0-9]*") if p.is_file()})
        other = [x for x in other if x.lower() != ".ply"]
        # A run's frames are .ply: "0 frame files" alone read as an empty folder.
        hint = f" (a run's frames are .ply; {', '.join(other)} files are not read)" if other else ""
        raise InputError(
            f"{len(frame_paths)} frame files in {FRAMES_DIR}/ but {len(groundtruth)} poses in "
            f"{GROUNDTRUTH}{hint}",
            root,
        )
    truth = None
    if scenario.get("scenario") == "orbit":
        if not (root / TRUTH).is_file():
            raise InputError(f"orbit run folder is missing {TRUTH}", root)
        truth = read_truth(root / TRUTH, groundtruth.timestamps)
    model = read_cloud(root / MODEL_CLOUD) if (root / MODEL_CLOUD).exists() else None
    return Run(root, scenario, groundtruth, model, frame_paths, truth)


def _warn_of_timestamps(root: Path) -> None:
    """Warn of a ``timestamps.txt`` (in any case) in a run folder or its ``frames/``: it times
    a folder of frame files, while a run's frames are timed by its ``groundtruth.tum``, and it
    was passed over without a word (the user's times never used)."""
    for folder in (root, root / FRAMES_DIR):
        for path in sorted(folder.iterdir()):
            if path.name.lower() == "timestamps.txt":
                warnings.warn(
                    SpaceposeWarning(
                        f"not read: a run folder's frames are timed by its {GROUNDTRUTH} "
                        f"(timestamps.txt times a folder of frame files; give {FRAMES_DIR}/ "
                        "itself to time its frames by it, or remove it)",
                        path,
                    ),
                    stacklevel=3,
                )


def _frame_name(k: int) -> str:
    return f"{k:06d}.ply"


def _numbered_frames(root: Path) -> tuple[Path, ...]:
    """The frame files of a run, frame ``k`` the one numbered ``k`` (``000000.ply``, or any
    zero padding), in that order.

    Raises
    ------
    InputError
        A ``.ply`` name in ``frames/`` that is not a number, or numbers that are not 0, 1, 2,
        ... without a gap or a repeat: frame ``k`` is timed and scored by the ``k``-th pose of
        ``groundtruth.tum``, and sorted as text (``10.ply`` before ``2.ply``) or past a gap
        every later frame would be paired with another frame's pose.
    """
    numbered: list[tuple[int, Path]] = []
    for path in (root / FRAMES_DIR).glob("[0-9]*.ply"):
        if not path.stem.isascii() or not path.stem.isdigit():
            raise InputError(
                f"{FRAMES_DIR}/{path.name} is not a frame name (a number, such as "
                f"{_frame_name(0)}): move it out of the run",
                root,
            )
        numbered.append((int(path.stem), path))
    numbered.sort(key=lambda item: (item[0], item[1].name))
    for k, (number, path) in enumerate(numbered):
        if number != k:
            what = "repeats" if k and numbered[k - 1][0] == number else f"is numbered {number}"
            # A run's frames are .ply: frame k written in another format fills no gap.
            other = sorted(
                p.name
                for p in (root / FRAMES_DIR).iterdir()
                if p.suffix.lower() != ".ply"
                and p.stem.isascii()
                and p.stem.isdigit()
                and int(p.stem) == k
            )
            also = f" ({', '.join(other)} not read: a run's frames are .ply)" if other else ""
            raise InputError(
                f"{FRAMES_DIR}/{path.name} {what} where frame {k} belongs{also}: frame k is pose "
                f"k of {GROUNDTRUTH}, so the files are numbered 0, 1, 2, ... without a gap",
                root,
            )
    return tuple(path for _, path in numbered)


def read_truth(
    path: str | Path, timestamps: NDArray[np.float64] | None = None
) -> NDArray[np.float64]:
    """``truth.csv``: one finite row of :data:`TRUTH_COLUMNS` per frame, at the frame times
    ``timestamps`` (``groundtruth.tum``'s). Every reader of a run's truth (:func:`read_run`,
    the report) takes it here, so the checks are the same.

    Parameters
    ----------
    path
        The truth file.
    timestamps
        The frames' times; None where a folder gives none (a report of a folder without
        ``groundtruth.tum``): the number of rows and their times are then not checked.

    Raises
    ------
    FileFormatError
        Another header, a row that does not parse, another number of rows, a value that is
        not finite, or a row at another time than its frame's: the truth is paired with the
        frames row by row, and another run's (or an edited) truth was scored against them
        without a word.
    """
    path = Path(path)
    rows = "rows" if timestamps is None else f"{len(timestamps)} rows"
    expected = f"expected {rows} of {len(TRUTH_COLUMNS)} values"
    lines = read_text(path, "the orbit's truth").splitlines()
    if not lines or lines[0].strip().split(",") != TRUTH_COLUMNS:
        raise FileFormatError(f"header must be {','.join(TRUTH_COLUMNS)}", path)
    # np.loadtxt only warns on a body without data (blank or '#' comment lines alone).
    if not any(line.split("#")[0].strip() for line in lines[1:]):
        raise FileFormatError(f"{expected}, got none", path)
    for k, line in enumerate(lines[1:], start=2):
        values = line.split("#")[0].strip()
        if values and len(values.split(",")) != len(TRUTH_COLUMNS):
            # numpy said "the number of columns changed ...; use `usecols` to select a subset".
            problem = (
                f"line {k} has {len(values.split(','))} values, the header {len(TRUTH_COLUMNS)}"
            )
            raise FileFormatError(f"{problem} (a truncated file?)", path)
    try:
        table = np.loadtxt(lines[1:], delimiter=",", ndmin=2)
    except ValueError as exc:
        raise FileFormatError(f"bad row: {exc}", path) from None
    n_rows = len(table) if timestamps is None else len(timestamps)
    if table.shape != (n_rows, len(TRUTH_COLUMNS)):
        raise FileFormatError(f"{expected}, got {table.shape}", path)
    bad = ~np.isfinite(table)
    if bad.any():  # a truth with a hole scores every estimate against NaN
        row, column = np.argwhere(bad)[0]
        raise FileFormatError(
            f"row {row + 1}: {TRUTH_COLUMNS[column]} is {table[row, column]}; the truth must be "
            "finite",
            path,
        )
    if timestamps is None:
        return table
    # Times as written by write_run (17 digits): equal to groundtruth.tum's but for rounding.
    off = np.flatnonzero(~np.isclose(table[:, 0], timestamps, rtol=1e-12, atol=1e-6))
    if len(off):
        k = off[0]
        raise FileFormatError(
            f"row {k + 1} is at t = {table[k, 0]:.10g} s, frame {k} at {timestamps[k]:.10g} s "
            f"({GROUNDTRUTH}): the truth and the frames must share their times",
            path,
        )
    return table
