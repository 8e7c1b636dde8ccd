"""What the tracker registers of a frame (docs/methods.md §5.1, §5.7).

:class:`FramePreparer` turns a raw frame into a :class:`~spacepose.core.keyframes.PreparedCloud`:
optional background removal, the target's points (:mod:`spacepose.core.segmentation`: the
nearest object on the first frame, then a sphere around where the prediction puts it), then
mpp-MLS or voxel downsampling at the voxel the first usable frame's spacing gives
(:mod:`spacepose.core.scale`), and the per-point covariances GICP reuses. It also prepares a
reference model at the frame's voxel. Every length it uses is derived on the first frame.
"""

from __future__ import annotations

import os
import warnings
from dataclasses import replace

import numpy as np
from numpy.typing import ArrayLike, NDArray

from spacepose.core import se3
from spacepose.core.background import remove_background
from spacepose.core.cloud import PointCloud, as_cloud, check_scale
from spacepose.core.correspondences import find_correspondences
from spacepose.core.gicp_covariances import compute_covariances
from spacepose.core.keyframes import Keyframe, PreparedCloud
from spacepose.core.mls import mpp_mls
from spacepose.core.moments import on_a_line
from spacepose.core.motion import Prediction
from spacepose.core.neighbors import knn
from spacepose.core.normals import estimate_normals, plane_offsets
from spacepose.core.reach import within_reach
from spacepose.core.scale import DataScale, derive_scale, point_spacing, sensor_frame_problem
from spacepose.core.scene_motion import SceneTest
from spacepose.core.segmentation import TargetRegion, crop_sphere, nearest_object, region_of
from spacepose.core.target_cut import cut_to_target
from spacepose.core.tracker_config import StageLengths, TrackerConfig, pairwise_kind, stage_lengths
from spacepose.core.viewpoint import facing_bin
from spacepose.core.voxel import voxel_cells, voxel_downsample
from spacepose.errors import DegenerateGeometryError, InputError, SpaceposeWarning

# A crop: center (3,) and radius (m), sensor frame.
Sphere = tuple[NDArray[np.float64], float]
# The model culled at every pose keeps one point per cell of the frame's voxel over this (or
# over ``keyframe_density`` when larger): its points stay on the mesh, with the mesh's normals.
_MODEL_THINNING = 3.0
# The name of a frame given as an array (a file reader's names its file).
_GIVEN = "frame"


