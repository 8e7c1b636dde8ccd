"""Relative navigation of a run folder: read the run, navigate, write NAV.csv and its config.

With registration poses (``measurements`` ``registration`` or ``both``) the model-based
tracker's per-frame health goes to ``NAV.health.csv`` (the tracker's columns; a pose the
filter's gate rejected is ``degraded`` with a ``navigation gate`` reason).

While the target's pose is ambiguous (a symmetric target, or a view that hides what breaks the
symmetry) NAV.csv has no state, and ``NAV.candidates.csv`` lists every candidate filter's
estimate per frame. A run in which no frame is navigated writes both files and then fails with
one line saying why.
"""

from __future__ import annotations

import csv
import json
import warnings
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

from numpy.typing import ArrayLike

from spacepose.core.cloud import PointCloud
from spacepose.core.config import dump_config
from spacepose.core.fused_navigation import FusedNavigator, FusionConfig, Measurements
from spacepose.core.moments import no_plane, on_a_line
from spacepose.core.nav_result import NavRow, nav_table
from spacepose.core.nav_start import scenario_geometry
from spacepose.core.navigation import NavigationConfig, RelativeNavigator, frame_pairs
from spacepose.core.pose_noise import POSE_NOISE_AXES, PoseNoiseScale
from spacepose.errors import ConfigError, InputError, Interrupted, SpaceposeWarning
from spacepose.tools.catalogue import parse_catalogue
from spacepose.tools.cloud_io import read_model
from spacepose.tools.frames import (
    TIMESTAMPS_FILE,
    Frames,
    input_files,
    open_frames,
    untimed_folder,
)
from spacepose.tools.navigation_config_io import read_scenario, scenario_model, with_run_settings
from spacepose.tools.navigation_reasons import (
    warn_if_mostly_predicted,
    warn_if_no_rectangle_used,
    warn_if_predicted_alone,
    warn_refused_frames,
    warn_unusable_frames,
    why_no_registration,
    why_nothing,
    with_unreadable,
)
from spacepose.tools.outputs import (
    check_not_anothers,
    check_spares_inputs,
    check_text_name,
    check_writable,
    companion,
)
from spacepose.tools.pose_bootstrap_run import bootstrapped_fusion, run_mesh_and_sensor
from spacepose.tools.track_tables import open_table, write_health_csv
from spacepose.tools.tracking_io import check_not_a_frame


@dataclass(frozen=True)
class NavigationSummary:
    """What :func:`navigate_run` wrote and how many frames the filter used."""

    nav_csv: Path
    config_json: Path
    frames: int
    navigated: int
    rows: tuple[NavRow, ...]
    ambiguous: int = 0
    candidates_csv: Path | None = None
    health_csv: Path | None = None
    pose_noise_json: Path | None = None


def write_nav_csv(path: str | Path, rows: Sequence[NavRow]) -> Path:
    """Write one NAV.csv row per frame (columns of :data:`nav_result.NAV_COLUMNS`)."""
    path = Path(path)
    columns, values = nav_table(rows)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open_table(path) as fh:
        writer = csv.writer(fh)
        writer.writerow(columns)
        writer.writerows(
            [f"{v:.17g}" if isinstance(v, float) else v for v in row] for row in values
        )
    return path


CANDIDATE_COLUMNS = "t,candidate,explained,rho_x,rho_y,rho_z,qx,qy,qz,qw".split(",")


def write_candidates_csv(path: str | Path, rows: Sequence[NavRow]) -> Path:
    """Write the candidates of every ``ambiguous`` row, one line each, best first
    (columns :data:`CANDIDATE_COLUMNS`: ρ in m and q_I_B scalar-last, as in NAV.csv)."""
    path = Path(path)
    with open_table(path) as fh:
        writer = csv.writer(fh)
        writer.writerow(CANDIDATE_COLUMNS)
        for row in rows:
            for i, c in enumerate(row.candidates):
                values = [c.explained, *c.state.rho, *c.state.q_I_B]
                writer.writerow([f"{row.t:.17g}", i, *(f"{v:.17g}" for v in values)])
    return path


