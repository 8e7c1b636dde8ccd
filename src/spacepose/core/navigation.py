"""Relative navigation from rectangles (Yu et al. 2019, methods.md §2.1–2.4): the whole pipeline.

Per frame: planes → rectangles measured and matched by size to the catalogue → coarse pose of
each rectangle with the 4-fold fix against the filter's predicted pose → EKF predict and update
(attitude and centroid of every recognised rectangle). ω and the inertia ratios start from the
configured priors (Yu et al. do the same: ρ̇ = 0, ω a prior with an initial error).

Start. Faces of equal size (the opposite faces of a box, the two faces of a panel) cannot be
told apart by their sides, and a symmetric target has several poses that explain every frame.
With a coarse attitude prior (``prior_q_I_B``) the first frame with a rectangle starts one
filter, as Yu et al. do. Without one (lost in space) every pose the frame's rectangles allow
(:func:`spacepose.core.attitude_fix.attitude_hypotheses`) is refined and scored on the target
model (:mod:`spacepose.core.lost_in_space`); those within ``start_margin`` of the best each
start a candidate filter. Each frame the candidates are scored again at their own estimates and
a candidate is dropped once it has been behind the best in each of ``decide_frames`` frames, by
a median shortfall above ``ambiguity_margin`` (frames whose best score is below
``min_explained`` do not count: they cannot tell candidates apart). While two or more remain
the rows say ``ambiguous``, give no state and list the candidates: a truly symmetric target
stays so, never confidently wrong.

The rows and the NAV.csv table are in :mod:`spacepose.core.nav_result`; the orbit geometry and
a filter's initial state in :mod:`spacepose.core.nav_start`.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Sequence
from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from spacepose.core import dynamics
from spacepose.core.attitude_fix import (
    attitude_hypotheses,
    coarse_target_pose,
    consistent_rectangles,
    explained_rectangles,
)
from spacepose.core.cloud import PointCloud, as_cloud
from spacepose.core.config import stage_config
from spacepose.core.ekf import RelativeNavEKF
from spacepose.core.innovation_scale import InnovationScale
from spacepose.core.lost_in_space import (
    FrameEvidence,
    ModelSurface,
    equally_good,
    explained_share,
    refine_on_model,
)
from spacepose.core.nav_config import NavigationConfig
from spacepose.core.nav_measurements import (
    area_weighted_centroid,
    attitude_covariance,
    centroid_covariance,
    incidence_cosine,
    pixel_area_weights,
)
from spacepose.core.nav_result import Candidate, NavRow
from spacepose.core.nav_start import scenario_geometry, start_filter
from spacepose.core.nav_state import seconds
from spacepose.core.rectangle_measurement import RectangleMeasurement
from spacepose.core.rectangle_search import measure_planes
from spacepose.core.rectangles import (
    CatalogueEntry,
    RectangleConfig,
    candidates,
    catalogue_entries,
    recognise,
)
from spacepose.core.scale import plane_range_sigma
from spacepose.errors import InputError, PredictionGapError, SpaceposeError

__all__ = [
    "NavigationConfig",
    "RelativeNavigator",
    "area_weighted_centroid",
    "attitude_covariance",
    "centroid_covariance",
    "incidence_cosine",
    "navigate",
]

# Rectangles of a frame: each measurement with the catalogue faces its sides allow.
Rects = list[tuple[RectangleMeasurement, list[CatalogueEntry]]]
# Candidates that all explain less than this share of a frame's data, frame after frame, were
# started on a frame that was not the target's: the start is made again.
_LOST_SHARE = 0.5


@dataclass(eq=False)
class _Track:
    """A candidate filter and the shortfalls of its explained share from the best, per frame."""

    ekf: RelativeNavEKF
    deficits: list[float] = field(default_factory=list)
    explained: float = float("nan")
    # Measured factors on the attitude and centroid covariance models (innovation_scale).
    attitude_scale: InnovationScale = field(default_factory=InnovationScale)
    centroid_scale: InnovationScale = field(default_factory=InnovationScale)


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
    model
        Optional surface samples of the target with outward normals, model frame B' (a run's
        ``model.ply``): the lost-in-space start scores its hypotheses on them. Without it the
        hypotheses are scored by the rectangles they explain, which cannot see the parts that
        break a symmetry, so more starts stay ambiguous.
    """

    def __init__(
        self,
        catalogue: Sequence[CatalogueEntry],
        mean_motion: float,
        R_O_C: ArrayLike,
        config: NavigationConfig | None = None,
        model: PointCloud | None = None,
    ) -> None:
        catalogue = catalogue_entries(catalogue)
        if len(catalogue) == 0:
            raise InputError("the rectangle catalogue is empty: nothing to navigate on")
        self.catalogue = {e.name: e for e in catalogue}
        self.config = (
            NavigationConfig() if config is None else stage_config(config, NavigationConfig)
        )
        if self.config.range_sigma is not None:
            self.config = self.config.with_range_sigma(self.config.range_sigma)
        self.n, self.R_O_C = orbit_geometry(mean_motion, R_O_C)
        self.model = None if model is None else ModelSurface.from_cloud(as_cloud(model, "model"))
        self.tracks: list[_Track] = []
        self._confident = False
        self._steps = 0  # frames seen, to pair a face's innovations in consecutive frames
        self._unexplained = 0  # consecutive frames no candidate explained half of

    @property
    def ekf(self) -> RelativeNavEKF | None:
        """The filter once one candidate remains; None before the start and while ambiguous."""
        return self.tracks[0].ekf if len(self.tracks) == 1 else None

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

        A frame without data (``cloud`` None) is a prediction-only step, never dropped; so is
        one whose points the plane search refuses. After a gap too long to predict across the
        navigator starts again. Either is said in the row's ``problem``.
        """
        t = seconds(t, "frame time t")
        cloud = None if cloud is None else as_cloud(cloud, "frame", say_dropped=False)
        problems = []
        try:
            for track in self.tracks:
                track.ekf.predict(t)
        except PredictionGapError as exc:  # the state says nothing after the gap
            self.tracks, self._confident = [], False
            problems.append(f"the filter starts again: {exc}")
        rects: Rects = []
        if cloud is not None and self.config.range_sigma is None:
            self._measure_range_sigma(cloud)
        if cloud is not None:
            try:
                rects = self.rectangles(cloud)
            except SpaceposeError as exc:  # the plane search refused the points: no data
                cloud = None
                problems.append(f"no rectangle measured, its rectangles left out: {exc}")
        row = self._step(t, cloud, rects)
        return replace(row, problem="; ".join(problems)) if problems else row

    def _measure_range_sigma(self, cloud: PointCloud) -> None:
        """Set the range noise from the first frame that shows it (methods.md §2.1,
        :func:`~spacepose.core.scale.plane_range_sigma`); a frame that does not is measured
        again on the next."""
        sigma = plane_range_sigma(cloud.points)
        if sigma is not None:
            self.config = self.config.with_range_sigma(sigma)

    def _step(self, t: float, cloud: PointCloud | None, rects: Rects) -> NavRow:
        """:meth:`step` once the filters are predicted to ``t`` and the frame's rectangles
        measured."""
        if not self.tracks:
            self.tracks = [_Track(self._start_filter(t, T)) for T in self._start(t, cloud, rects)]
            if not self.tracks:
                return NavRow(t, None, None, 0, "waiting")
        self._steps += 1
        used = [self._update(track, self._assign(track.ekf, rects)) for track in self.tracks]
        if len(self.tracks) > 1 and cloud is not None:
            used = self._prune(cloud, rects, used)
            if not self.tracks:  # no candidate explained the last frames: start on this one
                return self._step(t, cloud, rects)
        lead = self.tracks[0].ekf
        recognised = self._assign(lead, rects)
        coarse = raw = None
        if recognised:
            coarse = consistent_rectangles(recognised, lead.predict_pose()[:3, :3])
            m0, e0 = max(recognised, key=lambda p: p[0].n_points)
            raw = coarse_target_pose(m0, e0, None)
        if len(self.tracks) > 1:
            candidates = tuple(Candidate(tr.ekf.state(), tr.explained) for tr in self.tracks)
            return NavRow(t, None, None, used[0], "ambiguous", coarse, raw, candidates)
        status = "predict" if self._confident else "init"
        if self._confident and used[0]:
            status = "update"
        self._confident = True
        return NavRow(t, lead.state(), lead.sigmas(), used[0], status, coarse, raw)

    def run(self, frames: Iterable[tuple[float, PointCloud | None]]) -> list[NavRow]:
        """:meth:`step` over ``(t, cloud)`` pairs in time order; one row per frame."""
        return [self.step(t, cloud) for t, cloud in frame_pairs(frames)]

    def rectangles(self, cloud: PointCloud) -> Rects:
        """Whole rectangles of a frame (sensor frame) with the catalogue faces of their size.

        Each face is measured as a surface (every point weighted by its pixel's footprint,
        :func:`pixel_area_weights`) when ``config.area_weighted_centroid`` is set.
        """
        out = []
        weights = pixel_area_weights(cloud.points) if self.config.area_weighted_centroid else None
        planes = measure_planes(cloud, self.config.plane_config(), self.config.rectangle, weights)
        for found in planes:
            entries = candidates(
                found.measurement, list(self.catalogue.values()), self.config.rectangle
            )
            if not entries:
                continue
            out.append((found.measurement, entries))
        return out

    def recognise(
        self, cloud: PointCloud, R_pred: NDArray[np.float64] | None
    ) -> list[tuple[RectangleMeasurement, CatalogueEntry]]:
        """Rectangles of the frame named with a predicted attitude only (each name at most once).

        Faces of equal size are told apart by the predicted outward normal
        (:func:`spacepose.core.rectangles.recognise`); without a prediction they are left out.
        """
        named = []
        for m, entries in self.rectangles(cloud):
            name = recognise(m, entries, self.config.rectangle, R_pred)
            if name is not None:
                named.append((m, self.catalogue[name]))
        return _one_per_face(named)

    def _assign(
        self, ekf: RelativeNavEKF, rects: Rects
    ) -> list[tuple[RectangleMeasurement, CatalogueEntry]]:
        """The rectangles a filter's predicted pose explains, as catalogue faces (one per face)."""
        found = explained_rectangles(ekf.predict_pose(), rects)
        return _one_per_face([(rects[i][0], e) for i, e in found])

    def _start(self, t: float, cloud: PointCloud | None, rects: Rects) -> list[NDArray[np.float64]]:
        """Start poses ``T_sensor_model`` (4, 4): one from the prior, or the equally good
        lost-in-space hypotheses (none when the frame has no usable rectangle)."""
        R_prior = self.predicted_R_sensor_model(t)
        if R_prior is not None:
            config = self.config.rectangle
            named = [(m, e) for m, entries in rects
                     if (e := _named(m, entries, config, R_prior)) is not None]  # fmt: skip
            return [consistent_rectangles(_one_per_face(named), R_prior)] if named else []
        hypotheses = attitude_hypotheses(rects, self.config.lost_in_space.same_pose_deg)
        if not hypotheses or cloud is None:
            return []
        c = self.config.lost_in_space
        frame = FrameEvidence.build(cloud.points, rects, self.config.rectangle.sigma)
        poses = [h.T_sensor_model for h in hypotheses]
        if self.model is not None:
            poses = [refine_on_model(T, frame, self.model, c) for T in poses]
        scores = [explained_share(T, frame, self.model, c) for T in poses]
        keep = equally_good(scores, c.start_margin)[: c.max_candidates]
        return [poses[i] for i in keep]

    def _prune(self, cloud: PointCloud, rects: Rects, used: list[int]) -> list[int]:
        """Score every candidate at its estimate, drop those the data have decided against and
        those that became the same pose as a better one; the candidates left, best first (none
        when no candidate has explained half the data for ``decide_frames`` frames)."""
        c = self.config.lost_in_space
        frame = FrameEvidence.build(cloud.points, rects, self.config.rectangle.sigma)
        poses = [track.ekf.predict_pose() for track in self.tracks]
        if self.model is not None:
            poses = [refine_on_model(T, frame, self.model, c) for T in poses]
        scores = np.array([explained_share(T, frame, self.model, c) for T in poses])
        counted = scores.max() >= c.min_explained
        # A start on a glitched frame (moved metres) leaves candidates that explain nothing
        # after it: 60 frames stayed ambiguous. As many frames as decide between candidates.
        lost = scores.max() < _LOST_SHARE
        self._unexplained = self._unexplained + 1 if lost else 0
        if self._unexplained >= c.decide_frames:
            self.tracks, self._unexplained = [], 0
            return []
        for track, score in zip(self.tracks, scores, strict=True):
            if counted:
                track.deficits.append(float(scores.max() - score))
            track.explained = float(score)
        keep: list[int] = []
        for i in np.argsort(-scores, kind="stable"):
            d = np.array(self.tracks[i].deficits[-c.decide_frames :])
            # Behind the best in every one of the last frames, and by more than the margin.
            if len(d) == c.decide_frames and np.all(d > 0) and np.median(d) > c.ambiguity_margin:
                continue
            if any(_same_pose(poses[i], poses[j], c.same_pose_deg) for j in keep):
                continue
            keep.append(int(i))
        self.tracks = [self.tracks[i] for i in keep]
        return [used[i] for i in keep]

    def _start_filter(self, t: float, T_sensor_model: NDArray[np.float64]) -> RelativeNavEKF:
        return start_filter(t, T_sensor_model, self.n, self.R_O_C, self.config)

    def start_from_pose(self, t: float, T_sensor_model: ArrayLike) -> bool:
        """Start the filter from a pose measured otherwise (a registration) when none runs
        yet; whether it did. ``t`` is the time of the frame the pose belongs to."""
        if self.tracks:
            return False
        self.tracks = [_Track(self._start_filter(t, np.asarray(T_sensor_model, np.float64)))]
        return True

    def _update(
        self, track: _Track, rects: list[tuple[RectangleMeasurement, CatalogueEntry]]
    ) -> int:
        """Attitude then centroid updates of every rectangle; the number of rectangles used.

        Each covariance is the measurement model's times the factor the track has measured on
        its own innovations so far (:class:`InnovationScale`: noisier than modelled, or
        correlated from frame to frame).
        """
        ekf, used = track.ekf, 0
        att_factor, centroid_factor = track.attitude_scale.factor, track.centroid_scale.factor
        # Largest faces first: they constrain the attitude best before the others are gated.
        for m, e in sorted(rects, key=lambda p: -p[0].n_points):
            T = coarse_target_pose(m, e, ekf.predict_pose()[:3, :3])
            R_I_B = dynamics.R_I_O(self.n, ekf.t) @ self.R_O_C @ T[:3, :3]
            C_att = attitude_covariance(m, e, self.config)
            ok_att = ekf.update_attitude(Rotation.from_matrix(R_I_B).as_quat(), C_att * att_factor)
            if ok_att:
                track.attitude_scale.add(
                    e.name, self._steps, ekf.last_innovation, C_att, ekf.last_HPHt
                )
            C_c = centroid_covariance(m, e, self.config)
            ok_c = ekf.update_centroid(e.name, e.centre, m.centroid, C_c * centroid_factor)
            if ok_c:
                track.centroid_scale.add(
                    e.name, self._steps, ekf.last_innovation, C_c, ekf.last_HPHt
                )
            used += int(ok_att or ok_c)
        return used


