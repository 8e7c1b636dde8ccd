"""The per-stage trials of ``spacepose bench`` and the interleaved timer.

A :data:`Trial` is an untimed set-up that returns the call to time: the set-up builds the state a
step needs first (the earlier frames of a tracker, restored from a copy), the call is the step. For
each stage a ``*_trials`` function gives one trial per contender on identical inputs: ``ours``,
and ``open3d`` or ``small_gicp`` when the run has that peer
(:class:`~spacepose.tools.bench_peers.Peers`) and the peer has the stage. :func:`time_interleaved`
sets up and calls every contender in turn, round after round, so that a change in machine load
hits them alike.

:func:`stage_entry` makes a stage's timings its row of the JSON (median, min, max, and each peer's
ratio to ours); the tracking rows are times per frame (:func:`per_frame`) and carry the stage times
the tracker itself reported (:func:`tracking_shares`).
"""

from __future__ import annotations

import copy
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from spacepose.core.cloud import PointCloud
from spacepose.core.fpfh import FPFHConfig, compute_fpfh
from spacepose.core.gicp import GICPConfig, gicp
from spacepose.core.icp import ICPConfig, icp
from spacepose.core.normals import NormalsConfig, estimate_normals
from spacepose.core.ransac import RansacConfig, feature_ransac
from spacepose.core.sim import Frame, OrbitConfig, simulate_orbit
from spacepose.core.tracker_config import StageLengths
from spacepose.tools.bench_data import BenchData
from spacepose.tools.bench_peers import Peers

#: An untimed set-up that returns the call to time (set-up = state a step needs first).
Trial = Callable[[], Callable[[], Any]]


# --------------------------------------------------------------------------------------------
# Timing primitives


@dataclass(frozen=True)
class Timing:
    """Wall times (ms) of the timed calls of one contender and what each call returned."""

    times_ms: list[float]
    outputs: list[Any]

    @property
    def last(self) -> Any:
        return self.outputs[-1]


def time_interleaved(
    trials: Mapping[str, Trial], repeats: int, warmup: int = 1
) -> dict[str, Timing]:
    """Time several contenders in turn: set up and call each once per round, ``repeats`` rounds.

    Parameters
    ----------
    trials
        Contender name -> untimed set-up returning the call to time.
    repeats
        Timed rounds.
    warmup
        Untimed rounds first.

    Returns
    -------
    dict[str, Timing]
        One per contender, in the order given.
    """
    for _ in range(warmup):
        for setup in trials.values():
            setup()()
    timings = {name: Timing([], []) for name in trials}
    for _ in range(repeats):
        for name, setup in trials.items():
            call = setup()
            tic = time.perf_counter()
            out = call()
            timings[name].times_ms.append(1e3 * (time.perf_counter() - tic))
            timings[name].outputs.append(out)
    return timings


def summarize(times_ms: list[float]) -> dict[str, float]:
    """Median, min and max (ms) of a list of times, and how many there are."""
    t = np.asarray(times_ms, dtype=np.float64)
    return {
        "median_ms": float(np.median(t)),
        "min_ms": float(t.min()),
        "max_ms": float(t.max()),
        "repeats": len(t),
    }


def _ready(call: Callable[[], Any]) -> Trial:
    """A trial without set-up."""
    return lambda: call


# --------------------------------------------------------------------------------------------
# Stages: the trials of every contender of a stage, on identical inputs


def voxel_trials(cloud: PointCloud, voxel_size: float, peers: Peers) -> dict[str, Trial]:
    from spacepose.core.voxel import voxel_downsample

    trials = {"ours": _ready(lambda: voxel_downsample(cloud, voxel_size))}
    if peers.open3d is not None:
        trials["open3d"] = _ready(lambda: peers.open3d.voxel(cloud, voxel_size))
    return trials


def normals_trials(
    cloud: PointCloud, config: NormalsConfig, workers: int, peers: Peers
) -> dict[str, Trial]:
    trials = {"ours": _ready(lambda: estimate_normals(cloud, config, workers=workers))}
    if peers.open3d is not None:
        trials["open3d"] = _ready(lambda: peers.open3d.normals(cloud, config.k))
    if peers.small_gicp is not None:
        trials["small_gicp"] = _ready(lambda: peers.small_gicp.normals(cloud, config.k))
    return trials


def fpfh_trials(cloud: PointCloud, config: FPFHConfig, workers: int, peers: Peers) -> dict:
    trials = {"ours": _ready(lambda: compute_fpfh(cloud, config, workers))}
    if peers.open3d is not None:
        trials["open3d"] = _ready(lambda: peers.open3d.fpfh(cloud, config.radius, config.max_nn))
    return trials