def navigate_run(
    input_dir: str | Path,
    out: str | Path,
    config: NavigationConfig | None = None,
    *,
    scenario: str | Path | None = None,
    prior_q_I_B: ArrayLike | None = None,
    debug_prior_from_truth: bool = False,
    intrinsics: str | Path | None = None,
    topic: str | None = None,
    measurements: Measurements = "rectangles",
    model: str | Path | None = None,
    fusion: FusionConfig | None = None,
) -> NavigationSummary:
    """Navigate every frame of an orbit run; writes ``out`` and ``out``'s ``.config.json``.

    Parameters
    ----------
    input_dir
        A run folder written by ``spacepose simulate orbit`` (its scenario.json gives the orbit,
        the chaser attitude ``R_O_C`` and the rectangle catalogue), or a folder of frame files
        (sorted by name, optional ``timestamps.txt``: seconds since the epoch where I and O
        coincide) together with ``scenario``.
    out
        NAV.csv path.
    config
        Navigation config; defaults in code.
    scenario
        YAML or JSON file with ``mean_motion`` (rad/s), ``R_O_C`` (3×3) and ``rectangles`` (the
        catalogue), optionally ``model`` (a cloud file of the target's surface samples with
        normals, relative to the scenario file) and ``initial_q_I_B``; overrides a run
        folder's scenario.json. A run folder's ``model.ply`` is the model otherwise.
    prior_q_I_B
        Optional coarse attitude prior (x, y, z, w) that picks among the target's symmetric
        poses at start; without it the navigator starts lost in space.
    debug_prior_from_truth
        DEBUGGING ONLY: take the prior from the scenario's ``initial_q_I_B``, the simulator's
        true start attitude, which no real run has.
    intrinsics, topic
        Depth image intrinsics file and bag topic (see :func:`spacepose.tools.frames.open_frames`).
    measurements
        ``rectangles`` (Yu's pipeline), ``registration`` (the model-based tracker's poses) or
        ``both`` in one filter (:mod:`spacepose.core.fused_navigation`).
    model
        Cloud file of the target's surface samples (model frame B', normals estimated when
        absent); overrides the scenario's ``model`` and the run's model.ply.
    fusion
        Tracker and pose settings for ``registration`` / ``both`` (its ``navigation`` and
        ``measurements`` are replaced by ``config`` and ``measurements``).

    Raises
    ------
    InputError
        Besides bad input: ``out`` named as a trajectory (``.tum``, ``.kitti``), or no frame
        was navigated (after NAV.csv is written), saying why.
    ConfigError
        The attitude prior is not a rotation
        (:func:`~spacepose.tools.navigation_config_io.prior_quaternion`), or is given with
        ``debug_prior_from_truth``.
    Interrupted
        Ctrl-C, after the frames done are written.
    """
    cfg = config or NavigationConfig()
    out = Path(out)
    frames = _open_checked_frames(input_dir, out, measurements, scenario, model, intrinsics, topic)
    if debug_prior_from_truth and prior_q_I_B is not None:
        # The scenario's true attitude replaced the given prior without a word.
        raise ConfigError(
            "--prior and --debug-prior-from-truth both give the attitude prior (the second "
            "replaces the first): give one"
        )
    description, source = read_scenario(input_dir, scenario)
    n, R_O_C = scenario_geometry(description, source)
    catalogue = []
    if measurements != "registration" or description.get("rectangles"):
        catalogue = parse_catalogue(description, cfg.rectangle, source)
    # The run's own model and scenario: its mesh then is the model's (a bootstrap may render it).
    own_model = model is None and scenario is None
    if model is not None:
        model = read_model(model)
    else:
        model = scenario_model(input_dir, scenario, description)
    cfg = with_run_settings(cfg, description, source, prior_q_I_B, debug_prior_from_truth)
    if untimed_folder(input_dir):
        # The orbit and the target's turn are propagated over the frames' times.
        warnings.warn(
            SpaceposeWarning(
                f"no {TIMESTAMPS_FILE} times the frames: frame k is taken at k s (1 Hz), and the "
                "orbit and the target's turn are propagated over those times",
                input_dir,
            ),
            stacklevel=2,
        )
    unreadable: dict[int, str] = {}
    pairs = _readable_pairs(frames, unreadable, planes=measurements != "registration")
    tracks: list[Any] = []
    health_csv = pose_noise_json = None
    if measurements == "rectangles":
        navigator = RelativeNavigator(catalogue, n, R_O_C, cfg, model)
        rows, interrupted = _steps(navigator.step, pairs)
        # The effective settings: a range noise measured on the first frame among them.
        config_json = dump_config(navigator.config, companion(out, ".csv", ".config.json"))
    else:
        fusion = (fusion or FusionConfig()).model_copy(
            update={"measurements": measurements, "navigation": cfg}
        )
        run = run_mesh_and_sensor(input_dir, description) if own_model else None
        noise = None
        if run is not None and model is not None:
            with warnings.catch_warnings():  # the navigating pass warns of each frame's problem
                warnings.simplefilter("ignore")
                again = ((f.timestamp, f.cloud) for f in frames)
                fusion, noise = bootstrapped_fusion(again, *run, model, fusion)
            if noise is None and fusion.bootstrap_poses:
                # Kept without a word, the factor looked measured (NAV.config.json holds it).
                problem = (
                    "the poses' σ factor is not measured on the run (too few ok poses, or ok "
                    f"renders, for its batches): the configured {fusion.pose_sigma_scale:g} is used"
                )
                warnings.warn(SpaceposeWarning(problem, input_dir), stacklevel=2)
        fused = FusedNavigator(catalogue, n, R_O_C, fusion, model)
        rows, tracks, interrupted = _navigate_fused(fused, pairs, unreadable)
        health_csv = write_health_csv(companion(out, ".csv", ".health.csv"), tracks)
        if fused.rectangles is not None:  # the effective settings, as for rectangles alone
            fusion = fusion.model_copy(update={"navigation": fused.rectangles.config})
        config_json = dump_config(fusion, companion(out, ".csv", ".config.json"))
        pose_noise_json = _write_pose_noise(out, noise)
        warn_unusable_frames(tracks, unreadable, health_csv)
    warn_refused_frames(rows, unreadable)
    nav_csv = write_nav_csv(out, rows)
    navigated = sum(r.state is not None for r in rows)
    ambiguous = sum(r.status == "ambiguous" for r in rows)
    candidates_csv = _write_candidates(out, rows, ambiguous > 0)
    if interrupted:
        raise Interrupted(
            f"interrupted after {len(rows)} frames: the table and its companions hold those frames",
            nav_csv,
        )
    if navigated == 0:
        why = why_nothing(rows, candidates_csv, model is not None)
        if measurements == "registration":
            why = why_no_registration(tracks, fusion, model is not None, health_csv)
        raise InputError(with_unreadable(why, len(rows), unreadable), input_dir)
    warn_if_predicted_alone(rows, navigated, cfg.prior_q_I_B is not None, nav_csv)
    warn_if_mostly_predicted(rows, nav_csv)
    if measurements == "both":
        warn_if_no_rectangle_used(rows, nav_csv)
    return NavigationSummary(
        nav_csv,
        config_json,
        len(rows),
        navigated,
        tuple(rows),
        ambiguous,
        candidates_csv,
        health_csv,
        pose_noise_json,
    )


