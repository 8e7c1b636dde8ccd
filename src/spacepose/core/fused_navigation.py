"""Relative navigation from registration poses, rectangles, or both (methods.md §2.4, issue 12).

Per frame, with ``measurements``:

* ``rectangles``: Yu's pipeline alone (:class:`spacepose.core.navigation.RelativeNavigator`);
* ``registration``: the tracker (:class:`spacepose.core.tracker.Tracker`, model-based against
  the target's surface samples) registers the frame; its pose ``T_sensor_model`` and 6×6
  covariance are one pose measurement of the filter
  (:meth:`spacepose.core.ekf.RelativeNavEKF.update_pose`), gated by its Mahalanobis distance
  like any other measurement; only poses the tracker calls ``ok`` enter (``use_degraded``
  lets the unconfirmed ones in too). The first ``ok`` pose starts the filter (no
  prior: the tracker's first pose comes from coarse FPFH + RANSAC registration on the model);
  when the gate has rejected ``restart_after`` consecutive ``ok`` poses at least
  ``restart_deg`` from its prediction the filter restarts from the tracker (a start on a wrong
  coarse pose is otherwise never undone). The pose covariance is the tracker's times
  ``pose_sigma_scale²`` (measured on the run by :mod:`spacepose.tools.pose_bootstrap_run`
  where its mesh and sensor are known), times the factor measured on the pose innovations
  (:class:`spacepose.core.innovation_scale.InnovationScale`; with rectangles beside them, the
  tracker's slow errors show and the poses weigh less);
* ``both``: the rectangle pipeline runs first (its lost-in-space start and its updates), then
  the registration pose updates the same filter; while no rectangle has started the filter, a
  registration pose starts it.

The two help each other: once the filter has taken ``seed_after`` poses, its predicted pose and
its covariance (``H P Hᵀ``) replace the tracker's constant-velocity prediction as the start of
registration and the reference of the tracker's health check; and a pose the filter's gate
rejects is flagged in the tracker's result (status ``degraded``, reason ``navigation gate``).

Model-free (``registration`` without a model): the tracker's poses are ``T_k0``, in the frame F
of its first view, whose principal axes and centre of mass are unknown. The first
``model_free_frames`` ok poses are a batch (:mod:`spacepose.core.model_free_start`: angular
momentum conservation gives the axes and inertia ratios, a CW fit the centre of mass); the
filter then starts with that body frame ``T_F_B'`` and takes ``T_k0 T_F_B'`` as its pose
measurement. The alignment is fixed after the batch (not a filter state), and each principal
axis keeps the sign ambiguity no motion resolves.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import ArrayLike
from scipy.spatial.transform import Rotation
from scipy.stats import chi2

from spacepose.core import dynamics, se3
from spacepose.core.cloud import PointCloud
from spacepose.core.config import stage_config
from spacepose.core.ekf import RelativeNavEKF
from spacepose.core.frame_check import HELD
from spacepose.core.fusion_config import FusionConfig, Measurements
from spacepose.core.innovation_scale import InnovationScale
from spacepose.core.model_free_start import model_free_start
from spacepose.core.nav_result import NavRow
from spacepose.core.nav_start import start_filter
from spacepose.core.nav_state import NavState, seconds
from spacepose.core.navigation import RelativeNavigator, frame_pairs, orbit_geometry
from spacepose.core.pose_noise import scaled_about_target
from spacepose.core.rectangles import CatalogueEntry, catalogue_entries
from spacepose.core.track_result import TrackResult
from spacepose.core.tracker import Tracker
from spacepose.errors import ConfigError, PredictionGapError

__all__ = ["FusedNavigator", "FusedRow", "FusionConfig", "Measurements", "fused_navigate"]

GATE_REASON = "navigation gate"


@dataclass(frozen=True, eq=False)
class FusedRow:
    """One frame of :class:`FusedNavigator`.

    Attributes
    ----------
    nav
        The navigation row (NAV.csv), state after every update of the frame.
    track
        The tracker's result (None when registration is not used), flagged ``degraded`` with a
        ``navigation gate`` reason when the filter rejected its pose.
    pose_used
        Whether the registration pose entered the filter (None when none was offered).
    pose_nis
        Its normalised innovation squared (NaN when none was tested).
    seeded
        Whether the filter's prediction seeded the registration.
    """

    nav: NavRow
    track: TrackResult | None
    pose_used: bool | None
    pose_nis: float
    seeded: bool


class FusedNavigator:
    """Relative navigation from rectangles, registration poses or both, one frame at a time.

    Parameters
    ----------
    catalogue
        The target's rectangles (model frame B'); may be empty for ``registration``.
    mean_motion
        Orbital mean motion n, rad/s.
    R_O_C
        (3, 3) constant sensor (chaser) attitude in O.
    config
        Measurements, filter, tracker.
    model
        Surface samples of the target with outward normals in B' (a run's ``model.ply``): the
        tracker's reference, and the lost-in-space scorer of the rectangle start.

    Raises
    ------
    ConfigError
        Rectangles asked for with an empty catalogue, or registration without a model.
    """

    def __init__(
        self,
        catalogue: Sequence[CatalogueEntry],
        mean_motion: float,
        R_O_C: ArrayLike,
        config: FusionConfig | None = None,
        model: PointCloud | None = None,
    ) -> None:
        self.config = c = FusionConfig() if config is None else stage_config(config, FusionConfig)
        self.n, self.R_O_C = orbit_geometry(mean_motion, R_O_C)
        catalogue = catalogue_entries(catalogue)
        uses_rectangles = c.measurements in ("rectangles", "both")
        if uses_rectangles and len(catalogue) == 0:
            raise ConfigError(
                f"measurements {c.measurements!r} need a rectangle catalogue and this target "
                "has none: use 'registration'"
            )
        if c.measurements == "both" and model is None:
            raise ConfigError(
                "'both' needs a target model (model.ply or --model): rectangles live in the "
                "model frame, model-free poses in the first view's frame"
            )
        self.rectangles = (
            RelativeNavigator(catalogue, mean_motion, R_O_C, c.navigation, model)
            if uses_rectangles
            else None
        )
        self.tracker = None if c.measurements == "rectangles" else Tracker(c.tracker, model)
        self._ekf: RelativeNavEKF | None = None
        self._poses_used = 0
        self._rejected_ok = 0
        self._last_ok_used = False
        # Measured factor on the scaled pose covariance (innovation_scale) and the frame count
        # that pairs consecutive poses.
        self._pose_noise = InnovationScale()
        self._frames = 0
        # Model-free: the batch of (t, T_k0) before the start, then the body frame in F.
        self._batch: list[tuple[float, np.ndarray]] | None = [] if model is None else None
        self.T_F_B: np.ndarray | None = None
        self._gate = chi2.ppf(c.navigation.ekf.gate_probability, 6)

    @property
    def ekf(self) -> RelativeNavEKF | None:
        """The running filter (None before the start and while the rectangles are ambiguous)."""
        return self._ekf if self.rectangles is None else self.rectangles.ekf

    def step(self, t: float, cloud: PointCloud | None) -> FusedRow:
        """Process one frame taken at ``t`` (s since the epoch where I and O coincide)."""
        t = seconds(t, "frame time t")
        row = None
        if self.rectangles is not None:
            row = self.rectangles.step(t, cloud)
        elif self._ekf is not None:
            try:
                self._ekf.predict(t)
            except PredictionGapError as exc:  # the state says nothing after the gap
                self._ekf = None
                problem = f"the filter starts again: {exc}"
                row = NavRow(t, None, None, 0, "waiting", problem=problem)
        if self.tracker is None:
            return FusedRow(row, None, None, float("nan"), False)
        ekf, c = self.ekf, self.config
        seeded = (
            ekf is not None
            and self.config.seed_registration
            and self._poses_used >= self.config.seed_after
            and self._last_ok_used
        )
        # The filter's pose in the tracker's target frame (the first view's, model-free; the
        # model's with the tracker's biases, model-based). Its left-perturbation covariance
        # serves for both: a right factor leaves it as it is, and the sensor-frame bias (under
        # a millimetre) moves its translation block by that lever times the rotation's σ.
        T_pred = None if ekf is None else self._tracker_pose(ekf.predict_pose())
        prior = (T_pred, ekf.pose_covariance()) if seeded else None
        track = self.tracker.track_frame(cloud, t, prior)
        if track.revises and self._batch is not None:
            # Model-free, a first frame no later frame confirmed gave way to a later one
            # (core.spare_anchor): the batch's pose of it was in the abandoned target frame.
            self._batch = [
                (r.timestamp, r.T_sensor_target) for r in track.revises if r.status == "ok"
            ]
        used, nis, started = None, float("nan"), False
        # A frame the motion model's prediction held carries that prediction, the filter's own
        # when it seeded the registration: not a measurement.
        held = HELD in track.reasons
        offered = track.status == "ok" or (
            track.status == "degraded" and c.use_degraded and not held
        )
        if offered:
            if self.rectangles is None and self._rejected_ok >= c.restart_after:
                ekf = self._ekf = None
                self._pose_noise = InnovationScale()  # measured on the abandoned start
            T_meas = self._filter_pose(track.T_sensor_target)
            if ekf is None and (row is None or row.status == "waiting"):
                used = started = track.status == "ok" and self._start(t, T_meas)
            elif ekf is not None:
                scale = c.pose_sigma_scale if self.T_F_B is None else c.model_free_sigma_scale
                cov = scale**2 * track.covariance
                f_t = c.pose_sigma_scale_translation
                if f_t is not None and self.T_F_B is None:
                    cov = scaled_about_target(track.covariance, track.T_sensor_target, scale, f_t)
                used = ekf.update_pose(T_meas, cov * self._pose_noise.factor)
                nis = ekf.last_nis
                # With rectangles beside them every pose's innovation counts, the gated ones
                # too (counting only those the gate let through understates the tracker's
                # slow errors); alone, a rejected pose may be the filter's fault (a wrong
                # start, which the restart below undoes) and must not widen the poses' σ.
                if used or self.rectangles is not None:
                    self._pose_noise.add(
                        "pose", self._frames, ekf.last_innovation, cov, ekf.last_HPHt
                    )
                self._poses_used += int(used)
                far = _angle_deg(track.T_sensor_target, T_pred) >= c.restart_deg
                counts = not used and track.status == "ok" and far
                self._rejected_ok = self._rejected_ok + 1 if counts else 0
                if not used:
                    reason = f"{GATE_REASON}: NIS {nis:.1f} > {self._gate:.1f}"
                    track = replace(track, status="degraded", reasons=(*track.reasons, reason))
        self._last_ok_used = bool(used) and track.status == "ok"
        self._frames += 1
        return FusedRow(self._nav_row(t, row, bool(used), started), track, used, nis, seeded)

    def _filter_pose(self, T_track: np.ndarray) -> np.ndarray:
        """The tracker's pose (4, 4) as the filter's measurement: model-free ``T_k0 T_F_B'``
        once the batch has found the body frame; model-based ``S⁻¹ T B⁻¹``, the tracker's
        biases in the sensor's and the target's frames taken off (``pose_bias_sensor``,
        ``pose_bias_body``), which the filter would take for the target's position and its
        centre of mass."""
        if self.T_F_B is not None:
            return T_track @ self.T_F_B
        if self.tracker is None or not self.tracker.model_based:  # model-free, before the batch
            return T_track
        S, B = self._biases()
        return se3.invert(S) @ T_track @ se3.invert(B)

    def _tracker_pose(self, T_filter: np.ndarray) -> np.ndarray:
        """:meth:`_filter_pose` undone: the filter's pose in the tracker's target frame, bias
        and all (the pose the tracker would converge to)."""
        if self.T_F_B is not None:
            return T_filter @ se3.invert(self.T_F_B)
        if self.tracker is None or not self.tracker.model_based:
            return T_filter
        S, B = self._biases()
        return S @ T_filter @ B

    def _biases(self) -> tuple[np.ndarray, np.ndarray]:
        c = self.config
        S = se3.make_transform(np.eye(3), np.asarray(c.pose_bias_sensor, dtype=np.float64))
        return S, se3.make_transform(np.eye(3), np.asarray(c.pose_bias_body, dtype=np.float64))

    def run(self, frames: Iterable[tuple[float, PointCloud | None]]) -> list[FusedRow]:
        """:meth:`step` over ``(t, cloud)`` pairs in time order; one row per frame."""
        return [self.step(t, cloud) for t, cloud in frame_pairs(frames)]

    def _start(self, t: float, T_sensor_model: np.ndarray) -> bool:
        """Start the filter from a registration pose (the rectangles' navigator if there is one)."""
        if self.rectangles is not None:
            return self.rectangles.start_from_pose(t, T_sensor_model)
        if self._batch is not None:
            return self._start_model_free(t, T_sensor_model)
        self._ekf = start_filter(t, T_sensor_model, self.n, self.R_O_C, self.config.navigation)
        self._poses_used = self._rejected_ok = 0
        return True

    def _start_model_free(self, t: float, T_k0: np.ndarray) -> bool:
        """Collect the batch; at its end, the body frame in F and a filter started on it."""
        self._batch.append((t, T_k0))
        if len(self._batch) < self.config.model_free_frames:
            return False
        times = np.array([b[0] for b in self._batch])
        poses = np.array([b[1] for b in self._batch])
        found = model_free_start(times, poses, self.n, self.R_O_C)
        if not found.axes.physical:
            return False  # too little of the tumble seen yet: the batch grows
        self.T_F_B = found.T_F_B
        T = T_k0 @ found.T_F_B
        R_I_B = dynamics.R_I_O(self.n, t) @ self.R_O_C @ T[:3, :3]
        x = dynamics.cw_stm(self.n, t - times[0]) @ found.state0
        # The body rate over the batch's last interval, in B.
        R_I_B_prev = dynamics.R_I_O(self.n, times[-2]) @ self.R_O_C @ poses[-2][:3, :3]
        R_I_B_prev = R_I_B_prev @ found.T_F_B[:3, :3]
        step = Rotation.from_matrix(R_I_B_prev.T @ R_I_B).as_rotvec() / (t - times[-2])
        initial = NavState(t, x[:3], x[3:], Rotation.from_matrix(R_I_B).as_quat(),
                           step, found.axes.k, np.zeros(3))  # fmt: skip
        self._ekf = RelativeNavEKF(self.n, self.R_O_C, initial, self.config.navigation.ekf)
        self._batch = None
        self._poses_used = self._rejected_ok = 0
        return True

    def _nav_row(self, t: float, row: NavRow | None, pose_used: bool, started: bool) -> NavRow:
        """The frame's NAV row with the state after the pose update."""
        ekf = self.ekf
        if ekf is None:
            return row if row is not None else NavRow(t, None, None, 0, "waiting")
        if started or (row is not None and row.status == "init"):
            status = "init"
        elif pose_used or (row is not None and row.status == "update"):
            status = "update"
        else:
            status = "predict"
        base = row if row is not None else NavRow(t, None, None, 0, status)
        return replace(base, state=ekf.state(), sigmas=ekf.sigmas(), status=status)


def _angle_deg(T: np.ndarray, U: np.ndarray) -> float:
    """Rotation angle between the attitudes of two poses (4, 4), degrees."""
    return float(np.degrees(Rotation.from_matrix(T[:3, :3] @ U[:3, :3].T).magnitude()))


def fused_navigate(
    frames: Iterable[tuple[float, PointCloud | None]],
    catalogue: Sequence[CatalogueEntry],
    mean_motion: float,
    R_O_C: ArrayLike,
    config: FusionConfig | None = None,
    model: PointCloud | None = None,
) -> list[FusedRow]:
    """One call: run :class:`FusedNavigator` over ``(t, cloud)`` frames, one row per frame."""
    return FusedNavigator(catalogue, mean_motion, R_O_C, config, model).run(frames)
