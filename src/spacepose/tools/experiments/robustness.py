"""``robustness``: the default tracker over the robustness grid (issue 9; scores in
:mod:`spacepose.tools.experiments.robustness_scores`).

Grid (:class:`RobustnessGrid`): target (``lab`` mock-up, ``hubble``, ``panels`` or a mesh path),
range (0.5, 1.2, 3, 6 m with the ToF camera; 25 m with the flash LiDAR, chosen by
:func:`~spacepose.core.sim.grid.grid_scenario`), noise (×1, ×3), motion (constant, accelerating,
tumbling at 2, 5 and 10° a frame), clutter (none, wall and table; the wall alone, ``wall``, only
when named) and 5 seeds, 30 frames a run. Every run is tracked model-free by
``Tracker(TrackerConfig())``: no flag, no model, no prior from the truth (``tracker``: a config
file's settings instead, written into the outputs). A cell's metrics are the mean ± std over its
seeds.

Selecting cells (``ExperimentOptions.cells``): ``"target=lab,range=1.2+25,seed=0"`` (``+`` separates
values; an axis not named spans the grid, or with ``quick`` takes the default cell's value), or a
YAML / JSON file holding any subset of :class:`RobustnessGrid`'s fields. ``quick`` alone runs the
default cell (lab, 1.2 m, ×1, constant, none) and seven variants, six changing one axis and the wall
alone at 3 m, 8 frames each. ``frames_csv`` writes every frame's scores (status, reasons, stage
times, errors, σ, bounds) to ``robustness_frames.csv`` and returns them under ``frames``.

Outputs: ``robustness.json`` (definitions, one row per run, one per cell with the "Done when"
criteria it fails), ``robustness.md`` (the README table), ``robustness.png`` (summary) and
``robustness_runs.jsonl`` (each run as it finishes, so an interrupted grid keeps what it ran).
Runs go to ``jobs`` processes (results do not depend on it; ``ms_per_frame`` does).
"""

from __future__ import annotations

import csv
import itertools
import json
import math
import multiprocessing
from collections import Counter
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.figure import Figure
from pydantic import Field, NonNegativeInt

import spacepose
from spacepose.core.config import StageConfig, load_config, validate_config
from spacepose.core.sim import LabConfig, grid_scenario, simulate
from spacepose.core.sim.grid import CLUTTERS, MOTIONS, motion_fields
from spacepose.core.tracker import Tracker, TrackerConfig
from spacepose.errors import ConfigError, SpaceposeError
from spacepose.tools import plots
from spacepose.tools.experiments import ExperimentOptions, register
from spacepose.tools.experiments.robustness_scores import (
    DONE_WHEN,
    TRACKED_RANGE_FRACTION,
    FrameTruth,
    chain_bound,
    score_frame,
    summarise_cell,
)

MODELS_DIR = Path(spacepose.__file__).resolve().parents[2] / "data" / "models"
TARGETS = {"hubble": "hubble_model_kit.obj", "panels": "satellite_panels.obj"}
AXES = ("target", "range", "noise", "motion", "clutter", "seed")
QUICK_FRAMES = 8
# Quick subset: the default cell and one variant per axis; the wall alone at 3 m, where the
# mock-up holds 1 % of the cells that the wall's spacing sizes.
QUICK_VARIANTS: tuple[dict[str, Any], ...] = (
    {"target": "hubble"},
    {"target": "panels"},
    {"range": 25.0},
    {"noise": 3.0},
    {"motion": "tumbling-5"},
    {"clutter": "wall-table"},
    {"clutter": "wall", "range": 3.0},
)


class RobustnessGrid(StageConfig):
    """The axes of the robustness grid (the full grid by default) and the frames of a run."""

    target: list[str] = Field(["lab", "hubble", "panels"], min_length=1)
    range: list[float] = Field([0.5, 1.2, 3.0, 6.0, 25.0], min_length=1)
    noise: list[float] = Field([1.0, 3.0], min_length=1)
    motion: list[str] = Field(list(MOTIONS), min_length=1)
    # The wall alone (a third clutter) is an option, not in the full grid of the README.
    clutter: list[str] = Field(["none", "wall-table"], min_length=1)
    seed: list[NonNegativeInt] = Field([0, 1, 2, 3, 4], min_length=1)
    frames: int = Field(30, ge=2, description="Frames per run.")


