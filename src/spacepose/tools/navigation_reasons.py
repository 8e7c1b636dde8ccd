"""Why a navigation run went as it did, said in one line: the frames it navigated as empty,
the reason no frame was navigated (rectangles, registration poses, ambiguity, unreadable
frames) and a filter that predicted alone after its start."""

from __future__ import annotations

import warnings
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from spacepose.core.fused_navigation import FusionConfig
from spacepose.core.nav_result import NavRow
from spacepose.errors import SpaceposeWarning


def warn_unusable_frames(
    tracks: Sequence[Any], unreadable: dict[int, str], health_csv: Path
) -> None:
    """Warn of each frame read but unusable to the tracker, navigated as empty."""
    for k, track in enumerate(tracks):
        unusable = [r for r in track.reasons if r.startswith("unusable frame")]
        if k not in unreadable and unusable:  # said as the rectangles' path says its own
            problem = f"frame {k} navigated as empty: {unusable[0]}"
            warnings.warn(SpaceposeWarning(problem, health_csv), stacklevel=3)


def warn_refused_frames(rows: Sequence[NavRow], unreadable: dict[int, str]) -> None:
    """Warn of each frame whose points the plane search refused (its rectangles are left out)
    or before which the filter could not predict (it starts again): each ended the whole run."""
    for k, row in enumerate(rows):
        if row.problem is not None and k not in unreadable:
            warnings.warn(SpaceposeWarning(f"frame {k}: {row.problem}"), stacklevel=3)


def why_no_registration(
    tracks: Sequence[Any], fusion: FusionConfig, has_model: bool, health_csv: Path | None
) -> str:
    """One line: why registration poses navigated no frame. Model-free, the filter waits for
    a batch of ok poses: a run shorter than it was said to have given "no ok pose", though
    the tracker gave one on every frame."""
    ok = sum(track.status == "ok" for track in tracks)
    if ok == 0:
        return f"no frame navigated: the tracker gave no ok pose (see {health_csv})"
    if not has_model and ok >= fusion.model_free_frames:
        return (
            f"no frame navigated: without a model the filter starts once its batch of ok poses "
            f"shows a rigid body's moments, and the tracker's {ok} did not (too little of the "
            "tumble seen?): a longer run, or a model (--model)"
        )
    if not has_model:
        return (
            f"no frame navigated: without a model the filter starts on a batch of "
            f"{fusion.model_free_frames} ok poses (the body's axes and centre of mass), and "
            f"the tracker gave {ok} in {len(tracks)} frames: a longer run, or a model (--model)"
        )
    return f"no frame navigated from the tracker's {ok} ok poses (see {health_csv})"


def why_nothing(rows: Sequence[NavRow], candidates_csv: Path | None, has_model: bool) -> str:
    """One line: why no frame of the run was navigated."""
    if candidates_csv is not None:
        most = max(len(r.candidates) for r in rows)
        extra = "" if has_model else "; a target model (model.ply) might tell them apart"
        return (
            f"no frame navigated: the target's pose stayed ambiguous in all {len(rows)} frames "
            f"(up to {most} candidates explain the data equally well: a symmetric target?), "
            f"candidates in {candidates_csv}{extra}"
        )
    return (
        f"no frame navigated: none of the {len(rows)} frames shows a whole rectangle of the "
        "catalogue (check the catalogue's sizes and the plane settings)"
    )


def with_unreadable(why: str, frames: int, unreadable: dict[int, str]) -> str:
    """``why`` no frame was navigated, after the frames that could not be read, if any."""
    if not unreadable:
        return why
    k = min(unreadable)
    first = f"(frame {k}: {unreadable[k]})"
    # With none read, the rest of the reason (a catalogue's sizes, a tracker's poses)
    # would send the user after what no frame was there to show.
    return (
        f"no frame navigated: none of the {frames} frames could be read {first}"
        if len(unreadable) == frames
        else f"{len(unreadable)} of {frames} frames could not be read {first}; {why}"
    )


def warn_if_predicted_alone(
    rows: Sequence[NavRow], navigated: int, prior: bool, nav_csv: Path
) -> None:
    """Warn when no measurement updated the filter after its start."""
    if navigated > 1 and not any(r.status == "update" for r in rows):
        # Started, then predicted alone: counted as navigated, 4 m and 178° off after a --prior
        # of the wrong side (no rectangle agreed with the pose it started from).
        hint = " (a --prior far from the target's attitude?)" if prior else ""
        problem = (
            f"no measurement updated the filter after its start: {navigated - 1} frames "
            f"predicted alone{hint}"
        )
        warnings.warn(SpaceposeWarning(problem, nav_csv), stacklevel=3)


# Share of the frames after the start that may update nothing before it is warned of: a third.
# The orbit runs of seeds 1-3 left 1-9 % of theirs to the prediction (a face seen edge-on);
# a mean motion twice the run's left 49 %, timestamps twice theirs 35 %, shuffled frames 99 %.
GATED_SHARE = 1 / 3


def warn_if_mostly_predicted(rows: Sequence[NavRow], nav_csv: Path) -> None:
    """Warn when a third or more of the frames after the filter's start updated nothing, as
    a filter whose model does not fit the data leaves them: a mean motion twice the run's had
    95 of 195 frames' rectangles gated out without a word, and ended 14° off at a σ of 0.01°."""
    after = [r for r in rows if r.status in ("predict", "update")]
    idle = [r for r in after if r.status == "predict"]
    if len(after) > 1 and len(idle) > 1 and len(idle) >= GATED_SHARE * len(after):
        gated = sum(r.coarse_T_sensor_model is not None for r in idle)
        problem = (
            f"{len(idle)} of {len(after)} frames after the start updated nothing ({gated} of "
            "them with rectangles the gate refused, the rest with no measurement): a gate that "
            "refuses what the frames show says the filter's model does not fit them (mean "
            "motion, timestamps, catalogue, frame order), and its σ do not hold its state"
        )
        warnings.warn(SpaceposeWarning(problem, nav_csv), stacklevel=3)


def warn_if_no_rectangle_used(rows: Sequence[NavRow], nav_csv: Path) -> None:
    """Warn when a run fusing rectangles and registration poses used no rectangle in any
    frame: a catalogue of another target (25 % larger) navigated on the poses alone, as if
    both had been fused."""
    if rows and not any(r.n_rect for r in rows):
        problem = (
            "no rectangle of the catalogue was used in any frame: the run navigated on "
            "registration poses alone (check the catalogue's sizes against the target's faces)"
        )
        warnings.warn(SpaceposeWarning(problem, nav_csv), stacklevel=3)
