"""Li et al. 2024 on the simulator (methods.md §1.7): L3 and L4, tracking with every method.

- ``li-l3``: the lab run (570 mm, 57°) tracked model-free with every method of
  :data:`~spacepose.tools.experiments.li.METHODS`, over seeds (``--seeds``, 10 by default):
  Li's Table 2 (per-axis mean absolute error; its mean and std over seeds and the mean
  within-run std), the paper's values beside, a CRLB column (√diag of the frame-to-frame
  bound, methods.md §4, averaged over frames and seeds), on the clean profile and on the
  paper-like one with mpp-MLS off and on; error curves of the first seed (Li Figs. 11–12). In
  full mode the methods run again on the scene with background (wall, turntable) and
  background removal, first seed.
- ``li-l4``: time per frame per method on the paper-like profile, mpp-MLS off and on (Li
  Table 3).

``quick`` runs 5 frames (L4: 8) and 2 seeds, the clean profile and the paper-like one with
mpp-MLS, and skips the background run; the numbers then only smoke-test the pipeline.
"""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

import numpy as np

from spacepose.core.metrics import error_table, pose_errors
from spacepose.core.sim.sensors import sensor_config
from spacepose.core.sim.simulation import Simulation
from spacepose.core.tracker import TrackerConfig, track_sequence
from spacepose.tools import plots
from spacepose.tools.experiments import ExperimentOptions, register
from spacepose.tools.experiments.li import (
    AXES,
    METHOD_LABELS,
    METHODS,
    PAPER_JICP_OVER_ICP,
    PAPER_TABLE2,
    PAPER_TIME_MS,
    _lab,
    _write,
)


def method_configs(use_mls: bool = False) -> dict[str, TrackerConfig]:
    """The tracker config of every method of :data:`METHODS` (defaults otherwise)."""
    return {m: TrackerConfig(method=m, use_mls=use_mls) for m in METHODS}


def run_methods(
    sim: Simulation, options: ExperimentOptions, background: bool = False, use_mls: bool = False
) -> dict[str, dict[str, Any]]:
    """Track the run with every method of :func:`method_configs`; errors, σ and timings."""
    frames = [sim.frame(k) for k in range(len(sim))]
    gt = sim.groundtruth.rebased_first().poses
    out: dict[str, dict[str, Any]] = {}
    for name, cfg in method_configs(use_mls).items():
        cfg = cfg.model_copy(update={"use_background_removal": background})
        tic = time.perf_counter()
        tracked = track_sequence(
            [f.cloud for f in frames], sim.timestamps, cfg, workers=options.workers
        )
        wall = time.perf_counter() - tic
        poses = tracked.trajectory.poses
        dt, de = pose_errors(poses, gt)
        times = np.array([r.time_ms["total"] for r in tracked.results])
        out[name] = {
            "table": error_table(poses, gt).to_dict(),
            "errors": np.c_[1e3 * dt, np.degrees(de[:, [1, 0, 2]])],  # x y z mm, pitch yaw roll
            "status": [r.status for r in tracked.results],
            "time_ms": times,
            "stage_ms": {
                s: float(np.median([r.time_ms[s] for r in tracked.results[1:]]))
                for s in ("preprocess", "coarse", "fine")
            },
            "wall_s": wall,
        }
    return out


def crlb_column(sim: Simulation) -> dict[str, float]:
    """Mean over frames 1.. of √diag of the frame-to-frame CRLB, in the table's axes/units."""
    stds = np.array([sim.frame(k).crlb(frame_to_frame=True).std for k in range(1, len(sim))])
    m = stds.mean(axis=0)
    # Twist (rx, ry, rz, tx, ty, tz); pitch is about y, yaw about z, roll about x (methods.md §0).
    return {
        "x_mm": 1e3 * m[3],
        "y_mm": 1e3 * m[4],
        "z_mm": 1e3 * m[5],
        "pitch_deg": float(np.degrees(m[1])),
        "yaw_deg": float(np.degrees(m[2])),
        "roll_deg": float(np.degrees(m[0])),
    }


def l3_summary(runs: list[dict[str, dict[str, Any]]]) -> dict[str, Any]:
    """Table 2 over seeds: per method and axis, the mean over seeds of each run's mean absolute
    error, its standard deviation over seeds, and the mean of each run's own (frame) std."""
    means = {m: np.array([[r[m]["table"]["mean"][a] for a in AXES] for r in runs]) for m in METHODS}
    stds = {m: np.array([[r[m]["table"]["std"][a] for a in AXES] for r in runs]) for m in METHODS}
    table = {
        a: {
            m: {
                "mean": float(means[m][:, n].mean()),
                "seed_std": float(means[m][:, n].std()),
                "frame_std": float(stds[m][:, n].mean()),
            }
            for m in METHODS
        }
        for n, a in enumerate(AXES)
    }
    # Mean over the six axes of 1 − method/baseline, on the means over seeds.
    reduction = {
        m: {
            b: float(np.mean(1.0 - means[m].mean(axis=0) / means[b].mean(axis=0)))
            for b in ("point_to_point", "point_to_plane")
        }
        for m in ("jicp", "keyframe")
    }
    statuses = {m: [s for r in runs for s in r[m]["status"]] for m in METHODS}
    return {
        "table": table,
        "reduction_vs": reduction,
        "at_or_below_paper_jicp": {
            m: {a: table[a][m]["mean"] <= PAPER_TABLE2["jicp"][a][0] for a in AXES}
            for m in ("jicp", "keyframe")
        },
        "status_counts": {
            m: {s: statuses[m].count(s) for s in ("ok", "degraded", "lost")} for m in METHODS
        },
        "median_ms": {
            m: float(np.median(np.concatenate([r[m]["time_ms"][1:] for r in runs])))
            for m in METHODS
        },
    }


