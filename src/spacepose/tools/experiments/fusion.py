"""Registration poses in the navigation filter (issue 12): per target and measurement kind.

The orbit run (flash LiDAR 25 m behind a tumbling target, 1 Hz, truth from two-body + J2 orbits
and an independent attitude integration) is navigated by
:class:`spacepose.core.fused_navigation.FusedNavigator` with rectangles, registration poses
(the model-based tracker against the run's model) or both, and scored as Y4 is
(:func:`spacepose.tools.experiments.yu_nav.score`): second-half RMS of position, velocity,
attitude, rate, CoM and inertia ratios, and the share of frames whose NEES lies inside its
two-sided 95 % χ² bounds. No truth reaches the navigator: the rectangle start is lost in space,
the registration start is the tracker's coarse registration on the model.

Targets: the default (rectangles) target and each mesh of ``data/models``, scaled to fit the
sensor's 30° field at 25 m, or those named (``--targets``), generated spacecraft ``random:K``
among them (:mod:`spacepose.core.sim.random_targets`, nothing tuned on them). The meshes and
the generated targets have no rectangle catalogue: registration and model-free only. The
``model-free`` kind navigates the default target from the model-free tracker's poses (a batch
of ``model_free_frames`` gives the body frame) and is scored in the body frame it estimated,
up to the half turns about principal axes no motion tells apart (:func:`relabelled_truth`). Besides
the filter, the tracker's own covariance is scored against the truth (its NEES and the share of
frames whose per-axis error lies within 3σ about the target centre), since the filter trusts it.
"""

from __future__ import annotations

import warnings
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation
from scipy.stats import chi2

from spacepose.core import se3
from spacepose.core.fused_navigation import GATE_REASON, FusedNavigator, FusionConfig
from spacepose.core.nav_config import NavigationConfig
from spacepose.core.nav_start import scenario_geometry
from spacepose.core.sim.random_targets import generated_seed
from spacepose.core.sim.scenarios import OrbitConfig, simulate_orbit
from spacepose.errors import ConfigError, SpaceposeWarning
from spacepose.tools.catalogue import parse_catalogue
from spacepose.tools.experiments import ExperimentOptions, register
from spacepose.tools.experiments.yu_nav import (
    nav_record,
    navigation_config,
    record_filter,
    score,
)
from spacepose.tools.pose_bootstrap_run import bootstrapped_fusion
from spacepose.tools.text_io import strict_json

_MODELS = Path(__file__).resolve().parents[4] / "data" / "models"
# Target name -> (mesh file or None for the default target, scale, measurement kinds).
TARGETS: dict[str, tuple[str | None, float, tuple[str, ...]]] = {
    "default": (None, 1.0, ("rectangles", "registration", "both", "model-free")),
    "satellite_panels": ("satellite_panels.obj", 0.6, ("registration",)),
    "hubble": ("hubble_model_kit.obj", 0.1, ("registration",)),
}
SUMMARY_KEYS = (
    "position_rms_mm",
    "velocity_rms_mm_s",
    "attitude_rms_deg",
    "rate_rms_deg_s",
    "com_rms_mm",
    "inertia_rms_pct",
    "nees_inside_95_second_half",
    "frames_navigated",
    "gate_rejections",
    "tracker_nees_median",
    "tracker_in_3sigma",
)


# Measurement kinds of a generated spacecraft (no rectangle catalogue).
GENERATED_KINDS = ("registration", "model-free")
# The kinds a quick run navigates.
_QUICK_KINDS = ("registration", "both")


def target_kinds(target: str) -> tuple[str, ...]:
    """The measurement kinds of ``target``: a key of :data:`TARGETS` or ``random:K``.

    Raises
    ------
    ConfigError
        Any other name (the message lists the choices).
    """
    if target in TARGETS:
        return TARGETS[target][2]
    if generated_seed(target) is not None:
        return GENERATED_KINDS
    raise ConfigError(
        f"fusion target {target!r}: choose {', '.join(TARGETS)} or random:K (a generated "
        "spacecraft, K a whole number)"
    )


def orbit_config(target: str, frames: int, seed: int) -> OrbitConfig:
    """The orbit run with ``target`` (a key of :data:`TARGETS`, or ``random:K``)."""
    fields: dict[str, Any] = {"frames": frames, "seed": seed}
    if target not in TARGETS:
        return OrbitConfig(**fields, model=target)
    mesh, scale, _ = TARGETS[target]
    if mesh is not None:
        fields |= {"model": str(_MODELS / mesh), "model_scale": scale}
    return OrbitConfig(**fields)


