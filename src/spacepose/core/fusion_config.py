"""Settings of the fused navigation (:mod:`spacepose.core.fused_navigation`): which
measurements enter the filter, how much the tracker's poses are trusted, and what the filter
and the tracker do for each other."""

from __future__ import annotations

from typing import Literal

from pydantic import Field, field_validator

from spacepose.core.config import StageConfig
from spacepose.core.nav_config import NavigationConfig
from spacepose.core.tracker_config import TrackerConfig

Measurements = Literal["rectangles", "registration", "both"]
# Largest pose bias (m) a configuration may give: a tracker's biases are millimetres.
_LARGEST_BIAS_M = 1e3
# Largest factor on the tracker's σ: beyond a million times it a pose is no measurement, and a
# translation's factor of 1e50 drowned the rotation's variances in rounding ("measurement
# covariance must be positive definite"); 1e300 overflowed in a traceback. Neither named the key.
_LARGEST_SIGMA_SCALE = 1e6


class FusionConfig(StageConfig):
    """Settings of :class:`~spacepose.core.fused_navigation.FusedNavigator`: which measurements,
    the filter's and the tracker's."""

    measurements: Measurements = Field(
        "registration",
        description="rectangles (Yu), registration (the tracker's pose) or both in one filter.",
    )
    navigation: NavigationConfig = Field(
        default_factory=NavigationConfig, description="The filter and the rectangle pipeline."
    )
    tracker: TrackerConfig = Field(
        default_factory=lambda: TrackerConfig(range_bias=0.0),
        description="The model-based tracker giving the poses; its range_bias is 0: one offset "
        "shared by every frame is no independent noise of each pose, which the filter would "
        "average away (a consider state for it is not modelled).",
    )
    pose_sigma_scale: float = Field(
        3.0,
        gt=0,
        le=_LARGEST_SIGMA_SCALE,
        description="Factor on the tracker's 1-σ before the pose enters the filter (its "
        "covariance times the square): the tracker's errors are correlated from frame to "
        "frame, which a white-noise filter averages as if independent (×(1+ρ)/(1−ρ) in "
        "variance), and its σ fits its errors differently on each target (tracker NEES median "
        "2.4-2.6 on the default target, 3.0 on satellite_panels, 3.5-3.9 on the Hubble kit, "
        "χ²₆ 5.35). On the orbit run at 25 m (registration, seeds 0-2, 600 frames), the share "
        "of the second half with the filter's NEES inside its 95 % bounds, default / "
        "satellite_panels / Hubble kit: 2: 100 / 100 / 63 % (Hubble seed 2: 0), 3: 59 / 96 / "
        "95 %, 4: 11 / 76 / 95 % (docs/methods.md §2.4). Where bootstrap_poses measures "
        "the factor on the run, the measured one replaces it (and the effective config "
        "says so). With pose_sigma_scale_translation it is the rotation's factor, about the "
        "target's origin.",
    )
    pose_sigma_scale_translation: float | None = Field(
        None,
        gt=0,
        le=_LARGEST_SIGMA_SCALE,
        description="Factor on the translation's 1-σ about the target's origin, "
        "pose_sigma_scale then the rotation's there (None: pose_sigma_scale for the whole "
        "covariance). Where bootstrap_poses runs, both are measured: the rotation's errors "
        "are often correlated where the translation's, their biases taken off, are not, and "
        "one factor sized on the rotation widened the position and the centre of mass "
        '(docs/results.md, "The poses\' biases, taken off").',
    )
    pose_bias_sensor: tuple[float, float, float] = Field(
        (0.0, 0.0, 0.0),
        description="Translation (m) in the sensor's frame taken off each model-based pose "
        "before it enters the filter: a bias the tracker holds there (along the line of "
        "sight, where faces seen at a graze pull every frame alike) is taken for the "
        "target's position. Where bootstrap_poses runs it is measured there and replaces "
        "this.",
    )
    pose_bias_body: tuple[float, float, float] = Field(
        (0.0, 0.0, 0.0),
        description="Translation (m) in the target's model frame taken off each model-based "
        "pose: a bias the tracker holds in the target's frame moves the pose as the centre "
        "of mass would, and the filter takes it for one (satellite_panels at 25 m: -0.5 mm "
        "along x on five seeds of five). Where bootstrap_poses runs it is measured there "
        "and replaces this.",
    )
    bootstrap_poses: bool = Field(
        True,
        description="Where the run's mesh and sensor are known (a simulated run folder, the "
        "fusion experiment), measure pose_sigma_scale on the run instead: the mesh rendered "
        "at the tracker's own poses and tracked again, the errors' variance averaged over "
        "50-frame batches (a parametric bootstrap, docs/methods.md §2.4). One factor for "
        "every target left the filter too cautious on most (NEES inside its bounds on 0-31 "
        "% of the second half on generated spacecraft) and too sure on the Hubble kit at 2.",
    )
    model_free_sigma_scale: float = Field(
        1.0,
        gt=0,
        le=_LARGEST_SIGMA_SCALE,
        description="pose_sigma_scale for the model-free tracker's poses, whose covariance "
        "(with the keyframe chain) is already conservative: median NEES 0.26 of 6 on the orbit "
        "run, seed 0.",
    )
    seed_registration: bool = Field(
        True,
        description="Seed registration with the filter's predicted pose once it has taken "
        "seed_after poses (else the tracker's own constant-velocity prediction).",
    )
    seed_after: int = Field(
        10,
        ge=1,
        description="Pose updates the filter takes before its prediction seeds (and only "
        "after a frame the tracker called ok and the filter took: a filter started on a wrong "
        "pose must not hold the tracker there).",
    )
    use_degraded: bool = Field(
        False,
        description="Let poses the tracker flags degraded (unconfirmed, off the prediction) "
        "into the filter, but for those the prediction held (their pose carries it); by "
        "default only ok poses enter it.",
    )
    restart_after: int = Field(
        10,
        ge=1,
        description="Registration only: consecutive poses the tracker calls ok, the filter's "
        "gate rejects and restart_deg or more from the filter's prediction, before the filter "
        "restarts from the tracker's pose (a start on a wrong coarse registration, e.g. a "
        "near-symmetric twin, is otherwise never undone).",
    )
    model_free_frames: int = Field(
        200,
        ge=10,
        description="Model-free: ok poses collected before the batch estimate of the body "
        "frame (principal axes, centre of mass) starts the filter; the batch grows until its "
        "moments are a rigid body's.",
    )
    restart_deg: float = Field(
        5.0,
        gt=0,
        description="Rotation between a rejected pose and the filter's prediction that counts "
        "towards a restart (smaller disagreements are the tracker's slow errors, which the "
        "filter outlasts).",
    )

    @field_validator("pose_bias_sensor", "pose_bias_body")
    @classmethod
    def _bias_of_a_pose(cls, value: tuple[float, float, float]) -> tuple[float, float, float]:
        """A bias beyond a kilometre is no tracker's bias but a unit mistake (and 1e300
        overflowed the filter's pose)."""
        if max(abs(v) for v in value) > _LARGEST_BIAS_M:
            raise ValueError(f"{value} is beyond {_LARGEST_BIAS_M:g} m: metres expected")
        return value
