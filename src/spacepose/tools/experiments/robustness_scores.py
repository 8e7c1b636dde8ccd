"""Scores of one tracked run of the robustness grid against its ground truth (methods.md §4, §6).

Model-free tracking estimates ``T_k0`` (frame 0 defines the target frame, methods.md §0.7); its
truth is ``T_sensor_target(k) · T_sensor_target(0)⁻¹``. For frame k:

- the *error twist* ``δ = Log(T_est · T_true⁻¹)`` (rotation first, left perturbation in the sensor
  frame of frame k), the terms of the reported covariance, so ``|δ_i| / σ_i`` is the error in
  reported sigmas on axis i;
- the *error at the target*: ``e_t = |ΔR c + Δt − c|`` with c the centroid of the frame's true
  target points (the position error of the target, free of the lever arm of the sensor origin)
  and ``e_r`` the rotation angle of ``ΔR``;
- the *displacement* ``d``: RMS over the frame's target points of ``|ΔT p − p|``;
- two Cramér–Rao bounds (methods.md §4), each as ``sqrt(trace)`` of its translation block at c and
  of its rotation block, comparable with ``e_t`` and ``e_r`` (the mean norm of an efficient
  estimator's 3-vector error is about 0.9 of these):

  * *per frame*: the frame-to-frame bound of frame k alone (its points, true normals and σ, the
    reference as noisy as the frame), what registering frame k once onto frame 0 could reach;
  * *chain*: that bound accumulated along the tracker's own keyframe chain, ``C_k = B_k +
    Ad(T_kr) C_r Ad(T_kr)ᵀ`` with r the keyframe frame k was registered to. It is the floor for a
    tracker that hops through those keyframes; a long or tumbling run needs a chain (frame k no
    longer sees frame 0's surfaces), so an error within a few chain bounds but many per-frame
    bounds is drift from the hops, not a bad registration.

Definitions (one place, used by the table and the tests):

- *tracked*: status ``ok`` or ``degraded`` and ``d ≤`` :data:`TRACKED_RANGE_FRACTION` × range;
- *3σ coverage*: share of ``ok`` frames with ``|δ_i| ≤ 3σ_i`` on all six axes;
- *false ok*: an ``ok`` frame with ``|δ_i| > 5σ_i`` on any axis;
- mean errors and the error / bound ratios are over the frames not ``lost``; frame 0 (the
  identity by definition) is left out of everything.
"""

from __future__ import annotations

import re
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from numpy.typing import NDArray

from spacepose.core import se3
from spacepose.core.sim.simulation import Frame
from spacepose.core.track_result import TrackResult
from spacepose.errors import ConfigError

#: A frame is tracked when its target points lie within this share of the range, RMS.
TRACKED_RANGE_FRACTION = 0.01
COVERAGE_SIGMAS = 3.0
FALSE_OK_SIGMAS = 5.0
#: The issue's acceptance bounds per cell: (metric, comparison, bound).
DONE_WHEN: tuple[tuple[str, str, float], ...] = (
    ("tracked_share", ">=", 0.98),
    ("error_over_crlb", "<=", 3.0),
    ("false_ok", "<=", 0.0),
    ("coverage_3sigma", ">=", 0.95),
)
# Error components (rad, m) below this are rounding, not error.
_ROUNDING = 1e-12
_TWIST = ("rx", "ry", "rz", "tx", "ty", "tz")


