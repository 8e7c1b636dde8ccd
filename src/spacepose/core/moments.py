"""Second moments of a point set: centroid, distribution matrix, PCA plane (methods.md §2.2).

:func:`distribution` gives the centroid (3,) of N >= 3 points (N, 3), each optionally weighted by
the surface it stands for (:func:`normalised_weights`), and the eigen-decomposition of their
distribution matrix ``M = Σ w (p − c)(p − c)ᵀ / Σ w`` (3, 3; m²): eigenvalues ascending,
eigenvectors as columns. :func:`is_collinear` tells a line (or a single point) by its
eigenvalues; :func:`fit_plane` takes the eigenvector of the smallest as the unit normal of the
least-squares plane ``normal · x = offset`` (m). RANSAC plane extraction
(:mod:`spacepose.core.planes`) refits its planes with it, and rectangle measurement
(:mod:`spacepose.core.rectangle_measurement`) reads a face's axes and sides off the same matrix.
Every function checks its points with :func:`spacepose.core.cloud.as_points` (N >= 3, finite).

All coordinates are in the frame of the input points (usually the sensor frame), in metres; a
fitted normal is turned towards the origin of that frame (the sensor), so ``offset <= 0``.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from spacepose.core.cloud import as_points
from spacepose.errors import DegenerateGeometryError, InputError

# Relative size of the second eigenvalue below which points count as collinear.
_COLLINEAR_RTOL = 1e-10


def normalised_weights(weights: ArrayLike, n: int) -> NDArray[np.float64]:
    """Weights (n,) scaled to sum to 1.

    Raises
    ------
    InputError
        Not n finite non-negative numbers, or all of them 0.
    """
    w = np.asarray(weights, dtype=np.float64)
    if w.shape != (n,):
        raise InputError(f"weights must be ({n},) (one per point), got shape {w.shape}")
    if not np.all(np.isfinite(w)) or np.any(w < 0.0):
        raise InputError("weights must be finite and non-negative")
    total = float(w.sum())
    if total <= 0.0:
        raise InputError("weights are all 0: no point counts")
    return w / total


def distribution(
    points: ArrayLike, weights: ArrayLike | None = None
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """Centroid and eigen-decomposition of the distribution matrix (methods.md §2.2).

    Parameters
    ----------
    points
        (N, 3) points, N >= 3, finite.
    weights
        Optional (N,) non-negative weights (the surface each point stands for); uniform if None.

    Raises
    ------
    InputError
        Bad points, or bad weights (:func:`normalised_weights`).

    Returns
    -------
    centroid
        (3,) mean point (weighted).
    eigenvalues
        (3,) eigenvalues of ``M = Σ w (p − c)(p − c)ᵀ / Σ w``, ascending (m²).
    eigenvectors
        (3, 3) orthonormal eigenvectors as columns, in the same order.
    """
    pts = as_points(points, min_points=3)
    if weights is None:
        centroid = pts.mean(axis=0)
        centred = pts - centroid
        M = centred.T @ centred / len(pts)
    else:
        w = normalised_weights(weights, len(pts))
        centroid = w @ pts
        centred = pts - centroid
        M = (centred * w[:, None]).T @ centred
    eigenvalues, eigenvectors = np.linalg.eigh(M)
    return centroid, np.clip(eigenvalues, 0.0, None), eigenvectors


def is_collinear(eigenvalues: NDArray[np.float64]) -> bool:
    """Whether ascending eigenvalues (3,) of a distribution matrix describe a line or a point."""
    return bool(eigenvalues[1] <= _COLLINEAR_RTOL * max(eigenvalues[2], 1e-300))


def no_plane(points: NDArray[np.float64], source: object = None) -> DegenerateGeometryError:
    """The error for points (N, 3) that span no plane (:func:`is_collinear`), saying whether
    they lie on one line or all at one place ("collinear" misled for one repeated point);
    ``source`` names the file."""
    where = "at one place" if np.ptp(points, axis=0).max() == 0.0 else "collinear"
    return DegenerateGeometryError(f"all {len(points)} points are {where}: no plane to fit", source)


def on_a_line(points: NDArray[np.float64]) -> bool:
    """Whether every point (N ≥ 3, 3) lies on one line or at one place. A strided sample of
    about a thousand points clears almost every cloud (0.22 ms on 30,000 points, against 1.4 ms
    for all of them); only a sample on a line is confirmed on all of them, and then on their
    bulk: one stray return a million metres off spreads the distribution along its direction
    alone, and a box with it read as "collinear"."""
    sample = points[:: max(1, len(points) // 1024)]
    return (
        is_collinear(distribution(sample)[1])
        and is_collinear(distribution(points)[1])
        and is_collinear(distribution(_bulk(points))[1])
    )


def _bulk(points: NDArray[np.float64]) -> NDArray[np.float64]:
    """The points (M, 3) no farther from the median point than nine in ten of them are; all of
    them when that leaves fewer than 3."""
    d = np.linalg.norm(points - np.median(points, axis=0), axis=1)
    near = points[d <= np.quantile(d, 0.9)]
    return near if len(near) >= 3 else points


def fit_plane(points: ArrayLike) -> tuple[NDArray[np.float64], float]:
    """Least-squares plane (PCA) through points (N, 3).

    Returns
    -------
    normal
        (3,) unit normal (eigenvector of the smallest eigenvalue), towards the frame's origin.
    offset
        ``normal · centroid`` (m), so the plane is ``normal · x = offset``.

    Raises
    ------
    InputError
        Fewer than 3 points or non-finite values.
    DegenerateGeometryError
        Collinear or coincident points, which do not determine a plane.
    """
    centroid, eigenvalues, eigenvectors = distribution(points)
    if is_collinear(eigenvalues):
        raise no_plane(np.asarray(points, dtype=np.float64))
    normal = eigenvectors[:, 0]
    offset = float(normal @ centroid)
    # Face the sensor (origin): a visible surface's normal points back along the ray.
    if offset > 0:
        normal, offset = -normal, -offset
    return normal, offset
