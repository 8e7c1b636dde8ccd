"""``spacepose bench``: speed and accuracy of the pipeline's stages beside Open3D and small_gicp.

Every stage runs on the same simulated lab frames (ToF camera, default noise) for our code and
for each peer, in one process and interleaved (ours, open3d, small_gicp, ours, ...) so that a
change in machine load hits every contender alike. A peer's time includes turning the numpy
inputs into its own types, as a Python caller has to. Registrations (ICP, GICP, RANSAC) are
also scored against the simulator's ground truth beside the Cramér–Rao bound of the frame.

Inputs (methods.md §3 lab scenario, frames 0, 1, 2 of a three-frame run, and a longer run of
the same scenario for ``tracking_step``):

* ``normals``, ``mpp_mls``: frame 0 as rendered.
* ``voxel``: frame 0 voxel-downsampled at the default tracker's voxel (what it derives from it).
* ``fpfh``, ``ransac``: frames 0 and 1 voxel-downsampled (``coarse_voxel_size``), normals within
  2× and FPFH within 5× the voxel (Open3D's global-registration recipe); RANSAC gets the same
  features for every contender, so it compares the sampling and scoring alone.
* ``icp`` (point-to-plane, target normals given) and ``gicp``: frame 1 (source) onto frame 0
  (target) from the identity; truth ``T_s0_s1 = T_s0_target · T_s1_target⁻¹``.
* ``jicp_step``: the third step of a fresh :class:`~spacepose.core.jicp.JointICP` (Li's J-ICP).
* ``tracking_step``: the steady state of a running model-free
  :class:`~spacepose.core.tracker.Tracker` (preprocess + fine registration + health and
  covariance): the default tracker runs frames ``0 .. tracking_warmup_frames − 1`` once
  (untimed; its keyframe window is then full), and each timed call restores that state and
  tracks the next ``tracking_frames`` frames; the row is the time per frame. Open3D does its
  core steps on the same frames (voxel downsampling, normals, point-to-plane ICP onto the
  previous frame prepared as its keyframe, from the previous pose) without health checks or
  covariance.
* ``tracking_second_frame``: the cold start, the second frame of a fresh tracker (no motion
  history yet, so the motion model's wide robust first pass runs), beside Open3D's core steps
  against frame 0 prepared as a keyframe.
* ``ekf_step``: one predict + pose update of the orbit EKF, from the orbit truth.
* ``raw_<W>x<H>``: the ``tracking_step`` on raw frames of the lab mock-up before its wall at
  the ToF camera's full resolution (:mod:`spacepose.tools.bench_fullres`, 300k points at 640×480,
  900k at 1280×720): two untimed frames (the first, the scale estimate, and the second, the cold
  start, are reported beside the row), then ``raw_frames`` timed frames per call.
  The tracker's peak resident memory on a stream at the largest resolution is in ``memory``.

Set-up that a stage needs but is not part of it (the earlier frames of a tracker, restored from a
copy) is done before each timed call and not timed.

Here: the options, the run that assembles the JSON and its tables. Elsewhere: the stages' inputs
and truth (:mod:`~spacepose.tools.bench_data`), the peers and the environment record
(:mod:`~spacepose.tools.bench_peers`), the trials and the interleaved timer
(:mod:`~spacepose.tools.bench_trials`), the scaling runs and memory
(:mod:`~spacepose.tools.bench_scaling`).
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

from pydantic import Field, PositiveFloat, PositiveInt
from rich.table import Table

from spacepose.core.config import StageConfig, load_config
from spacepose.core.normals import NormalsConfig
from spacepose.errors import ConfigError, InputError
from spacepose.tools.bench_data import (
    coarse_fpfh,
    crlb_summary,
    gicp_config,
    icp_config,
    prepare_data,
    ransac_config,
    registration_error,
    render_frames,
)
from spacepose.tools.bench_fullres import max_rss_mb, raw_frames, stream_peak_rss
from spacepose.tools.bench_peers import (
    PEERS,
    Open3D,
    Peers,
    SmallGICP,
    environment,
    load_peers,
    thread_count,
)
from spacepose.tools.bench_scaling import peak_memory, run_scaling
from spacepose.tools.bench_trials import (
    Trial,
    ekf_trials,
    fpfh_trials,
    gicp_trials,
    icp_trials,
    jicp_trials,
    mls_trials,
    normals_trials,
    per_frame,
    ransac_trials,
    second_frame_trials,
    stage_entry,
    steady_trials,
    time_interleaved,
    tracker_lengths,
    tracking_shares,
    voxel_trials,
)
from spacepose.tools.outputs import check_writable
from spacepose.tools.text_io import strict_json

STAGES: tuple[str, ...] = (
    "voxel",
    "normals",
    "mpp_mls",
    "fpfh",
    "ransac",
    "icp",
    "gicp",
    "jicp_step",
    "tracking_step",
    "tracking_second_frame",
    "ekf_step",
)
REGISTRATIONS: tuple[str, ...] = ("ransac", "icp", "gicp")
FULL_SIZES: tuple[int, ...] = (5000, 10000, 20000, 40000, 80000)
QUICK_SIZES: tuple[int, ...] = (5000, 10000, 20000)
# Timed calls per stage and contender: each repeat times every stage again (5 take minutes).
MOST_REPEATS = 100


class BenchConfig(StageConfig):
    """What :func:`run_benchmark` measures, and on which data.

    Attributes
    ----------
    frame_scale
        Resolution of the stage frames relative to the 640×480 ToF camera (0.5: 320×240),
        0.1-3: below, the lab target holds too few points for its normals (0.05: none has 3
        neighbours); above 1920×1440 the stage frames outgrow the raw rows that time full
        resolution, and 100 (64,000×48,000) filled 24 GB before the kernel ended the run.
    scaling_sizes
        Point counts (at least two, each >= 100) of the scaling runs: random subsets of one
        high-resolution frame pair.
    warmup
        Untimed calls of every contender before the timed ones (first-call set-up costs).
    normals
        Neighbourhood of the ``normals`` stage and of the normals the registrations are given.
    coarse_voxel_size
        Voxel (m) of the clouds behind FPFH and RANSAC.
    max_correspondence_distance
        Gate (m) of ICP and GICP; the frame-to-frame motion is about 1 cm and 1°.
    max_iterations
        Iteration limit of ICP and GICP, for every contender.
    fpfh_spacing_factor
        FPFH radius of the scaling runs as a multiple of the point spacing, so that every size
        does the same work per point.
    tracking_warmup_frames
        Lab frames the ``tracking_step`` tracker runs untimed before the timed ones (by then the
        lab run's keyframe window is full).
    tracking_frames
        Lab frames each timed ``tracking_step`` call tracks (two keyframe periods of the lab run).
    full_resolutions
        (width, height) of the raw-frame rows, one row each; the last is also streamed for the
        tracker's peak memory. Empty: no raw rows.
    raw_frames
        Timed frames per call of a raw row (after its two untimed ones).
    stream_frames
        Frames of that stream.
    """

    frame_scale: float = Field(1.0, ge=0.1, le=3.0)
    # At least two sizes to fit an exponent; 100 points leave room for every k-neighbourhood.
    scaling_sizes: tuple[Annotated[int, Field(ge=100)], ...] = Field(FULL_SIZES, min_length=2)
    warmup: int = Field(1, ge=0)
    normals: NormalsConfig = NormalsConfig()
    coarse_voxel_size: PositiveFloat = 0.012
    max_correspondence_distance: PositiveFloat = 0.03
    max_iterations: int = Field(30, ge=1)
    fpfh_spacing_factor: PositiveFloat = 5.0
    tracking_warmup_frames: int = Field(9, ge=2)
    tracking_frames: PositiveInt = 8
    full_resolutions: tuple[tuple[PositiveInt, PositiveInt], ...] = ((640, 480), (1280, 720))
    raw_frames: PositiveInt = 4
    stream_frames: int = Field(8, ge=2)


def bench_config(quick: bool, path: str | Path | None = None) -> BenchConfig:
    """Defaults of a full or quick run (320×240 frames, scaling up to 20k points, raw frames at
    640×480 only, two timed raw frames per call).

    Parameters
    ----------
    quick
        Start from the quick defaults.
    path
        Optional YAML/JSON file; the options it sets replace the defaults (the rest are kept).

    Raises
    ------
    ConfigError
        An unreadable file or an invalid option.
    """
    quick_options = {"frame_scale": 0.5, "scaling_sizes": QUICK_SIZES}
    base = (
        BenchConfig(**quick_options, full_resolutions=((640, 480),), raw_frames=2, stream_frames=3)
        if quick
        else BenchConfig()
    )
    if path is None:
        return base
    overrides = load_config(BenchConfig, path)
    # Top-level options the file sets, as validated objects (a nested config stays a model).
    return base.model_copy(update={k: getattr(overrides, k) for k in overrides.model_fields_set})


# --------------------------------------------------------------------------------------------
# One call


def run_benchmark(
    quick: bool = False,
    peers: bool = False,
    repeats: int = 5,
    seed: int = 0,
    workers: int = -1,
    config: BenchConfig | None = None,
) -> dict:
    """Time every stage (and the peers' counterparts), score the registrations, measure memory.

    Parameters
    ----------
    quick
        Smaller frames and scaling sizes (:func:`bench_config`).
    peers
        Also run Open3D and small_gicp (both must be installed).
    repeats
        Timed calls per contender and stage (after ``config.warmup`` untimed ones).
    seed
        Seed of the simulated frames, the subsets and every RANSAC.
    workers
        Threads for our neighbour searches (-1: all cores); the peers get the same count.
    config
        Overrides the defaults chosen by ``quick``.

    Returns
    -------
    JSON-ready dict: ``environment``, ``config``, ``stages`` (per stage ``median_ms``,
    ``min_ms``, ``max_ms``, ``n_points``, ``peer``, ``ratio`` = peer median / our median;
    ``tracking_step`` also ``substages``), ``accuracy`` (per registration, each contender's
    errors and the Cramér–Rao bound), ``memory`` and ``scaling``.

    Raises
    ------
    ConfigError
        ``repeats`` < 1 or above :data:`MOST_REPEATS`, a bad ``workers``, or ``peers``
        without the peer libraries.
    """
    if repeats < 1:
        raise ConfigError(f"repeats must be at least 1, got {repeats}")
    if repeats > MOST_REPEATS:
        # 10**9 ran for ever (the timed calls of the first stage unfinished).
        raise ConfigError(
            f"--repeats: {repeats} timed calls per stage would run for days: at most "
            f"{MOST_REPEATS} (a stage's median steadies within a few)"
        )
    threads = thread_count(workers)
    config = config or bench_config(quick)
    modules = load_peers() if peers else {}
    contenders = Peers(
        open3d=Open3D(modules["open3d"], threads) if "open3d" in modules else None,
        small_gicp=SmallGICP(modules["small_gicp"], threads) if "small_gicp" in modules else None,
    )
    try:
        result = _measure(config, repeats, seed, workers, contenders)
    finally:
        if contenders.open3d is not None:
            contenders.open3d.close()
    return {"environment": environment(workers, threads, modules), **result}


def _measure(config: BenchConfig, repeats: int, seed: int, workers: int, contenders: Peers) -> dict:
    """Everything :func:`run_benchmark` reports but the environment."""
    data = prepare_data(config, seed, workers)
    (tgt, src), (tgt_coarse, _) = data.clouds, data.coarse
    frame0 = data.frames[0].cloud
    # The steady tracking row runs on a longer lab run (time per frame, after its warm-up).
    warm = config.tracking_warmup_frames
    lab = render_frames(config.frame_scale, warm + config.tracking_frames, seed)
    stage_trials: dict[str, dict[str, Trial]] = {
        "voxel": voxel_trials(frame0, tracker_lengths(frame0).voxel, contenders),
        "normals": normals_trials(data.frames[0].cloud, config.normals, workers, contenders),
        "mpp_mls": mls_trials(data, workers),
        "fpfh": fpfh_trials(tgt_coarse, coarse_fpfh(config), workers, contenders),
        "ransac": ransac_trials(data, ransac_config(config, seed), workers, contenders),
        "icp": icp_trials(src, tgt, icp_config(config), workers, contenders),
        "gicp": gicp_trials(src, tgt, gicp_config(config), workers, contenders),
        "jicp_step": jicp_trials(data, workers),
        "tracking_step": steady_trials(lab, warm, workers, contenders, []),
        "tracking_second_frame": second_frame_trials(*data.frames[:2], workers, contenders),
        "ekf_step": ekf_trials(seed),
    }
    n_points = {
        "voxel": len(frame0),
        "normals": len(data.frames[0].cloud),
        "mpp_mls": len(data.frames[0].cloud),
        "fpfh": len(tgt_coarse),
        "ransac": len(data.coarse[1]),
        "icp": len(src),
        "gicp": len(src),
        "jicp_step": len(data.frames[2].cloud),
        "tracking_step": len(lab[warm].cloud),
        "tracking_second_frame": len(data.frames[1].cloud),
        "ekf_step": 0,
    }
    # Raw rows: two untimed frames (their times reported beside), then the timed ones.
    raw, warm_ms = {}, {}
    for k, (width, height) in enumerate(config.full_resolutions):
        streamed = k == len(config.full_resolutions) - 1
        count = 2 + config.raw_frames
        rendered = max(count, config.stream_frames) if streamed else count
        frames = raw_frames(width, height, rendered, seed)
        name = f"raw_{width}x{height}"
        warm_ms[name] = []
        stage_trials[name] = steady_trials(frames[:count], 2, workers, contenders, warm_ms[name])
        n_points[name] = len(frames[2].cloud)
        if streamed:
            raw = {"width": width, "height": height, "frames": frames[: config.stream_frames]}
    stages, accuracy = {}, {}
    bound = crlb_summary(data.frames[0])
    for name, trials in stage_trials.items():
        timings = time_interleaved(trials, repeats, config.warmup)
        tracking = name.startswith(("tracking_", "raw_"))
        if tracking:
            timings = {who: per_frame(t) for who, t in timings.items()}
        stages[name] = stage_entry(timings, n_points[name])
        if name in REGISTRATIONS:
            accuracy[name] = {
                who: registration_error(t.last, data.T_gt) for who, t in timings.items()
            }
            accuracy[name]["crlb"] = bound
        if tracking:
            stages[name]["substages"] = tracking_shares(timings["ours"])
        if name in warm_ms:
            # One untimed run of each (every set-up restores a copy of the state after them).
            first, second = warm_ms[name]
            stages[name]["first_frame_ms"], stages[name]["second_frame_ms"] = first, second
    memory = peak_memory({name: trials["ours"] for name, trials in stage_trials.items()})
    scaling = run_scaling(config, data.frames[0], seed, workers, repeats, contenders)
    memory["max_rss_mb"] = max_rss_mb()
    if raw:
        memory["tracker_stream"] = {
            "width": raw["width"],
            "height": raw["height"],
            **stream_peak_rss(raw["frames"], workers),
        }
    return {
        "config": {**config.model_dump(mode="json"), "repeats": repeats, "seed": seed},
        "stages": stages,
        "accuracy": accuracy,
        "memory": memory,
        "scaling": scaling,
    }


# --------------------------------------------------------------------------------------------
# Output


def check_bench_output(path: str | Path) -> None:
    """Refuse a benchmark output that cannot be written, or is not named ``.json``.

    Raises
    ------
    InputError
        :func:`~spacepose.tools.outputs.check_writable`'s reasons, or another suffix: the
        benchmark's JSON written over a run's truth.csv destroyed it without a word.
    """
    path = Path(path)
    check_writable(path)
    if path.suffix.lower() != ".json":
        raise InputError(f"the benchmark writes JSON: name its file .json, not {path.name}", path)


def write_bench(result: dict, path: str | Path) -> Path:
    """Write a :func:`run_benchmark` result as JSON (non-finite numbers as null).

    Raises
    ------
    InputError
        When the file cannot be written, or is not named ``.json`` (:func:`check_bench_output`).
    """
    path = Path(path)
    check_bench_output(path)
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_text(strict_json(result, indent=2) + "\n")
    except OSError as exc:
        raise InputError(f"cannot write the benchmark: {exc.strerror}", path) from None
    return path


def _ms(entry: dict | None) -> str:
    return "-" if entry is None else f"{entry['median_ms']:.1f}"


def stage_table(result: dict) -> Table:
    """Rich table of the stage times: ours (median, min–max) and each peer with its ratio."""
    names = [p for p in PEERS if any(p in s["peer"] for s in result["stages"].values())]
    table = Table(title="stage times (ms, median of repeats; tracking rows: per frame)")
    for col in ("stage", "N", "ours", "ours min-max", *(f"{p} (x ours)" for p in names)):
        table.add_column(col, justify="left" if col == "stage" else "right")
    for stage, s in result["stages"].items():
        peers = [
            f"{_ms(s['peer'][p])} ({s['ratio'][p]:.2f})" if p in s["peer"] else "-" for p in names
        ]
        spread = f"{s['min_ms']:.1f}-{s['max_ms']:.1f}"
        table.add_row(stage, str(s["n_points"] or "-"), _ms(s), spread, *peers)
    return table


def accuracy_table(result: dict) -> Table:
    """Rich table of the registration errors beside the Cramér–Rao bound."""
    table = Table(title="registration error vs truth (frame-to-frame CRLB std)")
    for col in ("stage", "who", "translation mm", "rotation deg"):
        table.add_column(col, justify="left" if col in ("stage", "who") else "right")
    for stage, by_who in result["accuracy"].items():
        for who, err in by_who.items():
            label = "CRLB" if who == "crlb" else who
            table.add_row(
                stage, label, f"{err['translation_mm']:.3f}", f"{err['rotation_deg']:.4f}"
            )
    return table
