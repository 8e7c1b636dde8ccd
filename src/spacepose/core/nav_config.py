"""Settings of the rectangle navigation (:class:`spacepose.core.navigation.RelativeNavigator`)."""

from __future__ import annotations

from pydantic import Field

from spacepose.core.config import StageConfig
from spacepose.core.ekf_config import EKFConfig
from spacepose.core.lost_in_space import LostInSpaceConfig
from spacepose.core.planes import PlaneConfig
from spacepose.core.rectangles import RectangleConfig

__all__ = ["NavigationConfig"]


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
            sigma_chaser_attitude_deg=0.01,
        ),
        description="Filter noise model; sigma_attitude_deg and sigma_centroid are unused (each "
        "rectangle's attitude and centroid covariance is measured: nav_measurements); "
        "sigma_chaser_attitude_deg is the knowledge error of R_O_C (0.01°, a star tracker's), "
        "held as a consider state; sigma_accel is replaced by a scenario's measured one.",
    )
    tilt_scale: float = Field(
        1.0,
        gt=0,
        description="Scale of the normal's σ² = λ_0 / (N λ_lever) from the plane fit "
        "(nav_measurements.attitude_covariance).",
    )
    min_tilt_cosine: float = Field(
        0.25,
        gt=0,
        le=1,
        description="Floor of the incidence cosine: the normal's residual is taken as at least "
        "(rectangle.sigma max(cos θ, min_tilt_cosine))², and a side's foreshortening in the "
        "centroid's pixel pitch at least this (nav_measurements).",
    )
    spin_scale: float = Field(
        0.25,
        gt=0,
        description="Scale of the turn about the normal, σ ≈ a b / (√N (b² − a²)) (the bound of "
        "N random points; a pixel grid does better). Orbit run, seed 0 (394 faces): the errors' "
        "RMS is 1.6 σ at 0.25 (0.39 of the bound), heavy-tailed (6 % beyond 3 σ). 0.4 or 1 let the "
        "start wander (symmetric target, seed 1: 3.3° and 9° off in frame 4, 1.7° at 0.25).",
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
        description="Optional coarse attitude prior (qx, qy, qz, qw) at t = 0, used only "
        "before the filter starts, to tell equal-size faces and symmetric poses apart. Unset: "
        "the lost-in-space start (lost_in_space).",
    )
    lost_in_space: LostInSpaceConfig = Field(
        default_factory=LostInSpaceConfig,
        description="Start without a prior: hypotheses scored on the target model, and the "
        "bank of candidate filters kept while they explain the data equally well.",
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
        description="Weight each point by the area its pinhole pixel covers (∝ depth³ on a "
        "plane): a range image samples a tilted face more densely where it is nearer and more "
        "sparsely off the axis, which pulls the plain mean (about 2 cm at 25 m on the orbit "
        "run; weights ∝ range³ left 4 cm along the wing and a 5 mm bias of the CoM).",
    )

    def plane_config(self) -> PlaneConfig:
        """The plane extraction settings the navigator uses (with the ray share-out)."""
        if not self.ray_share_out:
            return self.plane.model_copy(update={"range_threshold": None})
        if self.plane.range_threshold is not None or self.rectangle.sigma <= 0:
            return self.plane
        return self.plane.model_copy(update={"range_threshold": 3.0 * self.rectangle.sigma})
