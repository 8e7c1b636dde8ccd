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
import warnings
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
import yaml
from numpy.typing import ArrayLike

from spacepose.core.cloud import PointCloud
from spacepose.core.config import (
    dump_config,
    load_structured,
    parse_problem,
    read_mapping,
    validate_config,
)
from spacepose.core.fused_navigation import FusionConfig, Measurements, fused_navigate
from spacepose.core.lost_in_space import with_sensor_fov
from spacepose.core.moments import distribution, is_collinear, no_plane
from spacepose.core.nav_result import NavRow, nav_table
from spacepose.core.nav_start import scenario_geometry
from spacepose.core.navigation import NavigationConfig, navigate
from spacepose.errors import ConfigError, FileFormatError, InputError, SpaceposeWarning
from spacepose.tools.catalogue import parse_catalogue
from spacepose.tools.cloud_io import read_cloud
from spacepose.tools.frames import Frames, input_files, open_frames
from spacepose.tools.outputs import check_spares_inputs, check_writable
from spacepose.tools.runs import SCENARIO, read_run
from spacepose.tools.text_io import read_text
from spacepose.tools.tracking_io import check_not_a_frame, open_table, write_health_csv

# How far from 1 a prior quaternion's norm may be before its normalisation is warned of: four
# numbers written to 3 decimals are within it, a norm of 2 (or 0.5) is not.
_PRIOR_NORM_TOLERANCE = 0.01