@dataclass(frozen=True, eq=False)
class FrameTruth:
    """What the scores need of a simulated frame.

    Attributes
    ----------
    T_true_k0
        (4, 4) true ``T_k0``: frame-0 sensor coordinates into frame-k sensor coordinates.
    target_points
        (N, 3) the frame's non-flying target points, sensor frame of frame k, m.
    crlb
        (6, 6) frame-to-frame Cramér–Rao bound of the frame, twist (ω, v) about the sensor
        origin, rad and m; NaN for a frame without noise (a render), which has none.
    """

    T_true_k0: NDArray[np.float64]
    target_points: NDArray[np.float64]
    crlb: NDArray[np.float64]

    @classmethod
    def from_frame(cls, frame: Frame, T_sensor_target_0: NDArray[np.float64]) -> FrameTruth:
        keep = frame.on_target & ~frame.flying
        try:
            bound = frame.crlb(frame_to_frame=True).covariance
        except ConfigError:  # noise 0: no bound, and the frame is still scored
            bound = np.full((6, 6), np.nan)
        return cls(
            frame.T_sensor_target @ se3.invert(T_sensor_target_0), frame.cloud.points[keep], bound
        )


def _at_point(covariance: NDArray[np.float64], c: NDArray[np.float64]) -> tuple[float, float]:
    """``sqrt(trace)`` of the translation (m) at point c and of the rotation (rad) of a (6, 6)
    twist covariance about the origin: the displacement at c is ``v − [c]× ω``."""
    J = np.hstack([-se3.skew(c), np.eye(3)])
    return float(np.sqrt(np.trace(J @ covariance @ J.T))), float(
        np.sqrt(np.trace(covariance[:3, :3]))
    )


def score_frame(
    result: TrackResult,
    truth: FrameTruth,
    chain: NDArray[np.float64],
    range_m: float,
) -> dict[str, Any]:
    """One row of scores for one frame (units in the keys: mm, deg, ms).

    Parameters
    ----------
    result
        The tracker's result for the frame.
    truth
        Its ground truth.
    chain
        (6, 6) the chain Cramér–Rao bound of the frame (module notes), about the sensor origin.
    range_m
        The cell's range, m (sets the tracked tolerance).
    """
    delta_T = result.T_sensor_target @ se3.invert(truth.T_true_k0)
    delta = se3.log(delta_T)
    sigma = result.sigma
    # Frame 0 has σ = 0 and an error of rounding size only.
    zero = np.abs(delta) <= _ROUNDING
    with np.errstate(divide="ignore", invalid="ignore"):
        nsigma = np.where(zero, 0.0, np.abs(delta) / sigma)
    pts = truth.target_points
    c = pts.mean(axis=0)
    moved = se3.transform_points(delta_T, pts) - pts
    disp = float(np.sqrt(np.mean(np.einsum("ij,ij->i", moved, moved))))
    crlb_t, crlb_r = _at_point(truth.crlb, c)
    chain_t, chain_r = _at_point(chain, c)
    ok = result.status == "ok"
    times = result.time_ms
    row: dict[str, Any] = {
        "frame": result.index,
        "status": result.status,
        "reasons": "; ".join(result.reasons),
        "coarse": result.coarse,
        "keyframe": result.keyframe,
        "reference": result.reference_index,
        "fitness": result.fitness,
        "rmse_mm": 1e3 * result.rmse,
        "condition": result.condition_number,
        "err_t_mm": 1e3 * float(np.linalg.norm(moved.mean(axis=0))),
        "err_r_deg": float(np.degrees(np.linalg.norm(delta[:3]))),
        "disp_mm": 1e3 * disp,
        "crlb_t_mm": 1e3 * crlb_t,
        "crlb_r_deg": float(np.degrees(crlb_r)),
        "chain_t_mm": 1e3 * chain_t,
        "chain_r_deg": float(np.degrees(chain_r)),
        "nsigma_max": float(np.max(nsigma)),
        "tracked": result.status != "lost" and disp <= TRACKED_RANGE_FRACTION * range_m,
        "within_3sigma": ok and bool(np.all(nsigma <= COVERAGE_SIGMAS)),
        "false_ok": ok and bool(np.any(nsigma > FALSE_OK_SIGMAS)),
        **{f"ms_{s}": float(times.get(s, 0.0)) for s in ("total", "preprocess", "coarse", "fine")},
    }
    scale = np.array([*[np.degrees(1.0)] * 3, *[1e3] * 3])  # deg, deg, deg, mm, mm, mm
    row |= {f"d_{a}": float(v) for a, v in zip(_TWIST, scale * delta, strict=True)}
    row |= {f"s_{a}": float(v) for a, v in zip(_TWIST, scale * sigma, strict=True)}
    return row


