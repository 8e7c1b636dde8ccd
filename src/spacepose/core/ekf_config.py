"""Settings of the relative-navigation EKF (:class:`spacepose.core.ekf.RelativeNavEKF`)."""

from __future__ import annotations

from pydantic import Field, ValidationInfo, field_validator

from spacepose.core.config import LARGEST_SQUARED, StageConfig

# Most RK4 steps a prediction may be asked for: the filter's own longest prediction takes 20,000.
_MOST_SUBSTEPS = 20_000


class EKFConfig(StageConfig):
    """Noise model, initial uncertainty and gating of :class:`RelativeNavEKF` (SI units)."""

    sigma_accel: float = Field(1e-6, ge=0, description="Process noise on ρ̈, m/s²/√Hz.")
    sigma_angular_accel: float = Field(1e-6, ge=0, description="Process noise on ω̇, rad/s²/√Hz.")
    sigma_inertia_walk: float = Field(0.0, ge=0, description="Random walk of k_x, k_y, 1/√s.")
    init_sigma_position: float = Field(0.05, gt=0, description="Initial σ of ρ, m.")
    init_sigma_velocity: float = Field(0.01, gt=0, description="Initial σ of ρ̇, m/s.")
    init_sigma_attitude_deg: float = Field(2.0, gt=0, description="Initial σ of attitude, deg.")
    init_sigma_rate_deg_s: float = Field(1.0, gt=0, description="Initial σ of ω, deg/s.")
    init_sigma_inertia: float = Field(0.3, gt=0, description="Initial σ of k_x and k_y.")
    init_sigma_com: float = Field(0.1, gt=0, description="Initial σ of the CoM offset Δ, m.")
    sigma_feature: float = Field(
        0.002,
        gt=0,
        description="Prior σ of a rectangle's location error δ_j, m (makes Δ "
        "observable: a common shift of Δ and every δ_j is invisible to the measurements).",
    )
    sigma_centroid: float = Field(0.005, gt=0, description="Centroid measurement σ, m.")
    sigma_attitude_deg: float = Field(0.2, gt=0, description="Attitude measurement σ, deg.")
    sigma_chaser_attitude_deg: float = Field(
        0.0,
        ge=0,
        description="1σ per axis of the knowledge error of the chaser attitude R_O_C, deg "
        "(a star tracker's); positive adds the consider state φ, 0 takes R_O_C as exact.",
    )
    gate_probability: float = Field(
        0.9999, gt=0, le=1, description="χ² gate on the innovation; 1 disables gating."
    )
    substeps: int = Field(
        10,
        ge=1,
        # As many as the filter takes over the longest gap it predicts across (ekf's
        # _LONGEST_TURN_RAD in _STEP_RAD steps): 10**9 ran for ever, its first frame unfinished.
        le=_MOST_SUBSTEPS,
        description="Fewest RK4 steps per prediction interval (more over long gaps).",
    )

    @field_validator("*", mode="after")
    @classmethod
    def _square_stays_finite(cls, value: object, info: ValidationInfo) -> object:
        # The filter multiplies variances by each other: 1e160 overflowed in a traceback, 1e300
        # gave NaN quaternions after numpy's overflow warnings.
        if "sigma" in info.field_name and isinstance(value, float) and value > LARGEST_SQUARED:
            raise ValueError(
                f"{value:g} is too large a sigma: the filter's products of its square overflow "
                f"(at most {LARGEST_SQUARED:g})"
            )
        return value
