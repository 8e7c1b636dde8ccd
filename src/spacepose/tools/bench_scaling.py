"""Scaling runs and memory of ``spacepose bench``.

:func:`run_scaling` times normals, FPFH, ICP and GICP, ours and the peers' interleaved, at each of
``BenchConfig.scaling_sizes`` points: random subsets of one frame pair rendered at a resolution that
holds the largest size (:func:`scaling_clouds`). Neighbourhoods are fixed in neighbours, not
metres, so that every size does the same work per point, and :func:`fit_exponent` gives the
exponent b of ``t ∝ N^b`` of each contender's median times; for ICP and GICP also our
step counts and the exponent of the time per step. :func:`peak_memory` is the tracemalloc
peak of one call of each of our stages.
"""

from __future__ import annotations

import math
import tracemalloc
from collections.abc import Mapping
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial import cKDTree

from spacepose.core.cloud import PointCloud
from spacepose.core.fpfh import FPFHConfig
from spacepose.core.gicp import gicp
from spacepose.core.icp import icp
from spacepose.core.normals import estimate_normals
from spacepose.core.sim import Frame
from spacepose.tools.bench_data import gicp_config, icp_config, render_frames
from spacepose.tools.bench_peers import Peers
from spacepose.tools.bench_trials import (
    Trial,
    fpfh_trials,
    gicp_trials,
    icp_trials,
    normals_trials,
    summarize,
    time_interleaved,
)

if TYPE_CHECKING:
    from spacepose.tools.bench import BenchConfig

SCALING_STAGES: tuple[str, ...] = ("normals", "fpfh", "icp", "gicp")
# Stages that iterate to a stopping test: their step count is reported beside their time, since
# a denser cloud may take more steps to meet the same tolerances (the peers' too).
_ITERATIVE: tuple[str, ...] = ("icp", "gicp")
# Render the scaling frames with this margin over the largest size, then subsample.
_RENDER_MARGIN = 1.15


# --------------------------------------------------------------------------------------------
# Scaling


def scaling_clouds(
    sizes: tuple[int, ...], base: Frame, seed: int, frame_scale: float
) -> tuple[list[tuple[PointCloud, PointCloud]], list[float]]:
    """Random subsets of one high-resolution frame pair, one pair of clouds per size.

    Parameters
    ----------
    sizes
        Point counts wanted.
    base
        A frame rendered at ``frame_scale``; its point count sets the resolution of the pair,
        rendered so that it holds ``max(sizes)`` points with a margin.
    seed, frame_scale
        Seed of the frames and the subsets; resolution of ``base``.

    Returns
    -------
    pairs, spacings
        (target = frame 0, source = frame 1) subsets, independent like two scans; and each
        size's point spacing (m): the rendered frame's median neighbour distance times
        ``sqrt(rendered / N)``, as a random subset thins the density in proportion.
    """
    scale = frame_scale * math.sqrt(_RENDER_MARGIN * max(sizes) / len(base.cloud))
    frames = render_frames(scale, 2, seed)
    full = frames[1].cloud.points
    spacing = float(np.median(cKDTree(full).query(full, k=2)[0][:, 1]))
    rng = np.random.default_rng(seed)
    pairs, spacings = [], []
    for n in sizes:
        subsets = []
        for f in frames:
            keep = np.sort(rng.choice(len(f.cloud), size=min(n, len(f.cloud)), replace=False))
            subsets.append(f.cloud.select(keep))
        pairs.append((subsets[0], subsets[1]))
        spacings.append(spacing * math.sqrt(len(full) / len(subsets[1])))
    return pairs, spacings


def run_scaling(
    config: BenchConfig,
    base: Frame,
    seed: int,
    workers: int,
    repeats: int,
    peers: Peers,
) -> dict:
    """Times of normals, FPFH, ICP and GICP over ``config.scaling_sizes``, and their exponents.

    Neighbourhoods are fixed in neighbours, not metres (normals k, GICP k, FPFH radius a fixed
    multiple of the point spacing), so the exponent measures the algorithm, not a neighbour
    count growing with density.
    """
    pairs, spacings = scaling_clouds(config.scaling_sizes, base, seed, config.frame_scale)
    series: dict[str, dict[str, list[float]]] = {s: {} for s in SCALING_STAGES}
    iterations: dict[str, list[int]] = {s: [] for s in _ITERATIVE}
    sizes = []
    for (target, source), spacing in zip(pairs, spacings, strict=True):
        sizes.append(len(source))
        target_n = estimate_normals(target, config.normals, workers=workers)
        source_n = estimate_normals(source, config.normals, workers=workers)
        fpfh = FPFHConfig(radius=config.fpfh_spacing_factor * spacing, max_nn=100)
        stage_trials = {
            "normals": normals_trials(source, config.normals, workers, peers),
            "fpfh": fpfh_trials(source_n, fpfh, workers, peers),
            "icp": icp_trials(source, target_n, icp_config(config), workers, peers),
            "gicp": gicp_trials(source, target, gicp_config(config), workers, peers),
        }
        for stage, trials in stage_trials.items():
            timings = time_interleaved(trials, repeats, config.warmup)
            for name, t in timings.items():
                series[stage].setdefault(name, []).append(summarize(t.times_ms)["median_ms"])
        # Untimed: how many steps our registrations took to meet the stopping test.
        icp_run = icp(source, target_n, np.eye(4), icp_config(config), workers)
        # Points only, as the GICP trials register them.
        src, tgt = PointCloud(source.points), PointCloud(target.points)
        gicp_run = gicp(src, tgt, np.eye(4), gicp_config(config), workers)
        iterations["icp"].append(icp_run.iterations)
        iterations["gicp"].append(gicp_run.iterations)
    stages: dict[str, dict[str, dict]] = {
        stage: {
            name: {"median_ms": times, "exponent": fit_exponent(sizes, times)}
            for name, times in by_name.items()
        }
        for stage, by_name in series.items()
    }
    for stage, counts in iterations.items():
        per_step = [t / n for t, n in zip(series[stage]["ours"], counts, strict=True)]
        stages[stage]["ours"] |= {
            "iterations": counts,
            "exponent_per_iteration": fit_exponent(sizes, per_step),
        }
    return {
        "sizes": sizes,
        "fpfh_radius_m": [config.fpfh_spacing_factor * s for s in spacings],
        "stages": stages,
    }


def fit_exponent(sizes: list[int], times_ms: list[float]) -> float:
    """Exponent b of ``t ∝ N^b``: least-squares slope of log t against log N."""
    return float(np.polyfit(np.log(sizes), np.log(times_ms), 1)[0])


# --------------------------------------------------------------------------------------------
# Memory


def peak_memory(trials: Mapping[str, Trial]) -> dict:
    """tracemalloc peak (MB) above the baseline of one call of each of our stages."""
    per_stage = {}
    tracemalloc.start()
    try:
        for name, setup in trials.items():
            call = setup()
            tracemalloc.reset_peak()
            base, _ = tracemalloc.get_traced_memory()
            call()
            per_stage[name] = (tracemalloc.get_traced_memory()[1] - base) / 2**20
    finally:
        tracemalloc.stop()
    return {"tracemalloc_peak_mb": per_stage, "pipeline_peak_mb": max(per_stage.values())}