class FramePreparer:
    """Prepares frames (and a model) for registration; holds the lengths of the first frame.

    Parameters
    ----------
    config
        The tracker's config.
    model
        The reference model (target frame), or None for model-free tracking: its bounding
        sphere is then the target's region.
    workers
        Threads of the searches.
    """

    def __init__(self, config: TrackerConfig, model: PointCloud | None, workers: int) -> None:
        self.config = config
        self.workers = workers
        self.scale: DataScale | None = None
        self.lengths: StageLengths | None = None
        self.region: TargetRegion | None = None
        # Model-free, while it is not known whether the target is the nearest object or the
        # whole scene (core.scene_motion): the test, and the last frame's points to tell by.
        self.scene_test: SceneTest | None = None
        self.last_frame: PointCloud | None = None
        # Model-free: the first frame held nothing beside the object, so nothing is cropped.
        self.alone = False
        self._model_region = None if model is None else region_of(model.points)
        self._covariances = pairwise_kind(config.method, config) == "gicp"

    def prepare(
        self,
        cloud: PointCloud | ArrayLike | None,
        T_predicted: NDArray[np.float64] | None,
        slack: float = 0.0,
    ) -> PreparedCloud:
        """The prepared frame.

        Parameters
        ----------
        cloud
            The raw frame, sensor frame.
        T_predicted
            (4, 4) predicted ``T_sensor_target``, or None (the nearest object is then found
            anew).
        slack
            Added to the crop sphere's radius (m): the prediction's uncertainty at the edge.

        Raises
        ------
        InputError
            No points, or too few after preprocessing.
        """
        cfg = self.config
        if cloud is None:
            raise InputError("no points")
        pc = as_cloud(cloud, _GIVEN, say_dropped=False)
        sphere = self._predicted_sphere(T_predicted, slack)
        # A first frame is checked for a line, a background is removed from the whole frame,
        # and the test of whether the target is the whole scene reads the whole frame.
        whole = self.scale is None or cfg.use_background_removal or self.scene_test is not None
        if sphere is None or whole:
            pc, sphere = self._whole_frame(pc, T_predicted, slack)
        # Cropped once, the returns kept in the same compiled pass (a raw 900k-point frame is
        # read once): the frame's downsampling, the grid moved half a voxel and a keyframe's
        # finer cloud then read the target's points only.
        pc = _cropped(pc, sphere, self.workers)
        if self.scale is None:
            self._set_scale(pc)
        L = self.lengths
        raw = pc
        if cfg.use_mls:
            pc = mpp_mls(pc, L.mls, workers=self.workers)
        else:
            pc = voxel_downsample(pc, L.voxel, stray_share=cfg.stray_share)
        if len(pc) < cfg.health.min_points:
            raise InputError(
                f"{len(pc)} points after preprocessing (< {cfg.health.min_points})", pc.source
            )
        prepared = self.with_covariances(pc)
        if not cfg.use_mls and cfg.keyframe_density > 1.0:
            prepared.raw = raw
        return prepared

    def keyframe_cloud(self, prepared: PreparedCloud) -> PreparedCloud | None:
        """The frame as a finer registration reference, with normals: downsampled again from
        its raw points at the voxel over ``keyframe_density`` (not below the point spacing),
        each point given the normal of its nearest point of ``prepared`` (estimated on it if
        it has none) and moved onto the plane of its neighbourhood when the noise explains its
        offset from it. None after mpp-MLS, for Li's J-ICP, at a density of 1, or when the
        frame has nothing finer to give (its voxel within twice its spacing: a sparse
        flash-LiDAR frame).

        A source registered onto a reference as coarse as itself pairs each point with a
        centroid up to half a voxel away, whose tangent plane misses a curved or edged surface
        under it; and voxel centroids cut corners, differently as the object moves through the
        sensor's grid: both become a pose bias (methods.md §5.4). A finer reference has noisier
        points, and a nearest neighbour picked among them leans towards the source (the pose
        the registration starts from); on the neighbourhood's plane that noise is averaged out.
        The source keeps the voxel: its count sets the step's cost.
        """
        L = self.lengths
        voxel = max(L.voxel / self.config.keyframe_density, self.scale.spacing)
        # Li's J-ICP registers a frame onto the frames before it as they are (methods.md §1.6):
        # onto finer clouds its point-to-point pairs took the lab run's mean error from 4.8 to
        # 27 mm (seed 0).
        if prepared.raw is None or voxel > L.voxel / 2.0 or self.config.method == "jicp":
            return None
        pc = voxel_downsample(prepared.raw, voxel)
        # Each point takes the normal of its nearest frame-voxel point: the finer cloud's own
        # neighbourhoods are D² times smaller, and their noisy normals gave a plane sliding in
        # itself in-plane information it does not have (condition number 180 instead of 1.6e4).
        frame = prepared.with_normals(L.normals, self.workers).cloud
        # A point a voxel from every frame point is a stray the frame's downsampling dropped
        # (the block rule cannot tell one at a voxel near the spacing: 640×480 lab frames kept
        # 525 flying pixels so; between 0.75 and 1.5 voxels the count moved by 2).
        near, nearest, _ = find_correspondences(prepared.tree, pc.points, L.voxel, self.workers)
        if len(near) < len(pc):
            pc = pc.select(near)
        pts = pc.points
        n = frame.normals[nearest]
        # Neighbourhoods within four frame voxels (a surface seen at 80° from its normal
        # spreads k points that far): a point without one is off any surface (a flying pixel),
        # keeps its place, and costs nothing to search; unbounded, a thousand such points took
        # this search from 21 to 130 ms on a 1280×720 frame. (Within two voxels some surface
        # points went unprojected: lab run yaw 0.029 -> 0.044°, 10 seeds.)
        k = min(L.normals.k, len(pts))
        _, idx = knn(pts, None, k, self.workers, distance_upper_bound=4.0 * L.voxel)
        off = plane_offsets(pts, n, idx, self.workers)
        local = np.isfinite(off)
        off[~local] = 0.0
        # Offsets the noise explains are removed; a larger one is shape (an edge, a corner)
        # that the plane would cut.
        if local.any():
            noise = 1.4826 * np.median(np.abs(off[local]))
            off[np.abs(off) > 3.0 * noise] = 0.0
        pc = replace(pc, points=pts - off[:, None] * n, normals=n)
        return self.with_covariances(pc)

    def prepare_model(self, model: PointCloud) -> Keyframe:
        """The model as a fixed reference (index −1, identity pose) at the frame's voxel, with
        outward normals when it has none. Needs the first frame's lengths."""
        cfg = self.config
        pc = model
        if not cfg.use_mls:
            try:
                pc = voxel_downsample(pc, self.lengths.voxel)
            except InputError as exc:
                # The model's fault, not the frame's (a model in other units or corrupt): say so.
                raise InputError(f"the model at the frame's voxel: {exc}", model.source) from None
        if len(pc) < cfg.health.min_points:
            raise InputError(
                f"model has {len(pc)} points at the frame's voxel (< {cfg.health.min_points})",
                model.source,
            )
        return Keyframe(
            -1, self.with_covariances(self.outward_normals(pc)), np.eye(4), np.zeros((6, 6))
        )

    def visible_model(self, model: PointCloud, T_sensor_target: NDArray[np.float64]) -> Keyframe:
        """The model's faces turned to the sensor at ``T_sensor_target`` (4, 4), as a fixed
        reference as fine as a keyframe (the voxel over ``keyframe_density``), normals towards
        the sensor as a frame's.

        A sensor sees only those. Against the whole model a frame point may pair with the
        back of a part thinner than the noise (the lab's 5 mm wings under 5 mm of noise at
        3 m, a 4 cm panel under 2 cm at 25 m): registration then pulls along the line of sight
        by a bias that grows with the noise (lab, 3 m: 1.6 mm against a σ of 0.1 mm), and
        voxel centroids of a thin part sit between its faces. At the frame's voxel the model's
        own centroids cut its edges and corners as a coarse keyframe does (methods.md §5.4):
        the Hubble kit at 5 m with the ToF camera (flying pixels off, seed 0, 40 frames) was
        0.16-0.27° off with a σ of 0.03-0.04° (NEES median 193 of 6), as fine as a keyframe
        0.04-0.07° (NEES 9). ``model`` needs normals (the tracker gives it outward ones).
        """
        o = se3.invert(T_sensor_target)[:3, 3]
        facing = np.einsum("ij,ij->i", model.normals, o - model.points) > 0.0
        pc = model.select(np.flatnonzero(facing))
        density = self.config.keyframe_density
        if not self.config.use_mls and density < _MODEL_THINNING:
            pc = voxel_downsample(pc, self.lengths.voxel / density)
        if len(pc) < self.config.health.min_points:
            raise InputError(
                f"{len(pc)} model points face the sensor at the frame's voxel "
                f"(< {self.config.health.min_points})",
                model.source,
            )
        pc = estimate_normals(pc, self.lengths.normals, viewpoint=o, workers=self.workers)
        return Keyframe(-1, self.with_covariances(pc), np.eye(4), np.zeros((6, 6)))

    def outward_normals(self, model: PointCloud) -> PointCloud:
        """``model`` with normals turned away from its centroid, as a sensor sees a closed
        model: its own normals (all flipped when most point inwards, as some mesh exports
        give them), or estimated ones."""
        centroid = model.points.mean(axis=0)
        if model.has_normals:
            inward = np.einsum("ij,ij->i", model.normals, model.points - centroid) < 0.0
            return model.with_normals(-model.normals) if inward.mean() > 0.5 else model
        inward = estimate_normals(
            model, self.config.normals, viewpoint=centroid, workers=self.workers
        )
        return inward.with_normals(-inward.normals)

    def sensor_model(self, model: PointCloud) -> PointCloud:
        """The model :meth:`visible_model` culls at every pose: outward normals, and one point
        (with its normal) per cell of a third of the frame's voxel (or the keyframes' finer
        voxel), so that a dense model (10⁶ points: 31 ms a call) costs what a sparse one does
        (2.5 ms at 2·10⁴)."""
        model = self.outward_normals(model)
        thinning = max(_MODEL_THINNING, self.config.keyframe_density)
        _, cell = voxel_cells(model.points, self.lengths.voxel / thinning)
        # One point per cell and side: a panel thinner than the cell has its two faces in one
        # cell, and a single point there would hide the panel from one side (satellite_panels
        # at 5 m: 1,669 of its arrays' cells held both faces).
        side = facing_bin(model.normals)
        first = np.unique(cell * 6 + side, return_index=True)[1]
        return model if len(first) == len(model) else model.select(np.sort(first))

    def shifted_source(self, prepared: PreparedCloud) -> PreparedCloud | None:
        """The frame downsampled again on the voxel grid shifted by half a voxel along each
        axis, from the same cropped raw points (None without them: after mpp-MLS, or with
        keyframes at the frame's voxel, whose raw points are not kept).

        Voxel centroids cut a surface's edges and corners, and how they cut them depends on
        where the grid falls: the registrations of the two samplings differ by an error the
        covariance of white range noise does not hold (methods.md §5.3).
        """
        if prepared.raw is None:
            return None
        voxel, share = self.lengths.voxel, self.config.stray_share
        half = np.full(3, 0.5 * voxel)
        pc = voxel_downsample(prepared.raw, voxel, stray_share=share, origin=-half)
        return self.with_covariances(pc)

    def with_covariances(self, pc: PointCloud) -> PreparedCloud:
        """``pc`` prepared; with its GICP covariances when the registration uses them (once
        per frame: reused whenever the frame is a source or a keyframe target)."""
        covariances = None
        if self._covariances:
            g = self.lengths.gicp
            covariances = compute_covariances(
                pc.points, min(g.k_covariance, len(pc)), g.epsilon, self.workers
            )
        return PreparedCloud(pc, covariances)

    def _predicted_sphere(
        self, T_predicted: NDArray[np.float64] | None, slack: float
    ) -> Sphere | None:
        """Where the prediction puts the target: the sphere around it (its region's, widened by
        the crop margin and ``slack`` m), or None when the frame is not cropped so (target
        isolation off, a target alone in view, no region or no prediction yet)."""
        if not self.crops or T_predicted is None:
            return None
        center = se3.transform_points(T_predicted, self.region.center[None])[0]
        return center, self.config.crop_margin * self.region.radius + slack

    @property
    def crops(self) -> bool:
        """Whether a later frame is cropped to where the prediction puts the target (target
        isolation on, something beside the object on the first frame, its region known)."""
        return self.config.isolate_target and not self.alone and self.region is not None

    def cut(
        self, prepared: PreparedCloud, reference: Keyframe, prediction: Prediction, reach: float
    ) -> PreparedCloud:
        """A frame cropped while the velocity is unknown, cut to the target's clusters
        (:func:`~spacepose.core.target_cut.cut_to_target`, within ``reach`` m and the fine
        gate of ``reference`` where ``prediction`` puts it); any other frame as it is.

        Then the crop is widened by the largest motion allowed, and takes in what lies
        around the target (a wall behind a large one) before any look for a support
        (methods.md §5.8) could split it off; later crops follow the target within the
        prediction's reach, and what they hold beside it is that look's to split (a table
        under the target, cut away, left the turntable in a compromise with the target)."""
        if not self.crops or prediction.velocity_known:
            return prepared
        L, h = self.lengths, self.config.health
        fitness = h.ok_fitness if self._model_region is None else h.model_fitness
        T, gate = prediction.T_sensor_target, reach + L.gate
        return cut_to_target(
            prepared, reference, T, gate, L.voxel, h.min_points, fitness, self.workers
        )

    def _whole_frame(
        self, pc: PointCloud, T_predicted: NDArray[np.float64] | None, slack: float
    ) -> tuple[PointCloud, Sphere | None]:
        """The frame's returns (its background removed, when so configured), and the target's
        points or the sphere to crop them to (:meth:`_isolate`): the steps a frame needs when a
        predicted sphere alone does not say which points are the target's."""
        # No-returns written as points at the sensor would be a dense object there, and set
        # the spacing and scale; returns far beyond the frame's surfaces are no target either.
        valid = within_reach(pc, self.workers)
        if not valid.all():
            pc = pc.select(np.flatnonzero(valid))
        if self.config.use_background_removal:
            pc, _ = remove_background(pc, self.config.background)
        if self.scale is None and len(pc) >= 3 and on_a_line(pc.points):
            # Not a first frame: its lengths and region would be a line's, and the next
            # frame, which may see a surface, would inherit them.
            raise DegenerateGeometryError(
                "all points lie on a line or at one place: no surface to derive lengths from",
                pc.source,
            )
        if not self.config.isolate_target:
            return pc, None
        if self.scene_test is not None:
            self.last_frame = pc
        return self._isolate(pc, T_predicted, slack)

    def _isolate(
        self, pc: PointCloud, T_predicted: NDArray[np.float64] | None, slack: float
    ) -> tuple[PointCloud, Sphere | None]:
        """The target's points: the nearest object on the first frame (or whenever there is
        no prediction); then the sphere around where the prediction puts the target, which
        the caller crops to."""
        if self.alone:
            return pc, None
        if self.region is None or T_predicted is None:
            spacing = point_spacing(pc.points)
            model_radius = None if self._model_region is None else self._model_region.radius
            mask = nearest_object(pc.points, spacing, self.config.health.min_points, model_radius)
            if mask.sum() < self.config.health.min_points:
                return pc, None
            if self.region is None:
                # Held in the target frame: model-free, frame 0 is the target frame; a model's
                # own bounding sphere is known.
                own = region_of(pc.points[mask])
                self.region = own if self._model_region is None else self._model_region
                min_points = self.config.health.min_points
                if self._model_region is None and (~mask).sum() < min_points:
                    # Nothing beside the object: a target alone in view, or a scene seen
                    # whole (a room), which a crop around its first view would cut off as
                    # the sensor turns.
                    self.alone = True
                elif self._model_region is None:
                    self.scene_test = SceneTest.of_first_frame(
                        pc.points, mask, spacing, self.config.points_per_frame, min_points
                    )
            return pc.select(np.flatnonzero(mask)), None
        return pc, self._predicted_sphere(T_predicted, slack)

    def _set_scale(self, first: PointCloud) -> None:
        """Derive every length from the first usable frame."""
        cfg = self.config
        scale = derive_scale(first.points, cfg.points_per_frame, cfg.voxel_size)
        if scale.radius <= 0:
            raise InputError("the first frame has no extent: no scale to derive", first.source)
        units = check_scale(first.points) if first.source in (None, _GIVEN) else None
        if units is not None and units.millimetres:
            # Points given in code (a millimetre cloud was tracked ok, its translations in
            # thousands of "metres"); a file reader, which names its file, has said so, or
            # what the unit's fault really was (a focal length of 1 px).
            problem = (
                f"the first frame looks like millimetres ({units.extent:.0f} m across, median "
                f"point spacing {units.spacing:.2f} m); the tracker works in metres"
            )
            warnings.warn(SpaceposeWarning(problem, first.source), stacklevel=6)
        if problem := sensor_frame_problem(first.points, scale.spacing):
            warnings.warn(SpaceposeWarning(problem, first.source), stacklevel=6)
        self.lengths = stage_lengths(cfg, scale.voxel, scale.radius)
        self.scale = scale