def _named(
    m: RectangleMeasurement,
    entries: list[CatalogueEntry],
    config: RectangleConfig,
    R_pred: NDArray[np.float64],
) -> CatalogueEntry | None:
    """The entry a predicted attitude names among a rectangle's candidates, or None."""
    name = recognise(m, entries, config, R_pred)
    return next((e for e in entries if e.name == name), None)


def _one_per_face(
    pairs: list[tuple[RectangleMeasurement, CatalogueEntry]],
) -> list[tuple[RectangleMeasurement, CatalogueEntry]]:
    """Two planes matched to one face: keep the larger (the other is a fragment)."""
    best: dict[str, tuple[RectangleMeasurement, CatalogueEntry]] = {}
    for m, e in pairs:
        if e.name not in best or m.n_points > best[e.name][0].n_points:
            best[e.name] = (m, e)
    return list(best.values())


def _same_pose(T: NDArray[np.float64], U: NDArray[np.float64], same_pose_deg: float) -> bool:
    """Whether two poses' attitudes lie within ``same_pose_deg`` (their positions then agree
    to the filters' accuracy: every candidate fits the same points)."""
    angle = Rotation.from_matrix(T[:3, :3] @ U[:3, :3].T).magnitude()
    return bool(np.rad2deg(angle) < same_pose_deg)