def _open_checked_frames(
    input_dir: str | Path,
    out: Path,
    measurements: Measurements,
    scenario: str | Path | None,
    model: str | Path | None,
    intrinsics: str | Path | None,
    topic: str | None,
) -> Frames:
    """The run's frames, once ``out`` is known to name a table and its outputs are writable and
    none of the run's inputs (a frame, the scenario, the model, the intrinsics)."""
    if out.suffix.lower() in (".tum", ".kitti"):
        # A CSV table under a trajectory's name: report scored it as a track and left it out,
        # evaluate refused it, as evo does.
        raise InputError(
            f"navigate writes a CSV table (t, rho_x, ...), and a {out.suffix} file is read as "
            "a trajectory (report, evaluate, evo): name it .csv",
            out,
        )
    outputs = output_paths(out, measurements)
    check_writable(*outputs)
    check_not_anothers(out, ".csv", ".cov.csv", "track")
    frames = open_frames(input_dir, intrinsics=intrinsics, topic=topic)
    given = [p for p in (scenario, model, intrinsics) if p is not None]
    check_spares_inputs(outputs, [*input_files(input_dir, frames), *given])
    # NAV.csv's own suffix is a frame's: only another folder keeps it out of the frames.
    check_not_a_frame(out, frames, "a navigation table", "write it elsewhere")
    check_text_name(out, "a CSV table", "name it .csv")
    return frames