def _cropped(pc: PointCloud, sphere: Sphere | None, workers: int) -> PointCloud:
    """The returns of ``pc`` within ``sphere`` (``pc`` itself without one), on ``workers``
    threads.

    Raises
    ------
    InputError
        No point within the sphere.
    """
    if sphere is None:
        return pc
    kept = crop_sphere(pc, *sphere, workers)
    if len(kept) == 0:
        center, radius = sphere
        raise InputError(
            f"no point within {radius:.3g} m of where the target is predicted "
            f"({np.round(center, 3).tolist()} m)",
            pc.source,
        )
    return pc.select(kept)


def checked_model(model: PointCloud | ArrayLike, min_points: int) -> PointCloud:
    """A reference model (target frame) as a cloud of at least ``min_points`` points.

    Raises
    ------
    InputError
        Not a finite (N, 3) cloud, or fewer points.
    DegenerateGeometryError
        Every point on one line or at one place: no surface to register onto (found on the
        first frame, it was reported as every frame's fault, after all of them were run).
    """
    if isinstance(model, str | os.PathLike):
        # Read as numbers, a path ended in "could not convert string to float".
        raise InputError(
            f"model is a file name ({model}): read it with spacepose.tools.cloud_io.read_model "
            "and pass the cloud"
        )
    pc = as_cloud(model, "model")
    if len(pc) < min_points:
        raise InputError(f"model has {len(pc)} points (< {min_points})", pc.source)
    if on_a_line(pc.points):
        raise DegenerateGeometryError(
            f"model: all {len(pc)} points lie on a line or at one place: no surface to register "
            "onto",
            pc.source,
        )
    return pc
