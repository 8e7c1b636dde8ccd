"""One rectangle measured from the distribution matrix of a plane's points (methods.md §2.2).

For an a×b rectangle (a <= b) sampled uniformly with isotropic noise σ, the distribution matrix has
eigenvalues ``(σ², a²/12 + σ², b²/12 + σ²)``, so the noise-corrected sides are
``a = √(12(λ_mid − σ²))`` and ``b = √(12(λ_max − σ²))``. :func:`measure_rectangle` reads them off,
with the plane frame (short side, long side, normal towards the sensor), the noise-corrected
fourth-moment ratio along each side, the 2 %–98 % quantile extents and the centroid's offset
from their middle; :func:`fill_ratio` compares the point count with what a whole rectangle of
the measured size gives a range camera. Whether these say a whole rectangle, and which face of
the catalogue it is, is decided in :mod:`spacepose.core.rectangles`.

Points are (N, 3) float64 in the frame they were taken in (the sensor frame, the sensor at the
origin); every vector is in that frame, lengths in metres, variances in m².
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from spacepose.core.moments import distribution, is_collinear, no_plane, normalised_weights
from spacepose.core.se3 import real_array

__all__ = ["RectangleMeasurement", "distribution", "fill_ratio", "measure_rectangle"]

# Tail share cut on each side by the quantile extent (robust to stray points and noise).
_EXTENT_QUANTILE = 0.02
# Tail share of the edge estimate of independent uniform samples (sides and centre, "random").
_EDGE_QUANTILE = 0.005


@dataclass(frozen=True, eq=False)
class RectangleMeasurement:
    """What the point distribution of one plane says about it (sensor frame, metres).

    Attributes
    ----------
    centroid
        (3,) centre of the rectangle: the mean of the points (``"grid"``), or the middle of its
        edges (``"random"``).
    normal
        (3,) unit normal, the third column of ``R_sensor_plane``.
    eigenvalues
        (3,) eigenvalues of the distribution matrix, ascending (m²), noise included.
    a, b
        Short and long sides (m), ``a <= b``: noise-corrected from the eigenvalues (``"grid"``,
        0 when the variance is below σ²), or from the edges (``"random"``).
    kurtosis
        (2,) noise-corrected ``E[u⁴]/E[u²]²`` along the short and the long side (1.8 when uniform).
    extent
        (2,) sides estimated from the 2 %–98 % quantile range along each axis (m).
    centre_offset
        (2,) centroid minus the middle of that quantile range, along each side (m).
    R_sensor_plane
        (3, 3) right-handed ``[v_mid v_max v_min]``: x along the short side, y along the long
        side, z the normal, pointing towards the sensor (origin). The sign of x and y is one of
        the four-fold ambiguous choices, fixed later by
        :func:`spacepose.core.attitude_fix.fix_four_fold`.
    n_points
        Number of points measured.
    sigma
        The noise σ (m) assumed in the correction.
    moment_sides
        (2,) the sides from the eigenvalues, whatever the sampling (the shape checks compare
        them with ``extent``).
    """

    centroid: NDArray[np.float64]
    normal: NDArray[np.float64]
    eigenvalues: NDArray[np.float64]
    a: float
    b: float
    kurtosis: NDArray[np.float64]
    extent: NDArray[np.float64]
    centre_offset: NDArray[np.float64]
    R_sensor_plane: NDArray[np.float64]
    n_points: int
    sigma: float
    moment_sides: NDArray[np.float64]


def measure_rectangle(
    points: ArrayLike,
    sigma: float = 0.0,
    sampling: Literal["grid", "random"] = "grid",
    weights: ArrayLike | None = None,
) -> RectangleMeasurement:
    """Centroid, sides, moment ratios and plane frame of the points of one plane.

    Parameters
    ----------
    points
        (N, 3) points of one plane, sensor frame (m), N >= 3.
    sigma
        Isotropic noise standard deviation (m) to remove from the eigenvalues.
    sampling
        ``"grid"``: sides from the eigenvalues and the centre from the mean (exact on a regular
        grid). ``"random"``: N independent uniform points, whose mean and variance scatter by
        ``s/√(12N)`` and the side from the variance by ``s √(0.2/N)`` (1.5 mm and 2.3 mm for Y1's
        18 cm side and N = 1250);
        their edges are far sharper, so the sides and the centre come from the 0.5 % and 99.5 %
        quantiles along each in-plane axis, ``side = (hi − lo) / 0.99`` (scatter about
        ``s √(2·0.005/N)``). In-plane noise widens those edges: keep σ well below the spacing.
    weights
        Optional (N,) surface each point stands for (a range image's pixel footprint,
        :func:`spacepose.core.nav_measurements.pixel_area_weights`): the centroid, the
        distribution matrix and the moments are then those of the surface, not of the samples.

    Raises
    ------
    InputError
        Fewer than 3 points, wrong shape or non-finite values.
    DegenerateGeometryError
        Collinear or coincident points (no plane, so no normal).
    """
    pts = real_array(points, "points")  # text ended in numpy's ValueError
    w = None if weights is None else normalised_weights(weights, len(pts))
    centroid, eigenvalues, V = distribution(pts, w)
    if is_collinear(eigenvalues):
        raise no_plane(pts)
    normal = V[:, 0]
    if normal @ centroid > 0:  # face the sensor, which sits at the origin
        normal = -normal
    y = V[:, 2]
    x = np.cross(y, normal)  # right-handed: x = y × z
    R = np.column_stack([x, y, normal])
    s2 = sigma**2
    var = eigenvalues[[1, 2]] - s2
    a, b = np.sqrt(12.0 * np.clip(var, 0.0, None))
    # In-plane coordinates along the short and long side.
    uv = (pts - centroid) @ R[:, :2]
    if w is None:
        m2, m4 = np.mean(uv**2, axis=0), np.mean(uv**4, axis=0)
    else:
        m2, m4 = w @ uv**2, w @ uv**4
    # Remove Gaussian noise: E[(u+n)⁴] = E[u⁴] + 6 E[u²] σ² + 3σ⁴ with E[(u+n)²] = E[u²] + σ².
    m2c = m2 - s2
    m4c = m4 - 6.0 * m2c * s2 - 3.0 * s2**2
    with np.errstate(divide="ignore", invalid="ignore"):
        kurtosis = np.where(m2c > 0, m4c / m2c**2, np.nan)
    lo, hi = np.quantile(uv, [_EXTENT_QUANTILE, 1.0 - _EXTENT_QUANTILE], axis=0)
    extent = (hi - lo) / (1.0 - 2.0 * _EXTENT_QUANTILE)
    moment_sides = np.array([a, b])
    centre = centroid
    if sampling == "random":
        lo_e, hi_e = np.quantile(uv, [_EDGE_QUANTILE, 1.0 - _EDGE_QUANTILE], axis=0)
        a, b = (hi_e - lo_e) / (1.0 - 2.0 * _EDGE_QUANTILE)
        centre = centroid + R[:, :2] @ (0.5 * (lo_e + hi_e))
    return RectangleMeasurement(
        centroid=centre,
        normal=normal,
        eigenvalues=eigenvalues,
        a=float(a),
        b=float(b),
        kurtosis=kurtosis,
        extent=extent,
        centre_offset=-0.5 * (lo + hi),
        R_sensor_plane=R,
        n_points=len(pts),
        sigma=float(sigma),
        moment_sides=moment_sides,
    )


def fill_ratio(measurement: RectangleMeasurement, focal_px: float) -> float:
    """Measured point count over the count a whole ``a × b`` rectangle gives a range camera.

    One pixel (focal length f pixels) covers ``(r/f)² / cos θ`` of a surface at range r seen at
    incidence θ, so a whole rectangle yields ``a b cos θ f² / r²`` points; the centroid's range
    and the normal's incidence stand for the whole face.
    """
    m = measurement
    r = float(np.linalg.norm(m.centroid))
    cos_incidence = abs(float(m.normal @ m.centroid)) / r
    expected = m.a * m.b * cos_incidence * focal_px**2 / r**2
    return m.n_points / expected if expected > 0 else float("inf")