@dataclass(frozen=True)
class Cell:
    """One run of the grid: a cell's coordinates and a seed."""

    target: str = "lab"
    range: float = 1.2
    noise: float = 1.0
    motion: str = "constant"
    clutter: str = "none"
    seed: int = 0

    @property
    def key(self) -> tuple[Any, ...]:
        """The coordinates without the seed (the runs a table row averages)."""
        return (self.target, self.range, self.noise, self.motion, self.clutter)

    @property
    def label(self) -> str:
        return f"{self.target} {self.range:g} m x{self.noise:g} {self.motion} {self.clutter}"


def mesh_path(target: str) -> str:
    """``"lab"``, or the mesh file of a target name of :data:`TARGETS` or path."""
    if target == "lab":
        return target
    path = MODELS_DIR / TARGETS[target] if target in TARGETS else Path(target)
    if not path.is_file():
        raise ConfigError(f"{path}: robustness target {target!r} is not a mesh file")
    return str(path)


def parse_cells(spec: str) -> dict[str, list[str]]:
    """``"target=lab,range=1.2+25"`` -> ``{"target": ["lab"], "range": ["1.2", "25"]}``.

    Raises
    ------
    ConfigError
        An item that is not ``AXIS=VALUE[+VALUE...]``, an axis named twice, or no item at all.
    """
    axes: dict[str, list[str]] = {}
    for item in filter(None, (s.strip() for s in spec.split(","))):
        name, sep, values = item.partition("=")
        name = name.strip()
        if not sep or name not in AXES or not values.strip():
            raise ConfigError(
                f"--cells {item!r}: write AXIS=VALUE[+VALUE...] with AXIS one of {', '.join(AXES)}"
            )
        if name in axes:
            raise ConfigError(f"--cells: axis {name} is named twice; join its values with +")
        axes[name] = [v.strip() for v in values.split("+")]
    if not axes:
        raise ConfigError(f"--cells {spec!r} names no cells; write AXIS=VALUE[+VALUE...]")
    return axes


def cell_scenario(cell: Cell, frames: int) -> LabConfig:
    """The scenario config of one run of the grid (:func:`~spacepose.core.sim.grid_scenario`)."""
    return grid_scenario(
        target=mesh_path(cell.target),
        range_m=cell.range,
        noise_scale=cell.noise,
        motion=cell.motion,
        clutter=cell.clutter,
        seed=cell.seed,
        frames=frames,
    )


def cell_problem(cell: Cell) -> str | None:
    """What keeps a run from simulating (None: nothing), naming the axis and its value.

    Builds the run's scenario config (no simulation), so a whole grid is checked in
    milliseconds; the range must also lie within the range of the sensor the scenario picks,
    or the target's frames would be empty.
    """
    if cell.target != "lab" and cell.target not in TARGETS and not Path(cell.target).is_file():
        return f"unknown target {cell.target!r}; choose lab, {', '.join(TARGETS)} or a mesh file"
    if not (math.isfinite(cell.range) and cell.range > 0):
        return f"range {cell.range:g} is not a positive number of metres"
    if not (math.isfinite(cell.noise) and cell.noise >= 0):
        return f"noise {cell.noise:g} is not a factor >= 0 of the sensor's sigma"
    if cell.clutter not in CLUTTERS:
        return f"unknown clutter {cell.clutter!r}; choose {', '.join(CLUTTERS)}"
    try:
        motion_fields(cell.motion)
    except ConfigError as exc:  # an unknown name, told as such rather than as the cell's
        return str(exc)
    try:
        config = cell_scenario(cell, 2)
    except ConfigError as exc:
        return f"cell {cell.label} seed {cell.seed}: {exc}"
    sensor = config.sensor
    if not sensor.min_range <= cell.range <= sensor.max_range:
        return (
            f"range {cell.range:g} m is outside the {sensor.min_range:g}-{sensor.max_range:g} m "
            f"that the {sensor.model} sees"
        )
    return None


def check_cells(runs: Sequence[Cell], source: str) -> None:
    """Check every run before any starts (:func:`cell_problem`), so that a bad value ends the
    experiment at once instead of as an error record among the results.

    Raises
    ------
    ConfigError
        ``source: `` and the first problem found.
    """
    for cell in dict.fromkeys(runs):
        problem = cell_problem(cell)
        if problem is not None:
            raise ConfigError(f"{source}: {problem}")


def is_cells_file(cells: str) -> bool:
    """Whether a ``cells`` option names a YAML / JSON file (else it is a selection string)."""
    return Path(cells).suffix.lower() in (".yaml", ".yml", ".json")


