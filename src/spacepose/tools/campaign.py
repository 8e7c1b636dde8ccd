"""Monte Carlo campaigns: a grid of cases (scenario × noise × method × seed × ...) run on Dask.

A campaign is described by a :class:`CampaignConfig`. Its cases are the Cartesian product of the
grid axes; each case is identified by :func:`case_id`, a short hash of its sorted parameters, so a
resumed run recognises finished cases whatever the order of the grid. A case is computed by a
*case runner*, a function ``params -> {metric: scalar}`` registered under a name with
:func:`case_runner`; the config's ``case_kind`` picks it.

Output folder layout::

    out/campaign.json        config, package version (written first, checked on resume)
    out/parts/<case_id>.json one record per finished case, written atomically as it completes
    out/results.parquet      one row per case of the grid, sorted by case_id (params, metrics,
                             error, time_s, case_id); config and version in the schema metadata
    out/summary.json         per grid cell and metric: n, mean, std, median, p95 over seeds
    out/<metric>.png         each metric against noise_scale, one line per method

Killing a run loses at most the cases in flight: a part file appears only through ``os.replace``
of a complete temporary file, and a started-again run skips every case with a part.
"""

from __future__ import annotations

import contextlib
import hashlib
import itertools
import json
import logging
import math
import numbers
import os
import re
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import (
    Field,
    StrictBool,
    StrictFloat,
    StrictInt,
    StrictStr,
    field_validator,
    model_validator,
)
from scipy.spatial.transform import Rotation

from spacepose.core import se3
from spacepose.core.config import StageConfig, load_config
from spacepose.core.sim.sensors import SENSOR_PRESETS
from spacepose.errors import ConfigError, FileFormatError, SpaceposeError

Scalar = bool | int | float | str
Metrics = dict[str, bool | int | float]
CaseFunction = Callable[[dict[str, Scalar]], Mapping[str, Any]]

REQUIRED_AXES: tuple[str, ...] = ("scenario", "noise_scale", "method", "seed")
# Columns the campaign adds itself; neither an axis nor a metric may take these names.
RESERVED_COLUMNS: tuple[str, ...] = ("case_id", "error", "time_s")
# Keys of a summary record; an axis of that name would be overwritten there.
_SUMMARY_KEYS: tuple[str, ...] = ("metric", "n", "n_failed", "mean", "std", "median", "p95")
CAMPAIGN_FILE = "campaign.json"
PARTS_DIR = "parts"
RESULTS_FILE = "results.parquet"
SUMMARY_FILE = "summary.json"
_NAME_RE = re.compile(r"^[A-Za-z_][A-Za-z0-9_]*$")
# Fields of the config that must match for a folder to be resumed (workers, out may change).
_IDENTITY_FIELDS: tuple[str, ...] = ("name", "case_kind")


# --------------------------------------------------------------------------------------------
# Case runners
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class CaseRunner:
    """A registered case runner.

    Attributes
    ----------
    name
        The ``case_kind`` that selects it.
    fn
        ``fn(params) -> {metric: scalar}``; it must be a module-level function (Dask pickles it by
        reference into the worker processes) and deterministic given ``params``.
    choices
        Axis name -> the values it accepts (e.g. the ``method`` names); other axes are free.
    extra_axes
        Names of the optional axes the runner reads besides the four required ones.
    """

    name: str
    fn: CaseFunction
    choices: dict[str, tuple[Scalar, ...]]
    extra_axes: tuple[str, ...]


_RUNNERS: dict[str, CaseRunner] = {}


def case_runner(
    name: str,
    *,
    choices: Mapping[str, Sequence[Scalar]] | None = None,
    extra_axes: Sequence[str] = (),
) -> Callable[[CaseFunction], CaseFunction]:
    """Decorator registering ``fn(params) -> metrics`` as the runner of ``case_kind=name``.

    The runner receives one case's parameters (every grid axis, e.g. ``scenario``,
    ``noise_scale``, ``method``, ``seed``) and returns scalar metrics (bool, int or float). It
    raises a :class:`~spacepose.errors.SpaceposeError` (not ``ConfigError``) for an expected
    failure such as a registration without correspondences: the case is then recorded with its
    ``error`` message and no metrics.
    """

    def wrap(fn: CaseFunction) -> CaseFunction:
        allowed = {axis: tuple(values) for axis, values in (choices or {}).items()}
        _RUNNERS[name] = CaseRunner(name, fn, allowed, tuple(extra_axes))
        return fn

    return wrap