def icp_trials(
    source: PointCloud, target: PointCloud, config: ICPConfig, workers: int, peers: Peers
) -> dict[str, Trial]:
    trials = {
        "ours": _ready(lambda: icp(source, target, np.eye(4), config, workers).T_target_source)
    }
    if peers.open3d is not None:
        trials["open3d"] = _ready(lambda: peers.open3d.icp(source, target, config))
    return trials


def gicp_trials(
    source: PointCloud, target: PointCloud, config: GICPConfig, workers: int, peers: Peers
) -> dict[str, Trial]:
    # Points only for every contender: each builds its own tree and covariances.
    src, tgt = PointCloud(source.points), PointCloud(target.points)
    trials = {"ours": _ready(lambda: gicp(src, tgt, np.eye(4), config, workers).T_target_source)}
    if peers.open3d is not None:
        trials["open3d"] = _ready(lambda: peers.open3d.gicp(src, tgt, config))
    if peers.small_gicp is not None:
        trials["small_gicp"] = _ready(lambda: peers.small_gicp.gicp(src, tgt, config))
    return trials


def ransac_trials(data: BenchData, config: RansacConfig, workers: int, peers: Peers) -> dict:
    (tgt, src), (f_tgt, f_src) = data.coarse, data.features
    trials = {
        "ours": _ready(
            lambda: feature_ransac(src, tgt, f_src, f_tgt, config, workers).T_target_source
        )
    }
    if peers.open3d is not None:
        trials["open3d"] = _ready(lambda: peers.open3d.ransac(src, tgt, f_src, f_tgt, config))
    return trials


def mls_trials(data: BenchData, workers: int) -> dict[str, Trial]:
    from spacepose.core.mls import MLSConfig, mpp_mls

    cloud = data.frames[0].cloud
    return {"ours": _ready(lambda: mpp_mls(cloud, MLSConfig(), workers))}


def jicp_trials(data: BenchData, workers: int) -> dict[str, Trial]:
    from spacepose.core.jicp import JointICP

    f0, f1, f2 = (f.cloud for f in data.frames)
    config = tracker_lengths(f0).jicp

    def setup() -> Callable[[], Any]:
        joint = JointICP(config, workers)
        joint.step(f0)
        joint.step(f1)
        return lambda: joint.step(f2)

    return {"ours": setup}


def second_frame_trials(
    f0: Frame, f1: Frame, workers: int, peers: Peers, first_ms: list[float] | None = None
) -> dict[str, Trial]:
    """A fresh default tracker's second frame ``f1`` (``f0`` first, untimed, its time appended
    to ``first_ms``) beside Open3D's core steps against ``f0`` prepared as a keyframe."""
    from spacepose.core.tracker import Tracker, TrackerConfig

    config = TrackerConfig()

    def setup() -> Callable[[], Any]:
        tracker = Tracker(config, None, workers)
        tic = time.perf_counter()
        tracker.track_frame(f0.cloud, f0.timestamp)
        if first_ms is not None:
            first_ms.append(1e3 * (time.perf_counter() - tic))
        return lambda: [tracker.track_frame(f1.cloud, f1.timestamp)]

    return {"ours": setup, **_open3d_tracking(f0, [f1], peers)}


def steady_trials(
    frames: list[Frame], warmup: int, workers: int, peers: Peers, warm_ms: list[float]
) -> dict[str, Trial]:
    """A running default tracker on ``frames[warmup:]``: it tracks ``frames[:warmup]`` once,
    untimed (each frame's time appended to ``warm_ms``), and every set-up restores a copy of
    that state; beside Open3D's core steps on the same frames."""
    from spacepose.core.tracker import Tracker, TrackerConfig

    tracker = Tracker(TrackerConfig(), None, workers)
    for frame in frames[:warmup]:
        tic = time.perf_counter()
        tracker.track_frame(frame.cloud, frame.timestamp)
        warm_ms.append(1e3 * (time.perf_counter() - tic))
    timed = frames[warmup:]

    def setup() -> Callable[[], Any]:
        running = copy.deepcopy(tracker)
        return lambda: [running.track_frame(f.cloud, f.timestamp) for f in timed]

    return {"ours": setup, **_open3d_tracking(frames[0], timed, peers, frames[warmup - 1])}