def select_cells(
    cells: str | None, quick: bool, frames: int | None, seed: int = 0
) -> tuple[list[Cell], int]:
    """The runs and the frames per run an experiment's options ask for (module notes).

    Raises
    ------
    ConfigError
        A bad selection or cells file (an empty one included), or a run that cannot simulate
        (:func:`check_cells`).
    """
    source = "--cells"
    if cells is not None and is_cells_file(cells):
        source = cells
        grid = load_config(RobustnessGrid, cells)
        # An empty file would otherwise mean the whole grid, hours of runs nobody asked for.
        if not grid.model_fields_set:
            raise ConfigError(f"{cells}: holds no cells; set any of {', '.join(AXES)}")
    elif cells is not None:
        named = parse_cells(cells)
        base = {} if not quick else {a: [v] for a, v in asdict(Cell(seed=seed)).items()}
        base |= {"frames": QUICK_FRAMES} if quick else {}
        grid = validate_config(RobustnessGrid, base | named, source=source)
    elif quick:
        default = Cell(seed=seed)
        runs = [default, *(replace(default, **variant) for variant in QUICK_VARIANTS)]
        check_cells(runs, "--seed")
        return runs, frames or QUICK_FRAMES
    else:
        grid = RobustnessGrid()
    runs = [Cell(*values) for values in itertools.product(*(getattr(grid, a) for a in AXES))]
    check_cells(runs, source)
    return runs, frames or grid.frames


def run_cell(
    cell: Cell, frames: int, workers: int = 1, tracker: TrackerConfig = TrackerConfig()
) -> dict[str, Any]:
    """Simulate and track one run with a ``tracker`` config; its coordinates, metrics and frame
    rows.

    An invalid cell (unknown motion, missing mesh) gives a record with ``error`` and no metrics,
    so that one bad cell does not end a grid.
    """
    record: dict[str, Any] = {"cell": asdict(cell)}
    try:
        config = cell_scenario(cell, frames)
    except SpaceposeError as exc:
        return record | {"error": str(exc)}
    sim = simulate(config)
    tracking = Tracker(tracker, workers=workers)
    results, truths = [], []
    for k in range(len(sim)):
        frame = sim.frame(k)
        results.append(tracking.track_frame(frame.cloud, frame.timestamp))
        truths.append(FrameTruth.from_frame(frame, sim.T_sensor_target[0]))
    chains = chain_bound(results, truths)
    rows = [
        score_frame(r, t, c, cell.range) for r, t, c in zip(results, truths, chains, strict=True)
    ]
    return record | {"sensor": config.sensor.model, "metrics": summarise_cell(rows), "frames": rows}


def _run_cell_task(args: tuple[Cell, int, int, TrackerConfig]) -> dict[str, Any]:
    return run_cell(*args)


def warm_up(workers: int = 1) -> None:
    """Track a few small frames, so that compiling (or loading) the numba kernels does not
    count in the first run's time per frame."""
    sim = simulate(grid_scenario(frames=3, range_m=25.0))
    tracker = Tracker(TrackerConfig(), workers=workers)
    for frame in sim.frames():
        tracker.track_frame(frame.cloud, frame.timestamp)


def run_cells(
    runs: Sequence[Cell],
    frames: int,
    jobs: int,
    workers: int,
    log: Path | None = None,
    tracker: TrackerConfig = TrackerConfig(),
) -> list[dict[str, Any]]:
    """Every run, in order, tracked with ``tracker``; in ``jobs`` processes (one search thread
    each) when ``jobs > 1``.

    Each finished run is appended to ``log`` (JSON lines, frame rows left out) as it comes.
    """
    if log is not None:
        log.write_text("")

    def logged(record: dict[str, Any]) -> dict[str, Any]:
        if log is not None:
            with log.open("a") as fh:
                fh.write(json.dumps({k: v for k, v in record.items() if k != "frames"}) + "\n")
        return record

    if jobs <= 1 or len(runs) <= 1:
        warm_up(workers)
        return [logged(run_cell(c, frames, workers, tracker)) for c in runs]
    # spawn: a forked child of a process that already started OpenMP threads can hang.
    context = multiprocessing.get_context("spawn")
    with ProcessPoolExecutor(jobs, mp_context=context, initializer=warm_up) as pool:
        tasks = [(c, frames, 1, tracker) for c in runs]
        return [logged(r) for r in pool.map(_run_cell_task, tasks)]


