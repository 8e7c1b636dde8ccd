"""Fine registration of a tracked frame onto one reference (docs/methods.md §1.6, §5.5).

:class:`FrameRegistrar` registers a prepared frame (the source) onto one reference, a keyframe
or a model (the target): ICP or GICP from an initial ``T_sensor_target`` (4, 4), giving
``T_ref_k`` (4, 4) with its (6, 6) covariance (twist order (omega, v), left perturbation in the
reference frame; rad², m²) from the point-to-plane residuals, scaled by the frame's residual
structure and with the σ floor. It measures the residual noise that sets the fine gate (m), the
residual structure and the influence of the frame's parts. When the motion model has been wrong
by more than the fine gate, a first point-to-plane pass with a gate of three model-error σ
brings the frame within reach of the fine gate (KISS-ICP's adaptive threshold, in two stages).
The frame's pose from these registrations onto the keyframe window (one reference, Li's J-ICP,
or our keyframe graph) is :mod:`spacepose.core.window_registration`'s.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from spacepose.core import se3
from spacepose.core.correspondences import Correspondences, find_correspondences
from spacepose.core.gicp import GICPConfig, gicp
from spacepose.core.icp import ICPConfig, icp, icp_correspondences
from spacepose.core.keyframes import Keyframe, PreparedCloud
from spacepose.core.motion import rigid
from spacepose.core.part_influence import PartInfluence, part_influence
from spacepose.core.pose_covariance import (
    CLUSTER_VOXELS,
    clustered_covariance,
    isotropic_about,
    plane_covariance,
    wider_of,
)
from spacepose.core.registration import RegistrationResult
from spacepose.core.residual_noise import ResidualNoise, point_to_plane_sigma
from spacepose.core.residual_structure import SAMPLING_SPREAD_VOXELS, Structure, structure_of
from spacepose.core.tracker_config import StageLengths, pairwise_kind
from spacepose.errors import RegistrationError, SpaceposeError

# Largest pose-graph update (rad, and voxels for the translation: about 1e-6 m at the lab's 6 mm)
# at which the keyframe graph and J-ICP stop iterating. Its Gauss-Newton shrinks the update
# about 1000× per iteration on the lab run: after a 1e-6 step the poses are within ~1e-9 of the
# optimum, and 1e-12 cost two more iterations (~1 ms per frame).
POSE_GRAPH_TOLERANCE = (1e-6, 1.6e-4)
# The wide first pass runs only when it is this much wider than the fine gate.
_WIDE_PASS_RATIO = 1.5
# Kernels of the wide first pass, in turn. A wide gate takes in wrong surfaces too, which a
# redescending kernel keeps out; but from a start far off, its scale (the median residual) is
# that of the pairs already close, the surfaces the motion slides along, and it weighs out the
# pairs that show the motion. A satellite receding 0.19 m a frame from 1.5 m stopped 60-90 mm
# short so, frame after frame. Huber's monotone kernel, which weighs no pair out, brings the
# frame into the basin first; the redescending one starts from there (methods.md §5.5).
_WIDE_PASS_KERNELS = ("huber", "geman_mcclure")
# Cells of the residual structure test, in fine gates: wide enough for a part's own residual to
# add up (about 50 pairs of a voxelised surface), small enough to tell two lab parts apart.
STRUCTURE_CELL_GATES = 8.0


@dataclass(frozen=True)
class PairRegistration:
    """A frame registered onto one reference.

    Attributes
    ----------
    result
        The registration, ``T_target_source`` = ``T_ref_k``.
    covariance
        (6, 6) covariance of ``T_ref_k`` (left perturbation in the reference frame, scaled, times
        the frame's residual structure when above 1, and with the voxel floor; see
        :func:`plane_covariance`).
    step
        (6,) the point-to-plane Gauss-Newton step from the result (same frame).
    structure
        :func:`~spacepose.core.residual_structure.structure_of` its final pairs, when
        measured.
    influence
        :func:`~spacepose.core.part_influence.part_influence` of its final pairs, when measured.
    """

    result: RegistrationResult
    covariance: NDArray[np.float64]
    step: NDArray[np.float64]
    structure: Structure | None = None
    influence: PartInfluence | None = None


@dataclass(frozen=True)
class _FinalPairs:
    """A registration's final pairs: (M, 3) source points moved into the reference frame, the
    (M, 3) reference normals, the (M,) signed point-to-plane residuals (m), and the robust
    kernel's (M,) weights (None: all 1)."""

    points: NDArray[np.float64]
    normals: NDArray[np.float64]
    residuals: NDArray[np.float64]
    weights: NDArray[np.float64] | None