def _open3d_tracking(
    first: Frame, timed: list[Frame], peers: Peers, previous: Frame | None = None
) -> dict[str, Trial]:
    """Open3D's trial tracking ``timed`` frame to frame, with the voxel and normals the default
    tracker derives from ``first``; ``previous`` (default ``first``) is prepared untimed as the
    keyframe of the first timed frame. Empty without Open3D."""
    o3d = peers.open3d
    if o3d is None:
        return {}
    from spacepose.core.tracker import TrackerConfig

    lengths, k = tracker_lengths(first.cloud), TrackerConfig().normals.k
    clouds = [f.cloud for f in timed]

    def setup() -> Callable[[], Any]:
        keyframe = o3d.prepared((previous or first).cloud, lengths.voxel, k)
        return lambda: o3d.track(clouds, keyframe, lengths.voxel, k, lengths.keyframe_graph.icp)

    return {"open3d": setup}


def tracker_lengths(first: PointCloud) -> StageLengths:
    """The default tracker's lengths for a first frame (what a fresh tracker derives)."""
    from spacepose.core.scale import derive_scale
    from spacepose.core.tracker_config import TrackerConfig, stage_lengths

    config = TrackerConfig()
    scale = derive_scale(first.points, config.points_per_frame, config.voxel_size)
    return stage_lengths(config, scale.voxel, scale.radius)


def ekf_trials(seed: int) -> dict[str, Trial]:
    from spacepose.core.ekf import RelativeNavEKF
    from spacepose.core.nav_state import NavState

    sim = simulate_orbit(OrbitConfig(frames=2, seed=seed))
    row0, row1 = sim.truth
    initial = NavState(
        t=row0[0],
        rho=row0[1:4],
        v=row0[4:7],
        q_I_B=row0[7:11],
        omega_B=row0[11:14],
        k=row0[14:17],
        com=row0[17:20],
    )
    extras = sim.extras or {}
    # A pose measurement with 1 mrad / 5 mm noise, the order of a registration at 25 m.
    cov6 = np.diag([1e-3**2] * 3 + [5e-3**2] * 3)
    T_meas = sim.T_sensor_target[1]

    def setup() -> Callable[[], Any]:
        ekf = RelativeNavEKF(extras["mean_motion"], np.array(extras["R_O_C"]), initial)

        def step() -> bool:
            ekf.predict(row1[0])
            return ekf.update_pose(T_meas, cov6)

        return step

    return {"ours": setup}


# --------------------------------------------------------------------------------------------
# Rows: a stage's timings as the JSON reports them


def stage_entry(timings: dict[str, Timing], n_points: int) -> dict:
    ours = summarize(timings["ours"].times_ms)
    peers = {name: summarize(t.times_ms) for name, t in timings.items() if name != "ours"}
    return {
        **ours,
        "n_points": int(n_points),
        "peer": peers,
        "ratio": {name: p["median_ms"] / ours["median_ms"] for name, p in peers.items()},
    }


def per_frame(timing: Timing) -> Timing:
    """A tracking contender's call times divided by the frames each call tracked (every output
    is the list of one call's per-frame results)."""
    return Timing(
        [t / len(out) for t, out in zip(timing.times_ms, timing.outputs, strict=True)],
        timing.outputs,
    )


def tracking_shares(timing: Timing) -> dict:
    """Per-frame stage times the tracker reported over the timed calls, and their shares.

    ``status`` is the last frame's health label and ``statuses`` counts every timed frame's: a
    lost frame would time the wrong work; ``tracker`` says which default pipeline was timed.
    """
    from spacepose.core.tracker import STAGES as TRACKER_STAGES
    from spacepose.core.tracker import TrackerConfig

    results = [result for call in timing.outputs for result in call]
    reports = [result.time_ms for result in results]
    medians = {s: float(np.median([r.get(s, 0.0) for r in reports])) for s in TRACKER_STAGES}
    # Shares as ratios of sums over the frames: the stages partition each frame's total, so the
    # shares add up to 1 (medians of the parts need not add up to the median of the whole).
    sums = {s: float(sum(r.get(s, 0.0) for r in reports)) for s in TRACKER_STAGES}
    total = sums["total"]
    statuses = [result.status for result in results]
    return {
        "tracker": TrackerConfig().model_dump(
            include={"method", "use_mls", "points_per_frame", "voxel_size"}
        ),
        "status": statuses[-1],
        "statuses": {s: statuses.count(s) for s in sorted(set(statuses))},
        "frames_per_call": len(timing.last),
        "median_ms": medians,
        "mean_ms": {s: v / len(reports) for s, v in sums.items()},
        "share": {s: v / total for s, v in sums.items() if s != "total" and total > 0},
    }