def orbit_geometry(mean_motion: float, R_O_C: ArrayLike) -> tuple[float, NDArray[np.float64]]:
    """Mean motion n (rad/s) and ``R_O_C`` (3, 3) checked as a scenario file's are
    (:func:`~spacepose.core.nav_start.scenario_geometry`): text ended in numpy's ValueError, a
    NaN rate in "SVD did not converge", a reflection in scipy's, a negative rate navigated."""
    return scenario_geometry({"mean_motion": mean_motion, "R_O_C": R_O_C}, source=None)


def frame_pairs(frames: Iterable[tuple[float, PointCloud | None]]) -> Iterator[tuple]:
    """``(t, cloud)`` pairs of ``frames``, each checked to be a pair (None, or a bare cloud,
    ended in a TypeError)."""
    try:
        items = iter(frames)
    except TypeError:
        raise InputError(f"frames must be (t, cloud) pairs, got {type(frames).__name__}") from None
    for k, item in enumerate(items):
        if not isinstance(item, tuple | list) or len(item) != 2:
            raise InputError(f"frame {k} must be a (t, cloud) pair, got {type(item).__name__}")
        yield item[0], item[1]


def navigate(
    frames: Iterable[tuple[float, PointCloud]],
    catalogue: Sequence[CatalogueEntry],
    mean_motion: float,
    R_O_C: ArrayLike,
    config: NavigationConfig | None = None,
    model: PointCloud | None = None,
) -> list[NavRow]:
    """One call: run :class:`RelativeNavigator` over ``(t, cloud)`` frames, one row per frame."""
    return RelativeNavigator(catalogue, mean_motion, R_O_C, config, model).run(frames)
