"""Case runners of ``spacepose campaign``: their registry and the two built-in ones.

A *case runner* is a function ``params -> {metric: scalar}`` registered under a name with
:func:`case_runner`; a campaign's ``case_kind`` picks it (:func:`get_runner`). Two come built in:
``registration`` (:func:`registration_case`: one simulated frame pair registered from a seeded,
perturbed start) and ``tracking`` (:func:`tracking_case`: a whole simulated lab run tracked and
scored against the truth). They are registered when this module is imported, which
:mod:`spacepose.tools.campaign_spec` does: a config's axes are checked against its runner.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from spacepose.core import se3
from spacepose.core.sim.sensors import SENSOR_PRESETS
from spacepose.errors import ConfigError

Scalar = bool | int | float | str
Metrics = dict[str, bool | int | float]
CaseFunction = Callable[[dict[str, Scalar]], Mapping[str, Any]]


# --------------------------------------------------------------------------------------------
# Case runners
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class Bound:
    """The values a numeric axis takes: numbers from ``low`` on (above it if ``strict``),
    integers only if ``integer``. Checked as the config is read, so that a bad value is one
    error naming the axis, not a failed case in a Dask worker."""

    low: float
    strict: bool = False
    integer: bool = False
    high: float = math.inf

    def problem(self, axis: str, values: Sequence[Scalar]) -> str | None:
        """What is wrong with an axis' values (None: nothing)."""
        kind = int if self.integer else (int, float)
        bad = [
            v
            for v in values
            if isinstance(v, bool) or not isinstance(v, kind) or not self._within(float(v))
        ]
        if not bad:
            return None
        what = "integers" if self.integer else "numbers"
        above = f"{'>' if self.strict else '>='} {self.low:g}"
        below = f" and <= {self.high:g}" if self.high < math.inf else ""
        return f"{axis} values must be {what} {above}{below}, got {bad}"

    def _within(self, value: float) -> bool:
        above = value > self.low if self.strict else value >= self.low
        return above and value <= self.high


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
        Axis name -> the values it accepts (e.g. the ``method`` names).
    extra_axes
        Names of the optional axes the runner reads besides the four required ones.
    bounds
        Numeric axis name -> the :class:`Bound` its values keep; axes in neither ``choices``
        nor ``bounds`` are free.
    scenario
        ``scenario(params)``: the simulator config a case's parameters make (raising
        ConfigError for values no scenario takes), or None.
    scenario_axes
        The axes ``scenario`` reads; every combination of their values is checked with it.
    """

    name: str
    fn: CaseFunction
    choices: dict[str, tuple[Scalar, ...]]
    extra_axes: tuple[str, ...]
    bounds: dict[str, Bound]
    scenario: Callable[[Mapping[str, Scalar]], object] | None = None
    scenario_axes: tuple[str, ...] = ()


_RUNNERS: dict[str, CaseRunner] = {}


def case_runner(
    name: str,
    *,
    choices: Mapping[str, Sequence[Scalar]] | None = None,
    extra_axes: Sequence[str] = (),
    bounds: Mapping[str, Bound] | None = None,
    scenario: Callable[[Mapping[str, Scalar]], object] | None = None,
    scenario_axes: Sequence[str] = (),
) -> Callable[[CaseFunction], CaseFunction]:
    """Decorator registering ``fn(params) -> metrics`` as the runner of ``case_kind=name``.

    The runner receives one case's parameters (every grid axis, e.g. ``scenario``,
    ``noise_scale``, ``method``, ``seed``) and returns scalar metrics (bool, int or float). It
    raises a :class:`~spacepose.errors.SpaceposeError` for an expected failure such as a
    registration without correspondences or a combination of values no scenario allows: the
    case is then recorded with its ``error`` message and no metrics. ``choices`` and
    ``bounds`` restrict an axis' values, ``scenario`` their combinations (:class:`CaseRunner`).
    """

    def wrap(fn: CaseFunction) -> CaseFunction:
        allowed = {axis: tuple(values) for axis, values in (choices or {}).items()}
        _RUNNERS[name] = CaseRunner(
            name, fn, allowed, tuple(extra_axes), dict(bounds or {}), scenario, tuple(scenario_axes)
        )
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


def _registration_scenario(params: Mapping[str, Scalar]) -> Any:
    """The two-frame run a registration case simulates (its seed 0 when not given)."""
    from spacepose.core.sim import scenario_config

    return scenario_config(
        str(params["scenario"]),
        sensor=params.get("sensor"),  # type: ignore[arg-type]
        noise_scale=float(params["noise_scale"]),
        frames=2,
        seed=int(params.get("seed", 0)),
    )


def _tracking_scenario(params: Mapping[str, Scalar]) -> Any:
    """The lab run a tracking case simulates (58 frames, its seed 0 when not given)."""
    from spacepose.core.sim import scenario_config

    return scenario_config(
        "lab",
        noise_scale=float(params["noise_scale"]),
        frames=int(params.get("frames", 58)),
        seed=int(params.get("seed", 0)),
        background=bool(params.get("background", False)),
    )


@case_runner(
    "registration",
    choices={
        "method": REGISTRATION_METHODS,
        "scenario": tuple(REGISTRATION_DEFAULTS),
        "sensor": tuple(SENSOR_PRESETS),
    },
    extra_axes=("sensor", "perturbation_deg", "perturbation_mm", "max_correspondence_mm"),
    bounds={
        # A turn of more than half a turn is a smaller one the other way.
        "perturbation_deg": Bound(0.0, high=180.0),
        "perturbation_mm": Bound(0.0),
        # ICP and GICP need a gate above zero.
        "max_correspondence_mm": Bound(0.0, strict=True),
    },
    scenario=_registration_scenario,
    scenario_axes=("scenario", "sensor", "noise_scale"),
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
    from spacepose.core.sim import simulate

    p = _registration_params(params)
    sim = simulate(_registration_scenario(p))
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
    # A model-free run of one frame scores its start against itself: every error zero.
    bounds={"frames": Bound(2, integer=True)},
    scenario=_tracking_scenario,
    scenario_axes=("noise_scale", "frames", "background"),
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
    from spacepose.core.sim import simulate
    from spacepose.core.tracker import TrackerConfig, track_sequence
    from spacepose.core.trajectory import Trajectory

    background = bool(params.get("background", False))
    sim = simulate(_tracking_scenario(params))
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