def get_runner(name: str) -> CaseRunner:
    """The runner registered for ``case_kind=name``; ConfigError listing the known ones if none."""
    if name not in _RUNNERS:
        raise ConfigError(
            f"unknown case_kind {name!r}; choose one of: {', '.join(sorted(_RUNNERS))}"
        )
    return _RUNNERS[name]


# --------------------------------------------------------------------------------------------
# The registration case: one simulated frame pair, a seeded initial error, one registration
# --------------------------------------------------------------------------------------------

REGISTRATION_METHODS: tuple[str, ...] = ("point_to_point", "point_to_plane", "gicp")
# The tracker's methods (TrackerConfig.method): the three above onto the current keyframe, Li's
# J-ICP and our keyframe graph.
TRACKER_METHODS: tuple[str, ...] = (*REGISTRATION_METHODS, "jicp", "keyframe")
# Defaults of the optional axes, per scenario: the lab mock-up is 0.3 m across at 1.2 m, the
# orbit satellite 6 m across at 25 m, so the initial offset and the gate scale with it.
REGISTRATION_DEFAULTS: dict[str, dict[str, float]] = {
    "lab": {"perturbation_deg": 2.0, "perturbation_mm": 10.0, "max_correspondence_mm": 50.0},
    "orbit": {"perturbation_deg": 2.0, "perturbation_mm": 100.0, "max_correspondence_mm": 500.0},
}
# Key of the perturbation's random stream; the simulator draws frame k from [seed, k] and the
# orbit truth from [seed, 2**31], so this stream is independent of both.
_PERTURBATION_STREAM = 2**31 + 1


def seeded_perturbation(
    center: ArrayLike, angle_deg: float, offset_m: float, seed: int
) -> NDArray[np.float64]:
    """A rigid motion (4, 4): a turn by ``angle_deg`` about a random axis through ``center``,
    then a shift by ``offset_m`` in a random direction (both drawn from ``seed``).

    Applied to the source cloud before the true transform (``T_true @ perturbation``) it
    misaligns the cloud by exactly ``angle_deg`` and moves its point ``center`` by ``offset_m``.
    """
    rng = np.random.default_rng([seed, _PERTURBATION_STREAM])
    axis, direction = rng.standard_normal((2, 3))
    R = Rotation.from_rotvec(np.radians(angle_deg) * axis / np.linalg.norm(axis))
    c = np.asarray(center, dtype=np.float64)
    return se3.make_transform(R, c - R.apply(c) + offset_m * direction / np.linalg.norm(direction))


def _registration_params(params: Mapping[str, Scalar]) -> dict[str, Any]:
    return REGISTRATION_DEFAULTS[str(params["scenario"])] | dict(params)


