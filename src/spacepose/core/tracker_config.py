"""The tracker's configuration: a few meaningful knobs, every length a multiple of the data's scale.

Lengths are never metres here. They are multiples of the voxel edge ``v`` derived from the first
frame (:mod:`spacepose.core.scale`) or of the target's RMS radius ``R``; a rotation bound given
"in voxels" is the rotation that moves a point at the radius by that many voxels (``f·v/R`` rad).
The factors reproduce the lab run's former metre values at 1.2 m (v ≈ 6 mm, R ≈ 0.25 m), which a
grid over range, target, noise and motion then checked (README, robustness table). The lengths
inside the nested stage configs (ICP and GICP gates, normal and FPFH radii, RANSAC gate, MLS
support) are replaced by the derived ones when the tracker runs; ``spacepose track`` writes them
beside its output, in ``EST.scale.json``.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from pydantic import Field, PositiveFloat, field_validator, model_validator

from spacepose.core.background import BackgroundConfig
from spacepose.core.config import StageConfig, square_stays_finite
from spacepose.core.fpfh import FPFHConfig
from spacepose.core.gicp import GICPConfig
from spacepose.core.icp import ICPConfig
from spacepose.core.jicp import JICPConfig
from spacepose.core.mls import MLSConfig
from spacepose.core.normals import NormalsConfig
from spacepose.core.ransac import RansacConfig

# Stopping tolerances of the fine registrations, in voxels: ICP's change of inlier RMSE and
# GICP's translation step (about 1 µm and 10 µm at the lab's 6 mm voxel, their defaults in
# metres). In metres they made a run in millimetres, or ten times the size, stop elsewhere
# (2.7e-4 rad apart on the lab run at ×10 with finer keyframes, whose slower convergence the
# RMSE test cut short).
_ICP_RMSE_TOLERANCE = 1.6e-4
_GICP_STEP_TOLERANCE = 1.6e-3


class KeyframeConfig(StageConfig):
    """When a model-free tracker promotes the current frame to a keyframe.

    Attributes
    ----------
    min_fitness
        Promote when the fitness against the current keyframe falls below this (overlap drops).
    max_translation
        Promote when the target centroid moved more than this many radii since the keyframe.
    max_rotation_deg
        Promote when the target turned more than this (degrees) since the keyframe.
    stale_fitness
        A degraded frame (one whose own registration passed the lost bounds) is promoted too
        when its fitness against the keyframe falls below this: otherwise a run that degrades
        keeps a keyframe it can no longer see and every later frame is lost.
    """

    min_fitness: float = Field(0.85, ge=0, le=1)
    max_translation: PositiveFloat = 0.16
    max_rotation_deg: PositiveFloat = 4.0
    stale_fitness: float = Field(0.7, ge=0, le=1)


class KeyframeGraphConfig(StageConfig):
    """The keyframe graph (method ``keyframe``, ours; docs/methods.md §5.5).

    Attributes
    ----------
    window
        Keyframes in the graph plus the new frame: the frame is registered to the last
        ``window − 1`` keyframes.
    registration
        Pairwise registration: ``"icp"`` (with ``icp``) or ``"gicp"`` (with ``gicp``).
    icp, gicp
        Configs of the pairwise registration (their gates are derived).
    weighting
        ``"information"``: each edge weighted by the inverse of its covariance; ``"equal"``:
        every edge alike.
    """

    window: int = Field(4, ge=2, le=10)
    registration: Literal["icp", "gicp"] = "icp"
    icp: ICPConfig = ICPConfig(method="point_to_plane", max_iterations=10)
    gicp: GICPConfig = GICPConfig()
    weighting: Literal["information", "equal"] = "information"


# The tracker's methods: the pairwise registrations onto the current keyframe, Li's J-ICP, and
# our keyframe graph.
Method = Literal["point_to_point", "point_to_plane", "gicp", "jicp", "keyframe"]


class HealthConfig(StageConfig):
    """Bounds of the per-frame health check, in voxels ``v`` unless named otherwise.

    A frame breaking any ``lost`` bound is lost (its pose is not used); one breaking only ``ok``
    bounds is degraded (used and flagged). Rotation bounds are displacements at the radius.

    Attributes
    ----------
    min_points
        Fewer points than this after preprocessing: lost.
    ok_fitness, lost_fitness
        Share of frame points with a reference point within the correspondence gate.
    model_fitness
        The ok fitness against a model. A frame of the target alone fits a model nearly whole
        at the true pose: 1.00 for the default orbit target at 25 m, 0.89 for the Hubble kit
        when the gate is down to 75 mm (thin parts the voxelised model misses). A wrong but
        stable optimum (the satellite half a turn away, or slid along its wing) fits 0.41-0.75
        from a view that misses the parts that tell them apart. A model-based frame below
        this, or above the ok RMSE, is degraded, and a coarse pose is tried as well. The
        margin is thin: the paper-like ToF camera (flying pixels, multipath) at 0.5 m fits the
        lab mock-up 0.77-0.79 at the true pose (1 mm off), so those frames are degraded.
    ok_rmse, lost_rmse
        Inlier RMSE of the fine registration (voxels, times the factor by which the measured
        residual noise widens the fine gate).
    ok_condition, lost_condition
        Condition number of the registration information at the cloud centroid, rotations
        taken as displacements at the radius (unit-free). The lab mock-up gives 45-100 at 0.5,
        1.2 and 3 m; a plane, which leaves three directions unobserved, 55-1.3e4 by its noise
        (its normals' noise puts a false information on them). The surfaces' condition at a
        coarse scale (:mod:`spacepose.core.degeneracy`: medians 7-262 and 99th percentiles
        15-7.2e3 over the seed-0 grid's targets, infinite on a plane, a sphere or a cylinder)
        is held to ``lost_condition``: above it the frame is degraded and its σ widened along
        the free directions.
    ok_sigma_translation, ok_sigma_rotation
        Largest 1-σ of the frame's own registration (voxels; rotation at the radius).
    ok_prediction_translation, ok_prediction_rotation
        Largest disagreement with the motion model's prediction (voxels), widened to
        ``model_error_sigmas`` times the model's observed error when that is larger (motion
        that is not constant velocity is input, not a fault); ``lost_prediction_factor`` times
        the bound is lost.
    ok_step_translation, ok_step_rotation
        Largest point-to-plane Gauss-Newton step from the registered pose (voxels): a
        registration that stopped off the surface optimum is not ok.
    ok_structure
        Largest residual structure of the registration onto the latest reference
        (:func:`~spacepose.core.residual_structure.residual_structure`, unit-free: 1 for white
        residuals). Part of the cloud moving otherwise (the lab's turntable and plinth under a
        turning target) leaves most of the surface a residual of its own sign: median 10 over
        the frames of the robustness grid's wall-and-table cells at 0.5-3 m that were ok while
        off by more than 5 σ (4.6 at 6 and 25 m), against at most 4.6 over its clean cells'
        right ok frames (docs/methods.md §5.3). Model-free only: against a model such a part
        has no surface within the gate (the fitness bound applies), and what is left is the
        sensor's own bias (the flash LiDAR's edge pixels). Set on simulated sensors: the real
        LiDAR pair of data/real gives 5.8-9.3 at its ICP optimum, so raise it for a real
        scanner whose errors are correlated over the surface.
    ok_shared_structure
        None (the default): off. Else a structure above ``ok_structure`` counts only where
        neighbouring cells share their offsets beyond this
        (:func:`~spacepose.core.residual_structure.shared_structure`, about 0 for white
        noise): a second motion biases whole parts, while a camera that filters its depth
        shares noise between nearby pixels only, which raised the lab frames' structure to
        4-15 at 1.2 m (a Gaussian of 2-4 pixels) with its shared part at most 1.1; 1 is the
        value for such a camera. Off by default: on the robustness grid's wall-and-table cells
        (seed 0) a bound of 1 let 40 more frames be ``ok`` while off by more than 5 σ
        (docs/methods.md §5.3).
    ok_influence
        Largest shift of the pose, in σ of its own covariance, when one part of the surface
        (a cube of the object's RMS radius) is left out of the registration onto the latest
        reference (:func:`~spacepose.core.part_influence.part_influence`); the bound also
        grows with the part's leverage, so that white noise alone passes it with probability
        0.999. A part that moves otherwise pulls the pose by many σ, while noise correlated
        over the surface widens the shift and the covariance together (docs/methods.md §5.3).
        Model-free only, as the structure.
    max_motion
        Largest motion (radii; rotation: radians) of the target between two frames while its
        velocity is unknown (a single pose in the history).
    model_error_sigmas
        See the prediction bounds.
    max_reference_factor
        Model-free: a frame further from its keyframe than this many times the keyframe
        promotion thresholds is at best degraded.
    """

    min_points: int = Field(100, ge=3)
    ok_fitness: float = Field(0.6, ge=0, le=1)
    lost_fitness: float = Field(0.3, ge=0, le=1)
    model_fitness: float = Field(0.8, ge=0, le=1)
    ok_rmse: PositiveFloat = 0.67
    lost_rmse: PositiveFloat = 1.0
    ok_condition: PositiveFloat = 1e3
    lost_condition: PositiveFloat = 1e4
    ok_sigma_translation: PositiveFloat = 0.167
    ok_sigma_rotation: PositiveFloat = 0.073
    ok_prediction_translation: PositiveFloat = 1.67
    ok_prediction_rotation: PositiveFloat = 1.09
    lost_prediction_factor: float = Field(4.0, ge=1)
    ok_step_translation: PositiveFloat = 0.083
    ok_step_rotation: PositiveFloat = 0.073
    ok_structure: float = Field(5.0, gt=1)
    ok_shared_structure: PositiveFloat | None = None
    ok_influence: PositiveFloat = 3.0
    max_motion: PositiveFloat = 0.5
    model_error_sigmas: PositiveFloat = 3.0
    max_reference_factor: float = Field(2.0, ge=1)

    @model_validator(mode="after")
    def _ok_inside_lost(self) -> HealthConfig:
        # An ok bound beyond its lost bound would let a frame be both: the statuses would
        # hang on the order of the checks.
        for name, ok, lost in (
            ("fitness", self.lost_fitness, self.ok_fitness),
            ("rmse", self.ok_rmse, self.lost_rmse),
            ("condition", self.ok_condition, self.lost_condition),
        ):
            if ok > lost:
                first, second = ("lost", "ok") if name == "fitness" else ("ok", "lost")
                raise ValueError(f"{first}_{name} {ok:g} must not exceed {second}_{name} {lost:g}")
        return self


class TrackerConfig(StageConfig):
    """Every parameter of the tracker; no length in metres unless the user sets ``voxel_size``.

    Attributes
    ----------
    method
        Fine registration: ``"point_to_point"`` (Li's Eq. 6 ICP), ``"point_to_plane"`` (ICP)
        or ``"gicp"``, each onto the current keyframe; ``"jicp"``, Li's J-ICP (the frame
        registered to the two frames before it, the two estimates averaged by Eq. 9 and the
        poses chained; ``jicp``); ``"keyframe"`` (ours, the default), the keyframe graph (the
        frame registered to the last ``keyframe_graph.window − 1`` keyframes and the window
        solved as a pose graph; ``keyframe_graph``).
    points_per_frame
        Points a frame keeps after downsampling: the voxel edge follows from it and the first
        frame's spacing (:func:`spacepose.core.scale.voxel_for`). 3,000 gives 6 mm on the lab
        run at 1.2 m.
    voxel_size
        Voxel edge (m) to use instead of the derived one.
    keyframe_density
        A keyframe is downsampled this many times finer than the frames registered onto it
        (never finer than the point spacing) and smoothed onto its surface (methods.md §5.4);
        1 keeps the frame's own cloud. 3 (against 1) took the robustness grid's false ``ok``
        frames from 92 to 20 (clean cells) and 218 to 101 (wall and table), and the lab run's
        pitch and yaw errors about 45 % down, while the centroid's drift along the keyframe
        chain doubles and a full-resolution frame's step costs 2.6 times as much (README).
    stray_share
        A voxel of a frame whose block of 3×3×3 voxels holds fewer raw points than this share
        of the frame's median block is dropped, and with it the keyframe's finer points a
        voxel from every kept one: a flying pixel or a stray return, not a surface
        (:func:`spacepose.core.voxel.stray_voxels`). 0 keeps every voxel. At 1/16 a surface
        more than about four times farther than the frame's median range goes too (methods.md
        §5.1).
    gate
        Correspondence gate of the fine registration (voxels). After the motion model's
        prediction the misalignment is well below a voxel; a wider gate lets silhouette points
        pair with the wrong surface (1.7 v doubled the lab run's yaw error).
    coarse_voxel
        Voxel of the sparse cloud behind FPFH + RANSAC (voxels); its normals use a radius of
        2, FPFH 5 and RANSAC's gate 1.5 of these.
    isolate_target
        Keep the target's points only (:mod:`spacepose.core.segmentation`): the nearest
        object of the first frame, then the points within ``crop_margin`` times its bounding
        radius (plus the motion model's error) of where the prediction puts it. Model-free,
        the whole scene is followed beside it until the data say which is the target: when
        the object moves with the rest of the scene (a camera carried through a room), the
        whole scene is (:mod:`spacepose.core.scene_motion`); a first frame with nothing
        beside the object is not cropped.
    crop_margin
        See ``isolate_target``: the first frame shows part of the target, and its centroid is
        off the target's centre.
    use_background_removal
        Remove walls, floor and turntable around the target first (``background``; the lab
        settings, in metres).
    use_mls
        mpp-MLS (denoise + downsample + normals) instead of voxel downsampling + PCA normals;
        its voxel is ``v`` and its kernel width ``mls_h`` voxels.
    mls_h
        mpp-MLS kernel width (voxels).
    covariance_scale
        Factor on every registration covariance from the information matrix (1: as computed).
    floor_translation, floor_rotation
        1-σ added to every registration, isotropically about the target centroid (voxels;
        rotation at the radius): the systematic error the information matrix cannot see
        (two different voxel samplings of one surface, normals near edges).
    floor_motion
        1-σ added to each reported pose per unit of motion between the frame and its
        reference (rotation angle, centroid displacement): the bias that grows with the motion
        (on the lab run a keyframe chain drifted about 0.015° per 4° keyframe, in one
        direction, 3.6 of its noise-only σ). It enters the reported covariance only, not the
        weights of the pose graph (there it made the lab run's y error 2-3× worse).
    range_bias
        Against a model: 1-σ of the sensor's unknown constant range offset, in units of its
        measured range noise; each reported pose's covariance carries its effect, a shift of
        the target along the line of sight, and that of a range error changing with range
        (a ToF camera's wiggling) that the residuals show (methods.md §5.3). A model-free pose
        relates two frames of one sensor and cancels both. 0: a sensor calibrated beyond its
        noise (neither is carried).
    """

    method: Method = "keyframe"
    # Fewer leaves every frame below health.min_points (100 by default): lost.
    points_per_frame: int = Field(3000, ge=100)
    voxel_size: PositiveFloat | None = None
    keyframe_density: float = Field(3.0, ge=1.0)
    stray_share: float = Field(1 / 16, ge=0.0, lt=1.0)
    gate: PositiveFloat = 0.83
    coarse_voxel: PositiveFloat = 2.0
    isolate_target: bool = True
    crop_margin: float = Field(1.2, ge=1)
    use_background_removal: bool = False
    use_mls: bool = False
    mls_h: PositiveFloat = 1.67
    covariance_scale: PositiveFloat = 1.0
    floor_translation: float = Field(0.0083, ge=0)
    floor_rotation: float = Field(0.00145, ge=0)
    floor_motion: float = Field(0.01, ge=0)
    range_bias: float = Field(1.0, ge=0)

    # Factors the tracker squares (σ floors, the range bias, the crop margin, the covariance's
    # scale): 1e160 ended ``track`` in an OverflowError traceback, and a covariance scale of
    # 1e300 made every frame "degraded" at σ of 1e146 without a word.
    _squares_finite = field_validator(
        "crop_margin",
        "floor_translation",
        "floor_rotation",
        "floor_motion",
        "range_bias",
        "covariance_scale",
    )(square_stays_finite)

    background: BackgroundConfig = BackgroundConfig()
    mls: MLSConfig = MLSConfig()
    normals: NormalsConfig = NormalsConfig(k=15)
    coarse_normals: NormalsConfig = NormalsConfig(k=30)
    fpfh: FPFHConfig = FPFHConfig(max_nn=100)
    ransac: RansacConfig = RansacConfig(mutual_filter=False)
    icp: ICPConfig = ICPConfig(method="point_to_plane")
    gicp: GICPConfig = GICPConfig()
    jicp: JICPConfig = JICPConfig()
    keyframe_graph: KeyframeGraphConfig = KeyframeGraphConfig()
    keyframe: KeyframeConfig = KeyframeConfig()
    health: HealthConfig = HealthConfig()


@dataclass(frozen=True)
class StageLengths:
    """The tracker's stage configs with their lengths in metres, for one scale.

    Attributes
    ----------
    voxel, gate, coarse_voxel
        Voxel edge, fine correspondence gate and coarse voxel edge (m).
    floor_translation, floor_rotation, floor_motion
        σ floor (m, rad, fraction of the motion) of every registration.
    icp, gicp, jicp, keyframe_graph, normals, coarse_normals, fpfh, ransac, mls
        The stage configs with every length set.
    """

    voxel: float
    gate: float
    coarse_voxel: float
    floor_translation: float
    floor_rotation: float
    floor_motion: float
    icp: ICPConfig
    gicp: GICPConfig
    jicp: JICPConfig
    keyframe_graph: KeyframeGraphConfig
    normals: NormalsConfig
    coarse_normals: NormalsConfig
    fpfh: FPFHConfig
    ransac: RansacConfig
    mls: MLSConfig

    def to_dict(self) -> dict[str, float]:
        """The derived lengths (m, rad) a run used, for its folder (``EST.scale.json``)."""
        return {
            "voxel_m": self.voxel,
            "gate_m": self.gate,
            "coarse_voxel_m": self.coarse_voxel,
            "floor_translation_m": self.floor_translation,
            "floor_rotation_rad": self.floor_rotation,
            "icp_rmse_tolerance_m": self.icp.relative_rmse,
        }


def stage_lengths(config: TrackerConfig, voxel: float, radius: float) -> StageLengths:
    """Every length of the tracker for a voxel edge ``voxel`` and target radius ``radius`` (m)."""
    gate = config.gate * voxel
    coarse = config.coarse_voxel * voxel

    def gated(stage: ICPConfig | GICPConfig) -> ICPConfig | GICPConfig:
        update = {"max_correspondence_distance": gate}
        if isinstance(stage, ICPConfig):
            update["relative_rmse"] = _ICP_RMSE_TOLERANCE * voxel
        else:
            update["translation_tolerance"] = _GICP_STEP_TOLERANCE * voxel
        return stage.model_copy(update=update)

    def pairs_gated(stage: JICPConfig | KeyframeGraphConfig) -> JICPConfig | KeyframeGraphConfig:
        return stage.model_copy(update={"icp": gated(stage.icp), "gicp": gated(stage.gicp)})

    return StageLengths(
        voxel=voxel,
        gate=gate,
        coarse_voxel=coarse,
        floor_translation=config.floor_translation * voxel,
        floor_rotation=config.floor_rotation * voxel / radius,
        floor_motion=config.floor_motion,
        icp=gated(config.icp),
        gicp=gated(config.gicp),
        jicp=pairs_gated(config.jicp),
        keyframe_graph=pairs_gated(config.keyframe_graph),
        normals=config.normals,
        coarse_normals=config.coarse_normals.model_copy(update={"radius": 2.0 * coarse}),
        fpfh=config.fpfh.model_copy(update={"radius": 5.0 * coarse}),
        ransac=config.ransac.model_copy(update={"max_correspondence_distance": 1.5 * coarse}),
        mls=config.mls.model_copy(update={"voxel_size": voxel, "h": config.mls_h * voxel}),
    )


def pairwise_kind(method: str, stages: TrackerConfig | StageLengths) -> Literal["icp", "gicp"]:
    """The pairwise registration a method runs: GICP for ``gicp``, the ``registration`` of
    the J-ICP or keyframe-graph stage for those, ICP otherwise."""
    if method == "gicp":
        return "gicp"
    if method == "jicp":
        return stages.jicp.registration
    if method == "keyframe":
        return stages.keyframe_graph.registration
    return "icp"
