"""The tracker's side of a support moving otherwise (methods.md §5.8): when to look for one, and
leaving it out of every frame once found (the geometry is :mod:`spacepose.core.bodies` and
:mod:`spacepose.core.clutter_body`)."""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import NDArray

from spacepose.core import se3
from spacepose.core.bodies import split_trial
from spacepose.core.clutter_body import ClutterBody, subset
from spacepose.core.correspondences import find_correspondences
from spacepose.core.frame_registration import FrameRegistrar
from spacepose.core.keyframes import FineEstimate, Keyframe, PreparedCloud
from spacepose.core.relocalise import Checked
from spacepose.core.segmentation import TargetRegion, region_of
from spacepose.errors import SpaceposeError

# The second motion of a support standing still before a sensor that stands still too.
_STILL = np.eye(4)


@dataclass(frozen=True)
class Look:
    """What a frame showed of a support moving otherwise (:meth:`SupportSeparation.look`).

    Attributes
    ----------
    checked
        The frame's registration and health, ``degraded`` when its residuals against the first
        keyframe carry structure above the bound.
    found
        After a split: (the target's part of the frame, initial ``T_sensor_target`` (4, 4)
        onto the first keyframe's target points); None without one.
    """

    checked: Checked
    found: tuple[PreparedCloud, NDArray[np.float64]] | None = None


