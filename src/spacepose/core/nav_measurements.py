"""Measurement noise of the rectangle navigation (Yu et al. 2019, METHODS §2.2–2.4).

The covariance of the attitude and of the centroid one recognised rectangle gives, from its
size, point count and incidence, and the area-weighted centroid of a range image's plane.
Used by :class:`spacepose.core.navigation.RelativeNavigator` (settings in
:class:`~spacepose.core.nav_config.NavigationConfig`).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from spacepose.core.nav_config import NavigationConfig
from spacepose.core.rectangles import CatalogueEntry, RectangleMeasurement

__all__ = [
    "area_weighted_centroid",
    "attitude_covariance",
    "centroid_covariance",
    "incidence_cosine",
]


def incidence_cosine(measurement: RectangleMeasurement) -> float:
    """``|cos θ|`` (-) of the angle between the face normal and the ray to its centroid.

    Range noise σ_r along the ray moves a point by ``σ_r |cos θ|`` along the face normal.
    """
    c = measurement.centroid
    return abs(float(measurement.normal @ c)) / max(float(np.linalg.norm(c)), 1e-300)


def attitude_covariance(
    measurement: RectangleMeasurement, entry: CatalogueEntry, config: NavigationConfig
) -> NDArray[np.float64]:
    """Covariance (3, 3, rad², body frame) of the attitude measured from one rectangle.

    The normal is fixed by the out-of-plane noise over the whole face (σ ≈ σ_n √12 / (side √N)
    about each in-plane axis, with ``σ_n = σ_r |cos θ|`` the range noise along the normal of a
    face seen at incidence θ, the cosine floored at ``min_tilt_cosine``); the turn about the
    normal only by the difference of the in-plane eigenvalues, ``σ² ≈ a² b² / (N (b² − a²)²)``
    — far weaker for a near-square face.
    """
    n = max(measurement.n_points, 1)
    a, b = entry.a, entry.b
    cos = max(incidence_cosine(measurement), config.min_tilt_cosine)
    sigma_n = max(config.rectangle.sigma * cos, 1e-6)
    tilt = config.tilt_scale * sigma_n * np.sqrt(12.0 / n) / np.array([b, a])
    spin = config.spin_scale * a * b / (np.sqrt(n) * (b**2 - a**2))
    floor = np.deg2rad(config.min_attitude_sigma_deg)
    sig = np.maximum(np.array([tilt[0], tilt[1], spin]), floor)
    R_B_plane = entry.rotation  # B' and B are parallel
    return R_B_plane @ np.diag(sig**2) @ R_B_plane.T


def centroid_covariance(
    measurement: RectangleMeasurement, config: NavigationConfig
) -> NDArray[np.float64]:
    """Covariance (3, 3, m², sensor frame) of one rectangle's measured centroid.

    Along the face normal the centroid is as good as the mean of N range errors projected on
    it, ``σ_r |cos θ| / √N`` (sub-millimetre); in the plane it is limited by where the pixel
    grid cuts the outline, ``ekf.sigma_centroid`` (the pixels are 8 cm wide at 25 m).
    """
    n_hat = measurement.normal
    along = (
        config.rectangle.sigma
        * incidence_cosine(measurement)
        / np.sqrt(max(measurement.n_points, 1))
    )
    along = max(along, config.min_centroid_sigma)
    in_plane = config.ekf.sigma_centroid
    N = np.outer(n_hat, n_hat)
    return in_plane**2 * (np.eye(3) - N) + along**2 * N


def area_weighted_centroid(points: ArrayLike) -> NDArray[np.float64]:
    """Centroid (3,) of a plane's points from a range image, each weighted by its pixel's area.

    A pixel of solid angle Ω at range r on a plane at distance h from the sensor covers
    ``Ω r² / cos(incidence) = Ω r³ / h``, so weights ``∝ |p|³`` turn the image-uniform samples
    into surface-uniform ones, whose mean is the face's centre (METHODS §2.2 assumes the latter).
    """
    p = np.asarray(points, dtype=np.float64)
    w = np.linalg.norm(p, axis=1) ** 3
    return w @ p / w.sum()