def fusion_plan(targets: str | None, quick: bool) -> dict[str, tuple[str, ...]]:
    """Target -> measurement kinds to navigate: every target of :data:`TARGETS`, or those of
    ``targets`` (comma-separated names); a quick run keeps registration and both only, and
    without ``targets`` the default target alone.

    Raises
    ------
    ConfigError
        An unknown target, or ``targets`` naming none.
    """
    if targets is None:
        names = ["default"] if quick else list(TARGETS)
    else:
        names = list(dict.fromkeys(n.strip() for n in targets.split(",") if n.strip()))
        if not names:
            raise ConfigError(f"--targets {targets!r} names no target")
    plan = {name: target_kinds(name) for name in names}
    if quick:
        plan = {name: tuple(k for k in kinds if k in _QUICK_KINDS) for name, kinds in plan.items()}
    return plan


def tracker_errors(
    T_est: NDArray[np.float64], cov: NDArray[np.float64], T_true: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.float64], float]:
    """Left error (6,) of a tracked pose about the target origin, its 1-σ (6,) there, NEES.

    The error ``log(T_est T_true⁻¹)`` and the covariance are moved from the sensor origin to the
    target's origin (methods.md §0.4), where a point on the target sees them.
    """
    D = T_est @ se3.invert(T_true)
    e = np.r_[Rotation.from_matrix(D[:3, :3]).as_rotvec(), D[:3, 3]]
    J = np.eye(6)
    J[3:, :3] = -se3.skew(T_true[:3, 3])
    Cc = J @ cov @ J.T
    singular = np.linalg.eigvalsh(cov)[0] <= 0  # a model-free track's first frame
    nees = float("nan") if singular else float(e @ np.linalg.solve(cov, e))
    return J @ e, np.sqrt(np.clip(np.diag(Cc), 0, None)), nees


def navigate_fused_with_truth(
    config: OrbitConfig, fusion: FusionConfig, model_free: bool = False
) -> dict[str, Any]:
    """Simulate the orbit run and navigate it with ``fusion``; errors against the truth.

    ``model_free``: the navigator gets no model; the truth is then expressed in its estimated
    body frame (:func:`relabelled_truth`).

    Returns the dict :func:`yu_nav.score` reads (``t``, ``errors``, ``sigmas``, ``nees``,
    ``status``, ``n_rect``, ``truth``, ``ekf``, coarse poses all NaN) plus ``tracker_error``
    (N, 6) and ``tracker_sigma`` (N, 6) about the target origin, ``tracker_nees`` (N,),
    ``seeded`` and ``gated`` (N,) booleans, the ``pose_sigma_scale`` the navigation used and
    its bootstrap's measurement (``pose_noise``, None when there was none).
    """
    sim = simulate_orbit(config)
    scenario = sim.scenario()
    n, R_O_C = scenario_geometry(scenario, "orbit simulation")
    nav_cfg = navigation_config(scenario, fusion.navigation)
    fusion = fusion.model_copy(update={"navigation": nav_cfg})
    catalogue = parse_catalogue(scenario, nav_cfg.rectangle) if scenario["rectangles"] else []
    model = None if model_free else sim.model_cloud()
    noise = None
    if model is not None:
        pairs = ((f.timestamp, f.cloud) for f in sim.frames())
        fusion, noise = bootstrapped_fusion(pairs, sim.target, sim.sensor, model, fusion)
    nav = FusedNavigator(catalogue, n, R_O_C, fusion, model)
    truth_rows = sim.truth
    N = len(sim)
    out = nav_record(sim) | {
        "tracker_error": np.full((N, 6), np.nan),
        "tracker_sigma": np.full((N, 6), np.nan),
        "tracker_nees": np.full(N, np.nan),
        "seeded": np.zeros(N, dtype=bool),
        "gated": np.zeros(N, dtype=bool),
    }
    for k in range(N):
        frame = sim.frame(k)
        row = nav.step(frame.timestamp, frame.cloud)
        out["status"].append(row.nav.status)
        out["n_rect"][k] = row.nav.n_rect
        out["seeded"][k] = row.seeded
        track = row.track
        for revised in () if track is None else track.revises:
            if revised.status == "lost":  # a first frame that gave way (core.spare_anchor)
                out["tracker_error"][revised.index] = out["tracker_sigma"][revised.index] = np.nan
                out["tracker_nees"][revised.index] = np.nan
        if track is not None and track.status != "lost":
            out["gated"][k] = any(r.startswith(GATE_REASON) for r in track.reasons)
            T_true = frame.T_sensor_target
            if model_free:  # the track is T_k0, 0 its first frame's (methods.md §0.7)
                T_true = T_true @ se3.invert(sim.T_sensor_target[nav.tracker.first_index])
            e, s, nees = tracker_errors(track.T_sensor_target, track.covariance, T_true)
            out["tracker_error"][k], out["tracker_sigma"][k], out["tracker_nees"][k] = e, s, nees
        ekf = nav.ekf
        if ekf is not None:
            if model_free and truth_rows is sim.truth:
                T_C_Bp0 = sim.T_sensor_target[nav.tracker.first_index]
                truth_rows = relabelled_truth(sim.truth, nav.T_F_B, T_C_Bp0)
            record_filter(out, k, ekf, truth_rows[k])
    out["ekf"] = nav.ekf
    out["truth"] = truth_rows
    out["pose_sigma_scale"] = fusion.pose_sigma_scale
    out["pose_noise"] = None if noise is None else noise.to_dict()
    return out