def chain_bound(
    results: Sequence[TrackResult], truths: Sequence[FrameTruth]
) -> list[NDArray[np.float64]]:
    """The chain Cramér–Rao bound of every frame (module notes), (6, 6) each, sensor origin.

    A frame's reference is the keyframe it was registered to; a lost frame (no reference) is
    charged from the latest keyframe; frame 0 (the first keyframe) has bound zero.
    """
    bounds: list[NDArray[np.float64]] = []
    latest = 0
    for k, (res, truth) in enumerate(zip(results, truths, strict=True)):
        r = res.reference_index if 0 <= res.reference_index < k else latest
        if k == 0:
            bounds.append(np.zeros((6, 6)))
        else:
            Ad = se3.adjoint(truth.T_true_k0 @ se3.invert(truths[r].T_true_k0))
            bounds.append(truth.crlb + Ad @ bounds[r] @ Ad.T)
        if res.keyframe:
            latest = k
    return bounds


def _mean(values: Sequence[float]) -> float:
    return float(np.mean(values)) if len(values) else float("nan")


def reason_kind(reason: str) -> str:
    """A reason without its numbers, so that reasons of one kind count together."""
    return re.sub(r"\s+", " ", re.sub(r"[-+]?\d[\d.eE+-]*", "#", reason)).strip()


def summarise_cell(rows: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """The metrics of one run from its frame rows (frame 0 left out; module notes)."""
    rows = [r for r in rows if r["frame"] > 0]
    used = [r for r in rows if r["status"] != "lost"]
    ok = [r for r in rows if r["status"] == "ok"]
    statuses = Counter(r["status"] for r in rows)
    ratio = {
        f"{name}_{a[0]}": _mean([r[f"err_{a}"] for r in used])
        / _mean([r[f"{name}_{a}"] for r in used])
        for name in ("crlb", "chain")
        for a in ("t_mm", "r_deg")
    }
    reasons = Counter(
        reason_kind(x) for r in rows if r["reasons"] for x in r["reasons"].split("; ")
    )
    return {
        "frames": len(rows),
        "tracked_share": _mean([float(r["tracked"]) for r in rows]),
        "ok": statuses["ok"],
        "degraded": statuses["degraded"],
        "lost": statuses["lost"],
        "coarse": sum(bool(r["coarse"]) for r in rows),
        "keyframes": sum(bool(r["keyframe"]) for r in rows),
        "err_t_mm": _mean([r["err_t_mm"] for r in used]),
        "err_r_deg": _mean([r["err_r_deg"] for r in used]),
        "crlb_t_mm": _mean([r["crlb_t_mm"] for r in used]),
        "crlb_r_deg": _mean([r["crlb_r_deg"] for r in used]),
        "error_over_crlb_t": ratio["crlb_t"],
        "error_over_crlb_r": ratio["crlb_r"],
        "error_over_crlb": float(np.max([ratio["crlb_t"], ratio["crlb_r"]])),
        "error_over_chain": float(np.max([ratio["chain_t"], ratio["chain_r"]])),
        "coverage_3sigma": _mean([float(r["within_3sigma"]) for r in ok]),
        "false_ok": sum(bool(r["false_ok"]) for r in ok),
        "ms_per_frame": _mean([r["ms_total"] for r in rows]),
        "first_untracked": next((r["frame"] for r in rows if not r["tracked"]), -1),
        "first_false_ok": next((r["frame"] for r in ok if r["false_ok"]), -1),
        "reasons": dict(reasons.most_common(6)),
    }