@case_runner(
    "registration",
    choices={
        "method": REGISTRATION_METHODS,
        "scenario": tuple(REGISTRATION_DEFAULTS),
        "sensor": tuple(SENSOR_PRESETS),
    },
    extra_axes=("sensor", "perturbation_deg", "perturbation_mm", "max_correspondence_mm"),
)
def registration_case(params: dict[str, Scalar]) -> Metrics:
    """Register simulated frame 1 to frame 0 of a two-frame run from a perturbed start.

    The scenario (``lab`` or ``orbit``, optional ``sensor`` preset) is simulated with the case's
    ``noise_scale`` and ``seed``; the start is the true ``T_frame0_frame1`` composed with
    :func:`seeded_perturbation` about the source centroid (``perturbation_deg``,
    ``perturbation_mm``); ``method`` is ``point_to_point``/``point_to_plane`` (:func:`icp`) or
    ``gicp``, gated at ``max_correspondence_mm``. Defaults: :data:`REGISTRATION_DEFAULTS`.
    Neighbour searches use one thread: a Dask worker process runs one case at a time.

    Returns
    -------
    dict
        ``rotation_error_deg`` (angle of ``R_est R_trueᵀ``), ``translation_error_mm`` (distance
        between the source centroid mapped by the estimate and by the truth), ``fitness``,
        ``inlier_rmse_mm``, ``iterations``, ``converged``, ``n_source``, ``n_target``,
        ``time_registration_s``.
    """
    from spacepose.core.gicp import GICPConfig, gicp
    from spacepose.core.icp import ICPConfig, icp
    from spacepose.core.sim import scenario_config, simulate

    p = _registration_params(params)
    sim_config = scenario_config(
        str(p["scenario"]),
        sensor=p.get("sensor"),
        noise_scale=float(p["noise_scale"]),
        frames=2,
        seed=int(p["seed"]),
    )
    sim = simulate(sim_config)
    target, source = sim.frame(0), sim.frame(1)
    T_true = target.T_sensor_target @ se3.invert(source.T_sensor_target)
    center = source.cloud.points.mean(axis=0)
    init_T_target_source = T_true @ seeded_perturbation(
        center, float(p["perturbation_deg"]), 1e-3 * float(p["perturbation_mm"]), int(p["seed"])
    )
    gate = 1e-3 * float(p["max_correspondence_mm"])
    start = time.perf_counter()
    if p["method"] == "gicp":
        config = GICPConfig(max_correspondence_distance=gate)
        result = gicp(source.cloud, target.cloud, init_T_target_source, config, workers=1)
    else:
        config = ICPConfig(max_correspondence_distance=gate, method=p["method"])
        result = icp(source.cloud, target.cloud, init_T_target_source, config, workers=1)
    elapsed = time.perf_counter() - start
    T_est = result.T_target_source
    delta_R = Rotation.from_matrix(T_est[:3, :3] @ T_true[:3, :3].T)
    shift = se3.transform_points(T_est, center[None]) - se3.transform_points(T_true, center[None])
    return {
        "rotation_error_deg": float(np.degrees(delta_R.magnitude())),
        "translation_error_mm": float(1e3 * np.linalg.norm(shift)),
        "fitness": float(result.fitness),
        "inlier_rmse_mm": float(1e3 * result.inlier_rmse),
        "iterations": int(result.iterations),
        "converged": bool(result.converged),
        "n_source": len(source.cloud),
        "n_target": len(target.cloud),
        "time_registration_s": elapsed,
    }


@case_runner(
    "tracking",
    choices={"method": TRACKER_METHODS, "scenario": ("lab",), "background": (False, True)},
    extra_axes=("frames", "background"),
)
def tracking_case(params: dict[str, Scalar]) -> Metrics:
    """Track a whole simulated lab run (model-free) and score it against the ground truth.

    Axes: ``method`` (tracker method), ``noise_scale``, ``seed``; optional ``frames`` (default
    58, the paper's run) and ``background`` (wall and turntable in the scene, removed by the
    tracker). Neighbour searches use one thread: a Dask worker process runs one case at a time.

    Returns
    -------
    dict
        Li's Table 2 means (``x_mm`` ... ``roll_deg``), the ATE RMSEs, the frame counts per
        status, the share of frames whose error lies within 3σ of the reported covariance on
        every axis, and the mean time per frame.
    """
    from spacepose.core.metrics import evaluate
    from spacepose.core.sim import scenario_config, simulate
    from spacepose.core.tracker import TrackerConfig, track_sequence
    from spacepose.core.trajectory import Trajectory

    background = bool(params.get("background", False))
    sim = simulate(
        scenario_config(
            "lab",
            noise_scale=float(params["noise_scale"]),
            frames=int(params.get("frames", 58)),
            seed=int(params["seed"]),
            background=background,
        )
    )
    config = TrackerConfig(method=str(params["method"]), use_background_removal=background)
    frames = [sim.frame(k) for k in range(len(sim))]
    output = track_sequence(
        [f.cloud for f in frames], [f.timestamp for f in frames], config, workers=1
    )
    gt = Trajectory(sim.timestamps, sim.T_sensor_target).rebased_first()
    table = evaluate(output.trajectory, gt, rebase_first=False).to_dict()
    # Errors in the covariance's own terms: left twist of T_est · T_gt⁻¹, one σ per axis.
    covered = []
    for result, T_gt in zip(output.results[1:], gt.poses[1:], strict=True):
        err = np.abs(se3.log(result.T_sensor_target @ se3.invert(T_gt)))
        covered.append(bool(np.all(err <= 3.0 * result.sigma)))
    statuses = [r.status for r in output.results]
    return {
        **{k: float(v) for k, v in table["mean"].items()},
        "ate_translation_mm": float(1e3 * table["ate_translation_rmse"]),
        "ate_rotation_deg": float(table["ate_rotation_rmse"]),
        "n_ok": statuses.count("ok"),
        "n_degraded": statuses.count("degraded"),
        "n_lost": statuses.count("lost"),
        "within_3sigma_share": float(np.mean(covered)) if covered else float("nan"),
        "time_per_frame_ms": float(np.mean([r.time_ms["total"] for r in output.results])),
    }


