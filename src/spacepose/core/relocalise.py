"""Coarse re-initialisation of a tracked frame: FPFH + RANSAC at the tracker's scale
(docs/methods.md §5.6).

The sparse cloud is the frame at the coarse voxel (twice the tracker's), its normals use a radius
of two coarse voxels, FPFH five and RANSAC's gate one and a half: every length follows from the
frame's own scale, so the same settings re-initialise a 1 m mock-up and a 10 m satellite.

:class:`Relocaliser` is the tracker's re-initialisation stage. Against a model it also retries a
frame that fits poorly, registers each coarse pose's twins and carries an undecided twin along
(:mod:`spacepose.core.twins`).
"""

from __future__ import annotations

import time
from collections.abc import Callable
from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from spacepose.core import se3
from spacepose.core.cloud import PointCloud
from spacepose.core.fpfh import compute_fpfh
from spacepose.core.frame_registration import FrameRegistrar
from spacepose.core.health import HealthBounds, Status, pose_disagreement
from spacepose.core.keyframes import FineEstimate, Keyframe, PreparedCloud
from spacepose.core.motion import Prediction
from spacepose.core.normals import estimate_normals
from spacepose.core.ransac import feature_ransac
from spacepose.core.track_result import elapsed_ms
from spacepose.core.tracker_config import StageLengths
from spacepose.core.twins import FitComparison, compare_fits, principal_turns
from spacepose.core.voxel import evenly_thinned, voxel_downsample
from spacepose.errors import SpaceposeError

# A registered frame: the estimate (None when registration failed), its status and reasons.
Checked = tuple[FineEstimate | None, Status, tuple[str, ...]]
# Most points the coarse stage describes. A surface at the coarse voxel holds a few hundred to a
# few thousand (the lab run: about 1,450); a frame of depth noise filling a volume held 292,000,
# and their FPFH and feature matching took 4.3 s. Beyond it the sparse cloud is thinned evenly.
COARSE_POINTS = 10_000
# Fine registration from an initial T_sensor_target, after a first pass at a wide gate (m), and
# the health check against a prediction (None: unconfirmed).
Register = Callable[[PreparedCloud, NDArray[np.float64], float, Prediction | None], Checked]
# The health check of an estimate against a prediction.
Confirm = Callable[[FineEstimate, PreparedCloud, Prediction], tuple[Status, tuple[str, ...]]]


def coarse_features(
    prepared: PreparedCloud, lengths: StageLengths, outward: bool, workers: int = -1
) -> tuple[PointCloud, NDArray[np.float64]]:
    """Sparse cloud (with normals) and (M, 33) FPFH descriptors of a prepared cloud, once:
    the cloud at the coarse voxel, at most ``COARSE_POINTS`` of its cells.

    ``outward``: a model's normals point away from its centroid (as a sensor sees them; FPFH is
    sign-sensitive); a frame's point towards the sensor.
    """
    if prepared.coarse is None:
        sparse = evenly_thinned(
            voxel_downsample(prepared.cloud, lengths.coarse_voxel), COARSE_POINTS
        )
        if outward:
            centroid = sparse.points.mean(axis=0)
            sparse = estimate_normals(sparse, lengths.coarse_normals, centroid, workers)
            sparse = sparse.with_normals(-sparse.normals)
        else:
            sparse = estimate_normals(sparse, lengths.coarse_normals, workers=workers)
        prepared.coarse = (sparse, compute_fpfh(sparse, lengths.fpfh, workers=workers))
    return prepared.coarse


def coarse_pose(
    prepared: PreparedCloud,
    ref: Keyframe,
    lengths: StageLengths,
    ref_is_model: bool,
    workers: int = -1,
) -> NDArray[np.float64] | None:
    """Initial ``T_sensor_target`` (4, 4) of a frame by FPFH + RANSAC onto ``ref``, or None when
    RANSAC finds no consensus (or the frame has no surface to describe: all on a line)."""
    try:
        src, src_f = coarse_features(prepared, lengths, False, workers)
        tgt, tgt_f = coarse_features(ref.prepared, lengths, ref_is_model, workers)
        res = feature_ransac(src, tgt, src_f, tgt_f, lengths.ransac, workers=workers)
    except SpaceposeError:
        return None
    return se3.invert(res.T_target_source) @ ref.T_ref_target


