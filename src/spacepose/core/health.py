"""The per-frame health check of the tracker (docs/methods.md §5.3): ``ok``, ``degraded``, ``lost``.

:class:`HealthBounds` turns the unit-free :class:`~spacepose.core.tracker_config.HealthConfig`
into metres and degrees for one frame, from the voxel edge, the target's radius and the motion
model's observed error; :func:`assess_health` applies them. The primitives (pose disagreement,
covariance about a point, unit-free twists and condition number) are public.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from spacepose.core import se3
from spacepose.core.part_influence import PartInfluence
from spacepose.core.residual_structure import Structure
from spacepose.core.tracker_config import HealthConfig

Status = Literal["ok", "degraded", "lost"]


# Reason of a registration that leaves a direction (nearly) unobserved: a view of a wall and a
# floor alone lets the pose slide along their corner.
CONDITION = "condition"
# Reason of a pose no prediction was there to confirm (a coarse pose found anywhere).
UNCONFIRMED = "no prediction to confirm the pose"
# Reason of a frame whose prediction is the last pose alone (the run's second frame).
NO_VELOCITY = "no velocity yet to confirm the pose"
# Reason of a registration less precise than the precision bounds (voxels of the first frame).
IMPRECISE = "registration sigma"


@dataclass(frozen=True)
class HealthBounds:
    """The health bounds of one frame in metres and degrees (see :class:`HealthConfig`).

    Attributes
    ----------
    ok_rmse, lost_rmse, ok_sigma_translation, ok_prediction_translation, ok_step_translation,
    max_motion_translation
        Metres.
    ok_sigma_rotation_deg, ok_prediction_rotation_deg, ok_step_rotation_deg,
    max_motion_rotation_deg
        Degrees.
    """

    min_points: int
    ok_fitness: float
    lost_fitness: float
    ok_rmse: float
    lost_rmse: float
    ok_condition: float
    lost_condition: float
    ok_sigma_translation: float
    ok_sigma_rotation_deg: float
    ok_prediction_translation: float
    ok_prediction_rotation_deg: float
    lost_prediction_factor: float
    ok_step_translation: float
    ok_step_rotation_deg: float
    ok_structure: float
    ok_shared_structure: float | None
    max_motion_translation: float
    max_motion_rotation_deg: float

    @classmethod
    def from_scale(
        cls,
        config: HealthConfig,
        voxel: float,
        radius: float,
        model_error: tuple[float, float] | None = None,
        model_reference: bool = False,
        noise_factor: float = 1.0,
    ) -> HealthBounds:
        """Bounds for a voxel edge ``voxel`` (m) and a target radius ``radius`` (m).

        ``model_error`` is the motion model's observed RMS error (centroid displacement m,
        rotation rad); the prediction bounds widen to ``model_error_sigmas`` times it.
        ``model_reference``: frames are registered onto a model, and the ok fitness is
        ``model_fitness``. ``noise_factor`` (>= 1): the measured residual noise widened the
        fine gate this many times beyond its voxel value; the RMSE bounds widen as much, since
        the inlier RMSE grows with the gate and the noise, so that a sensor noisier than its
        sampling is not degraded for its noise alone. The precision bounds stay in voxels:
        widened too, they let rocket bodies 17-45° off about their axis be ok (the σ bound
        alone held them; methods.md §5.3).
        """
        noisy = voxel * max(1.0, noise_factor)

        def deg_at_radius(voxels: float) -> float:
            return math.degrees(voxels * voxel / radius)

        ok_pred_t = config.ok_prediction_translation * voxel
        ok_pred_r = deg_at_radius(config.ok_prediction_rotation)
        if model_error is not None:
            n = config.model_error_sigmas
            ok_pred_t = max(ok_pred_t, n * model_error[0])
            ok_pred_r = max(ok_pred_r, math.degrees(n * model_error[1]))
        return cls(
            min_points=config.min_points,
            ok_fitness=config.model_fitness if model_reference else config.ok_fitness,
            lost_fitness=config.lost_fitness,
            ok_rmse=config.ok_rmse * noisy,
            lost_rmse=config.lost_rmse * noisy,
            ok_condition=config.ok_condition,
            lost_condition=config.lost_condition,
            ok_sigma_translation=config.ok_sigma_translation * voxel,
            ok_sigma_rotation_deg=deg_at_radius(config.ok_sigma_rotation),
            ok_prediction_translation=ok_pred_t,
            ok_prediction_rotation_deg=ok_pred_r,
            lost_prediction_factor=config.lost_prediction_factor,
            ok_step_translation=config.ok_step_translation * voxel,
            ok_step_rotation_deg=deg_at_radius(config.ok_step_rotation),
            ok_structure=config.ok_structure,
            ok_shared_structure=config.ok_shared_structure,
            max_motion_translation=config.max_motion * radius,
            max_motion_rotation_deg=math.degrees(config.max_motion),
        )


def covariance_at(covariance: NDArray[np.float64], point: ArrayLike) -> NDArray[np.float64]:
    """Covariance of a left perturbation re-expressed about ``point`` (3,) instead of the origin.

    The rotation part is unchanged; the translation part becomes the displacement of ``point``,
    so a rotation about a far origin no longer shows up as a large translation.
    """
    # The point moves by v + ω × c = v − skew(c) ω under a left perturbation (ω, v).
    J = np.eye(6)
    J[3:, :3] = -se3.skew(np.asarray(point, dtype=np.float64))
    return J @ covariance @ J.T


def normalising_map(centroid: ArrayLike, radius: float) -> NDArray[np.float64]:
    """(6, 6) ``M`` taking a unit-free twist ``η = (ρ, v_c)`` to the twist ``ξ = M η`` about the
    origin: ``v_c`` the translation of ``centroid`` (3,), ``ρ = r ω`` the rotation as the
    displacement it gives at ``radius`` (m). An information ``Λ`` in ξ is ``Mᵀ Λ M`` in η."""
    # About the origin a twist about c is (ω, v_c + skew(c) ω): the inverse of covariance_at.
    M = np.eye(6)
    M[3:, :3] = se3.skew(np.asarray(centroid, dtype=np.float64))
    # ω = ρ / r: the information of ρ is that of ω over r².
    return M @ np.diag([1.0 / radius] * 3 + [1.0] * 3)


def normalised_condition(
    information: NDArray[np.float64], centroid: ArrayLike, radius: float
) -> float:
    """Condition number of an information matrix made unit-free (see :class:`HealthConfig`)."""
    M = normalising_map(centroid, radius)
    info = M.T @ information @ M
    ev = np.linalg.eigvalsh(0.5 * (info + info.T))
    return float(ev[-1] / ev[0]) if ev[0] > 0 else float("inf")


def pose_disagreement(
    T_a: NDArray[np.float64], T_b: NDArray[np.float64], point: ArrayLike
) -> tuple[float, float]:
    """(displacement of ``point`` in m, rotation angle in degrees) between two poses of it."""
    D = T_a @ se3.invert(T_b)
    p = np.asarray(point, dtype=np.float64)
    moved = se3.transform_points(D, p[None])[0]
    cos = np.clip((np.trace(D[:3, :3]) - 1.0) / 2.0, -1.0, 1.0)
    return float(np.linalg.norm(moved - p)), float(np.degrees(np.arccos(cos)))


def step_size(step: NDArray[np.float64], point: NDArray[np.float64]) -> tuple[float, float]:
    """(displacement of ``point`` in m, rotation in degrees) of a small twist ``step`` (6,)."""
    omega, v = step[:3], step[3:]
    return float(np.linalg.norm(v + np.cross(omega, point))), float(
        np.degrees(np.linalg.norm(omega))
    )


def assess_health(
    fitness: float,
    rmse: float,
    condition: float,
    own_covariance: NDArray[np.float64],
    centroid: NDArray[np.float64],
    disagreement: tuple[float, float] | None,
    bounds: HealthBounds,
    velocity_known: bool = True,
    surface_step: tuple[float, float] = (0.0, 0.0),
    model_reference: bool = False,
    structure: Structure | None = None,
    influence: PartInfluence | None = None,
) -> tuple[Status, tuple[str, ...]]:
    """Status and reasons of one registered frame.

    Parameters
    ----------
    fitness, rmse, condition
        Of the fine registration (rmse in m; condition from :func:`normalised_condition`).
    own_covariance
        (6, 6) covariance of the frame's own registration, about the origin.
    centroid
        (3,) point at which translations are measured (the cloud's centroid).
    disagreement
        :func:`pose_disagreement` against the prediction, or None when there is none (then
        the frame is at best degraded: unconfirmed).
    bounds
        From :meth:`HealthBounds.from_scale`.
    velocity_known
        False when the prediction is only the last pose: the motion bound applies, and the
        frame is at best degraded (unconfirmed) unless ``model_reference``.
    surface_step
        (displacement m, rotation deg) of the point-to-plane step from the registered pose.
    model_reference
        The frame was registered onto a model: its fit to the model confirms it (two views of
        one sensor share a sampling and its noise; a model shares neither).
    structure
        :func:`~spacepose.core.residual_structure.structure_of` the registration (None: not
        measured; the tracker measures it onto keyframes only).
    influence
        :func:`~spacepose.core.part_influence.part_influence` of the registration (None: not
        measured; likewise onto keyframes only).
    """
    lost: list[str] = []
    weak: list[str] = []
    b = bounds
    if fitness < b.lost_fitness:
        lost.append(f"fitness {fitness:.2f} < {b.lost_fitness}")
    elif fitness < b.ok_fitness:
        weak.append(f"fitness {fitness:.2f} < {b.ok_fitness}")
    if rmse > b.lost_rmse:
        lost.append(f"rmse {1e3 * rmse:.2f} mm > {1e3 * b.lost_rmse:.2f} mm")
    elif rmse > b.ok_rmse:
        weak.append(f"rmse {1e3 * rmse:.2f} mm > {1e3 * b.ok_rmse:.2f} mm")
    if not condition <= b.lost_condition:
        lost.append(f"{CONDITION} {condition:.3g} > {b.lost_condition:.3g}")
    elif condition > b.ok_condition:
        weak.append(f"{CONDITION} {condition:.3g} > {b.ok_condition:.3g}")
    cov_c = covariance_at(own_covariance, centroid)
    sig_t = float(np.sqrt(max(np.linalg.eigvalsh(cov_c[3:, 3:])[-1], 0.0)))
    sig_r = float(np.degrees(np.sqrt(max(np.linalg.eigvalsh(cov_c[:3, :3])[-1], 0.0))))
    if sig_t > b.ok_sigma_translation or sig_r > b.ok_sigma_rotation_deg:
        weak.append(f"{IMPRECISE} {1e3 * sig_t:.2f} mm / {sig_r:.3f} deg too large")
    st, sr = surface_step
    f = b.lost_prediction_factor
    msg = f"{1e3 * st:.2f} mm / {sr:.3f} deg off the surface optimum"
    if st > f * b.ok_step_translation or sr > f * b.ok_step_rotation_deg:
        lost.append(msg)
    elif st > b.ok_step_translation or sr > b.ok_step_rotation_deg:
        weak.append(msg)
    if structure is not None and structure.shows_another_motion(
        b.ok_structure, b.ok_shared_structure
    ):
        weak.append(
            f"residual structure {structure.within:.1f} > {b.ok_structure:g}: part of the cloud "
            "fits another motion"
        )
    if influence is not None and influence.excessive:
        weak.append(
            f"part influence {influence.largest:.1f} > {influence.bound:.1f}: leaving one part "
            "out moves the pose beyond its sigma"
        )
    if disagreement is None:
        weak.append(UNCONFIRMED)
    else:
        dt, dr = disagreement
        ok_t, ok_r = b.ok_prediction_translation, b.ok_prediction_rotation_deg
        if not velocity_known:
            # The last pose alone bounds the motion but confirms no pose within the bound: a
            # second frame's registration can stop well short of the true step (11 of the 26
            # false oks of the robustness grid's clean constant-motion cells were second
            # frames).
            ok_t, ok_r = b.max_motion_translation, b.max_motion_rotation_deg
            if not model_reference:
                weak.append(NO_VELOCITY)
        msg = f"off the prediction by {1e3 * dt:.1f} mm / {dr:.2f} deg"
        if dt > f * ok_t or dr > f * ok_r:
            lost.append(msg)
        elif dt > ok_t or dr > ok_r:
            weak.append(msg)
    if lost:
        return "lost", tuple(lost + weak)
    return ("degraded" if weak else "ok"), tuple(weak)