def _steps(
    step: Callable[[float, Any], Any], pairs: Iterable[tuple[float, Any]]
) -> tuple[list, bool]:
    """``step`` over the ``(t, cloud)`` pairs in time order, and whether Ctrl-C stopped it (the
    rows of the frames done are kept and written: a run of minutes lost them all)."""
    rows: list[Any] = []
    try:
        for t, cloud in frame_pairs(pairs):
            rows.append(step(t, cloud))
    except KeyboardInterrupt:
        return rows, True
    return rows, False


def _navigate_fused(
    navigator: FusedNavigator, pairs: Iterator[tuple[float, Any]], unreadable: dict[int, str]
) -> tuple[list[NavRow], list[Any], bool]:
    """The rows of a :class:`~spacepose.core.fused_navigation.FusedNavigator` over the pairs,
    the tracker's results (an unreadable frame's with its reason from ``unreadable``), and
    whether Ctrl-C stopped it (:func:`_steps`)."""
    fused, interrupted = _steps(navigator.step, pairs)
    rows = [r.nav for r in fused]
    tracks = [
        replace(r.track, reasons=(unreadable[k],)) if k in unreadable else r.track
        for k, r in enumerate(fused)
    ]
    return rows, tracks, interrupted


def _write_candidates(out: Path, rows: Sequence[NavRow], ambiguous: bool) -> Path | None:
    """Write ``out``'s ``.candidates.csv`` when some frame is ``ambiguous``; None otherwise."""
    path = companion(out, ".csv", ".candidates.csv")
    if ambiguous:
        return write_candidates_csv(path, rows)
    # An earlier run's candidates are not this run's (left beside it, they read as so).
    path.unlink(missing_ok=True)
    return None


def _write_pose_noise(out: Path, noise: PoseNoiseScale | None) -> Path | None:
    """The bootstrap's measurement of the poses' σ factor beside ``out`` (``.pose_noise.json``:
    the factor, each axis's batch ratio, the frames and batches), or None, and an earlier run's
    file removed, when it was not measured."""
    path = companion(out, ".csv", ".pose_noise.json")
    if noise is None:
        path.unlink(missing_ok=True)
        return None
    text = json.dumps(noise.to_dict() | {"axes": list(POSE_NOISE_AXES)}, indent=2)
    path.write_text(text + "\n", encoding="utf-8")
    return path


def output_paths(out: str | Path, measurements: Measurements = "rectangles") -> tuple[Path, ...]:
    """What :func:`navigate_run` may write for ``out`` (NAV.csv): ``out`` and its
    ``.config.json`` and ``.candidates.csv``, and with registration poses its ``.health.csv``
    and ``.pose_noise.json``."""
    out = Path(out)
    companions = [".config.json", ".candidates.csv"]
    companions += [".health.csv", ".pose_noise.json"] if measurements != "rectangles" else []
    return (out, *(companion(out, ".csv", c) for c in companions))


def _readable_pairs(
    frames: Frames, unreadable: dict[int, str], planes: bool = True
) -> Iterator[tuple[float, Any]]:
    """``(timestamp, cloud)`` of each frame; a frame that cannot be read, or (``planes``: its
    rectangles are measured) whose points hold no plane, goes in as an empty one (the filter
    predicts through it), is warned about, and its reason kept in ``unreadable``."""
    for frame in frames:
        cloud, what = frame.cloud, "cannot be read"
        if frame.error is not None:
            unreadable[frame.index] = frame.error
        elif planes and cloud is not None and (problem := _no_plane(cloud)) is not None:
            # Plane extraction refuses it, and that error ended the whole run.
            unreadable[frame.index], cloud, what = (
                f"{frame.source}: {problem}",
                None,
                "holds no plane",
            )
        if frame.index in unreadable:
            warnings.warn(
                SpaceposeWarning(
                    f"frame {frame.index} {what}, navigated as empty: {unreadable[frame.index]}"
                ),
                stacklevel=2,
            )
        yield frame.timestamp, cloud


def _no_plane(cloud: PointCloud) -> str | None:
    """Why a frame's points span no plane (fewer than 3, on one line or at one place), or None."""
    if len(cloud) < 3:
        return f"{len(cloud)} point(s): a plane needs 3"
    if on_a_line(cloud.points):
        return no_plane(cloud.points).reason
    return None