class Relocaliser:
    """The tracker's re-initialisation stage: a coarse pose when fine registration fails, and,
    against a model, its twins, retries of poor fits and an undecided twin carried along.

    Parameters
    ----------
    registrar
        The tracker's registrar (lengths, fine gate).
    reference
        The current registration reference (the model, or the latest keyframe).
    model
        The prepared model, or None (model-free: no twins, no retries).
    register, confirm
        The tracker's fine registration with health check, and its health check alone.
    ok_fitness
        Share of a frame's points within the gate that a pose needs to be ``ok``: a twin test
        whose winner fits less decides nothing.
    workers
        Threads of the searches.
    """

    def __init__(
        self,
        registrar: FrameRegistrar,
        reference: Callable[[], Keyframe],
        model: Keyframe | None,
        register: Register,
        confirm: Confirm,
        ok_fitness: float,
        workers: int = -1,
    ) -> None:
        self.registrar = registrar
        self.ok_fitness = ok_fitness
        self.reference = reference
        self.model = model
        self.register = register
        self.confirm = confirm
        self.workers = workers
        # The model's half turns, and the twin the data cannot yet tell from the tracked pose
        # (``T_target_twin``), if any.
        self.turns = [] if model is None else principal_turns(model.prepared.cloud.points)
        self.twin: NDArray[np.float64] | None = None
        # Retries of poor fits that found nothing better, in a row, and poor frames to skip.
        self._misses = self._skip = 0

    def coarse(self, prepared: PreparedCloud) -> NDArray[np.float64] | None:
        """Initial ``T_sensor_target`` by FPFH + RANSAC against the reference, or None."""
        is_model = self.model is not None
        return coarse_pose(
            prepared, self.reference(), self.registrar.lengths, is_model, self.workers
        )

    def retry_due(self, checked: Checked, bounds: HealthBounds) -> bool:
        """Whether to retry a model-based frame kept (not lost) from a coarse pose: its fitness
        or RMSE is outside ``bounds``, or its pose has a twin not yet told apart from it.

        An undecided pair may both be wrong: `random:2` at 25 m (seed 0) was held 90° off at a
        fitness of 0.95 for 40 frames, ambiguous with another wrong pose, while the true pose
        fitted 1.0; no half turn of a pose 90° off reaches it, and a coarse pose found it on
        frame 2.

        After n retries in a row that found nothing better, the next n poor frames are not
        retried: clutter the model lacks (the table under a mock-up) keeps the fit poor on the
        true pose, and a retry (a coarse pose and up to ten fine registrations) costs several
        frames' time. Over N poor frames about √(2N) are retried.
        """
        estimate, status = checked[:2]
        if self.model is None or status == "lost" or estimate is None:
            return False
        res = estimate.result
        fits = res.fitness >= bounds.ok_fitness and res.inlier_rmse <= bounds.ok_rmse
        if fits and self.twin is None:
            self._misses = self._skip = 0
            return False
        if self._skip > 0:
            self._skip -= 1
            return False
        return True

    def reinitialise(
        self,
        prepared: PreparedCloud,
        prediction: Prediction | None,
        failed: Checked,
        times: dict[str, float],
    ) -> Checked:
        """Coarse registration, then fine registration from it, from its twins and from the
        twins of ``failed`` (the pose the frame was kept at, when it has one).

        Returns ``failed`` itself when that does no better: a lost ``failed`` is replaced by
        anything not lost, a kept one only by a clearly better fit (:func:`fits_better`).
        ``times`` gains the ``coarse`` and ``fine`` milliseconds. Of the residual noise the
        candidates measured, only the returned pose's is kept: a wrong candidate's residuals
        say nothing of the sensor, and six of them widened the fine gate until every frame of
        the Hubble kit at 5 m was above the RMSE bound.
        """
        tic = time.perf_counter()
        init = self.coarse(prepared)
        times["coarse"] = elapsed_ms(tic)
        if init is None and failed[1] != "lost":
            return self._missed(failed)
        if init is None:
            return (*failed[:2], (*failed[2], "coarse registration found no consensus"))
        tic = time.perf_counter()
        # RANSAC is good to about its own gate: the first pass starts there.
        wide = self.registrar.lengths.ransac.max_correspondence_distance
        noise = self.registrar.noise
        measured_by_failed = noise.take()
        starts = [init] + [init @ turn for turn in self.turns]
        if failed[0] is not None:
            # The failed pose's own twins: a tracker that follows a twin fits poorly where the
            # view cuts the target, and RANSAC may miss the true pose there too (orbit run at
            # 15 m, seed 1: the twin followed for 340 frames, 7 of them ok 180° off).
            starts += [failed[0].T_sensor_target @ turn for turn in self.turns]
        candidates = [self._candidate(prepared, T, wide) for T in starts]
        best = max(candidates, key=lambda c: _fitness(c[0]))[0][0]
        if best is not None:
            # The best pose's own twins, registered afresh: those started from the coarse
            # pose's turns need not have converged (symmetric orbit target, seed 2: the twin
            # fitted every point yet stopped 0.24 m short of its optimum and was lost, and the
            # tracker went on ok on one of the two poses for 273 frames).
            candidates += [
                self._candidate(prepared, best.T_sensor_target @ turn, wide) for turn in self.turns
            ]
        candidates.sort(key=lambda c: _fitness(c[0]), reverse=True)
        ranked = [checked for checked, _ in candidates]
        # The twins are tested at the gate the best candidate's own residuals set.
        noise.restore(candidates[0][1])
        (estimate, status, reasons), rival = self._rival(prepared, ranked)
        times["fine"] += elapsed_ms(tic)
        if prediction is not None and estimate is not None:
            # A stale prediction confirms the re-initialised pose when it agrees; when it does
            # not, the pose stands unconfirmed (degraded), not rejected.
            confirmed = self.confirm(estimate, prepared, prediction)
            if confirmed[0] != "lost":
                status, reasons = confirmed
        if failed[1] != "lost":
            if not self._replaces(prepared, (estimate, status, reasons), failed):
                return self._missed(self._restore(measured_by_failed, failed))
        elif status == "lost" and failed[0] is not None:
            return self._restore(measured_by_failed, failed)
        self.twin = None
        if rival is not None:
            self.twin, test = rival
            # Still undecided: the retry decided nothing and backs off as a miss. Reset, a
            # symmetric target retried every frame (18 -> 124 ms a frame at 25 m).
            return self._missed((estimate, "degraded", (*reasons, _ambiguous(test, self.twin))))
        self._misses = self._skip = 0
        return estimate, status, reasons

    def _candidate(
        self, prepared: PreparedCloud, T_init: NDArray[np.float64], wide: float
    ) -> tuple[Checked, list[float]]:
        """A candidate pose registered from ``T_init`` at the gate of the frames before (not
        of another candidate's residuals), and the residual noise it measured, set aside
        until the candidate is kept; the frame's measurements so far stay."""
        noise = self.registrar.noise
        before = noise.take()
        checked = self.register(prepared, T_init, wide, None)
        measured = noise.take()
        noise.restore(before)
        return checked, measured

    def _restore(self, measured: list[float], kept: Checked) -> Checked:
        """``kept``, with this frame's residual noise set back to what it measured."""
        self.registrar.noise.take()
        self.registrar.noise.restore(measured)
        return kept

    def _missed(self, kept: Checked) -> Checked:
        """A retry that found nothing better: skip as many poor frames as retries missed."""
        self._misses += 1
        self._skip = self._misses
        return kept

    def settle_twin(self, prepared: PreparedCloud, checked: Checked) -> tuple[Checked, bool]:
        """Register the undecided twin of this frame's pose too and test which fits.

        Returns the pose kept (flagged ambiguous while undecided) and whether it is the twin
        (the motion model restarts from it). The residual noise the twin's registrations
        measured is kept only when the twin is.
        """
        estimate = checked[0]
        wide = self.registrar.lengths.ransac.max_correspondence_distance
        twin, measured_by_twin = self._candidate(
            prepared, estimate.T_sensor_target @ self.twin, wide
        )
        self.twin = None
        if twin[0] is None or twin[1] == "lost":
            return checked, False
        (checked, twin), test = self._rematch(prepared, (checked, twin))
        if test.winner is not None:
            if test.winner == 0:
                return checked, False
            return self._restore(measured_by_twin, twin), True
        estimate = checked[0]
        self.twin = se3.invert(estimate.T_sensor_target) @ twin[0].T_sensor_target
        return (estimate, "degraded", (*checked[2], _ambiguous(test, self.twin))), False

    def _rematch(
        self, prepared: PreparedCloud, pair: tuple[Checked, Checked]
    ) -> tuple[tuple[Checked, Checked], FitComparison]:
        """Test which of two kept poses half a turn apart fits the frame; when one wins, test
        again with the loser registered afresh from the winner half a turn away.

        A pose that lost because its own registration slipped fits as well from there (a
        symmetric target: the pair stays undecided); one that lost to what the target's twin
        lacks does not. The refit replaces the loser either way, being the better-started of
        the two registrations of it.
        """
        first, second = pair[0][0], pair[1][0]
        test = self._compare(prepared, first, second)
        if test.winner is not None and pair[test.winner][0].result.fitness < self.ok_fitness:
            # A winner that leaves much of the frame off the model may itself have slipped:
            # its count decides nothing (orbit run, seed 2: a start fitting 0.44 beat its
            # twin, then tracked ok, 177° off, once the next frame fitted 0.955).
            test = replace(test, winner=None)
        if test.winner is None:
            return pair, test
        won = test.winner
        winner, loser = (first, second) if won == 0 else (second, first)
        relative = se3.invert(winner.T_sensor_target) @ loser.T_sensor_target
        origin = np.zeros(3)
        turn = min(self.turns, key=lambda T: pose_disagreement(T, relative, origin)[1])
        wide = self.registrar.lengths.ransac.max_correspondence_distance
        refit = self._candidate(prepared, winner.T_sensor_target @ turn, wide)[0]
        if refit[0] is None or refit[1] == "lost":
            return pair, test
        again = self._compare(prepared, winner, refit[0])
        counts = (again.only_first, again.only_second)
        b, c = counts if won == 0 else counts[::-1]
        # The loser refitted and winning is a contradiction: undecided too.
        retest = FitComparison(b, c, again.statistic, won if again.winner == 0 else None)
        return ((pair[0], refit) if won == 0 else (refit, pair[1])), retest

    def _rival(
        self, prepared: PreparedCloud, ranked: list[Checked]
    ) -> tuple[Checked, tuple[NDArray[np.float64], FitComparison] | None]:
        """The pose to keep of the ranked candidates, and its twin that the data cannot tell
        from it (``T_target_twin`` with the test), or None (decided, or no twin kept).

        The best-fitting candidate is tested against the next distinct one by
        :meth:`_rematch`: a candidate may fit worse only because its registration from the
        coarse pose had not converged (orbit run, seed 4: the true pose 27 mm short of its
        optimum fitted 0.76 of the points, its twin 0.95, and the tracker went on ``ok`` on
        the twin, 180° off, for 39 frames).
        """
        best = ranked[0][0]
        if best is None or ranked[0][1] == "lost":
            return ranked[0], None
        c = prepared.centroid
        for other in ranked[1:]:
            estimate, status = other[:2]
            if estimate is None or status == "lost":
                continue
            if pose_disagreement(estimate.T_sensor_target, best.T_sensor_target, c)[1] < 90.0:
                continue  # the same pose, reached from another start
            (first, second), test = self._rematch(prepared, (ranked[0], other))
            if test.winner is None:
                T_target_twin = se3.invert(first[0].T_sensor_target) @ second[0].T_sensor_target
                return first, (T_target_twin, test)
            return (first if test.winner == 0 else second), None
        return ranked[0], None

    def _replaces(self, prepared: PreparedCloud, found: Checked, kept: Checked) -> bool:
        """Whether a re-initialised pose replaces the ``kept`` one: it fits clearly better
        (:func:`fits_better`), or it lies in another basin (90° or more away) and fits
        significantly more of the frame's points in the twin test. Flying pixels between a
        dish and the bus behind it kept the true pose of a 1 m bus at 2.5 m at a fitness of
        0.80, short of the margin over a pose half a turn off at 0.73, though 2,410 points
        fitted the true pose only against 497 the wrong one."""
        estimate, status = found[:2]
        if fits_better(estimate, status, kept):
            return True
        if estimate is None or status == "lost" or estimate.result.fitness < self.ok_fitness:
            # A pose that leaves much of the frame off the model may have slipped itself: its
            # count decides nothing, as between twins.
            return False
        T_kept = kept[0].T_sensor_target
        if pose_disagreement(estimate.T_sensor_target, T_kept, prepared.centroid)[1] < 90.0:
            return False
        return self._compare(prepared, estimate, kept[0]).winner == 0

    def _compare(self, prepared: PreparedCloud, a: FineEstimate, b: FineEstimate) -> FitComparison:
        return compare_fits(
            self.model.prepared.tree,
            prepared.cloud.points,
            a.T_sensor_target,
            b.T_sensor_target,
            self.registrar.noise.gate,
            workers=self.workers,
        )