class FrameRegistrar:
    """Registers prepared frames onto keyframes or a model, with covariances.

    Parameters
    ----------
    method
        ``"point_to_point"``, ``"point_to_plane"``, ``"gicp"``, ``"jicp"`` or ``"keyframe"``
        (see :class:`~spacepose.core.tracker_config.TrackerConfig`).
    lengths
        The stage configs with their derived lengths.
    covariance_scale
        Factor on every registration covariance.
    workers
        Threads of the searches.
    influence_sigmas
        The shift, in σ, beyond which a part's influence on a registration is reported
        (:func:`~spacepose.core.part_influence.part_influence`).
    """

    def __init__(
        self,
        method: str,
        lengths: StageLengths,
        covariance_scale: float,
        workers: int,
        influence_sigmas: float = 3.0,
    ) -> None:
        self.method = method
        self.lengths = lengths
        self.influence_sigmas = influence_sigmas
        # The fine gate widens to three measured residual σ on a sensor noisier than the voxel.
        self.noise = ResidualNoise(lengths.gate)
        rotation, translation = POSE_GRAPH_TOLERANCE
        self.graph_tolerance = (rotation, translation * lengths.voxel)
        self.covariance_scale = covariance_scale
        # Design effect of the frame being registered (set by its measured registration).
        self._design = 1.0
        self.workers = workers
        L = lengths
        self._icp: ICPConfig = L.icp
        self._gicp: GICPConfig = L.gicp
        # The pairwise registration, "icp" or "gicp", and its configs.
        self.pairwise = pairwise_kind(method, L)
        if method in ("jicp", "keyframe"):
            stage = L.jicp if method == "jicp" else L.keyframe_graph
            self._icp, self._gicp = stage.icp, stage.gicp
        elif method in ("point_to_point", "point_to_plane"):
            self._icp = L.icp.model_copy(update={"method": method})

    def as_target(self, prepared: PreparedCloud) -> PreparedCloud:
        """The prepared cloud with normals, estimated the first time it is a registration
        target (a keyframe): most frames never are, and sources need none."""
        return prepared.with_normals(self.lengths.normals, self.workers)

    def set_aside(self) -> tuple[list[float], float]:
        """Take the frame's measurements so far (its pending residual σ, its design effect)
        out of the registrar before a trial registration, whose own :meth:`put_back` drops."""
        return self.noise.take(), self._design

    def put_back(self, measured: tuple[list[float], float]) -> None:
        """Drop a trial registration's measurements and put back those :meth:`set_aside`
        took."""
        self.noise.take()
        pending, self._design = measured
        self.noise.restore(pending)

    def approach(
        self,
        prepared: PreparedCloud,
        ref: Keyframe,
        T_init_sensor_target: NDArray[np.float64],
        wide_gate: float,
    ) -> NDArray[np.float64]:
        """First pass with a gate ``wide_gate`` (m) when that is well above the fine gate.

        Returns the improved initial ``T_sensor_target`` (the input when no pass is needed).
        """
        cfg = self.lengths.icp
        if wide_gate <= _WIDE_PASS_RATIO * self.noise.gate:
            return T_init_sensor_target
        tgt = self.as_target(ref.registration_target)
        T_ref_k = ref.T_ref_target @ se3.invert(T_init_sensor_target)
        try:
            for kernel in _WIDE_PASS_KERNELS:
                wide = cfg.model_copy(
                    update={"max_correspondence_distance": wide_gate, "robust_kernel": kernel}
                )
                T_ref_k = icp(
                    prepared.cloud,
                    tgt.cloud,
                    T_ref_k,
                    wide,
                    workers=self.workers,
                    target_tree=tgt.tree,
                ).T_target_source
        except SpaceposeError:
            return T_init_sensor_target
        return rigid(se3.invert(T_ref_k) @ ref.T_ref_target)

    def register(
        self,
        prepared: PreparedCloud,
        ref: Keyframe,
        T_init_sensor_target: NDArray[np.float64],
        measure: bool = True,
        robust: bool = False,
    ) -> PairRegistration:
        """Register the frame (source) onto a reference.

        ``measure``: measure the residual noise after it, and onto a keyframe its structure (the
        design effect of its covariances) and the influence of its parts (once a frame, on the
        latest reference: the extra search costs about a fifth of a lab frame's step).
        ``robust``: weigh the residuals by a redescending kernel (:meth:`_pairwise`).
        """
        init_T_ref_k = ref.T_ref_target @ se3.invert(T_init_sensor_target)
        tgt = self.as_target(ref.registration_target)
        res, matches = self._pairwise(prepared, tgt, init_T_ref_k, robust)
        pairs = None
        if measure:
            sigma = point_to_plane_sigma(
                res.T_target_source,
                prepared.cloud.points,
                tgt,
                self.noise.window,
                self.workers,
                _hint(matches, len(prepared.cloud)),
            )
            if self.noise.add(sigma):
                # The gate cut the residuals: again with the gate the noise asks for.
                res, matches = self._pairwise(prepared, tgt, res.T_target_source, robust)
            if ref.index >= 0:
                # Against a model a part moving otherwise finds no surface within the gate
                # (the fitness bound sees it); the tests are for two views of one sensor.
                pairs = self._final_pairs(prepared, tgt, res, matches)
        structure = None
        if pairs is not None:
            structure = self._structure(pairs)
        if measure:
            # Residuals correlated over the surface carry less information than their count
            # says: the variance of their cell means over white noise's (the design effect)
            # scales this frame's covariances, onto every reference.
            self._design = 1.0 if structure is None else max(1.0, structure.within)
        cov, step = plane_covariance(
            res.T_target_source,
            prepared.cloud.points,
            tgt,
            self.noise.gate,
            self.workers,
            matches,
            self._sampling_spread,
        )
        if ref.index < 0:
            cov = self._model_covariance(cov, prepared, tgt, res, matches)
        cov = self.covariance_scale * self._design * cov + self._floor(prepared, res)
        influence = None
        if pairs is not None:
            # Parts of the object's RMS radius: a few across it, each a surface of its own.
            influence = part_influence(
                pairs.points,
                pairs.normals,
                pairs.residuals,
                cov,
                prepared.radius,
                pairs.weights,
                self.influence_sigmas,
            )
        return PairRegistration(res, cov, step, structure, influence)

    def structure_onto(
        self, prepared: PreparedCloud, ref: Keyframe, T_init_sensor_target: NDArray[np.float64]
    ) -> tuple[Structure | None, float]:
        """:func:`~spacepose.core.residual_structure.structure_of` the frame registered
        onto ``ref`` with one motion from ``T_init_sensor_target``, at the fine gate, and that
        registration's fitness; the measured noise and the frame's design effect are left as
        they are."""
        init_T_ref_k = ref.T_ref_target @ se3.invert(T_init_sensor_target)
        tgt = self.as_target(ref.registration_target)
        res, matches = self._pairwise(prepared, tgt, init_T_ref_k)
        pairs = self._final_pairs(prepared, tgt, res, matches)
        return self._structure(pairs), res.fitness

    def _structure(self, pairs: _FinalPairs) -> Structure | None:
        """:func:`~spacepose.core.residual_structure.structure_of` a registration's
        final pairs, in cells of :data:`STRUCTURE_CELL_GATES` fine gates, the spread floored
        at the sampling's own."""
        cell = STRUCTURE_CELL_GATES * self.noise.gate
        return structure_of(pairs.points, pairs.residuals, cell, self._sampling_spread)

    @property
    def _sampling_spread(self) -> float:
        """The spread (m) of the residuals sampling the surface leaves without noise, the floor
        of σ in a registration's covariance and structure
        (:data:`~spacepose.core.residual_structure.SAMPLING_SPREAD_VOXELS` of the voxel)."""
        return SAMPLING_SPREAD_VOXELS * self.lengths.voxel

    def _model_covariance(
        self,
        cov: NDArray[np.float64],
        prepared: PreparedCloud,
        tgt: PreparedCloud,
        res: RegistrationResult,
        matches: Correspondences | None,
    ) -> NDArray[np.float64]:
        """``cov`` of a registration onto the model, widened to the cluster-robust form of its
        residuals where that is wider. No structure is measured against a model (a design
        effect is for two views of one sensor), yet a frame's residuals against the model's
        samples are correlated too: on third-party renders of debris and a satellite at 5-15 m,
        48 runs, the model-based σ was 1.06-1.42 times short (RMS error over σ per axis), 93.5 %
        of `ok` frames within 3σ and 3 beyond 5σ."""
        pairs = self._final_pairs(prepared, tgt, res, matches)
        cell = CLUSTER_VOXELS * self.lengths.voxel
        try:
            clustered = clustered_covariance(
                pairs.points, pairs.normals, pairs.residuals, cell, pairs.weights
            )
        except RegistrationError:  # too few cells to see a correlation
            return cov
        return wider_of(cov, clustered)

    def _final_pairs(
        self,
        prepared: PreparedCloud,
        tgt: PreparedCloud,
        res: RegistrationResult,
        matches: Correspondences | None,
    ) -> _FinalPairs:
        """A registration's final pairs (searched within the fine gate for GICP)."""
        moved = se3.transform_points(res.T_target_source, prepared.cloud.points)
        weights = None
        if matches is None:
            s, t, _ = find_correspondences(tgt.tree, moved, self.noise.gate, self.workers)
        else:
            s, t = matches.src_idx, matches.tgt_idx
            weights = None if matches.weights is None else matches.weights.weights
        normals = tgt.cloud.normals[t]
        r = np.einsum("ij,ij->i", moved[s] - tgt.cloud.points[t], normals)
        return _FinalPairs(moved[s], normals, r, weights)

    def _pairwise(
        self,
        prepared: PreparedCloud,
        tgt: PreparedCloud,
        init_T_ref_k: NDArray[np.float64],
        robust: bool = False,
    ) -> tuple[RegistrationResult, Correspondences | None]:
        """The pairwise registration at the current gate, with ICP's final correspondences
        (None for GICP); ``robust``: the residuals weighed by a Geman-McClure kernel at their
        own scale."""
        gated: dict[str, object] = {"max_correspondence_distance": self.noise.gate}
        if robust:
            gated["robust_kernel"] = "geman_mcclure"
        if self.pairwise == "gicp":
            res = gicp(
                prepared.cloud,
                tgt.cloud,
                init_T_ref_k,
                self._gicp.model_copy(update=gated),
                workers=self.workers,
                source_covariances=prepared.covariances,
                target_covariances=tgt.covariances,
                target_tree=tgt.tree,
            )
            return res, None
        # ICP hands back its final correspondences (and point-to-plane sums): the covariance
        # need not search or sum again.
        return icp_correspondences(
            prepared.cloud,
            tgt.cloud,
            init_T_ref_k,
            self._icp.model_copy(update=gated),
            workers=self.workers,
            target_tree=tgt.tree,
        )

    def _floor(self, prepared: PreparedCloud, res: RegistrationResult) -> NDArray[np.float64]:
        """The voxel floor (see TrackerConfig) about the centroid, in the reference frame."""
        L = self.lengths
        c_ref = se3.transform_points(res.T_target_source, prepared.centroid[None])[0]
        return isotropic_about(c_ref, (L.floor_rotation, L.floor_translation))


def _hint(matches: Correspondences | None, n_source: int) -> NDArray[np.int64] | None:
    """(N,) each source point's last match (-1: none), to narrow a search from the same
    pose; None for GICP, which returns no matches."""
    if matches is None:
        return None
    hint = np.full(n_source, -1, dtype=np.int64)
    hint[matches.src_idx] = matches.tgt_idx
    return hint
