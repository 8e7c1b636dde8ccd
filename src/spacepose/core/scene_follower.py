"""The whole scene followed beside the nearest object until the data say which is the target
(:mod:`spacepose.core.scene_motion`, docs/methods.md §5.7)."""

from __future__ import annotations

from typing import TYPE_CHECKING

from numpy.typing import ArrayLike

from spacepose.core.cloud import PointCloud
from spacepose.core.frame_preparation import FramePreparer
from spacepose.core.scene_motion import Verdict
from spacepose.core.track_result import TrackResult
from spacepose.core.tracker_config import TrackerConfig

if TYPE_CHECKING:
    from spacepose.core.tracker import Tracker

# Frames the scene is followed (or its background stays where it was) before the object is kept
# as the target: nothing has moved enough to tell by then.
MAX_UNDECIDED = 30
# The reason on the frame from which the whole scene is the target.
SCENE_NOTE = "the object moves with the whole scene: the whole scene is the target"

Frame = tuple["PointCloud | ArrayLike | None", float, "tuple[ArrayLike, ArrayLike] | None"]


class SceneFollower:
    """A tracker of the whole frame beside the object's, and the verdict on each frame.

    The scene's tracker starts only when the first frame's background no longer stays where
    it was (:meth:`~spacepose.core.scene_motion.SceneTest.background_stays`): before a static
    wall with a still sensor it never runs. It then tracks the first frame and every frame
    from this one, so that it can carry on as the run's tracker.

    Parameters
    ----------
    config
        The run's tracker config; the scene's tracker has target isolation off.
    workers
        Threads of the scene's tracker.
    """

    def __init__(self, config: TrackerConfig, workers: int) -> None:
        self._config = config.model_copy(update={"isolate_target": False})
        self._workers = workers
        self.scene: Tracker | None = None
        self._first: tuple[int, Frame] | None = None
        self._undecided = 0

    def follow(
        self,
        frame: Frame,
        result: TrackResult,
        frames: FramePreparer,
    ) -> tuple[Verdict, TrackResult | None]:
        """Judge a frame against the object tracker's ``result`` on it.

        Parameters
        ----------
        frame
            ``(cloud, timestamp, prior)`` as given to the object's tracker.
        result
            The object tracker's result on it.
        frames
            The object tracker's frame preparation: the first frame's test and the frame's
            points (:attr:`FramePreparer.scene_test`, :attr:`FramePreparer.last_frame`).

        Returns
        -------
        verdict, scene_result
            ``undecided`` until the test decides (``target`` after :data:`MAX_UNDECIDED`
            frames, or when the first frame held the object alone); the scene tracker's result
            on the frame (None while it has not started).
        """
        test, points = frames.scene_test, frames.last_frame
        if test is None:
            # The first frame held nothing beside the object (or has not come yet).
            return ("target" if frames.region is not None else "undecided"), None
        if self._first is None and self.scene is None:
            # The first frame: the scene's tracker may need it later.
            self._first = (result.index, frame)
            return "undecided", None
        self._undecided += 1
        scene = None
        verdict: Verdict = "undecided"
        started = self.scene is not None
        if points is not None and (started or not test.background_stays(points.points)):
            scene = self._scene_tracker(result.index).track_frame(*frame)
            if "lost" not in (result.status, scene.status):
                verdict = test.decide(points.points, result.T_sensor_target, scene.T_sensor_target)
        if verdict == "undecided" and self._undecided >= MAX_UNDECIDED:
            verdict = "target"
        return verdict, scene

    def _scene_tracker(self, index: int) -> Tracker:
        """The scene's tracker, started on the first frame when first needed (frame ``index``
        comes next)."""
        if self.scene is None:
            from spacepose.core.tracker import Tracker

            first_index, first = self._first
            self.scene = Tracker(self._config, None, self._workers)
            self.scene._spare = None  # a spare's revisions would be of frames it never reported
            # Frame numbers as the run's.
            self.scene.continue_at(first_index)
            self.scene.track_frame(*first)
            self.scene.continue_at(index)
            self._first = None
        return self.scene