# What navigation reads from a scenario file (the orbit, the chaser's attitude, the catalogue,
# a model, the sensor's field of view, the debugging prior), and the rest of what a simulated
# orbit run's scenario.json holds (a test keeps these in step with the simulator).
NAVIGATION_KEYS = ("mean_motion", "R_O_C", "rectangles", "model", "sensor_fov_deg")
SCENARIO_KEYS = frozenset(
    {
        *NAVIGATION_KEYS, "initial_q_I_B", "R_O_C_true", "com_offset", "config", "frames",
        "inertia", "inertia_ratios", "initial_state", "process_noise", "rate_rad_s",
        "rectangles_true", "scenario", "seed", "spacepose_version", "target",
    }
)  # fmt: skip


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
        The attitude prior is not a rotation (:func:`prior_quaternion`), or is given with
        ``debug_prior_from_truth``.
    """
    cfg = config or NavigationConfig()
    out = Path(out)
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
    frames = open_frames(input_dir, intrinsics=intrinsics, topic=topic)
    given = [p for p in (scenario, model, intrinsics) if p is not None]
    check_spares_inputs(outputs, [*input_files(input_dir, frames), *given])
    # NAV.csv's own suffix is a frame's: only another folder keeps it out of the frames.
    check_not_a_frame(out, frames, "a navigation table", "write it elsewhere")
    if debug_prior_from_truth and prior_q_I_B is not None:
        # The scenario's true attitude replaced the given prior without a word.
        raise ConfigError(
            "--prior and --debug-prior-from-truth both give the attitude prior (the second "
            "replaces the first): give one"
        )
    if scenario is not None:
        source = str(scenario)
        description = _read_mapping(Path(scenario))
        _refuse_a_config(description, source)
        _warn_unknown_keys(description, source)
    elif (Path(input_dir) / SCENARIO).is_file():
        source = str(Path(input_dir) / SCENARIO)
        description = read_run(input_dir).scenario
        if description.get("scenario") == "orbit":  # an edited run's misspelt key, as above
            _warn_unknown_keys(description, source)
    else:
        raise InputError(
            "a folder of frames needs a scenario file (mean_motion, R_O_C, rectangles)", input_dir
        )
    n, R_O_C = scenario_geometry(description, source)
    catalogue = []
    if measurements != "registration" or description.get("rectangles"):
        catalogue = parse_catalogue(description, cfg.rectangle, source)
    model = read_cloud(model) if model is not None else _model(input_dir, scenario, description)
    if cfg.lost_in_space.fov_deg is None and "sensor_fov_deg" in description:
        fov = with_sensor_fov(cfg.lost_in_space, description["sensor_fov_deg"], source)
        cfg = cfg.model_copy(update={"lost_in_space": fov})
    prior_name = "prior_q_I_B"
    if debug_prior_from_truth:
        if "initial_q_I_B" not in description:
            raise InputError("missing key 'initial_q_I_B' for the attitude prior", source)
        prior_q_I_B, prior_name = description["initial_q_I_B"], f"{source}: initial_q_I_B"
    if prior_q_I_B is None:
        prior_q_I_B = cfg.prior_q_I_B  # from a config file, if any
    if prior_q_I_B is not None:
        prior = prior_quaternion(prior_q_I_B, prior_name)
        cfg = NavigationConfig.model_validate(cfg.model_dump() | {"prior_q_I_B": prior})
    unreadable: dict[int, str] = {}
    pairs = _readable_pairs(frames, unreadable, planes=measurements != "registration")
    health_csv = None
    if measurements == "rectangles":
        rows = navigate(pairs, catalogue, n, R_O_C, cfg, model)
        config_json = dump_config(cfg, Path(out).with_suffix(".config.json"))
    else:
        fusion = (fusion or FusionConfig()).model_copy(
            update={"measurements": measurements, "navigation": cfg}
        )
        fused = fused_navigate(pairs, catalogue, n, R_O_C, fusion, model)
        rows = [r.nav for r in fused]
        tracks = [
            replace(r.track, reasons=(unreadable[k],)) if k in unreadable else r.track
            for k, r in enumerate(fused)
        ]
        health_csv = write_health_csv(Path(out).with_suffix(".health.csv"), tracks)
        config_json = dump_config(fusion, Path(out).with_suffix(".config.json"))
        for k, track in enumerate(tracks):
            unusable = [r for r in track.reasons if r.startswith("unusable frame")]
            if k not in unreadable and unusable:  # said as the rectangles' path says its own
                problem = f"frame {k} navigated as empty: {unusable[0]}"
                warnings.warn(SpaceposeWarning(problem, health_csv), stacklevel=2)
    nav_csv = write_nav_csv(out, rows)
    navigated = sum(r.state is not None for r in rows)
    ambiguous = sum(r.status == "ambiguous" for r in rows)
    candidates_csv = None
    if ambiguous:
        candidates_csv = write_candidates_csv(Path(out).with_suffix(".candidates.csv"), rows)
    else:  # an earlier run's candidates are not this run's (left beside it, they read as so)
        Path(out).with_suffix(".candidates.csv").unlink(missing_ok=True)
    if navigated == 0:
        why = _why_nothing(rows, candidates_csv, model is not None)
        if measurements == "registration":
            why = _why_no_registration(tracks, fusion, model is not None, health_csv)
        if unreadable:
            k = min(unreadable)
            first = f"(frame {k}: {unreadable[k]})"
            # With none read, the rest of the reason (a catalogue's sizes, a tracker's poses)
            # would send the user after what no frame was there to show.
            why = (
                f"no frame navigated: none of the {len(rows)} frames could be read {first}"
                if len(unreadable) == len(rows)
                else f"{len(unreadable)} of {len(rows)} frames could not be read {first}; {why}"
            )
        raise InputError(why, input_dir)
    if navigated > 1 and not any(r.status == "update" for r in rows):
        # Started, then predicted alone: counted as navigated, 4 m and 178° off after a --prior
        # of the wrong side (no rectangle agreed with the pose it started from).
        hint = " (a --prior far from the target's attitude?)" if prior_q_I_B is not None else ""
        problem = (
            f"no measurement updated the filter after its start: {navigated - 1} frames "
            f"predicted alone{hint}"
        )
        warnings.warn(SpaceposeWarning(problem, nav_csv), stacklevel=2)
    return NavigationSummary(
        nav_csv,
        config_json,
        len(rows),
        navigated,
        tuple(rows),
        ambiguous,
        candidates_csv,
        health_csv,
    )


def load_navigation_config(
    path: str | Path, measurements: Measurements
) -> tuple[NavigationConfig, FusionConfig | None]:
    """A ``--config`` file: a :class:`NavigationConfig`, or the :class:`FusionConfig` that
    ``navigate --measurements registration|both`` writes as NAV.config.json (the filter's
    config and the fusion's).

    Raises
    ------
    ConfigError
        Not a valid config of either kind, or a fusion config whose ``measurements`` are not
        those of ``--measurements``.
    """
    data = read_mapping(path) or {}
    # NAV.config.json of a fused run: refused as eleven "Extra inputs" though navigate wrote it.
    if "navigation" not in data and "tracker" not in data:
        return _with_checked_prior(validate_config(NavigationConfig, data, path), path), None
    fusion = validate_config(FusionConfig, data, path)
    fusion = fusion.model_copy(update={"navigation": _with_checked_prior(fusion.navigation, path)})
    if fusion.measurements != measurements:
        raise ConfigError(
            f"{path}: a fusion config for --measurements {fusion.measurements}, given with "
            f"--measurements {measurements}: give --measurements {fusion.measurements}, or a "
            "navigation config"
        )
    return fusion.navigation, fusion


def _with_checked_prior(config: NavigationConfig, path: str | Path) -> NavigationConfig:
    """``config`` with its ``prior_q_I_B`` checked and normalised here, where the file is known
    (checked later, its error named the key alone, not the file)."""
    if config.prior_q_I_B is None:
        return config
    prior = prior_quaternion(config.prior_q_I_B, f"{path}: prior_q_I_B")
    return config.model_copy(update={"prior_q_I_B": prior})


def output_paths(out: str | Path, measurements: Measurements = "rectangles") -> tuple[Path, ...]:
    """What :func:`navigate_run` may write for ``out`` (NAV.csv): ``out`` and its
    ``.config.json`` and ``.candidates.csv``, and with registration poses its ``.health.csv``."""
    out = Path(out)
    companions = [".config.json", ".candidates.csv"]
    companions += [".health.csv"] if measurements != "rectangles" else []
    return (out, *(out.with_suffix(c) for c in companions))


def prior_quaternion(values: ArrayLike, name: str) -> tuple[float, float, float, float]:
    """``values`` as a unit attitude prior ``(qx, qy, qz, qw)``.

    Parameters
    ----------
    values
        The quaternion, scalar last; any non-zero norm.
    name
        What the values came from (``--prior``, a file's key), named by the error.

    Raises
    ------
    ConfigError
        Not four finite numbers, or a zero norm: no rotation (scipy would fail on it mid-run).

    Warns
    -----
    SpaceposeWarning
        The norm is more than 0.01 from 1 (it is normalised, as before, but no longer silently).
    """
    try:
        q = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError):
        q = np.empty(0)
    if q.shape != (4,) or not np.all(np.isfinite(q)) or not np.any(q):
        got = " ".join(repr(values).split())  # an array's repr may span lines
        raise ConfigError(
            f"{name}: the quaternion must be four finite numbers with a non-zero norm, got {got}"
        )
    # Scaled first: the norm of 1e-200s underflows to 0 and that of 1e308s overflows.
    largest = float(np.max(np.abs(q)))
    q = q / largest
    norm = float(np.linalg.norm(q)) * largest  # inf past 1.8e308, and warned of as such
    q /= np.linalg.norm(q)
    if not abs(norm - 1.0) <= _PRIOR_NORM_TOLERANCE:
        # Accepted (its direction is the rotation), but a norm of 2 is a typo or a scaled
        # vector more often than a deliberate choice: it was normalised without a word.
        warnings.warn(
            SpaceposeWarning(f"{name}: the quaternion has norm {norm:.6g}, not 1; normalised"),
            stacklevel=2,
        )
    return (float(q[0]), float(q[1]), float(q[2]), float(q[3]))


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
    if is_collinear(distribution(cloud.points)[1]):
        return no_plane(cloud.points).reason
    return None


def _why_no_registration(
    tracks: Sequence[Any], fusion: FusionConfig, has_model: bool, health_csv: Path | None
) -> str:
    """One line: why registration poses navigated no frame. Model-free, the filter waits for
    a batch of ok poses: a run shorter than it was said to have given "no ok pose", though
    the tracker gave one on every frame."""
    ok = sum(track.status == "ok" for track in tracks)
    if ok == 0:
        return f"no frame navigated: the tracker gave no ok pose (see {health_csv})"
    if not has_model and ok >= fusion.model_free_frames:
        return (
            f"no frame navigated: without a model the filter starts once its batch of ok poses "
            f"shows a rigid body's moments, and the tracker's {ok} did not (too little of the "
            "tumble seen?): a longer run, or a model (--model)"
        )
    if not has_model:
        return (
            f"no frame navigated: without a model the filter starts on a batch of "
            f"{fusion.model_free_frames} ok poses (the body's axes and centre of mass), and "
            f"the tracker gave {ok} in {len(tracks)} frames: a longer run, or a model (--model)"
        )
    return f"no frame navigated from the tracker's {ok} ok poses (see {health_csv})"


def _why_nothing(rows: Sequence[NavRow], candidates_csv: Path | None, has_model: bool) -> str:
    """One line: why no frame of the run was navigated."""
    if candidates_csv is not None:
        most = max(len(r.candidates) for r in rows)
        extra = "" if has_model else "; a target model (model.ply) might tell them apart"
        return (
            f"no frame navigated: the target's pose stayed ambiguous in all {len(rows)} frames "
            f"(up to {most} candidates explain the data equally well: a symmetric target?), "
            f"candidates in {candidates_csv}{extra}"
        )
    return (
        f"no frame navigated: none of the {len(rows)} frames shows a whole rectangle of the "
        "catalogue (check the catalogue's sizes and the plane settings)"
    )


def _refuse_a_config(description: dict, source: str) -> None:
    """Refuse a navigation or fusion config given as the scenario (NAV.config.json): its
    fourteen keys were warned of as unknown, then "missing key 'mean_motion'" ended the run.

    Raises
    ------
    ConfigError
        ``description`` holds no orbit key and a config's own sections.
    """
    sections = {"ekf", "plane", "rectangle", "lost_in_space", "navigation", "tracker"}
    if not set(description) & {"mean_motion", "R_O_C"} and set(description) & sections:
        raise ConfigError(
            f"{source}: a navigation config (--config), not a scenario (mean_motion, R_O_C, "
            "rectangles)"
        )


def _warn_unknown_keys(description: dict, source: str) -> None:
    """Warn, naming ``source``, of a scenario file's keys no scenario holds: a misspelt
    optional key (``rectangle`` for ``rectangles``) would otherwise be ignored without a
    word."""
    unknown = sorted(set(description) - SCENARIO_KEYS)
    if unknown:
        problem = (
            f"unknown keys {unknown} ignored (misspelt? navigation reads "
            f"{', '.join(NAVIGATION_KEYS)})"
        )
        warnings.warn(SpaceposeWarning(problem, source), stacklevel=3)


def _model(
    input_dir: str | Path, scenario: str | Path | None, description: dict
) -> PointCloud | None:
    """The target's surface samples: the scenario's ``model`` file (``null``: none given), else
    a run's model.ply.

    Raises
    ------
    InputError
        The scenario's ``model`` is not a file name (a number, a list, empty text): read as
        one it named a file "5" or "None", or the scenario's folder, not the scenario's key.
    """
    name = description.get("model") if scenario is not None else None
    if name is not None:
        if not isinstance(name, str) or not name.strip():
            raise InputError(
                f"model must name a cloud file (relative to the scenario), got {name!r}",
                scenario,
            )
        return read_cloud(Path(scenario).parent / name)
    if (Path(input_dir) / SCENARIO).is_file() and (Path(input_dir) / "model.ply").is_file():
        return read_run(input_dir).model
    return None


def _read_mapping(path: Path) -> dict:
    """A YAML or JSON file holding one mapping."""
    text = read_text(path, "the scenario")
    try:
        data = load_structured(text, "yaml")
    except yaml.YAMLError as exc:
        raise FileFormatError(f"not valid YAML/JSON: {parse_problem(exc)}", path) from None
    if not isinstance(data, dict):
        raise FileFormatError("a scenario file must hold a mapping", path)
    return data
