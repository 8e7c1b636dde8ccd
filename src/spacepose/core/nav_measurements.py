"""Measurement noise of the rectangle navigation (Yu et al. 2019, methods.md §2.2–2.4).

The covariance of the attitude and of the centroid one recognised rectangle gives, from its
size, point count, incidence and the sides measured against the catalogue's, and the
area-weighted centroid of a pinhole range image's plane.
Used by :class:`spacepose.core.navigation.RelativeNavigator` (settings in
:class:`~spacepose.core.nav_config.NavigationConfig`).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from spacepose.core.nav_config import NavigationConfig
from spacepose.core.rectangle_measurement import RectangleMeasurement
from spacepose.core.rectangles import CatalogueEntry

__all__ = [
    "area_weighted_centroid",
    "attitude_covariance",
    "centroid_covariance",
    "incidence_cosine",
    "pixel_area_weights",
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

    The tilt of the normal about each side from the plane fit itself, ``σ² = λ_0' / (N λ_l)``:
    ``λ_l`` the measured spread (eigenvalue) along the other side, the lever, and ``λ_0'`` the
    mean squared residual off the plane ``λ_0`` (range noise and whatever else bends the face),
    no less than the range noise along the normal, ``(σ_r max(|cos θ|, min_tilt_cosine))²``:
    near grazing the outline's stretched pixels bend the fit more than its residual shows
    (orbit run, seed 0: with the residual alone the attitude ran 3° off and 1,410 updates were
    gated out).

    The turn about the normal, ``σ² ≈ a² b² / (N (b² − a²)²)`` with the catalogue's sides (the
    eigenvector-angle scatter of N random points, far weaker for a near-square face), scaled by
    ``spin_scale``. Not from the measured spreads: a face seen in part can show sides further
    apart than its own, and the turn then looked better than it is (seed 0 diverged, 1,057
    updates gated out).

    Each σ is scaled, floored at ``min_attitude_sigma_deg`` and the diagonal turned from the
    face's axes into B.
    """
    n = max(measurement.n_points, 1)
    lam = np.maximum(np.asarray(measurement.eigenvalues, dtype=np.float64), 1e-300)
    cos = max(incidence_cosine(measurement), config.min_tilt_cosine)
    residual = max(lam[0], (config.rectangle.sigma * cos) ** 2)
    tilt = config.tilt_scale * np.sqrt(residual / (n * lam[[2, 1]]))
    a, b = entry.a, entry.b
    spin = config.spin_scale * a * b / (np.sqrt(n) * (b**2 - a**2))
    floor = np.deg2rad(config.min_attitude_sigma_deg)
    sig = np.maximum(np.array([tilt[0], tilt[1], spin]), floor)
    R_B_plane = entry.rotation  # B' and B are parallel
    return R_B_plane @ np.diag(sig**2) @ R_B_plane.T


def centroid_covariance(
    measurement: RectangleMeasurement, entry: CatalogueEntry, config: NavigationConfig
) -> NDArray[np.float64]:
    """Covariance (3, 3, m², sensor frame) of one rectangle's measured centroid.

    Along the face normal the centroid is as good as the mean of N range errors projected on
    it, ``σ_r |cos θ| / √N`` (sub-millimetre, floored at ``min_centroid_sigma``). In the plane,
    along each side u (the measurement's own axes), two things measured on the frame:

    - where the pixel grid cuts the outline: the points start and stop within one pitch
      ``p_u`` of each edge, two independent uniform gaps, so the mean moves by
      ``σ² = p_u² / 24``. The pitch comes from the points: each covers ``a_m b_m / N`` of the
      face (measured sides), and a side foreshortened by the view, ``c_u = √(1 − (u·r̂)²)``
      (r̂ the ray to the centroid, floored at ``min_tilt_cosine``), is crossed by pixels
      ``1 / c_u`` times as long: ``p_u² = (a_m b_m / N) c_a c_b / c_u²``.
      This is the bound of a grid aligned with the face; a turned grid cuts each row at
      another phase and does better (measured on the default orbit run: a third of it);
    - how much of the side is missing (hidden, out of view, or cut by a neighbour's share):
      a side measured ``d_u`` shorter (or longer) than the catalogue's has its centroid moved
      by up to ``d_u / 2``, taken as ``σ² = (d_u / 2)²``. On the default orbit run the 6 m wing
      seen in part gives the largest centroid errors (8-18 cm), each with such a deficit.
    """
    n_hat = measurement.normal
    n_points = max(measurement.n_points, 1)
    along = config.rectangle.sigma * incidence_cosine(measurement) / np.sqrt(n_points)
    along = max(along, config.min_centroid_sigma)
    ray = measurement.centroid / max(float(np.linalg.norm(measurement.centroid)), 1e-300)
    axes = measurement.R_sensor_plane[:, :2].T  # (2, 3): the short and the long side
    cos = np.maximum(np.sqrt(np.clip(1.0 - (axes @ ray) ** 2, 0.0, 1.0)), config.min_tilt_cosine)
    sides = np.array([measurement.a, measurement.b])
    area_per_point = max(float(np.prod(sides)), 0.0) / n_points
    pitch_sq = area_per_point * np.prod(cos) / cos**2
    deficit = np.array([entry.a, entry.b]) - sides
    var = pitch_sq / 24.0 + (deficit / 2.0) ** 2
    C = along**2 * np.outer(n_hat, n_hat)
    return C + np.einsum("k,ki,kj->ij", var, axes, axes)


def pixel_area_weights(points: ArrayLike) -> NDArray[np.float64]:
    """Surface (N,), up to a common factor, that each point of a pinhole range image stands for
    on the plane it lies on.

    Points in the sensor frame, z along the optical axis. A pinhole pixel at angle α off the
    axis sees the solid angle ``Ω₀ cos³α``; at range r on a plane at distance h from the
    sensor it covers ``Ω₀ cos³α r² / cos(incidence) = Ω₀ cos³α r³ / h = Ω₀ z³ / h`` (with
    ``z = r cos α``), so weights ``∝ z³`` turn the image-uniform samples of one plane into
    surface-uniform ones, whose mean is the face's centre and whose distribution matrix has
    the face's axes (methods.md §2.2 assumes both). Weighting by ``r³`` instead forgets the
    ``cos³α`` and pulls a long face towards the axis: 4 cm along the 6 m wing of the orbit
    run, the same way in every frame.

    A cloud with a point at or behind the image plane (z ≤ 0) is no pinhole image (a scanner
    turning about its axis, or a cloud in another frame): each point then stands for a constant
    solid angle, and the weights are ``r³``.
    """
    p = np.asarray(points, dtype=np.float64)
    if len(p) and np.all(p[:, 2] > 0.0):
        return p[:, 2] ** 3
    return np.linalg.norm(p, axis=1) ** 3


def area_weighted_centroid(points: ArrayLike) -> NDArray[np.float64]:
    """Centroid (3,) of a plane's points from a pinhole range image, each weighted by the
    surface its pixel covers (:func:`pixel_area_weights`)."""
    p = np.asarray(points, dtype=np.float64)
    w = pixel_area_weights(p)
    return w @ p / w.sum()