def fits_better(estimate: FineEstimate | None, status: Status, kept: Checked) -> bool:
    """Whether a re-initialised ``estimate`` replaces the ``kept`` one: not lost, and fitting
    at least half of the share of points the kept one left off the reference.

    Fitness, not status, decides: the kept pose agrees with its own prediction while the new
    one, off that prediction, is at best unconfirmed. The half-gap margin keeps two poses that
    fit alike (a frame with clutter the model lacks) from trading places frame after frame.
    """
    if status == "lost" or estimate is None:
        return False
    f_kept = kept[0].result.fitness
    return estimate.result.fitness >= f_kept + 0.5 * (1.0 - f_kept)


def _ambiguous(test: FitComparison, T_target_twin: NDArray[np.float64]) -> str:
    """The reason of a frame whose pose and twin (a half or, on a model nearly round about an
    axis, a quarter turn away) the data do not tell apart."""
    turn = pose_disagreement(T_target_twin, np.eye(4), np.zeros(3))[1]
    return (
        f"ambiguous: the model turned {turn:.0f}° is not told apart ({test.only_first} / "
        f"{test.only_second} points fit one pose only)"
    )


def _fitness(checked: Checked) -> float:
    """The fitness of a kept registration; −1 for a lost one."""
    estimate, status = checked[:2]
    return -1.0 if estimate is None or status == "lost" else estimate.result.fitness
