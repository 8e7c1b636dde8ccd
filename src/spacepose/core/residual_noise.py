"""The noise a registration actually meets, measured from its residuals (docs/methods.md §5.5).

The fine gate is set in voxels (0.83 v), which suits a sensor whose noise is well below the
voxel. A noisier sensor (three times the ToF noise at 6 m) puts the point-to-plane residuals'
σ near the gate: the gate then cuts the residual distribution, ICP stops short of the optimum
(truncated pairs pull less), and the covariance ``σ² H⁻¹`` takes σ from the truncated
residuals.

:class:`ResidualNoise` measures, after each registration, the robust σ (1.4826 · MAD) of the
point-to-plane residuals within a window of several gates, keeps the median of the last few,
and gives the gate back as the larger of the voxel gate and three of those σ (KISS-ICP's
adaptive 3σ threshold, here driven by the measured noise rather than the motion); the
covariance's σ, taken from the residuals within that gate, is then no longer truncated.
"""

from __future__ import annotations

import statistics
from collections import deque

import numpy as np
from numpy.typing import NDArray

from spacepose.core import se3
from spacepose.core.correspondences import find_correspondences
from spacepose.core.keyframes import PreparedCloud

# The gate spans this many residual σ: the fine registration sees the whole noise distribution.
GATE_SIGMAS = 3.0
# The residuals are measured within this many gates, so that a gate below the noise does not
# truncate the measurement that is to widen it.
WINDOW_GATES = 3.0
# Frames whose measurements make the estimate (a median: one misregistered frame moves nothing).
MEMORY = 9
# MAD to σ of a normal distribution.
_MAD_TO_SIGMA = 1.4826


def point_to_plane_sigma(
    T_target_source: NDArray[np.float64],
    source_points: NDArray[np.float64],
    target: PreparedCloud,
    window: float,
    workers: int = -1,
    hint: NDArray[np.int64] | None = None,
) -> float | None:
    """Robust σ (m) of the point-to-plane residuals of a registration, pairs within ``window``.

    Parameters
    ----------
    T_target_source
        (4, 4) the registration (source frame -> target frame).
    source_points
        (N, 3) source points, source frame.
    target
        The target, with normals (target frame).
    window
        Largest pair distance (m).
    workers
        Threads for the search.
    hint
        (N,) a target index near each source point (-1: none), such as the registration's
        last matches: it only narrows the search (:func:`find_correspondences`).

    Returns
    -------
    float or None
        1.4826 · median absolute deviation of the signed normal distances; None with fewer
        than 7 pairs.
    """
    moved = se3.transform_points(T_target_source, source_points)
    s, t, _ = find_correspondences(target.tree, moved, window, workers, hint)
    if len(s) < 7:
        return None
    cloud = target.cloud
    r = np.einsum("ij,ij->i", moved[s] - cloud.points[t], cloud.normals[t])
    return float(_MAD_TO_SIGMA * np.median(np.abs(r - np.median(r))))


class ResidualNoise:
    """The running estimate of the residual σ and the fine gate it implies.

    A frame's measurements are pending until the tracker accepts the frame (:meth:`commit`)
    or loses it (:meth:`discard`): a garbage frame's residuals say nothing of the sensor.

    Parameters
    ----------
    voxel_gate
        The gate set in voxels (m): the gate never goes below it.
    """

    def __init__(self, voxel_gate: float) -> None:
        self.voxel_gate = voxel_gate
        self._sigmas: deque[float] = deque(maxlen=MEMORY)
        self._pending: list[float] = []

    @property
    def sigma(self) -> float | None:
        """Median of the last measurements, this frame's included (m); None before any."""
        values = [*self._sigmas, *self._pending][-MEMORY:]
        # statistics.median: the same value as numpy's for these few floats, a twentieth of the
        # time (the gate is read about ten times a frame).
        return float(statistics.median(values)) if values else None

    @property
    def gate(self) -> float:
        """The fine gate (m): the voxel gate, or three residual σ when that is wider."""
        sigma = self.sigma
        return self.voxel_gate if sigma is None else max(self.voxel_gate, GATE_SIGMAS * sigma)

    @property
    def accepted_factor(self) -> float:
        """How many times the voxel gate the gate of the accepted frames alone is (>= 1): the
        factor by which the measured noise, not the sampling, sets the registration's scale.
        The current frame's own measurements are left out: a garbage frame's residuals must
        not widen the bounds it is checked against."""
        if not self._sigmas:
            return 1.0
        sigma = float(statistics.median(self._sigmas))
        return max(1.0, GATE_SIGMAS * sigma / self.voxel_gate)

    @property
    def window(self) -> float:
        """Distance (m) within which the next measurement takes pairs."""
        return WINDOW_GATES * self.gate

    def add(self, sigma: float | None) -> bool:
        """Record a measurement of the current frame; True when it alone asks for a gate a
        quarter wider than the one the registration ran with (worth repeating it)."""
        if sigma is None:
            return False
        before = self.gate
        self._pending.append(sigma)
        return GATE_SIGMAS * sigma > 1.25 * before

    def take(self) -> list[float]:
        """Remove and return the current frame's measurements so far (a candidate pose's, set
        aside until it is chosen)."""
        taken, self._pending = self._pending, []
        return taken

    def restore(self, values: list[float]) -> None:
        """Put back measurements :meth:`take` set aside."""
        self._pending.extend(values)

    def commit(self) -> None:
        """The frame was accepted: its measurements join the estimate."""
        self._sigmas.extend(self._pending)
        self._pending.clear()

    def discard(self) -> None:
        """The frame was lost: its measurements are dropped."""
        self._pending.clear()