def cell_table(records: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """One row per cell: mean and std over its seeds of every metric, and the criteria it fails.

    ``false_ok`` and the status counts are summed over the seeds; the "Done when" criteria
    (:data:`~spacepose.tools.experiments.robustness_scores.DONE_WHEN`) are checked on the means
    (the sum for ``false_ok``).
    """
    groups: dict[tuple[Any, ...], list[dict[str, Any]]] = {}
    for rec in records:
        groups.setdefault(Cell(**rec["cell"]).key, []).append(rec)
    table = []
    for key, recs in groups.items():
        done = [r for r in recs if "metrics" in r]
        row: dict[str, Any] = dict(zip(AXES[:-1], key, strict=True))
        row |= {
            "seeds": [r["cell"]["seed"] for r in done],
            "errors": [r["error"] for r in recs if "error" in r],
        }
        if done:
            metrics = [r["metrics"] for r in done]
            for name, value in metrics[0].items():
                if name == "reasons":
                    row[name] = dict(sum((Counter(m[name]) for m in metrics), Counter()))
                elif name.startswith("first_"):
                    row[name] = [m[name] for m in metrics]
                elif name in ("false_ok", "ok", "degraded", "lost", "coarse", "keyframes"):
                    row[name] = int(sum(m[name] for m in metrics))
                elif isinstance(value, int | float):
                    vals = np.array([m[name] for m in metrics], dtype=np.float64)
                    row[name], row[f"{name}_std"] = float(np.mean(vals)), float(np.std(vals))
        row["fails"] = failed_criteria(row)
        table.append(row)
    return table


def failed_criteria(row: dict[str, Any]) -> list[str]:
    """Names of the "Done when" criteria a cell row fails (a missing or NaN metric fails).

    A cell without any ``ok`` frame has no 3σ coverage: it fails as ``no_ok_frame``.
    """
    fails = []
    for name, op, bound in DONE_WHEN:
        value = row.get(name, float("nan"))
        good = value >= bound if op == ">=" else value <= bound
        if not good:  # NaN compares False
            fails.append(
                "no_ok_frame" if name == "coverage_3sigma" and row.get("ok") == 0 else name
            )
    return fails


def _fails(row: dict[str, Any], criterion: str) -> bool:
    """Whether a cell row fails a criterion (no ok frame counts as failing the coverage)."""
    no_ok = criterion == "coverage_3sigma" and "no_ok_frame" in row["fails"]
    return criterion in row["fails"] or no_ok


def _pm(row: dict[str, Any], name: str, fmt: str, scale: float = 1.0) -> str:
    if name not in row or not np.isfinite(row[name]):
        return "–"
    std = row.get(f"{name}_std", 0.0)
    text = format(scale * row[name], fmt)
    return text if len(row["seeds"]) < 2 else f"{text} ± {format(scale * std, fmt)}"


def markdown_table(table: Sequence[dict[str, Any]]) -> str:
    """The cell rows as a Markdown table (mean ± std over seeds), for the README."""
    head = (
        "| target | range (m) | noise | motion | clutter | seeds | tracked (%) | error (mm) | "
        "error (deg) | error / CRLB | error / chain CRLB | 3σ coverage (%) | false ok | "
        "ms / frame | fails |"
    )
    lines = [head, "|" + "---|" * head.count(" | ") + "---|"]
    for r in table:
        cells = [
            r["target"], f"{r['range']:g}", f"×{r['noise']:g}", r["motion"], r["clutter"],
            str(len(r["seeds"])), _pm(r, "tracked_share", ".1f", 100.0), _pm(r, "err_t_mm", ".3g"),
            _pm(r, "err_r_deg", ".3g"), _pm(r, "error_over_crlb", ".2g"),
            _pm(r, "error_over_chain", ".2g"), _pm(r, "coverage_3sigma", ".0f", 100.0),
            str(r.get("false_ok", "–")), _pm(r, "ms_per_frame", ".0f"),
            ", ".join(r["fails"] + [f"error: {e}" for e in r["errors"]]) or "–",
        ]  # fmt: skip
        lines.append("| " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


def summary_figure(table: Sequence[dict[str, Any]]) -> Figure:
    """Left: share of cells passing each criterion per axis value; right: every cell's error /
    CRLB against its tracked share, marked by whether its ok frames are consistent."""
    fig, (ax_pass, ax_cells) = plots.plt.subplots(1, 2, figsize=(13, 5.5))
    criteria = [name for name, _, _ in DONE_WHEN]
    labels, shares = [], []
    for axis in AXES[:-1]:
        for value in dict.fromkeys(r[axis] for r in table):
            rows = [r for r in table if r[axis] == value]
            labels.append(
                f"{axis} = {value:g}" if isinstance(value, float) else f"{axis} = {value}"
            )
            shares.append([np.mean([not _fails(r, c) for r in rows]) for c in criteria])
    image = ax_pass.imshow(np.array(shares), vmin=0, vmax=1, cmap="RdYlGn", aspect="auto")
    ax_pass.set_xticks(range(len(criteria)), criteria, rotation=20)
    ax_pass.set_yticks(range(len(labels)), labels, fontsize=8)
    ax_pass.set_title("share of cells passing each criterion")
    fig.colorbar(image, ax=ax_pass)
    for consistent in (True, False):
        rows = [
            r for r in table
            if (_fails(r, "false_ok") or _fails(r, "coverage_3sigma")) != consistent
        ]  # fmt: skip
        ax_cells.scatter(
            [100.0 * r.get("tracked_share", np.nan) for r in rows],
            [r.get("error_over_crlb", np.nan) for r in rows],
            marker="o" if consistent else "x",
            label="σ consistent" if consistent else "false ok or coverage < 95 %",
        )
    ax_cells.axhline(3.0, color="0.5", ls="--", lw=0.8)
    ax_cells.axvline(98.0, color="0.5", ls="--", lw=0.8)
    ax_cells.set_yscale("log")
    ax_cells.set_xlabel("frames tracked (%)")
    ax_cells.set_ylabel("mean error / per-frame CRLB")
    ax_cells.grid(alpha=0.3)
    ax_cells.legend()
    fig.tight_layout()
    return fig


def write_outputs(
    out_dir: Path,
    records: Sequence[dict[str, Any]],
    frames: int,
    frames_csv: bool,
    tracker: TrackerConfig = TrackerConfig(),
) -> dict[str, Any]:
    """Write robustness.json / .md / .png (and the frames CSV); return the JSON table."""
    table = cell_table(records)
    changed = tracker.model_dump(exclude_defaults=True)
    result: dict[str, Any] = {
        "experiment": "robustness",
        "frames_per_run": frames,
        "tracker": f"Tracker(TrackerConfig({changed or ''})): model-free, no prior",
        "tracker_config": tracker.model_dump(mode="json"),
        "definitions": {
            "tracked": f"status ok or degraded and the target points within "
            f"{100 * TRACKED_RANGE_FRACTION:g} % of the range (RMS) of the truth",
            "error": "position error of the target's centroid (mm), rotation angle (deg); "
            "frames not lost",
            "error_over_crlb": "mean error / mean per-frame frame-to-frame CRLB (sqrt trace at "
            "the centroid), the larger of translation and rotation",
            "error_over_chain": "the same against the CRLB accumulated along the tracker's own "
            "keyframe chain",
            "coverage_3sigma": "share of ok frames within 3 sigma on all six axes",
            "false_ok": "ok frames beyond 5 sigma on any axis (summed over seeds)",
            "done_when": [f"{n} {op} {b:g}" for n, op, b in DONE_WHEN],
        },
        "table": table,
        "runs": [{k: v for k, v in r.items() if k != "frames"} for r in records],
    }
    if frames_csv:
        rows = [r["cell"] | f for r in records for f in r.get("frames", [])]
        result["frames"] = rows
        if rows:
            with (out_dir / "robustness_frames.csv").open("w", newline="") as fh:
                writer = csv.DictWriter(fh, fieldnames=list(rows[0]))
                writer.writeheader()
                writer.writerows(rows)
    (out_dir / "robustness.json").write_text(json.dumps(result, indent=2, default=float) + "\n")
    (out_dir / "robustness.md").write_text(markdown_table(table))
    (out_dir / "robustness.png").write_bytes(plots.figure_png(summary_figure(table)))
    return result


@register("robustness", uses=("cells", "tracker"))
def robustness_experiment(out_dir: Path, options: ExperimentOptions) -> dict[str, Any]:
    """The default tracker over the robustness grid (module notes)."""
    runs, frames = select_cells(options.cells, options.quick, options.frames, options.seed)
    tracker = TrackerConfig()
    if options.tracker is not None:
        tracker = load_config(TrackerConfig, options.tracker)
    log = out_dir / "robustness_runs.jsonl"
    records = run_cells(runs, frames, options.jobs, options.workers, log, tracker)
    return write_outputs(out_dir, records, frames, options.frames_csv, tracker)
