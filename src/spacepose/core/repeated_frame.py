"""A frame that repeats the one before it: a driver's stale buffer, no new measurement
(docs/methods.md §5.3).

A camera whose driver hands out its last buffer again gives a frame with the very same points.
Registered, it holds the last pose exactly (fitness 1), and against a target turning 2° a frame
the tracker flagged two such frames ``ok`` 2° and 4° off at 9 and 18σ: within the prediction's
bound, which leaves room for accelerations. Range noise makes two real frames differ in every
point, so equal points are a repeat; but a noise-free render of a target standing still repeats
itself rightly. A repeat is therefore no measurement only while the motion model predicts the
target to move by more than a registration resolves (the health check's bound on the step from
a registration's optimum); the tracker then reports the frame ``lost`` at the predicted pose and
leaves its state as it was.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

from spacepose.core.cloud import PointCloud

# Rows of a frame compared with the last frame's: a strided share, so that a 900,000-point
# frame costs microseconds; noisy frames differ in their first row, repeats in none.
_ROWS = 1024


class RepeatWatch:
    """Remembers a sample of the last frame's points and tells whether a frame repeats it."""

    def __init__(self) -> None:
        self._last: tuple[int, NDArray[np.float64]] | None = None

    def repeats(self, cloud: object) -> bool:
        """Whether ``cloud`` (a PointCloud or (N, 3) array; None, empty or unreadable counts
        as new) has the points of the frame seen before it, and remember it for the next. A
        copy of the sample is kept: a driver that refills one array in place must not compare
        it with itself."""
        try:
            points = np.asarray(cloud.points if isinstance(cloud, PointCloud) else cloud)
            sample = np.array(points[:: max(1, len(points) // _ROWS)], dtype=np.float64)
        except (TypeError, ValueError, IndexError):
            # Text, ragged rows, a scalar: the frame's own check names what is wrong (numpy's
            # "could not convert string to float" was raised here before it).
            points = sample = None
        if points is None or points.ndim != 2 or len(points) == 0:
            self._last = None
            return False
        last, self._last = self._last, (len(points), sample)
        return last is not None and last[0] == len(points) and np.array_equal(last[1], sample)


def stale_reason(moved_m: float, turned_deg: float) -> str:
    """The reason a repeated frame is lost, with the motion the model predicted."""
    return (
        f"the same points as the frame before while the motion model predicts "
        f"{1e3 * moved_m:.1f} mm / {turned_deg:.2f} deg: a repeated (stale) frame, no new "
        "measurement"
    )
