"""Relative navigation from rectangles (Yu et al. 2019, METHODS §2.1–2.4): the whole pipeline.

Per frame: planes → rectangles recognised against the catalogue → coarse pose of each rectangle
with the 4-fold fix against the filter's predicted attitude → EKF predict and update (attitude
and centroid of every recognised rectangle). The filter starts at the first frame where a
rectangle is recognised: the coarse pose gives q and ρ; ω and the inertia ratios come from the
configured priors (Yu et al. do the same: ρ̇ = 0, ω a prior with an initial error).

Before the filter has a prediction, faces of equal size (the opposite faces of a box, the two
faces of a panel) cannot be told apart, and a shape symmetric under a 180° turn (a box with a
wing on its axis) has two poses that explain every frame equally. A coarse attitude prior
``prior_q_I_B`` resolves both at initialisation; without it only rectangles of unique size
start the filter (NavigationConfig.prior_q_I_B).
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import Field
from scipy.spatial.transform import Rotation

from spacepose.core import dynamics
from spacepose.core.attitude_fix import coarse_target_pose, consistent_rectangles
from spacepose.core.cloud import PointCloud
from spacepose.core.config import StageConfig
from spacepose.core.ekf import EKFConfig, NavState, RelativeNavEKF
from spacepose.core.planes import PlaneConfig
from spacepose.core.rectangles import (
    CatalogueEntry,
    RectangleConfig,
    RectangleMeasurement,
    find_rectangles,
)
from spacepose.errors import InputError

STATE_COLUMNS = (
    "t,rho_x,rho_y,rho_z,v_x,v_y,v_z,qx,qy,qz,qw,w_x,w_y,w_z,k_x,k_y,k_z,com_x,com_y,com_z"
).split(",")
SIGMA_COLUMNS = [
    f"sig_{name}_{axis}" for name in ("rho", "v", "att", "w", "k", "com") for axis in "xyz"
]
NAV_COLUMNS = [*STATE_COLUMNS, *SIGMA_COLUMNS, "n_rect", "status"]


class NavigationConfig(StageConfig):
    """Settings of :class:`RelativeNavigator` (defaults: the flash LiDAR of the orbit run)."""

    plane: PlaneConfig = Field(
        default_factory=lambda: PlaneConfig(distance_threshold=0.03),
        description="RANSAC plane extraction; thickness about 3σ of the range noise. Its "
        "range_threshold, when unset, is 3 rectangle.sigma (see ray_share_out).",
    )
    rectangle: RectangleConfig = Field(
        default_factory=lambda: RectangleConfig(sigma=0.01),
        description="Recognition; sigma is the range noise removed from the eigenvalues.",
    )
    ekf: EKFConfig = Field(
        default_factory=lambda: EKFConfig(
            sigma_accel=3e-8,
            sigma_angular_accel=3e-8,
            sigma_centroid=0.01,
            init_sigma_position=0.1,
            init_sigma_velocity=0.01,
            init_sigma_attitude_deg=3.0,
            init_sigma_rate_deg_s=3.0,
            init_sigma_inertia=0.3,
            init_sigma_com=0.1,
            sigma_feature=0.005,
        ),
        description="Filter noise model; sigma_attitude_deg is unused (see the scales below); "
        "sigma_centroid is the in-plane σ of a centroid (where the 8 cm pixels cut the outline: "
        "7-11 mm per axis on the orbit run; along the normal see centroid_covariance); the "
        "process noise is small because the simulated target feels no unmodelled force.",
    )
    tilt_scale: float = Field(
        1.0,
        gt=0,
        description="Scale of the normal-direction σ ≈ σ_r |cos θ| √12 / (side √N) of a "
        "rectangle seen at incidence θ.",
    )
    min_tilt_cosine: float = Field(
        0.25,
        gt=0,
        le=1,
        description="Floor of the incidence cosine in the normal-direction σ (1 ignores the "
        "incidence). Near grazing the outline's pixels and the in-plane part of the range "
        "noise, not the normal part, limit the normal: without a floor the filter trusts such "
        "faces too much (orbit run, seed 1: NEES far above its bound).",
    )
    spin_scale: float = Field(
        0.25,
        gt=0,
        description="Scale of the in-plane σ ≈ a b / (√N (b² − a²)) of a rectangle (the "
        "eigenvector angle of N random points; the sensor's regular grid does better: a "
        "quarter of it on the orbit run).",
    )
    min_attitude_sigma_deg: float = Field(
        0.01, gt=0, description="Floor of every attitude measurement σ, deg."
    )
    min_centroid_sigma: float = Field(
        1e-4, gt=0, description="Floor of the centroid σ along the face normal, m."
    )
    init_rate_deg_s: tuple[float, float, float] = Field(
        (0.0, 0.0, 0.0), description="Prior of ω in B, deg/s."
    )
    init_k: tuple[float, float, float] = Field(
        (0.0, 0.0, 0.0), description="Prior of the inertia ratios (0: a sphere)."
    )
    prior_q_I_B: tuple[float, float, float, float] | None = Field(
        None,
        description="Coarse attitude prior (qx, qy, qz, qw) at t = 0, used only before the "
        "filter starts, to tell equal-size faces and symmetric poses apart.",
    )
    ray_share_out: bool = Field(
        True,
        description="Share the planes' points out again along the rays (PlaneConfig."
        "range_threshold, 3 rectangle.sigma when unset). Without it the face found first "
        "keeps a strip of each neighbour's points along their shared edge, and the centroids "
        "move about 5 mm away from the sensor on the orbit run.",
    )
    area_weighted_centroid: bool = Field(
        True,
        description="Weight each point by the area its pixel covers (∝ range³ on a plane): a "
        "range image samples a tilted face more densely where it is nearer, which pulls the "
        "plain mean towards the sensor (about 2 cm at 25 m on the orbit run).",
    )

    def plane_config(self) -> PlaneConfig:
        """The plane extraction settings the navigator uses (with the ray share-out)."""
        if not self.ray_share_out:
            return self.plane.model_copy(update={"range_threshold": None})
        if self.plane.range_threshold is not None or self.rectangle.sigma <= 0:
            return self.plane
        return self.plane.model_copy(update={"range_threshold": 3.0 * self.rectangle.sigma})


@dataclass(frozen=True, eq=False)
class NavRow:
    """The navigation output of one frame.

    Attributes
    ----------
    state
        The estimate after the frame's updates; None before initialisation.
    sigmas
        1-σ per block (``rho, v, att, omega, k, com``), None before initialisation.
    n_rect
        Rectangles recognised and used in this frame.
    status
        ``waiting`` (no filter yet), ``init`` (filter started here), ``update`` (at least one
        measurement used) or ``predict`` (nothing usable: prediction only).
    coarse_T_sensor_model
        Coarse pose of the frame from its rectangles after the 4-fold fix (4, 4), or None.
    raw_T_sensor_model
        Coarse pose from the largest rectangle's raw eigenvector frame (no 4-fold fix), or None;
        kept for the ablation of the fix.
    """

    t: float
    state: NavState | None
    sigmas: dict[str, NDArray[np.float64]] | None
    n_rect: int
    status: str
    coarse_T_sensor_model: NDArray[np.float64] | None = None
    raw_T_sensor_model: NDArray[np.float64] | None = None

    def values(self) -> list[float | int | str]:
        """The row in the order of :data:`NAV_COLUMNS` (NaN before initialisation)."""
        if self.state is None or self.sigmas is None:
            numbers = [self.t] + [float("nan")] * (len(STATE_COLUMNS) + len(SIGMA_COLUMNS) - 1)
        else:
            s = self.state
            numbers = [s.t, *s.rho, *s.v, *s.q_I_B, *s.omega_B, *s.k, *s.com]
            numbers += [float(v) for key in ("rho", "v", "att", "omega", "k", "com")
                        for v in self.sigmas[key]]  # fmt: skip
        return [*numbers, self.n_rect, self.status]


def scenario_geometry(
    scenario: Mapping[str, Any], source: str = "scenario.json"
) -> tuple[float, NDArray[np.float64]]:
    """Mean motion n (rad/s) and ``R_O_C`` (3, 3) from a run's scenario description.

    Raises
    ------
    InputError
        A key is missing, or ``R_O_C`` is not a rotation matrix, or n is not positive.
    """
    for key in ("mean_motion", "R_O_C"):
        if key not in scenario:
            raise InputError(f"missing key {key!r} (navigation needs an orbit run)", source)
    try:
        n = float(scenario["mean_motion"])
        R = np.asarray(scenario["R_O_C"], dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"mean_motion / R_O_C are not numeric: {exc}", source) from None
    if not np.isfinite(n) or n <= 0:
        raise InputError(f"mean_motion must be positive, got {n}", source)
    if R.shape != (3, 3) or not np.allclose(R.T @ R, np.eye(3), atol=1e-6) or np.linalg.det(R) < 0:
        raise InputError("R_O_C must be a 3x3 rotation matrix", source)
    return n, R


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


class RelativeNavigator:
    """The rectangle-based relative navigation pipeline for one run.

    Parameters
    ----------
    catalogue
        The target's known rectangles (model frame B').
    mean_motion
        Orbital mean motion n, rad/s.
    R_O_C
        (3, 3) constant sensor (chaser) attitude in O.
    config
        Pipeline settings (``config.prior_q_I_B``: the optional coarse attitude prior).
    """

    def __init__(
        self,
        catalogue: Sequence[CatalogueEntry],
        mean_motion: float,
        R_O_C: ArrayLike,
        config: NavigationConfig | None = None,
    ) -> None:
        if len(catalogue) == 0:
            raise InputError("the rectangle catalogue is empty: nothing to navigate on")
        self.catalogue = {e.name: e for e in catalogue}
        self.config = config or NavigationConfig()
        self.n = float(mean_motion)
        self.R_O_C = np.asarray(R_O_C, dtype=np.float64)
        self.ekf: RelativeNavEKF | None = None

    def predicted_R_sensor_model(self, t: float) -> NDArray[np.float64] | None:
        """Predicted target attitude in the sensor frame: the filter's, else the prior's."""
        if self.ekf is not None:
            return self.ekf.predict_pose()[:3, :3]
        if self.config.prior_q_I_B is None:
            return None
        R_I_B = Rotation.from_quat(self.config.prior_q_I_B).as_matrix()
        return self.R_O_C.T @ dynamics.R_I_O(self.n, t).T @ R_I_B

    def step(self, t: float, cloud: PointCloud | None) -> NavRow:
        """Process one frame taken at time ``t`` (s since the epoch where I and O coincide).

        A frame without data (``cloud`` None) is a prediction-only step, never dropped.
        """
        if self.ekf is not None:
            self.ekf.predict(t)
        R_pred = self.predicted_R_sensor_model(t)
        rects = [] if cloud is None else self.recognise(cloud, R_pred)
        coarse = raw = None
        if rects:
            coarse = consistent_rectangles(rects, R_pred)
            m0, e0 = max(rects, key=lambda p: p[0].n_points)
            raw = coarse_target_pose(m0, e0, None)
        if self.ekf is None:
            if coarse is None:
                return NavRow(t, None, None, 0, "waiting")
            self.ekf = self._start_filter(t, coarse)
            status = "init"
        else:
            status = "predict"
        used = self._update(rects)
        if status == "predict" and used:
            status = "update"
        return NavRow(t, self.ekf.state(), self.ekf.sigmas(), used, status, coarse, raw)

    def run(self, frames: Iterable[tuple[float, PointCloud | None]]) -> list[NavRow]:
        """:meth:`step` over ``(t, cloud)`` pairs in time order; one row per frame."""
        return [self.step(t, cloud) for t, cloud in frames]

    def recognise(
        self, cloud: PointCloud, R_pred: NDArray[np.float64] | None
    ) -> list[tuple[RectangleMeasurement, CatalogueEntry]]:
        """Planes of the frame recognised as catalogue rectangles (each name at most once)."""
        found = find_rectangles(
            cloud,
            list(self.catalogue.values()),
            self.config.plane_config(),
            self.config.rectangle,
            R_pred,
        )
        seen: dict[str, RectangleMeasurement] = {}
        for f in found:
            # Two planes matched to one face: keep the larger (the other is a fragment).
            if f.name is None or (
                f.name in seen and f.measurement.n_points <= seen[f.name].n_points
            ):
                continue
            m = f.measurement
            if self.config.area_weighted_centroid:
                m = replace(m, centroid=area_weighted_centroid(cloud.points[f.plane.inliers]))
            seen[f.name] = m
        return [(m, self.catalogue[name]) for name, m in seen.items()]

    def _start_filter(self, t: float, T_sensor_model: NDArray[np.float64]) -> RelativeNavEKF:
        """Filter initialised from a coarse pose (Δ = 0, so ρ is the B' origin) and priors."""
        R_O_B = self.R_O_C @ T_sensor_model[:3, :3]
        R_I_B = dynamics.R_I_O(self.n, t) @ R_O_B
        c = self.config
        initial = NavState(
            t,
            self.R_O_C @ T_sensor_model[:3, 3],
            np.zeros(3),
            Rotation.from_matrix(R_I_B).as_quat(),
            np.deg2rad(c.init_rate_deg_s),
            np.asarray(c.init_k, dtype=np.float64),
            np.zeros(3),
        )
        return RelativeNavEKF(self.n, self.R_O_C, initial, c.ekf)

    def _update(self, rects: list[tuple[RectangleMeasurement, CatalogueEntry]]) -> int:
        """Attitude then centroid updates of every rectangle; the number of rectangles used."""
        assert self.ekf is not None
        ekf = self.ekf
        used = 0
        # Largest faces first: they constrain the attitude best before the others are gated.
        for m, e in sorted(rects, key=lambda p: -p[0].n_points):
            T = coarse_target_pose(m, e, ekf.predict_pose()[:3, :3])
            R_I_B = dynamics.R_I_O(self.n, ekf.t) @ self.R_O_C @ T[:3, :3]
            ok_att = ekf.update_attitude(
                Rotation.from_matrix(R_I_B).as_quat(), attitude_covariance(m, e, self.config)
            )
            ok_c = ekf.update_centroid(
                e.name, e.centre, m.centroid, centroid_covariance(m, self.config)
            )
            used += int(ok_att or ok_c)
        return used


def nav_table(rows: Sequence[NavRow]) -> tuple[list[str], list[list[float | int | str]]]:
    """Column names (:data:`NAV_COLUMNS`) and one list of values per row."""
    return list(NAV_COLUMNS), [row.values() for row in rows]


def navigate(
    frames: Iterable[tuple[float, PointCloud]],
    catalogue: Sequence[CatalogueEntry],
    mean_motion: float,
    R_O_C: ArrayLike,
    config: NavigationConfig | None = None,
) -> list[NavRow]:
    """One call: run :class:`RelativeNavigator` over ``(t, cloud)`` frames, one row per frame."""
    return RelativeNavigator(catalogue, mean_motion, R_O_C, config).run(frames)