# --------------------------------------------------------------------------------------------
# Config and cases
# --------------------------------------------------------------------------------------------


class CampaignConfig(StageConfig):
    """A Monte Carlo campaign.

    Attributes
    ----------
    name
        Campaign name (stored with the results; a folder holds one campaign).
    grid
        Axis name -> list of values. ``scenario``, ``noise_scale``, ``method`` and ``seed`` are
        required; a runner may accept extra axes (e.g. ``frames``). Every axis is non-empty,
        without duplicates, of one type (numbers mixing int and float become float).
    out
        Output folder (relative paths are taken from the current directory).
    case_kind
        Name of the registered case runner.
    workers
        Worker processes of the local Dask cluster.
    threads_per_worker
        Threads per worker process (cases run concurrently in a worker).
    connect_timeout_s
        How long to wait for an external scheduler (``--scheduler``).
    """

    name: str = Field("campaign", min_length=1)
    grid: dict[str, list[StrictBool | StrictInt | StrictFloat | StrictStr]]
    out: Path = Path("runs/campaign")
    case_kind: str = "registration"
    workers: int = Field(2, ge=1)
    threads_per_worker: int = Field(1, ge=1)
    connect_timeout_s: float = Field(10.0, gt=0)

    @field_validator("grid")
    @classmethod
    def _check_grid(cls, grid: dict[str, list[Scalar]]) -> dict[str, list[Scalar]]:
        missing = [axis for axis in REQUIRED_AXES if axis not in grid]
        if missing:
            raise ValueError(f"missing axis {', '.join(missing)} (required: {REQUIRED_AXES})")
        return {axis: _check_axis(axis, values) for axis, values in grid.items()}

    @model_validator(mode="after")
    def _check_runner(self) -> CampaignConfig:
        # ConfigError is a ValueError, so pydantic reports it as this field's error.
        runner = get_runner(self.case_kind)
        for axis, allowed in runner.choices.items():
            unknown = [v for v in self.grid.get(axis, ()) if v not in allowed]
            if unknown:
                raise ValueError(
                    f"unknown {axis} {', '.join(map(repr, unknown))} for case_kind "
                    f"{self.case_kind!r}; choose from: {', '.join(map(str, allowed))}"
                )
        extra = [a for a in self.grid if a not in REQUIRED_AXES and a not in runner.extra_axes]
        if extra:
            raise ValueError(
                f"axis {', '.join(map(repr, extra))} is not used by case_kind {self.case_kind!r} "
                f"(it accepts: {', '.join(REQUIRED_AXES + runner.extra_axes)})"
            )
        return self


def _check_axis(axis: str, values: list[Scalar]) -> list[Scalar]:
    """Validate one grid axis; int/float mixtures become float so a column has one type."""
    if not _NAME_RE.match(axis) or axis in RESERVED_COLUMNS + _SUMMARY_KEYS:
        raise ValueError(
            f"axis name {axis!r} must be an identifier other than "
            f"{', '.join(RESERVED_COLUMNS + _SUMMARY_KEYS)}"
        )
    if not values:
        raise ValueError(f"axis {axis!r} is empty")
    kinds = {bool if isinstance(v, bool) else str if isinstance(v, str) else float for v in values}
    if len(kinds) > 1:
        raise ValueError(f"axis {axis!r} mixes value types: {values}")
    # noise_scale is always float, so 1 and 1.0 give one case id across config edits.
    if float in kinds and (axis == "noise_scale" or any(isinstance(v, float) for v in values)):
        values = [float(v) for v in values]
    if any(isinstance(v, float) and not math.isfinite(v) for v in values):
        raise ValueError(f"axis {axis!r} has a non-finite value: {values}")
    if len(set(values)) != len(values):
        raise ValueError(f"axis {axis!r} has duplicate values: {values}")
    if axis == "seed" and not all(isinstance(v, int) and not isinstance(v, bool) for v in values):
        raise ValueError(f"seeds must be integers, got {values}")
    if axis == "noise_scale" and not (float in kinds and all(v >= 0 for v in values)):
        raise ValueError(f"noise_scale values must be numbers >= 0, got {values}")
    if axis in ("scenario", "method") and kinds != {str}:
        raise ValueError(f"{axis} values must be names (strings), got {values}")
    return values


