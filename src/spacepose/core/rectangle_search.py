"""Rectangles of a whole cloud: planes → each plane's own support → measurement → recognition.

RANSAC (:func:`spacepose.core.planes.extract_planes`) finds the planes; each keeps only its
dense connected region (:func:`spacepose.core.plane_support.dense_support`), since the stray
points a slab collects around a face pull its distribution matrix; the support is measured as a
rectangle (:func:`spacepose.core.rectangle_measurement.measure_rectangle`) and recognised
against the catalogue (:func:`spacepose.core.rectangles.recognise`). All vectors are in the
frame of the points (the sensor frame), in metres.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from spacepose.core.cloud import PointCloud, as_points
from spacepose.core.config import stage_config
from spacepose.core.moments import (
    distribution,
    is_collinear,
    no_plane,
    normalised_weights,
    on_a_line,
)
from spacepose.core.plane_support import dense_support
from spacepose.core.planes import Plane, PlaneConfig, extract_planes
from spacepose.core.rectangle_measurement import RectangleMeasurement, measure_rectangle
from spacepose.core.rectangles import CatalogueEntry, RectangleConfig, recognise
from spacepose.errors import InputError

__all__ = ["FoundPlane", "MeasuredPlane", "find_rectangles", "measure_planes"]


@dataclass(frozen=True, eq=False)
class MeasuredPlane:
    """One extracted plane and the measurement of its rectangle.

    Attributes
    ----------
    plane
        From :func:`spacepose.core.planes.extract_planes`; inliers index the input cloud.
    support
        Indices (into the input cloud) of the points measured: the plane's dense connected
        region when ``RectangleConfig.support`` is set, else all its inliers.
    measurement
        :func:`measure_rectangle` of the support.
    """

    plane: Plane
    support: NDArray[np.intp]
    measurement: RectangleMeasurement


def measure_planes(
    cloud_or_points: PointCloud | ArrayLike,
    plane_config: PlaneConfig = PlaneConfig(),
    config: RectangleConfig = RectangleConfig(),
    weights: ArrayLike | None = None,
) -> list[MeasuredPlane]:
    """Extract the planes of a cloud and measure each one's support as a rectangle.

    Parameters
    ----------
    cloud_or_points
        (N, 3) points or a PointCloud in the sensor frame (m).
    plane_config, config
        RANSAC settings; the noise σ, sampling and support of the measurement.
    weights
        Optional (N,) surface each point stands for (see :func:`measure_rectangle`).

    Returns
    -------
    One :class:`MeasuredPlane` per extracted plane, in extraction order.
    """
    pts = as_points(cloud_or_points, min_points=3)
    all_weights = None if weights is None else normalised_weights(weights, len(pts))
    out = []
    # The cloud itself, not its points: a degenerate cloud's error names its file.
    for plane in extract_planes(cloud_or_points, plane_config):
        support = plane.inliers
        if config.support:
            dense = plane.inliers[dense_support(pts[plane.inliers], plane.normal)]
            if len(dense) >= 3 and not is_collinear(distribution(pts[dense])[1]):
                support = dense
        if on_a_line(pts[support]):
            # Copies of one return (a driver's mark of no return, written 2,000 times) and a
            # stray or two fit a plane: no face to measure.
            continue
        w = None if all_weights is None else all_weights[support]
        m = measure_rectangle(pts[support], config.sigma, config.sampling, w)
        out.append(MeasuredPlane(plane, support, m))
    return out


@dataclass(frozen=True, eq=False)
class FoundPlane:
    """One extracted plane, its measurement and, if recognised, its catalogue entry's name.

    Attributes
    ----------
    plane
        From :func:`spacepose.core.planes.extract_planes`; inliers index the input cloud.
    measurement
        :func:`measure_rectangle` of the plane's support.
    name
        The recognised catalogue rectangle, or None.
    support
        Indices (into the input cloud) of the points measured (see :class:`MeasuredPlane`).
    """

    plane: Plane
    measurement: RectangleMeasurement
    name: str | None
    support: NDArray[np.intp]


def find_rectangles(
    cloud_or_points: PointCloud | ArrayLike,
    catalogue: Sequence[CatalogueEntry] = (),
    plane_config: PlaneConfig = PlaneConfig(),
    config: RectangleConfig = RectangleConfig(),
    predicted_R_sensor_model: ArrayLike | None = None,
) -> list[FoundPlane]:
    """Extract planes, measure each as a rectangle and recognise it against the catalogue.

    Parameters
    ----------
    cloud_or_points
        (N, 3) points or a PointCloud in the sensor frame (m).
    catalogue
        Known rectangles; with none, every ``name`` is None.
    plane_config, config
        RANSAC and recognition settings (``config.sigma`` is the noise removed).
    predicted_R_sensor_model
        Optional (3, 3) predicted attitude, to tell faces of equal size apart.

    Returns
    -------
    One :class:`FoundPlane` per extracted plane, in extraction order.

    Raises
    ------
    InputError
        ``config.sigma`` as large as the cloud's RMS radius (every side would measure 0), or
        ``plane_config.distance_threshold`` (one slab would hold every face).
    DegenerateGeometryError
        The points span no plane (all on a line or at one place).
    """
    plane_config = stage_config(plane_config, PlaneConfig, "plane_config")
    config = stage_config(config, RectangleConfig)
    pts = as_points(cloud_or_points, min_points=3)
    if on_a_line(pts):
        raise no_plane(pts, getattr(cloud_or_points, "source", None))
    rms_radius = float(np.sqrt(np.mean(np.sum((pts - pts.mean(axis=0)) ** 2, axis=1))))
    if config.sigma >= rms_radius:
        # Every side would come out as 0 (its variance less the noise's): a σ in the wrong
        # unit, or the target's size given for the noise.
        raise InputError(
            f"noise sigma {config.sigma:g} m is as large as the cloud itself (RMS radius "
            f"{rms_radius:.3g} m): sigma is the points' noise",
            getattr(cloud_or_points, "source", None),
        )
    if plane_config.distance_threshold >= rms_radius:
        # One slab would hold the whole cloud, every face in one "plane" of tilted normal.
        raise InputError(
            f"plane threshold {plane_config.distance_threshold:g} m is as large as the cloud "
            f"itself (RMS radius {rms_radius:.3g} m): it is a plane's half-thickness",
            getattr(cloud_or_points, "source", None),
        )
    return [
        FoundPlane(
            f.plane,
            f.measurement,
            recognise(f.measurement, catalogue, config, predicted_R_sensor_model),
            f.support,
        )
        for f in measure_planes(cloud_or_points, plane_config, config)
    ]
