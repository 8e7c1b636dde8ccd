"""The model-free tracker's references: a window of keyframes and its policy (methods.md §5.4).

Li's J-ICP registers each frame onto the two accepted frames before it; our keyframe graph onto
a window of keyframes, promoting a frame when :func:`~spacepose.core.keyframes.needs_keyframe`
says so. A trusted frame (``ok``, or degraded only by its distance from the keyframe) also
refreshes the window's poses that its registration re-estimated. A frame degraded by its
precision alone is promoted when it sees the target much closer than its keyframe did.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from spacepose.core.frame_check import FAR_KEYFRAME, UNTESTED_MODEL
from spacepose.core.health import CONDITION, IMPRECISE, NO_VELOCITY, UNCONFIRMED, Status
from spacepose.core.keyframes import FineEstimate, Keyframe, PreparedCloud, needs_keyframe
from spacepose.core.tracker_config import TrackerConfig

# A frame degraded by its precision alone becomes a keyframe when seen at this share of its
# keyframe's range or less: its samples are then at least twice as dense on the target (a
# camera samples solid angle), and a ToF's range noise, growing with the square of the range,
# at most half.
CLOSER_RANGE = 0.5**0.5


class KeyframeWindow:
    """The keyframes a model-free frame is registered onto, oldest first.

    Parameters
    ----------
    config
        The tracker's config: its method (``"jicp"`` keeps the last two accepted frames), the
        keyframe graph's window and the promotion thresholds.
    """

    def __init__(self, config: TrackerConfig) -> None:
        self.config = config
        self.keyframes: list[Keyframe] = []
        # A frame since the latest keyframe, and since the latest `ok` frame, left a direction
        # unobserved: its pose, carried by the motion model, may have slid, and so may every
        # pose predicted from it.
        self._slid = False
        # The latest frame fitted its keyframe below the stale fitness.
        self._stale = False
        # The window before a provisional keyframe, until the next frame confirms it.
        self._provisional: tuple[list[Keyframe], bool] | None = None

    def __bool__(self) -> bool:
        return bool(self.keyframes)

    @property
    def latest(self) -> Keyframe:
        return self.keyframes[-1]

    @property
    def li(self) -> bool:
        """Li's J-ICP: every accepted frame becomes the next frame's reference."""
        return self.config.method == "jicp"

    def references(self) -> list[Keyframe]:
        """What a frame's joint registration uses: J-ICP the two latest accepted frames, the
        keyframe graph the window it is about to end."""
        if self.li:
            return self.keyframes[-2:]
        return self.keyframes[-(self.config.keyframe_graph.window - 1) :]

    def restart(self, first: Keyframe) -> None:
        """Only ``first`` is kept (a new start, or the first keyframe cut to the target)."""
        self.keyframes = [first]
        self._slid = self._stale = False
        self._provisional = None

    def confirm(self, fitness_onto: Callable[[Keyframe], float]) -> None:
        """Settle a provisional keyframe on the frame after it: kept when that frame fits it
        better (``fitness_onto``, a keyframe -> the frame's fitness registered onto it) than
        the keyframe before it and that one no longer serves as well as a keyframe must (a
        fitness under the promotion bound, ``min_fitness``), else dropped with the window as
        it was before. A view turning away fits its
        newest keyframe best and its older one poorly; after a glitch the scene is back in the
        older one's view. Fitness counts the frame's points only, so a glitch that added a
        surface (a second return 3 m behind the lab target) fitted the next frame as well as
        the keyframe before it: kept, its cloud 1.5 m across held every later frame's coarse
        surfaces degenerate, `degraded` at σ 0.4 m to the end of the run."""
        if self._provisional is None:
            return
        before, self._provisional = self._provisional, None
        old = fitness_onto(before[0][-1])
        if fitness_onto(self.latest) <= old or old >= self.config.keyframe.min_fitness:
            self.restore(before)

    def snapshot(self) -> tuple[list[Keyframe], bool]:
        """The window's state, for :meth:`restore` after a trial restart."""
        return list(self.keyframes), self._slid

    def restore(self, state: tuple[list[Keyframe], bool]) -> None:
        """Back to a :meth:`snapshot`."""
        self.keyframes, self._slid = list(state[0]), state[1]

    def update(
        self,
        index: int,
        timestamp: float,
        prepared: PreparedCloud,
        estimate: FineEstimate,
        health: tuple[Status, tuple[str, ...]],
        radius: float,
        dense_cloud: Callable[[PreparedCloud], PreparedCloud | None],
    ) -> bool:
        """Refresh the window's poses and promote the frame if the policy says so.

        Parameters
        ----------
        index, timestamp, prepared, estimate
            The accepted frame: its index, time (s), cloud and fine registration.
        health
            Its status and reasons.
        radius
            The target's RMS radius (m) that scales the promotion distance.
        dense_cloud
            Makes the frame a registration reference and returns its finer cloud (None: the
            frame's own is the reference); called only when the frame is promoted.

        Returns
        -------
        bool
            Whether the frame became a keyframe.
        """
        status, reasons = health
        # A frame degraded only by the distance to its keyframe passed every check of its own
        # registration: promoting it is how the tracker gets back to ok after a re-initialisation.
        # One degraded only because the motion model is untested did too: it is kept as an ok
        # frame would be, and only its flag waits for the model.
        pending = bool(reasons) and all(
            r.startswith(FAR_KEYFRAME) or r == UNTESTED_MODEL for r in reasons
        )
        trusted = status == "ok" or pending
        if trusted:
            for kf, T_kf, cov_kf in estimate.window_poses:
                kf.T_ref_target, kf.covariance = T_kf, cov_kf
        # An `ok` frame since then was registered onto the window without a slide and passed
        # the prediction check: the motion model carries its pose on, not the slid one.
        self._slid = status != "ok" and (
            self._slid or any(r.startswith(CONDITION) for r in reasons) or _unconfirmed(reasons)
        )
        stale = estimate.result.fitness < self.config.keyframe.stale_fitness
        sudden, self._stale = stale and not self._stale, stale
        if (
            not self.li
            and not _closer(status, reasons, prepared, estimate.reference)
            and not needs_keyframe(estimate, prepared, self.config.keyframe, radius, not trusted)
        ):
            return False
        # A degraded frame that fits the window poorly right after one that fitted it may be a
        # view turning away, or a glitch of the sensor (a torn readout: the image shifted
        # 40 px). Its keyframe is provisional until the next frame says which (:meth:`confirm`):
        # promoted for good, a torn lab frame held the 12 frames after it 40 mm off, `ok` at
        # 7-13σ.
        self._provisional = self.snapshot() if sudden and not trusted and not self.li else None
        # The keyframe keeps the noise covariance; its drift is carried apart.
        kf = Keyframe(
            index,
            prepared,
            estimate.T_sensor_target,
            estimate.covariance - (0.0 if estimate.drift is None else estimate.drift),
            list(estimate.edges),
            estimate.bias,
            timestamp,
            dense_cloud(prepared),
            # A slide the frame's own registration, a frame since the latest keyframe, or the
            # chain before it could not see (a hand-held camera turning 90°/s past a wall and
            # a floor slid 1.4 m over frames 2-5 that were never keyframes; from a keyframe
            # made after them, 23 frames were `ok` 1.4 m off).
            self._slid or estimate.reference.unobserved,
        )
        self._slid = False
        keep = 1 if self.li else self.config.keyframe_graph.window
        self.keyframes = [*self.keyframes[-keep:], kf]
        return True


def _closer(
    status: Status, reasons: tuple[str, ...], prepared: PreparedCloud, reference: Keyframe
) -> bool:
    """A frame degraded by its precision alone, seen at most :data:`CLOSER_RANGE` times its
    keyframe's range. An approaching target's keyframe from far off is sparse and noisy, and a
    frame registered onto it is no more precise than it: every frame stayed `degraded` by its
    σ and none became a keyframe. satellite_panels at 1.57 m approaching from 9.5 to 1.5 m
    kept its first keyframe (491 points) to the end, every frame 0.5-6° off."""
    return (
        status == "degraded"
        and bool(reasons)
        and all(r.startswith(IMPRECISE) for r in reasons)
        and float(np.linalg.norm(prepared.centroid))
        <= CLOSER_RANGE * float(np.linalg.norm(reference.prepared.centroid))
    )


def _unconfirmed(reasons: tuple[str, ...]) -> bool:
    """A pose no prediction confirmed that fits its reference poorly. A coarse one, a near-twin
    of the target's view (a box 8 m out, turned 120° onto another face pair at a fitness of
    0.39), gives every later frame a consistent step and a wrong pose, `ok` at 123σ. So does a
    second frame registered from the first pose alone: a target receding 0.19 m a frame from
    1.5 m, registered 77 mm short at a fitness of 0.53, held every later frame 150 mm off, four
    of them `ok` at 31-41σ."""
    unconfirmed = UNCONFIRMED in reasons or NO_VELOCITY in reasons
    return unconfirmed and any(r.startswith("fitness") for r in reasons)
