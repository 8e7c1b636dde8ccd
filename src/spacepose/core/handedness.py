"""Are the frames mirrored? Their fit to the model against their mirror image's tells.

A cloud written with one axis flipped (a left-handed frame, a depth image read mirrored) is a
mirror image of the scene. No rigid pose maps a model onto it, but a model close to symmetric
under a reflection fits it at a pose turned about half a turn: a probe's mirrored lab frames
were `ok` 178-180° off at 5-35σ, with a fitness of 0.90-0.93 against 0.977 unmirrored.

The frame mirrored back (x -> -x in the sensor frame) is a right view if the frames were
mirrored. Its pose is the tracker's composed with a reflection that maps the model onto itself
as nearly as any does: the model's three principal planes are tried, and the tracker's coarse
registration of the mirrored frame, each refined by point-to-plane ICP; the truncated cost
(:func:`~spacepose.core.basin_probe.truncated_cost`) of the best is compared with that of the
frame as given, refined alike. Checked once, on the first frame the other checks take for `ok`.
"""

from __future__ import annotations

import warnings
from collections.abc import Callable

import numpy as np
from numpy.typing import NDArray

from spacepose.core import se3
from spacepose.core.basin_probe import BETTER_BY, truncated_cost
from spacepose.core.cloud import PointCloud, as_points
from spacepose.core.health import Status
from spacepose.core.icp import ICPConfig, icp
from spacepose.errors import InputError, SpaceposeError, SpaceposeWarning

# The mirrored frame must fit with a truncated cost below this share of the frame's as given
# (and lower by more than BETTER_BY): a model close to mirror-symmetric fits the two alike, and
# such a model's frames cannot tell a mirror. Mirrored lab frames read 0.18-0.47; unmirrored
# frames of 66 simulated runs and 30 renders 1, but satellite_panels (nearly symmetric) at
# 1.2-3 m 0.89-0.97: between the two in ratio.
MIRROR_COST_SHARE = 0.6
# Returns used, at most (every k-th): the fit of a few hundred points tells a mirror.
SAMPLED_RETURNS = 1000
_MIRROR = np.diag([-1.0, 1.0, 1.0, 1.0])


def principal_reflections(points: NDArray[np.float64]) -> list[NDArray[np.float64]]:
    """The three reflections (4, 4) of the model frame about the principal planes of ``points``
    (N, 3) through their centroid."""
    centroid = points.mean(axis=0)
    _, vectors = np.linalg.eigh(np.cov((points - centroid).T))
    reflections = []
    for axis in vectors.T:
        S = np.eye(4)
        S[:3, :3] -= 2.0 * np.outer(axis, axis)
        S[:3, 3] = 2.0 * axis * (axis @ centroid)
        reflections.append(S)
    return reflections


def mirror_cost_share(
    points_sensor: NDArray[np.float64],
    model: PointCloud,
    T_sensor_target: NDArray[np.float64],
    gate: float,
    sigma: float,
    coarse: Callable[[PointCloud], NDArray[np.float64] | None] | None = None,
    workers: int = 1,
) -> float:
    """The truncated cost of the frame mirrored back at its best pose over that of the frame as
    given at its own (both refined by point-to-plane ICP onto ``model``, within ``gate`` m,
    residuals in units of ``sigma`` m): below 1 when the mirror image fits better, 1 when it
    does not fit better by more than :data:`~spacepose.core.basin_probe.BETTER_BY`.

    Parameters
    ----------
    points_sensor
        (N, 3) returns, sensor frame.
    model
        The model with normals, target frame.
    T_sensor_target
        (4, 4) the tracker's pose of the frame as given.
    coarse
        A coarse registration of a cloud (sensor frame) onto the model, its ``T_sensor_target``
        or None: a start for the mirror image besides the principal reflections (the lab
        mock-up's near symmetry is no principal plane's: those starts lay 42-180° off).
    """
    points_sensor = as_points(points_sensor, "returns")
    if model.normals is None:
        raise InputError("the model needs normals for point-to-plane fits", model.source)
    step = -(-len(points_sensor) // SAMPLED_RETURNS)
    given = points_sensor[::step]
    mirrored = given * _MIRROR.diagonal()[:3]
    config = ICPConfig(max_correspondence_distance=gate, method="point_to_plane")

    def refined_cost(points: NDArray[np.float64], T_target_sensor: NDArray[np.float64]) -> float:
        try:
            T = icp(points, model, T_target_sensor, config, workers).T_target_source
        except SpaceposeError:  # too few pairs within the gate: it fits nothing
            T = T_target_sensor
        return truncated_cost(model, points, T, gate, sigma, workers)

    T_target_sensor = se3.invert(T_sensor_target)
    as_given = refined_cost(given, T_target_sensor)
    # x -> -x in the sensor frame, composed with a reflection of the model: a rigid start.
    starts = [S @ T_target_sensor @ _MIRROR for S in principal_reflections(model.points)]
    found = None if coarse is None else coarse(PointCloud(points_sensor * _MIRROR.diagonal()[:3]))
    if found is not None:
        starts.append(se3.invert(found))
    best = min(refined_cost(mirrored, T) for T in starts)
    if as_given - best <= BETTER_BY or as_given <= 0:
        return 1.0
    return best / as_given


class HandednessCheck:
    """The run's test, once, of whether its frames are a mirror image (model-based only).

    On the first frame the other checks take for `ok`, a mirror image that fits with a
    truncated cost below :data:`MIRROR_COST_SHARE` of the frame's as given is said once as a
    warning, and that frame and every later one is `degraded` with it.
    """

    def __init__(
        self,
        model: PointCloud,
        coarse: Callable[[PointCloud], NDArray[np.float64] | None] | None = None,
    ) -> None:
        self.model = model
        self.coarse = coarse
        self.tested = False
        self.verdict: str | None = None

    def assess(
        self,
        points_sensor: NDArray[np.float64],
        T_sensor_target: NDArray[np.float64],
        gate: float,
        sigma: float,
        health: tuple[Status, tuple[str, ...]],
        workers: int = 1,
    ) -> tuple[Status, tuple[str, ...]]:
        """``health`` of a frame, degraded once the frames are found mirrored."""
        status, reasons = health
        if not self.tested and status == "ok":
            self.tested = True
            share = mirror_cost_share(
                points_sensor, self.model, T_sensor_target, gate, sigma, self.coarse, workers
            )
            if share < MIRROR_COST_SHARE:
                self.verdict = (
                    "the frames look mirrored: mirrored back (x -> -x) they fit the model with "
                    f"{100 * share:.0f} % of the cost (a left-handed frame, or an image read "
                    "flipped?)"
                )
                warnings.warn(SpaceposeWarning(self.verdict), stacklevel=3)
        if self.verdict is not None and status != "lost":
            return "degraded", (*reasons, self.verdict)
        return health
