"""A model's twins: the same model half a turn about a principal axis (docs/methods.md §5.6).

A satellite built of a box and panels is nearly symmetric under a half turn about each of its
principal axes. From a view that misses its asymmetric parts (an antenna behind the bus, an
instrument edge-on) the twin fits the frame almost as well as the true pose: on the orbit run at
25 m, 0.95-0.97 of a frame's points lie within the fine gate of the twin against 0.99-1.00 for
the true pose, so a coarse registration returns either.

The model-based tracker therefore registers each coarse pose's twins too, keeps the best fit
and asks whether the data tell the best from the runner-up (:func:`compare_fits`): the points
that only one of the two poses fits are counted, and McNemar's test on those counts says
whether one pose fits significantly more of them. While it cannot tell, the frame is flagged
ambiguous and the twin is carried along and tested again on every frame, until a view shows
what breaks the symmetry. A win is taken only when it survives the loser registered afresh
from the winner half a turn away, so a registration that slipped does not decide a symmetric
target (docs/methods.md §5.6).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.stats import chi2

from spacepose.core import se3
from spacepose.core.correspondences import find_correspondences
from spacepose.core.neighbors import SearchIndex

# False-decision rate of the test between a pose and its twin.
ALPHA = 1e-3
# Largest ratio of two principal variances that makes a model nearly round about the third
# axis, so that its quarter turns are twins too: a 1 m square bus with a dish on a boom has
# 1.02 (it was held 90° off, ambiguous, for 20 frames), random:2 1.14 (held 90° off at a
# fitness of 0.95); the lab mock-up 1.29, the orbit target 3.5.
ROUND_RATIO = 1.15


def principal_turns(points: NDArray[np.float64]) -> list[NDArray[np.float64]]:
    """The three half turns of a model about its principal axes through its centroid, and
    both quarter turns about an axis the model is nearly round about (the other two
    principal variances within :data:`ROUND_RATIO`).

    Parameters
    ----------
    points
        (N, 3) model points, target frame.

    Returns
    -------
    list of (4, 4) float64
        ``T_target_twin``: a pose ``T_sensor_target`` has the twin ``T_sensor_target @ T``.
    """
    centroid = points.mean(axis=0)
    variances, axes = np.linalg.eigh(np.cov((points - centroid).T))
    turns = []
    for k in range(3):
        a = axes[:, k]
        # Half a turn about the unit axis a: R = 2 a aᵀ − I.
        rotations = [2.0 * np.outer(a, a) - np.eye(3)]
        low, high = sorted(np.delete(variances, k))
        if high <= ROUND_RATIO * low:
            # Quarter turns about a: R = a aᵀ ± [a]×.
            rotations += [np.outer(a, a) + sign * se3.skew(a) for sign in (1.0, -1.0)]
        turns += [se3.make_transform(R, centroid - R @ centroid) for R in rotations]
    return turns


@dataclass(frozen=True)
class FitComparison:
    """McNemar's test between two poses of a frame against the same model.

    Attributes
    ----------
    only_first, only_second
        Frame points within the gate of the model at the first pose only, at the second only.
    statistic
        ``(b − c)² / (b + c)`` (0 when no point tells them apart), χ² with one degree of
        freedom when the two fit alike.
    winner
        0: the first pose fits significantly more points, 1: the second, None: undecided.
    """

    only_first: int
    only_second: int
    statistic: float
    winner: int | None


def compare_fits(
    tree: SearchIndex,
    points: NDArray[np.float64],
    T_sensor_target_a: NDArray[np.float64],
    T_sensor_target_b: NDArray[np.float64],
    gate: float,
    alpha: float = ALPHA,
    workers: int = -1,
) -> FitComparison:
    """Which of two poses fits more of a frame's points onto a model, if the data can tell.

    Parameters
    ----------
    tree
        Search index of the model points (target frame).
    points
        (N, 3) frame points, sensor frame.
    T_sensor_target_a, T_sensor_target_b
        (4, 4) the two poses.
    gate
        A point fits when a model point lies within this distance (m).
    alpha
        Probability of a decision between two poses that fit alike.

    Returns
    -------
    FitComparison
    """
    fits = []
    for T in (T_sensor_target_a, T_sensor_target_b):
        moved = se3.transform_points(se3.invert(T), points)
        mask = np.zeros(len(points), dtype=bool)
        mask[find_correspondences(tree, moved, gate, workers)[0]] = True
        fits.append(mask)
    b = int(np.count_nonzero(fits[0] & ~fits[1]))
    c = int(np.count_nonzero(fits[1] & ~fits[0]))
    statistic = (b - c) ** 2 / (b + c) if b + c else 0.0
    winner = None
    if statistic > chi2.ppf(1.0 - alpha, 1):
        winner = 0 if b > c else 1
    return FitComparison(b, c, float(statistic), winner)
