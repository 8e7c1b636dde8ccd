"""Settings of the rectangle navigation (:class:`spacepose.core.navigation.RelativeNavigator`)."""

from __future__ import annotations

from pydantic import Field, field_validator

from spacepose.core.config import StageConfig, square_stays_finite
from spacepose.core.ekf_config import EKFConfig
from spacepose.core.lost_in_space import LostInSpaceConfig
from spacepose.core.nav_state import params_from_k
from spacepose.core.planes import PlaneConfig
from spacepose.core.rectangles import RectangleConfig

# Largest floor of a centroid's σ (m): no face is measured to worse than a kilometre.
_LARGEST_CENTROID_SIGMA_M = 1e3

__all__ = [
    "NavigationConfig",
    "NavigatorEKFConfig",
    "NavigatorPlaneConfig",
    "NavigatorRectangleConfig",
]


class NavigatorPlaneConfig(PlaneConfig):
    """:class:`PlaneConfig` with the navigator's default slab (the flash LiDAR's 1 cm noise);
    a config file's ``plane`` block changes only the keys it names."""

    distance_threshold: float = Field(0.03, gt=0)


class NavigatorRectangleConfig(RectangleConfig):
    """:class:`RectangleConfig` with the navigator's default range noise."""

    sigma: float = Field(0.01, ge=0)


class NavigatorEKFConfig(EKFConfig):
    """:class:`EKFConfig` with the navigator's defaults (the orbit run's flash LiDAR at 25 m);
    a config file's ``ekf`` block changes only the keys it names (a block naming sigma_accel
    alone had rebuilt the rest from EKFConfig's defaults: the chaser attitude taken as exact,
    the filter 19σ off across the line of sight)."""

    sigma_accel: float = Field(3e-8, ge=0, description="Process noise on ρ̈, m/s²/√Hz.")
    sigma_angular_accel: float = Field(3e-8, ge=0, description="Process noise on ω̇, rad/s²/√Hz.")
    sigma_centroid: float = Field(0.01, gt=0, description="Centroid measurement σ, m.")
    init_sigma_position: float = Field(0.1, gt=0, description="Initial σ of ρ, m.")
    init_sigma_attitude_deg: float = Field(3.0, gt=0, description="Initial σ of attitude, deg.")
    init_sigma_rate_deg_s: float = Field(3.0, gt=0, description="Initial σ of ω, deg/s.")
    sigma_feature: float = Field(
        0.005, gt=0, description="Prior σ of a rectangle's location error δ_j, m."
    )
    sigma_chaser_attitude_deg: float = Field(
        0.01, ge=0, description="1σ per axis of the knowledge error of R_O_C, deg."
    )


class NavigationConfig(StageConfig):
    """Settings of :class:`RelativeNavigator` (defaults: the flash LiDAR of the orbit run)."""

    plane: NavigatorPlaneConfig = Field(
        default_factory=NavigatorPlaneConfig,
        description="RANSAC plane extraction; thickness about 3σ of the range noise. Its "
        "range_threshold, when unset, is 3 rectangle.sigma (see ray_share_out).",
    )
    rectangle: NavigatorRectangleConfig = Field(
        default_factory=NavigatorRectangleConfig,
        description="Recognition; sigma is the range noise removed from the eigenvalues.",
    )
    ekf: NavigatorEKFConfig = Field(
        default_factory=NavigatorEKFConfig,
        description="Filter noise model; sigma_attitude_deg and sigma_centroid are unused (each "
        "rectangle's attitude and centroid covariance is measured: nav_measurements); "
        "sigma_chaser_attitude_deg is the knowledge error of R_O_C (0.01°, a star tracker's), "
        "held as a consider state. A run's scenario gives sigma_accel (measured from what CW "
        "misses) and sigma_chaser_attitude_deg where a config file does not "
        "(tools.navigation_config_io.with_run_settings).",
    )
    range_sigma: float | None = Field(
        None,
        gt=0,
        description="Range noise σ of the sensor, m: the plane slab is 3σ and the rectangles' "
        "sigma σ, where plane.distance_threshold and rectangle.sigma are not set themselves "
        "(with_range_sigma). Unset: a simulated run's scenario gives its sensor's σ at the "
        "standoff, else it is measured on the first frame with points "
        "(spacepose.core.scale.range_noise). The defaults, 3 cm and 1 cm, fit the orbit run's "
        "flash LiDAR alone: at 3 cm of noise the wing came out as two parallel planes and the "
        "filter diverged, 5 m and 129° off at the end of 200 frames.",
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
        1e-4,
        gt=0,
        # A floor of 1e50 m drowned the faces' in-plane σ in rounding ("measurement covariance
        # must be positive definite", naming neither the key nor the file); 1e300 overflowed.
        le=_LARGEST_CENTROID_SIGMA_M,
        description="Floor of the centroid σ along the face normal, m (at most a kilometre).",
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

    def with_range_sigma(self, sigma: float) -> NavigationConfig:
        """This config for a sensor of range noise ``sigma`` (m): ``range_sigma`` set, and the
        plane slab (3σ) and the rectangles' sigma (σ) where they are not set themselves."""
        update: dict[str, object] = {"range_sigma": sigma}
        if "distance_threshold" not in self.plane.model_fields_set:
            update["plane"] = self.plane.model_copy(update={"distance_threshold": 3.0 * sigma})
        if "sigma" not in self.rectangle.model_fields_set:
            update["rectangle"] = self.rectangle.model_copy(update={"sigma": sigma})
        return self.model_copy(update=update)

    _squares_finite = field_validator(
        "range_sigma", "tilt_scale", "spin_scale", "min_attitude_sigma_deg"
    )(square_stays_finite)

    @field_validator("init_k")
    @classmethod
    def _rigid_body_ratios(cls, k: tuple[float, float, float]) -> tuple[float, float, float]:
        """Ratios of positive principal moments: others were refused when the filter started,
        in a message that named neither ``init_k`` nor the file."""
        params_from_k(k)
        return k

    @field_validator("plane", "rectangle", "ekf", mode="before")
    @classmethod
    def _navigator_defaults(cls, value: object) -> object:
        # A base config given in code (PlaneConfig(range_threshold=0.02)) keeps the navigator's
        # defaults for what it leaves unset, as a config file's block does.
        if isinstance(value, StageConfig):
            return value.model_dump(exclude_unset=True)
        return value

    def plane_config(self) -> PlaneConfig:
        """The plane extraction settings the navigator uses (with the ray share-out)."""
        if not self.ray_share_out:
            return self.plane.model_copy(update={"range_threshold": None})
        if self.plane.range_threshold is not None or self.rectangle.sigma <= 0:
            return self.plane
        return self.plane.model_copy(update={"range_threshold": 3.0 * self.rectangle.sigma})
