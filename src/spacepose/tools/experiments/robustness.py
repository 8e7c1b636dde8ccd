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

Selecting cells (``ExperimentOptions.cells``, ``quick``):
:mod:`spacepose.tools.experiments.robustness_cells`. ``frames_csv`` writes every frame's scores
(status, reasons, stage times, errors, σ, bounds) to ``robustness_frames.csv`` and returns them
under ``frames``.

Outputs: ``robustness.json`` (definitions, one row per run, one per cell with the "Done when"
criteria it fails), ``robustness.md`` (the README table), ``robustness.png`` (summary) and
``robustness_runs.jsonl`` (each run as it finishes, so an interrupted grid keeps what it ran).
Runs go to ``jobs`` processes (results do not depend on it; ``ms_per_frame`` does).
"""

from __future__ import annotations

import csv
import multiprocessing
from collections import Counter
from collections.abc import Sequence
from concurrent.futures import ProcessPoolExecutor
from dataclasses import asdict, replace
from pathlib import Path
from typing import Any

import numpy as np
from matplotlib.figure import Figure

from spacepose.core import se3
from spacepose.core.config import load_config
from spacepose.core.sim import grid_scenario, simulate
from spacepose.core.track_result import revise_results
from spacepose.core.tracker import Tracker, TrackerConfig
from spacepose.errors import SpaceposeError
from spacepose.tools import plots
from spacepose.tools.experiments import ExperimentOptions, register
from spacepose.tools.experiments.robustness_cells import AXES, Cell, cell_scenario, select_cells
from spacepose.tools.experiments.robustness_scores import (
    DONE_WHEN,
    TRACKED_RANGE_FRACTION,
    FrameTruth,
    chain_bound,
    score_frame,
    summarise_cell,
)
from spacepose.tools.text_io import strict_json


def run_cell(
    cell: Cell, frames: int, workers: int = 1, tracker: TrackerConfig = TrackerConfig()
) -> dict[str, Any]:
    """Simulate and track one run with a ``tracker`` config; its coordinates, metrics and frame
    rows.

    An invalid cell (unknown motion, missing mesh), or a frame the tracker fails on with an
    error of the package's, gives a record with ``error`` and no metrics, so that one bad cell
    does not end a grid.
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
        try:
            results.append(tracking.track_frame(frame.cloud, frame.timestamp))
        except SpaceposeError as exc:  # a fault of the tracker's: this run's row says so
            return record | {"error": f"frame {k}: {exc}"}
        revise_results(results, results[-1])
        truths.append(FrameTruth.from_frame(frame, sim.T_sensor_target[0]))
    # The truth re-based on the frame whose sensor frame is the target frame: a later one
    # when the first was never confirmed (core.spare_anchor).
    first = tracking.first_index or 0
    if first:
        rebase = sim.T_sensor_target[0] @ se3.invert(sim.T_sensor_target[first])
        truths = [replace(t, T_true_k0=t.T_true_k0 @ rebase) for t in truths]
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
                fh.write(strict_json({k: v for k, v in record.items() if k != "frames"}) + "\n")
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

    ``false_ok`` and the status counts are summed over the seeds, the 3σ coverage is pooled
    over the ``ok`` frames of every seed; the "Done when" criteria
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
                elif name == "coverage_3sigma":
                    row[name], row[f"{name}_std"] = _pooled_coverage(metrics)
                elif isinstance(value, int | float):
                    vals = np.array([m[name] for m in metrics], dtype=np.float64)
                    row[name], row[f"{name}_std"] = float(np.mean(vals)), float(np.std(vals))
        row["fails"] = failed_criteria(row)
        table.append(row)
    return table


def _pooled_coverage(metrics: Sequence[dict[str, Any]]) -> tuple[float, float]:
    """Share of a cell's ``ok`` frames within 3σ, pooled over its runs, and the std over the
    runs that have ``ok`` frames (a run without one has no coverage, and must not make the
    cell's NaN); NaN, NaN when no run has one."""
    runs = [(m["coverage_3sigma"], m["ok"]) for m in metrics if m["ok"] > 0]
    if not runs:
        return float("nan"), float("nan")
    share, count = np.array(runs, dtype=np.float64).T
    return float(np.sum(share * count) / np.sum(count)), float(np.std(share))


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
            "coverage_3sigma": "share of ok frames within 3 sigma on all six axes (pooled over "
            "the seeds' ok frames)",
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
    (out_dir / "robustness.json").write_text(strict_json(result, indent=2, default=float) + "\n")
    (out_dir / "robustness.md").write_text(markdown_table(table))
    (out_dir / "robustness.png").write_bytes(plots.figure_png(summary_figure(table)))
    return result


@register("robustness", uses=("cells", "tracker", "frames", "frames_csv", "jobs"))
def robustness_experiment(out_dir: Path, options: ExperimentOptions) -> dict[str, Any]:
    """The default tracker over the robustness grid (module notes)."""
    runs, frames = select_cells(options.cells, options.quick, options.frames, options.seed)
    tracker = TrackerConfig()
    if options.tracker is not None:
        tracker = load_config(TrackerConfig, options.tracker)
    log = out_dir / "robustness_runs.jsonl"
    records = run_cells(runs, frames, options.jobs, options.workers, log, tracker)
    return write_outputs(out_dir, records, frames, options.frames_csv, tracker)