# Half turns about principal axes: the dynamics cannot tell them apart.
_FLIPS = [np.diag(d) for d in ([1, 1, 1], [1, -1, -1], [-1, 1, -1], [-1, -1, 1])]


def relabelled_truth(
    truth: NDArray[np.float64], T_F_B: NDArray[np.float64], T_C_Bp0: NDArray[np.float64]
) -> NDArray[np.float64]:
    """The truth table (N, 20) in a model-free navigator's body frame.

    ``T_F_B`` (4, 4) is its estimated body frame in F (the sensor frame of the first view) and
    ``T_C_Bp0`` the true model pose at that view, so that the true principal axes in F are
    ``R_C_Bp0`` (B' has B's axes) and the true centre of mass ``T_C_Bp0 Δ``. Of the four
    labellings that differ by half turns about the axes (which no motion tells apart) the one
    nearest the estimate is taken; ρ, ρ̇ and k do not change; q and ω turn with it and Δ
    becomes the true centre of mass relative to the estimated one, in the estimated axes.
    """
    R_est = T_F_B[:3, :3]
    angles = [Rotation.from_matrix(R_est.T @ T_C_Bp0[:3, :3] @ S).magnitude() for S in _FLIPS]
    S = _FLIPS[int(np.argmin(angles))]
    out = truth.copy()
    out[:, 7:11] = (Rotation.from_quat(truth[:, 7:11]) * Rotation.from_matrix(S)).as_quat()
    out[:, 11:14] = truth[:, 11:14] @ S
    com_F = T_C_Bp0[:3, :3] @ truth[0, 17:20] + T_C_Bp0[:3, 3]
    out[:, 17:20] = R_est.T @ (com_F - T_F_B[:3, 3])
    return out


def fused_score(result: dict[str, Any]) -> dict[str, Any]:
    """:func:`_fused_score` without numpy's warnings about runs with no navigated frame (a
    model-free run shorter than its batch): their figures are NaN."""
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        return _fused_score(result)


def _fused_score(result: dict[str, Any]) -> dict[str, Any]:
    """:func:`yu_nav.score` (second half) plus the tracker's consistency over every frame it
    tracked: median NEES (6 dof), share inside the 95 % χ²(6) bounds, share of frames with each
    axis (rx, ry, rz in rad; tx, ty, tz about the target origin) within 3σ, RMS error / mean σ
    per axis, the frames seeded and gated, and the bootstrap's ``pose_noise`` (a dict, or None)."""
    table = score(result)  # its coarse rectangle poses are all NaN here (no ablation)
    e, s, ne = result["tracker_error"], result["tracker_sigma"], result["tracker_nees"]
    tracked = np.isfinite(ne) & np.all(np.isfinite(e), axis=1)
    lo, hi = chi2.ppf([0.025, 0.975], 6)
    table |= {
        "frames_tracked": int(tracked.sum()),
        "frames_seeded": int(result["seeded"].sum()),
        "frames_gated": int(result["gated"].sum()),
        "pose_sigma_scale": result["pose_sigma_scale"],
        "pose_noise": result["pose_noise"],  # the bootstrap's measurement (None: not measured)
        "tracker_nees_median": float(np.median(ne[tracked])) if tracked.any() else float("nan"),
        "tracker_nees_inside_95": float(np.mean((ne[tracked] >= lo) & (ne[tracked] <= hi)))
        if tracked.any()
        else float("nan"),
        "tracker_in_3sigma": np.mean(np.abs(e[tracked]) <= 3 * s[tracked], axis=0).tolist(),
        "tracker_rms_over_sigma": (
            np.sqrt(np.mean(e[tracked] ** 2, axis=0)) / np.mean(s[tracked], axis=0)
        ).tolist(),
        "tracker_rms_rot_deg": np.degrees(np.sqrt(np.mean(e[tracked, :3] ** 2, 0))).tolist(),
        "tracker_rms_trans_mm": (1e3 * np.sqrt(np.mean(e[tracked, 3:] ** 2, 0))).tolist(),
    }
    return table


