"""Model-free: a first frame that no later frame confirms is replaced (docs/methods.md §5.6).

The first usable frame defines the target frame (§0.7). When it is garbage a sensor gave (a
warm-up frame of flying pixels, a glitch 1 km off), every later frame is lost against it, or
registered onto it with a poor fit, and the run never starts. While no frame after it has been
accepted with a fit, each frame the run's tracker loses or fits badly is also given to a spare
tracker started on such a frame; once the spare registers a frame onto its own first one with a
fit, it carries on as the run's tracker, and the target frame is that first frame's sensor
frame.
"""

from __future__ import annotations

import dataclasses
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike

from spacepose.core.cloud import PointCloud
from spacepose.core.track_result import TrackResult
from spacepose.core.tracker_config import TrackerConfig

if TYPE_CHECKING:
    from spacepose.core.tracker import Tracker

Frame = tuple["PointCloud | ArrayLike | None", float]
# Frames the run's tracker may accept without a fit before its first frame stands: a spare costs
# a frame's work each, and a scene that no registration fits within the bounds (a support
# moving otherwise, noise ×3) never confirms a first frame.
MAX_UNFIT = 3


def abandoned_anchor(first: TrackResult, new_anchor: int) -> TrackResult:
    """The revised result of a first frame no later frame confirmed: lost, its pose unknown."""
    reason = (
        f"a first frame no later frame confirmed: the target frame is frame {new_anchor}'s "
        "sensor frame instead"
    )
    return dataclasses.replace(
        first, status="lost", covariance=np.diag(np.full(6, np.inf)), reasons=(reason,)
    )


def orphaned(result: TrackResult, old_anchor: int, new_anchor: int) -> TrackResult:
    """The revised result of a frame between an abandoned first frame and the new one: lost,
    for its pose was relative to the abandoned target frame (the identity, σ infinite, as a
    lost frame's with nothing known)."""
    reason = (
        f"tracked against frame {old_anchor}, a first frame no later frame confirmed: the "
        f"target frame is frame {new_anchor}'s sensor frame instead"
    )
    # A frame lost already keeps why (an unreadable file's error) before the revision's reason.
    reasons = (*result.reasons, reason) if result.status == "lost" else (reason,)
    return dataclasses.replace(
        result,
        status="lost",
        T_sensor_target=np.eye(4),
        covariance=np.diag(np.full(6, np.inf)),
        reasons=reasons,
    )


def new_anchor(first: TrackResult, old_anchor: int) -> TrackResult:
    """The revised result of the frame that now defines the target frame (it was lost against
    the first one): the identity, as every model-free first frame's."""
    reason = f"the target frame restarts here: frame {old_anchor}, the first, was never confirmed"
    return dataclasses.replace(first, reasons=(reason,))


class SpareAnchor:
    """A tracker started on a frame the run's tracker lost or fitted badly, while the run's
    first frame is still unconfirmed.

    Parameters
    ----------
    config, workers
        The run's tracker config and threads.
    """

    def __init__(self, config: TrackerConfig, workers: int) -> None:
        self._config, self._workers = config, workers
        self.tracker: Tracker | None = None
        self._unfit = 0
        # The run's results after its first frame: relative to a target frame that may go.
        self._after_first: list[TrackResult] = []
        # A pose found with no prediction to confirm it (a coarse jump) came between: later
        # fits confirm it, not the first frame.
        self._jumped = False

    def follow(
        self,
        frame: Frame,
        result: TrackResult,
        first: TrackResult | None,
        fits: bool,
        jumped: bool = False,
    ) -> tuple[bool, tuple[Tracker, TrackResult] | None]:
        """Follow the run's tracker's ``result`` on ``frame`` ``(cloud, timestamp)``, its first
        frame's result ``first`` (None before it); ``fits``: the result is accepted and fits
        (fitness and RMSE within their ok bounds, :meth:`TrackerState.fits`); ``jumped``: it
        is a coarse jump beyond any motion from the first frame (:meth:`TrackerState.jumped`),
        and no later fit confirms the first frame.

        Returns
        -------
        needed
            False once a frame after the first was accepted and fits (the first frame is
            confirmed and stays the target frame), or after :data:`MAX_UNFIT` frames
            accepted without fitting.
        adopted
            Once the spare registered a frame that the run's tracker lost or did not fit onto
            its own first one, and it fits: the spare, which the run's tracker should carry on
            as, and its result on the frame, revising the two first frames' results
            (:attr:`TrackResult.revises`); None otherwise.
        """
        if first is None or result.index == first.index:
            return True, None
        self._after_first.append(result)
        self._jumped = self._jumped or jumped
        if fits and not self._jumped:
            return False, None
        if result.status != "lost":
            self._unfit += 1
            if self._unfit > MAX_UNFIT:
                return False, None
        spare = self._track(frame, result.index)
        if spare is None:
            return True, None
        tracker, spare_result = spare
        anchor = tracker._first
        # The frames between the two first frames were tracked in the abandoned target frame
        # (a degraded frame's pose stayed in it, beside poses in the new one).
        between = [
            orphaned(r, first.index, anchor.index)
            for r in self._after_first
            if r.index < anchor.index
        ]
        revised = (
            abandoned_anchor(first, anchor.index),
            *between,
            new_anchor(anchor, first.index),
        )
        return False, (tracker, dataclasses.replace(spare_result, revises=revised))

    def _track(self, frame: Frame, index: int) -> tuple[Tracker, TrackResult] | None:
        """The spare's result on frame ``index``, once it registered the frame onto its own
        first one and it fits; None otherwise: the spare then starts afresh on this frame (or,
        when the frame is unusable, on the next one)."""
        if self.tracker is not None:
            self.tracker.continue_at(index)  # numbered as the run's (a frame skipped between)
            result = self.tracker.track_frame(*frame)
            if self.tracker.fits(result):
                return self.tracker, result
        self.tracker = self._fresh(index)
        if self.tracker.track_frame(*frame).status == "lost":
            self.tracker = None
        return None

    def _fresh(self, index: int) -> Tracker:
        from spacepose.core.tracker import Tracker

        tracker = Tracker(self._config, None, self._workers)
        tracker.continue_at(index)
        tracker._spare = None  # a spare keeps no spare of its own
        return tracker