def load_campaign_config(
    path: str | Path, *, workers: int | None = None, out: str | Path | None = None
) -> CampaignConfig:
    """Read a campaign YAML/JSON file; ``workers`` and ``out`` override the file's values."""
    config = load_config(CampaignConfig, path)
    update: dict[str, Any] = {}
    if workers is not None:
        if workers < 1:
            raise ConfigError(f"workers must be >= 1, got {workers}")
        update["workers"] = workers
    if out is not None:
        update["out"] = Path(out)
    return config.model_copy(update=update)


@dataclass(frozen=True)
class Case:
    """One point of the grid: its parameters and their hash."""

    case_id: str
    params: dict[str, Scalar]


def case_id(params: Mapping[str, Scalar]) -> str:
    """Stable 12-hex-digit identifier of a parameter set (independent of key order)."""
    canonical = json.dumps(dict(params), sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(canonical.encode()).hexdigest()[:12]


def expand_grid(grid: Mapping[str, Sequence[Scalar]]) -> list[Case]:
    """All cases of the grid (Cartesian product of the axes), sorted by ``case_id``."""
    axes = list(grid)
    cases = []
    for values in itertools.product(*(grid[a] for a in axes)):
        params = dict(zip(axes, values, strict=True))
        cases.append(Case(case_id(params), params))
    return sorted(cases, key=lambda c: c.case_id)


# --------------------------------------------------------------------------------------------
# One case (runs in a Dask worker)
# --------------------------------------------------------------------------------------------


def execute_case(fn: CaseFunction, params: dict[str, Scalar]) -> dict[str, Any]:
    """Run one case and return its part record (what is stored in ``parts/<case_id>.json``).

    An expected failure (a :class:`SpaceposeError` other than ``ConfigError``) is recorded in
    ``error`` with empty metrics; any other exception propagates and stops the campaign.

    Raises
    ------
    TypeError
        If the runner returns something other than a mapping of scalar metrics, or a metric name
        that clashes with an axis or a reserved column.
    """
    start = time.perf_counter()
    error = None
    try:
        raw = fn(dict(params))
    except ConfigError:
        raise
    except SpaceposeError as exc:
        raw, error = {}, f"{type(exc).__name__}: {exc}"
    elapsed = time.perf_counter() - start
    return {
        "case_id": case_id(params),
        "params": dict(params),
        "metrics": _clean_metrics(raw, params, getattr(fn, "__name__", repr(fn))),
        "error": error,
        "time_s": elapsed,
    }


def _clean_metrics(raw: Any, params: Mapping[str, Scalar], who: str) -> Metrics:
    if not isinstance(raw, Mapping):
        raise TypeError(f"case runner {who} returned {type(raw).__name__}, not a dict of metrics")
    out: Metrics = {}
    for name, value in raw.items():
        if not isinstance(name, str) or not _NAME_RE.match(name):
            raise TypeError(f"case runner {who}: metric name {name!r} is not an identifier")
        if name in params or name in RESERVED_COLUMNS:
            raise TypeError(f"case runner {who}: metric {name!r} clashes with a column name")
        if isinstance(value, np.generic):
            value = value.item()
        if not isinstance(value, numbers.Real):  # bool and int are Real too
            raise TypeError(
                f"case runner {who}: metric {name!r} is a {type(value).__name__}, not a scalar"
            )
        out[name] = value
    return out


# --------------------------------------------------------------------------------------------
# Output folder
# --------------------------------------------------------------------------------------------


def _atomic_write(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` so that the file is either absent or complete."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    with open(tmp, "wb") as fh:
        fh.write(data)
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)


def _campaign_record(config: CampaignConfig) -> dict[str, Any]:
    from spacepose import __version__

    return {
        "config": config.model_dump(mode="json", exclude={"out"}),
        "spacepose_version": __version__,
    }


def prepare_out_dir(config: CampaignConfig) -> Path:
    """Create (or check, when resuming) the output folder and write ``campaign.json``.

    Raises
    ------
    ConfigError
        If the folder holds another campaign (different name, case kind or grid axes), or is a
        non-empty folder that is not a campaign folder.
    """
    out = Path(config.out)
    record_path = out / CAMPAIGN_FILE
    if out.exists() and not out.is_dir():
        raise ConfigError(f"{out}: campaign output must be a folder, this is a file")
    if record_path.exists():
        try:
            old = json.loads(record_path.read_text())["config"]
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise ConfigError(f"{record_path}: unreadable campaign record: {exc}") from None
        new = config.model_dump(mode="json")
        for field in _IDENTITY_FIELDS:
            if old.get(field) != new[field]:
                raise ConfigError(
                    f"{record_path}: folder holds campaign with {field}={old.get(field)!r}, "
                    f"config has {new[field]!r}; use another --out"
                )
        if sorted(old.get("grid", {})) != sorted(new["grid"]):
            raise ConfigError(
                f"{record_path}: folder holds campaign with axes {sorted(old.get('grid', {}))}, "
                f"config has {sorted(new['grid'])}; use another --out"
            )
    elif out.exists() and any(out.iterdir()):
        raise ConfigError(f"{out}: not empty and not a campaign folder (no {CAMPAIGN_FILE})")
    (out / PARTS_DIR).mkdir(parents=True, exist_ok=True)
    # Temporary files of a killed run are incomplete by construction: drop them.
    for tmp in (out / PARTS_DIR).glob(".*.tmp"):
        tmp.unlink()
    _atomic_write(record_path, (json.dumps(_campaign_record(config), indent=2) + "\n").encode())
    return out


def write_part(out_dir: Path, record: Mapping[str, Any]) -> Path:
    """Persist one finished case atomically as ``parts/<case_id>.json``."""
    path = Path(out_dir) / PARTS_DIR / f"{record['case_id']}.json"
    _atomic_write(path, json.dumps(record, sort_keys=True).encode())
    return path


def read_parts(out_dir: str | Path) -> dict[str, dict[str, Any]]:
    """Every finished case in ``out_dir/parts``: case_id -> part record.

    Raises
    ------
    FileFormatError
        If a part cannot be parsed or its parameters do not hash to its name (edited by hand).
    """
    parts: dict[str, dict[str, Any]] = {}
    for path in sorted((Path(out_dir) / PARTS_DIR).glob("*.json")):
        try:
            record = json.loads(path.read_text())
            ok = case_id(record["params"]) == path.stem == record["case_id"]
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise FileFormatError(f"unreadable campaign part: {exc}", path) from None
        if not ok:
            raise FileFormatError("part parameters do not match its case_id", path)
        parts[path.stem] = record
    return parts


def results_table(
    config: CampaignConfig, cases: Sequence[Case], parts: Mapping[str, Mapping[str, Any]]
) -> Any:
    """One ``pyarrow.Table`` row per case (sorted by case_id), config and version in metadata.

    Columns: the grid axes (config order), the metrics (sorted union over cases; null where a
    case failed), ``error`` (null when it succeeded), ``time_s``, ``case_id``.
    """
    import pyarrow as pa

    records = [parts[c.case_id] for c in sorted(cases, key=lambda c: c.case_id)]
    metric_names = sorted({m for r in records for m in r["metrics"]})
    columns: dict[str, Any] = {}
    for axis in config.grid:
        columns[axis] = pa.array([r["params"][axis] for r in records])
    for name in metric_names:
        values = [r["metrics"].get(name) for r in records]
        kinds = {type(v) for v in values if v is not None}
        # Mixed int/float (e.g. a metric that is sometimes nan) is stored as float.
        dtype = pa.float64() if (kinds <= {int, float} and float in kinds) or not kinds else None
        columns[name] = pa.array(values, type=dtype)
    columns["error"] = pa.array([r["error"] for r in records], type=pa.string())
    columns["time_s"] = pa.array([r["time_s"] for r in records], type=pa.float64())
    columns["case_id"] = pa.array([r["case_id"] for r in records], type=pa.string())
    record = _campaign_record(config)
    metadata = {
        b"spacepose.campaign": json.dumps(record["config"]).encode(),
        b"spacepose.version": str(record["spacepose_version"]).encode(),
    }
    return pa.table(columns).replace_schema_metadata(metadata)


def write_results(table: Any, out_dir: Path) -> Path:
    """Write the consolidated table to ``out_dir/results.parquet`` (atomically)."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    sink = pa.BufferOutputStream()
    pq.write_table(table, sink)
    path = Path(out_dir) / RESULTS_FILE
    _atomic_write(path, sink.getvalue().to_pybytes())
    return path


# --------------------------------------------------------------------------------------------
# Summary and plots
# --------------------------------------------------------------------------------------------


def summarize(
    rows: Sequence[Mapping[str, Any]],
    group_by: Sequence[str],
    metrics: Sequence[str],
) -> list[dict[str, Any]]:
    """Statistics of each metric per grid cell, in long form (one record per cell and metric).

    Parameters
    ----------
    rows
        One mapping per case (e.g. ``table.to_pylist()``), holding ``group_by`` keys, metrics
        and ``error``.
    group_by
        The axes that define a cell (every axis but ``seed``).
    metrics
        Metric names to summarise.

    Returns
    -------
    Records ``{**cell, "metric", "n", "n_failed", "mean", "std", "median", "p95"}`` sorted by
    cell then metric. Statistics use the finite values of the cell's successful cases; ``std`` is
    the sample standard deviation (ddof=1); ``p95`` the linearly interpolated 95th percentile;
    a statistic that is undefined (no value; std of one value) is ``None``.
    """
    cells: dict[tuple, list[Mapping[str, Any]]] = {}
    for row in rows:
        cells.setdefault(tuple(row[a] for a in group_by), []).append(row)
    out = []
    for key in sorted(cells):
        members = cells[key]
        n_failed = sum(r.get("error") is not None for r in members)
        for metric in metrics:
            v = np.array(
                [float(r[metric]) for r in members if r.get(metric) is not None], dtype=float
            )
            v = v[np.isfinite(v)]
            stats: dict[str, Any] = {"metric": metric, "n": int(v.size), "n_failed": n_failed}
            stats["mean"] = float(np.mean(v)) if v.size else None
            stats["std"] = float(np.std(v, ddof=1)) if v.size > 1 else None
            stats["median"] = float(np.median(v)) if v.size else None
            stats["p95"] = float(np.percentile(v, 95)) if v.size else None
            out.append({**dict(zip(group_by, key, strict=True)), **stats})
    return out


def plot_metrics(summary: Sequence[Mapping[str, Any]], group_by: Sequence[str]) -> dict[str, bytes]:
    """One PNG per metric: its mean (±std bars) against ``noise_scale``, one line per method.

    Scenarios and extra axes that take several values get their own lines too; the label names
    the method and those axes. Returns metric -> PNG bytes.
    """
    import matplotlib.pyplot as plt

    from spacepose.tools.plots import figure_png

    label_axes = [
        a
        for a in group_by
        if a == "method" or (a != "noise_scale" and len({s[a] for s in summary}) > 1)
    ]
    pngs = {}
    for metric in sorted({s["metric"] for s in summary}):
        fig, ax = plt.subplots(figsize=(6.5, 4))
        lines: dict[tuple, list[Mapping[str, Any]]] = {}
        for s in summary:
            if s["metric"] == metric and s["mean"] is not None:
                lines.setdefault(tuple(s[a] for a in label_axes), []).append(s)
        for key, points in sorted(lines.items()):
            points = sorted(points, key=lambda s: s["noise_scale"])
            x = [s["noise_scale"] for s in points]
            y = [s["mean"] for s in points]
            err = [s["std"] or 0.0 for s in points]
            label = ", ".join(f"{a}={v}" for a, v in zip(label_axes, key, strict=True))
            ax.errorbar(x, y, yerr=err, marker="o", capsize=3, label=label)
        ax.set_xlabel("noise_scale")
        ax.set_ylabel(f"{metric} (mean ± std over seeds)")
        ax.grid(alpha=0.3)
        if lines:
            ax.legend(fontsize=7)
        pngs[metric] = figure_png(fig)
    return pngs


# --------------------------------------------------------------------------------------------
# Running
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class CampaignResult:
    """What :func:`run_campaign` did.

    Attributes
    ----------
    out_dir
        The campaign folder.
    table
        The consolidated ``pyarrow.Table`` (also in ``results.parquet``).
    summary
        :func:`summarize` records (also in ``summary.json``).
    n_computed, n_skipped
        Cases computed by this call, and cases found already finished.
    """

    out_dir: Path
    table: Any
    summary: list[dict[str, Any]]
    n_computed: int
    n_skipped: int


@contextlib.contextmanager
def _dask_client(config: CampaignConfig, scheduler: str | None) -> Iterator[Any]:
    """A client of the given scheduler, or of a fresh local process cluster."""
    from dask.distributed import Client, LocalCluster

    if scheduler is not None:
        try:
            client = Client(scheduler, timeout=f"{config.connect_timeout_s}s")
        except (OSError, ValueError) as exc:
            raise ConfigError(f"cannot connect to Dask scheduler {scheduler!r}: {exc}") from None
        with client:
            yield client
        return
    with (
        LocalCluster(
            n_workers=config.workers,
            threads_per_worker=config.threads_per_worker,
            processes=True,
            # No dashboard, and the scheduler's HTTP endpoint on a free port (not 8787): several
            # campaigns may run side by side without port warnings.
            dashboard_address=":0",
            scheduler_kwargs={"dashboard": False},
            silence_logs=logging.ERROR,
        ) as cluster,
        Client(cluster) as client,
    ):
        yield client


def run_campaign(
    config: CampaignConfig, *, scheduler: str | None = None, progress: bool = True
) -> CampaignResult:
    """Run (or resume) a campaign and consolidate its results.

    Parameters
    ----------
    config
        The campaign; ``config.out`` is the folder.
    scheduler
        Address of a running Dask scheduler (``tcp://host:port``); by default a
        ``LocalCluster`` of ``config.workers`` processes is started and stopped.
    progress
        Show a rich progress bar on stderr.

    Returns
    -------
    CampaignResult
        The table, the summary and how many cases were computed or skipped.

    Raises
    ------
    ConfigError
        Incompatible existing folder, unreachable scheduler.
    """
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TimeRemainingColumn

    runner = get_runner(config.case_kind)
    out = prepare_out_dir(config)
    cases = expand_grid(config.grid)
    done = read_parts(out)
    todo = [c for c in cases if c.case_id not in done]
    if todo:
        with (
            _dask_client(config, scheduler) as client,
            Progress(
                "[progress.description]{task.description}",
                BarColumn(),
                MofNCompleteColumn(),
                TimeRemainingColumn(),
                console=Console(stderr=True),
                disable=not progress,
            ) as bar,
        ):
            from dask.distributed import as_completed

            task = bar.add_task(f"campaign {config.name}", total=len(cases))
            bar.update(task, completed=len(cases) - len(todo))
            futures = [client.submit(execute_case, runner.fn, c.params, pure=False) for c in todo]
            for future in as_completed(futures):
                record = future.result()
                write_part(out, record)
                done[record["case_id"]] = record
                bar.advance(task)
    table = results_table(config, cases, done)
    write_results(table, out)
    group_by = [a for a in config.grid if a != "seed"]
    metrics = [
        n for n in table.column_names if n not in config.grid and n not in ("error", "case_id")
    ]
    summary = summarize(table.to_pylist(), group_by, metrics)
    _atomic_write(out / SUMMARY_FILE, (json.dumps(summary, indent=2) + "\n").encode())
    for metric, png in plot_metrics(summary, group_by).items():
        _atomic_write(out / f"{metric}.png", png)
    return CampaignResult(out, table, summary, len(todo), len(cases) - len(todo))