def over_seeds(
    target: str, kind: str, seeds: list[int], frames: int, base: FusionConfig
) -> dict[str, Any]:
    """Mean and std (ddof 1 from 2 seeds on) over seeds of :data:`SUMMARY_KEYS`, and the
    per-seed tables. A seed whose filter never started (its errors NaN) is left out of each
    figure it has no value for, and ``seeds_navigated`` counts the seeds that started."""
    model_free = kind == "model-free"
    update: dict[str, Any] = {"measurements": "registration" if model_free else kind}
    fusion = base.model_copy(update=update)
    tables = []
    for seed in seeds:
        config = orbit_config(target, frames, seed)
        result = navigate_fused_with_truth(config, fusion, model_free)
        tables.append(fused_score(result) | {"seed": seed})
    summary: dict[str, Any] = {}
    for key in SUMMARY_KEYS:
        values = np.array([t[key] for t in tables], dtype=np.float64)
        summary[key] = _mean_std(values)
    started = sum(t["frames_navigated"] > 0 for t in tables)
    return {"summary": summary, "per_seed": tables, "seeds_navigated": started}


def _mean_std(values: NDArray[np.float64]) -> dict[str, list[float] | float]:
    """Mean and std over axis 0 of the finite values (ddof 1 from two on, 0 with one; NaN with
    none)."""
    with warnings.catch_warnings():
        # A figure no seed has is NaN, as wanted, without numpy's "empty slice" warnings.
        warnings.simplefilter("ignore", RuntimeWarning)
        mean = np.nanmean(values, axis=0)
        std = np.nanstd(values, axis=0, ddof=1)
    std = np.where(np.isfinite(values).sum(axis=0) == 1, 0.0, std)
    return {"mean": mean.tolist(), "std": std.tolist()}


def markdown_table(runs: dict[str, dict[str, Any]]) -> str:
    """One row per target and measurement kind, mean ± std over seeds per axis."""

    def one(m: float, s: float, seeds: int) -> str:
        if not np.isfinite(m):  # no seed has the figure (nothing navigated): "nan ± nan" before
            return "–"
        return f"{m:.3g}" if seeds < 2 else f"{m:.3g} ± {s:.2g}"  # one seed has no spread

    def cell(stat: dict[str, Any], seeds: int) -> str:
        mean, std = np.atleast_1d(stat["mean"]), np.atleast_1d(stat["std"])
        return " / ".join(one(m, s, seeds) for m, s in zip(mean, std, strict=True))

    lines = ["| run | " + " | ".join(SUMMARY_KEYS) + " |", "|---" * (len(SUMMARY_KEYS) + 1) + "|"]
    for name, run in runs.items():
        seeds = len(run["per_seed"])
        cells = [cell(run["summary"][k], seeds) for k in SUMMARY_KEYS]
        lines.append(f"| {name} | " + " | ".join(cells) + " |")
    return "\n".join(lines) + "\n"


@register("fusion", uses=("targets", "seeds", "frames"))
def fusion(out_dir: Path, options: ExperimentOptions) -> dict[str, Any]:
    """Every target of :data:`TARGETS` (or of ``--targets``) with each of its measurement
    kinds (:func:`fusion_plan`): ``fusion.json``, ``fusion.md``. Full: 3 seeds of 600 frames
    (``--seeds``, ``--frames`` override); quick: the default target, registration and both, 1
    seed of 30 frames (``--seeds``, ``--frames`` override these too)."""
    plan = fusion_plan(options.targets, options.quick)
    # Given, --seeds and --frames win in a quick run too: --quick --seeds 3 ran one seed.
    n_seeds = options.seeds or (1 if options.quick else 3)
    frames = options.frames or (30 if options.quick else 600)
    seeds = list(range(options.seed, options.seed + n_seeds))
    base = FusionConfig(navigation=NavigationConfig())
    runs = {
        f"{target} / {kind}": over_seeds(target, kind, seeds, frames, base)
        for target, kinds in plan.items()
        for kind in kinds
    }
    table = {"frames": frames, "seeds": seeds, "runs": runs}
    (out_dir / "fusion.json").write_text(strict_json(table, indent=2, default=float) + "\n")
    (out_dir / "fusion.md").write_text(markdown_table(runs))
    for name, run in runs.items():
        if run["seeds_navigated"] < len(seeds):  # its figures stand on the other seeds alone
            problem = (
                f"{name} navigated no frame on {len(seeds) - run['seeds_navigated']} of "
                f"{len(seeds)} seeds ({frames} frames: too few to start?)"
            )
            warnings.warn(SpaceposeWarning(problem, out_dir / "fusion.md"), stacklevel=2)
    return table