def l3_variants(quick: bool) -> dict[str, tuple[str, bool]]:
    """Noise profile and mpp-MLS of each L3 variant: both profiles, mpp-MLS off and on the
    paper-like one (quick: the paper-like profile with mpp-MLS only)."""
    if quick:
        return {"tof-clean": ("tof-clean", False), "tof-paper+mls": ("tof-paper", True)}
    return {
        "tof-clean": ("tof-clean", False),
        "tof-paper": ("tof-paper", False),
        "tof-paper+mls": ("tof-paper", True),
    }


@register("li-l3", uses=("seeds",))
def lab_run_experiment(out_dir: Path, options: ExperimentOptions) -> dict[str, Any]:
    """Li Table 2 and Figs. 11–12 on the simulated lab run, every method, over seeds."""
    n_seeds = options.seeds or (2 if options.quick else 10)
    seeds = list(range(options.seed, options.seed + n_seeds))
    table: dict[str, Any] = {
        "experiment": "li-l3",
        "seeds": seeds,
        "methods": METHOD_LABELS,
        "paper": PAPER_TABLE2,
        "variants": {},
    }
    figures = {}
    frames = 5 if options.quick else None  # None: the run's 58
    variants = l3_variants(options.quick)
    runs: dict[str, list[dict[str, Any]]] = {v: [] for v in variants}
    crlb: dict[str, list[dict[str, float]]] = {v: [] for v in variants}
    for seed in seeds:
        for sensor in dict.fromkeys(p for p, _ in variants.values()):
            sim = _lab(options, frames, seed=seed, sensor=sensor_config(sensor))
            for variant, (profile, use_mls) in variants.items():
                if profile == sensor:
                    runs[variant].append(run_methods(sim, options, use_mls=use_mls))
                    crlb[variant].append(crlb_column(sim))
    t = sim.timestamps - sim.timestamps[0]
    table["frames"] = len(sim)
    for variant, (sensor, use_mls) in variants.items():
        table["variants"][variant] = {
            "sensor": sensor,
            "mls": use_mls,
            **l3_summary(runs[variant]),
            "crlb_frame_to_frame": {a: float(np.mean([c[a] for c in crlb[variant]])) for a in AXES},
        }
        first = runs[variant][0]
        figures[f"_{variant}"] = plots.pose_error_curves(
            t,
            {m: r["errors"] for m, r in first.items()},
            f"lab run, {variant}, seed {seeds[0]}: pose errors (Li Figs. 11-12)",
        )
        figures[f"_{variant}_health"] = plots.health_timeline(
            t, {m: r["status"] for m, r in first.items()}
        )
    if not options.quick:
        bg = run_methods(_lab(options, background=True), options, background=True)
        table["background"] = {"seed": options.seed, **l3_summary([bg])}
    return _write(out_dir, "li-l3", table, figures)


@register("li-l4")
def timing_experiment(out_dir: Path, options: ExperimentOptions) -> dict[str, Any]:
    """Li Table 3: time per frame per method (frame 0 excluded: no registration), on the
    paper-like ToF profile with mpp-MLS off and on."""
    sim = _lab(options, sensor=sensor_config("tof-paper"))
    rows = {}
    for use_mls in (False, True):
        for m, r in run_methods(sim, options, use_mls=use_mls).items():
            rows[f"{m}+mls" if use_mls else m] = {
                "mean_ms": float(r["time_ms"][1:].mean()),
                "median_ms": float(np.median(r["time_ms"][1:])),
                "stage_median_ms": r["stage_ms"],
            }
    table = {
        "experiment": "li-l4",
        "sensor": "tof-paper",
        "frames": len(sim),
        "workers": options.workers,
        "rows": rows,
        "jicp_over_point_to_point": rows["jicp"]["median_ms"] / rows["point_to_point"]["median_ms"]
        - 1.0,
        "paper": {"jicp_ms": PAPER_TIME_MS, "jicp_over_icp": PAPER_JICP_OVER_ICP},
        "note": "wall time on this machine, shared with other jobs; see `spacepose bench`",
    }
    fig, ax = plots.plt.subplots(figsize=(9, 3.5))
    names = list(rows)
    ax.bar(names, [rows[m]["median_ms"] for m in names])
    ax.axhline(PAPER_TIME_MS, color="0.4", ls="--", label="paper J-ICP (i7-7700)")
    ax.set_ylabel("median time per frame (ms)")
    ax.tick_params(axis="x", labelrotation=30)
    ax.legend()
    fig.tight_layout()
    return _write(out_dir, "li-l4", table, {"": fig})
