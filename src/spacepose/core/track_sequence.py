"""A whole sequence tracked in one call (:func:`track_sequence`; the stateful tracker is
:class:`spacepose.core.tracker.Tracker`, which offers this function too)."""

from __future__ import annotations

from collections.abc import Iterable

import numpy as np
from numpy.typing import ArrayLike

from spacepose.core.cloud import PointCloud
from spacepose.core.se3 import real_array
from spacepose.core.track_result import TrackingOutput
from spacepose.core.tracker_config import TrackerConfig
from spacepose.core.trajectory import Trajectory
from spacepose.errors import InputError


def track_sequence(
    clouds: Iterable[PointCloud | ArrayLike | None],
    timestamps: ArrayLike,
    config: TrackerConfig = TrackerConfig(),
    model: PointCloud | ArrayLike | None = None,
    workers: int = -1,
) -> TrackingOutput:
    """Track every frame of a sequence with a fresh :class:`~spacepose.core.tracker.Tracker`.

    Parameters
    ----------
    clouds
        One cloud per frame (sensor frame); None / empty for frames without data.
    timestamps
        (N,) seconds, one per cloud.
    config, model, workers
        As for :class:`~spacepose.core.tracker.Tracker`.
    """
    # Imported here: core.tracker imports this module to offer track_sequence beside Tracker.
    from spacepose.core.tracker import Tracker

    stamps = real_array(timestamps, "timestamps").reshape(-1)
    one_array = isinstance(clouds, np.ndarray) and clouds.ndim != 3
    if clouds is None or isinstance(clouds, str | bytes) or one_array:
        # None ended in a TypeError; text was iterated as one lost frame per character; one
        # (N, 3) array as N frames of one row each.
        raise InputError(
            f"clouds must be a list of clouds (one per frame), got {type(clouds).__name__} "
            f"of shape {np.shape(clouds)}"
        )
    clouds = list(clouds)
    if not clouds or len(clouds) != len(stamps):
        raise InputError(f"{len(clouds)} clouds for {len(stamps)} timestamps; need one each (>0)")
    results = Tracker(config, model, workers).track(zip(clouds, stamps, strict=True))
    poses = np.array([r.T_sensor_target for r in results])
    return TrackingOutput(Trajectory(stamps, poses), results)