class SupportSeparation:
    """Finds a support split off a model-free target, then takes it out of every frame.

    Parameters
    ----------
    registrar
        The tracker's registrar: its measured residual noise sets the split's σ.
    min_points
        Fewest points a body must keep (the tracker's health bound).
    workers
        Threads of the searches.
    stale_fitness
        Fitness onto a keyframe below which it is going stale (the keyframe policy's): a
        frame that fits the first keyframe less is not compared with it (:meth:`parted`).
    max_condition
        Largest condition number of the target body's own motion after a split (the health
        check's ok bound, :func:`~spacepose.core.bodies.split_trial`).
    """

    def __init__(
        self,
        registrar: FrameRegistrar,
        min_points: int,
        workers: int,
        stale_fitness: float,
        max_condition: float,
    ) -> None:
        self.registrar = registrar
        self.min_points = min_points
        self.workers = workers
        self.stale_fitness = stale_fitness
        self.max_condition = max_condition
        # The support moving otherwise (found by a fitted second motion: the looks end), and a
        # support standing still (the looks go on: a turntable may stand on the still table).
        self.support: ClutterBody | None = None
        self.still: ClutterBody | None = None
        # Time of the frame of the latest split (s).
        self.found_at: float | None = None
        # The first keyframe: the split's reference, the one pose no compromise has touched
        # (the target frame itself); and the time from it to the last look (s).
        self.first: Keyframe | None = None
        self._tried = 0.0
        # The last measure against the first keyframe showed two motions (:meth:`parted`).
        self._parting = False
        # The last still split found the still part apart, the target's not yet: the next
        # frame looks again (:meth:`look`).
        self._apart = False

    def due(self, timestamp: float) -> bool:
        """No support known yet, and the time from the first keyframe has doubled since the
        last look (the first frame after it is looked at): two motions part as they go, and a
        run has a few looks, not one a frame. (Time, not the estimated turn: a tracker that
        follows the support sees no turn.)

        Whatever the latest registration's residual structure or part influence: each frame is
        registered onto a keyframe a few frames back, where a turntable and the target on it
        have hardly parted, so a frame that follows their compromise passes both (robustness
        grid, wall-table cells: structure 1.3-4.9, under its bound 5, on frames beyond 5 σ).
        :func:`~spacepose.core.bodies.split_trial` against the first keyframe decides."""
        if self.support is not None or self.first is None:
            return False
        return timestamp - self.first.timestamp >= 2.0 * self._tried

    def looked(self, timestamp: float) -> None:
        """A look made (:meth:`due`) that tried no split: the schedule moves on as after one."""
        if self.first is not None:
            self._tried = timestamp - self.first.timestamp

    def look(
        self,
        prepared: PreparedCloud,
        checked: Checked,
        bound: tuple[float, float | None],
        timestamp: float,
        reach: float,
    ) -> Look:
        """Model-free, one frame's look for a support: on the schedule of :meth:`due` and on a
        frame after one that parted (:meth:`parted`), a split tried (:meth:`split`) when the
        frame's residuals against the first keyframe or its own reference carry structure
        above ``bound`` (the health check's bounds of the structure and of its shared part,
        :meth:`~spacepose.core.residual_structure.Structure.shows_another_motion`), or a part
        pulls its pose.

        A scheduled look without those signs, from the second on, tries a support standing
        still (its motion held at the identity, :func:`~spacepose.core.bodies.split_trial`),
        and once one is split off a fitted second motion (a turntable on the table): a fitted
        motion tried on every look of a clean run split the target in two (methods.md §5.8),
        while a table under a target sliding over it slides along itself and shows no sign
        (lab mock-up at 6 m, noise ×3: structure 1.3-4.7, bound 5). A still split whose still
        part stood apart while the target's did not yet
        (:class:`~spacepose.core.bodies.SplitTrial`) is tried again on the next frame, not on
        the next scheduled look: under noise the target's part needs more turn to fit its own
        motion clearly better than the still part does (the lab mock-up at 6 m, ×3, constant
        motion, seed 1: apart on frame 4's look, at fit ratios 0.51 and 0.40, and split on
        frame 5; before, no look split it in 12 frames, and frames 5-7 were `ok` 1.4-2.0° off
        at 14σ, after 0.4-0.8° at 2-4σ).
        """
        estimate = checked[0]
        if estimate is None or self.support is not None:
            return Look(checked)
        due = self.due(timestamp)
        parted = self.parted(prepared, estimate, bound, timestamp)
        if parted is not None and estimate.reference is not self.first:
            checked = _parted(checked, parted, bound)
        structure = estimate.structure
        structured = structure is not None and structure.shows_another_motion(*bound)
        pulled = estimate.influence is not None and estimate.influence.excessive
        if parted is None and not (due and (structured or pulled)):
            if not due and not (self._apart and self.still is None):
                return Look(checked)
            if self._tried == 0.0:
                # Not on the first look: one step after the first keyframe a still split took
                # the table and wall alone and left a turntable that, turning under the target,
                # failed the support's test (lab mock-up at 0.5 m, tumbling 2° a frame, seed 1).
                self.looked(timestamp)
                return Look(checked)
            second = _STILL if self.still is None else None
            return Look(checked, self.split(prepared, estimate, timestamp, reach, second))
        return Look(checked, self.split(prepared, estimate, timestamp, reach))

    def parted(
        self,
        prepared: PreparedCloud,
        estimate: FineEstimate,
        bound: tuple[float, float | None],
        timestamp: float,
    ) -> float | None:
        """The frame's residual structure against the first keyframe when it shows another
        motion by ``bound`` (the health check's, :meth:`look`), else None.

        Measured on the looks' schedule (:meth:`due`) and on each frame after one above the
        bound, until the support is split off (not on every frame: a frame of one body may
        exceed the bound by chance, 5.1-5.3 on clean panels runs): the frame registered with
        one motion onto the first keyframe from its estimated pose (or its own registration's,
        when that was onto the first keyframe). There a turntable and the target on it have
        parted by the run's whole relative turn, not by a few frames', and their compromise
        shows before the split can find two bodies (panels 1.2 m, noise x3, tumbling 2° a frame
        on the turntable: 7.6-16 on frames 3-6, against 2.1-3.8 onto the latest keyframe;
        bound 5)."""
        first = self.first
        if self.support is not None or first is None:
            return None
        if not (self._parting or self.due(timestamp)):
            return None
        if estimate.reference is first:
            structure, fitness = estimate.structure, estimate.result.fitness
        else:
            try:
                structure, fitness = self.registrar.structure_onto(
                    prepared, first, estimate.T_sensor_target
                )
            except SpaceposeError:
                return None
        # A first keyframe gone stale for the frame shows the change of view, not a second
        # motion (lab mock-up tumbling 10° a frame, alone: structure 6.2-17 at fitness
        # 0.63-0.40, frames 8-10; the wall-and-table frames above the bound fit it 0.71-0.93).
        self._parting = (
            structure is not None
            and structure.shows_another_motion(*bound)
            and fitness >= self.stale_fitness
        )
        return structure.within if self._parting else None

    def split(
        self,
        prepared: PreparedCloud,
        estimate: FineEstimate,
        timestamp: float,
        reach: float,
        second: NDArray[np.float64] | None = None,
    ) -> tuple[PreparedCloud, NDArray[np.float64]] | None:
        """Split the frame and the first keyframe into the target and a support moving
        otherwise (or, with ``second`` the identity, standing still).

        The first keyframe, not the latest: the keyframes made while the compromise was
        followed carry its error in their poses, and a split against one of them would keep
        it. On success the first keyframe keeps its target points only, and the support
        (:attr:`support`, or :attr:`still`) is followed from now on.

        Parameters
        ----------
        prepared, estimate
            The frame and its one-motion registration.
        timestamp
            The frame's time (s).
        reach
            Farthest a point may pair (m): the motion model's wide gate.
        second
            The support's motion when it is known (:func:`~spacepose.core.bodies.split_trial`);
            None: fitted.

        Returns
        -------
        (target's part of the frame, initial T_sensor_target) or None
            None when one motion explains the frame.
        """
        ref = self.first
        T_ref_frame = self._T_first_frame(estimate)
        if self.due(timestamp):
            # A try off the schedule (:meth:`parted`) leaves it as it was: it would put off the
            # next look, and a support is harder to find once the target has turned far.
            self._tried = timestamp - ref.timestamp
        noise = self.registrar.noise
        sigma = noise.sigma if noise.sigma else noise.gate / 3.0
        trial = split_trial(
            prepared.cloud.points,
            self.registrar.as_target(ref.prepared),
            T_ref_frame,
            sigma,
            max(reach, noise.window),
            noise.window,
            self.workers,
            second,
            self.max_condition,
        )
        found = trial.split
        if second is not None:
            self._apart = trial.support_apart
        if found is None:
            return None
        # Its velocity from the start: the reference's pose and this frame's.
        poses = [(ref.timestamp, np.eye(4)), (timestamp, found.T_ref_frame_support)]
        body = ClutterBody(subset(ref.prepared, found.ref_support), poses)
        if second is None:
            self.support = body
        else:
            self.still = body
        self.found_at = timestamp
        if ref.dense is not None:
            ref.dense = subset(ref.dense, self._carried(ref, found.ref_target))
        ref.prepared = subset(ref.prepared, found.ref_target)
        T_init = se3.invert(found.T_ref_frame) @ ref.T_ref_target
        return subset(prepared, found.frame_target), T_init

    def _carried(self, ref: Keyframe, labels: NDArray[np.bool_]) -> NDArray[np.bool_]:
        """The labels of the keyframe's points carried to its dense cloud: each dense point
        takes its nearest point's, within the noise window (farther: neither body's)."""
        points = ref.dense.cloud.points
        near, nearest, _ = find_correspondences(
            ref.prepared.tree, points, self.registrar.noise.window, self.workers
        )
        carried = np.zeros(len(points), dtype=bool)
        carried[near] = labels[nearest]
        return carried

    def target_region(self, region: TargetRegion | None) -> TargetRegion | None:
        """After a split, the crop region cut to the target: the sphere of the first
        keyframe's target points (target frame), no larger than ``region`` (the object's:
        the target is part of it, stray points labelled so are not); None without one
        (target isolation off: no crop)."""
        if region is None:
            return None
        first = self.first
        own = region_of(
            se3.transform_points(se3.invert(first.T_ref_target), first.prepared.cloud.points)
        )
        return replace(own, radius=min(own.radius, region.radius))

    def _T_first_frame(self, estimate: FineEstimate) -> NDArray[np.float64]:
        """(4, 4) the frame's estimated motion from the first keyframe (``T_ref_frame``)."""
        return self.first.T_ref_target @ se3.invert(estimate.T_sensor_target)

    def remove(
        self,
        prepared: PreparedCloud,
        reference: Keyframe,
        T_sensor_target: NDArray[np.float64],
        timestamp: float,
        gate: float,
    ) -> PreparedCloud:
        """The frame without the supports' points, each support followed to it (and forgotten
        once it no longer registers).

        ``T_sensor_target`` is the target's predicted pose, ``reference`` its latest keyframe
        and ``gate`` (m) the target prediction's reach, which the separation takes until a
        support's own prediction has shown its error.
        """
        if self.support is None and self.still is None:
            return prepared
        target_ref = self.registrar.as_target(reference.prepared)
        T_ref_frame = reference.T_ref_target @ se3.invert(T_sensor_target)
        into = (target_ref, T_ref_frame, timestamp, gate)
        if self.still is not None:
            prepared, self.still = self._without(self.still, prepared, *into)
        if self.support is not None:
            prepared, self.support = self._without(self.support, prepared, *into)
        return prepared

    def _without(
        self,
        body: ClutterBody,
        prepared: PreparedCloud,
        target_ref: PreparedCloud,
        T_ref_frame: NDArray[np.float64],
        timestamp: float,
        gate: float,
    ) -> tuple[PreparedCloud, ClutterBody | None]:
        """The frame without ``body``'s points, and the body followed to it (None: it no longer
        registers, and is forgotten)."""
        window = self.registrar.noise.window
        gate = body.gate(max(gate, window), window)
        points = prepared.cloud.points
        keep = body.separate(points, timestamp, target_ref, T_ref_frame, gate, self.workers)
        others = points[~keep]
        if len(others) < self.min_points or not body.follow(others, timestamp, gate, self.workers):
            body = None
        if np.count_nonzero(keep) < self.min_points:
            return prepared, body
        return subset(prepared, keep), body


def _parted(checked: Checked, structure: float, bound: tuple[float, float | None]) -> Checked:
    """The frame degraded: against the first keyframe its residuals carry structure."""
    estimate, status, reasons = checked
    reason = (
        f"residual structure {structure:.1f} > {bound[0]:g} against the first keyframe: part "
        "of the cloud moves otherwise"
    )
    return estimate, "degraded" if status == "ok" else status, (*reasons, reason)
