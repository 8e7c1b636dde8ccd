"""The lab scene of methods.md §3: the target's motion profiles, its size and the clutter around it.

The sensor is fixed and level (sensor −y is up). The table frame has the sensor's axes and its
origin on the turntable axis at the target-frame origin, ``range_m`` ahead; the slide carries it
along sensor x. Frame k of N, with ``c_k = k − (N − 1)/2``:

- ``constant`` (the lab run): slide offset ``c_k·step_m``, turntable angle ``θ_0 + c_k·step_deg``
  about the vertical; ``T_sensor_target = Trans(x_k, 0, range) · Rot(−y, θ_k) · R_table_model``.
- ``accelerating``: both rates ramp up linearly, from about 0 in the first step to about twice
  the constant step in the last: ``x_k = step_m·(k²/(N − 1) − (N − 1)/2)``, likewise the angle.
  The extremes, hence the field of view covered, are those of ``constant``.
- ``tumbling``: the slide as in ``constant``; the attitude is the closed-form torque-free motion
  of an axisymmetric body (transverse / axial inertia 2): the symmetry axis ``e`` keeps the
  angle ``tumble_cone_deg`` to the fixed angular momentum ``h`` and precesses about it while the
  body spins about ``e``, ``R_k = Rot(h, k·α) · Rot(e_0, k·ρα) · R_0`` with the spin-to-
  precession ratio ``ρ = cos(cone)·(2 − 1)``. The step from frame k to k + 1 is
  ``Rot(h, α) · Rot(e_k, ρα)`` with ``e_k = Rot(h, kα) e_0``: the same angle every frame (α is
  solved so that it equals ``tumble_deg``) about an axis that turns about ``h`` frame by frame.
  No estimator model enters: the truth is these closed-form rotations.

The clutter (``background``) is a wall fixed in the sensor frame that covers the view at its
distance, and a turntable (post, disc, plinth) under the target carried by the slide; the
turntable scales with the target (``target_size_m``), the wall with its distance. Reflectances:
the target 1 (white mock-up), the wall :data:`WALL_ALBEDO`, the turntable :data:`TABLE_ALBEDO`.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING, Literal

import numpy as np
import trimesh
from numpy.typing import NDArray
from scipy.optimize import brentq
from scipy.spatial.transform import Rotation

from spacepose.core.sim.targets import Rectangle, Target

if TYPE_CHECKING:
    from spacepose.core.sim.scenarios import LabConfig

MotionProfile = Literal["constant", "accelerating", "tumbling"]
# Largest extent of the lab mock-up (its wing span), m: the turntable is sized for it.
LAB_TARGET_EXTENT_M = 0.89
WALL_ALBEDO = 0.6
TABLE_ALBEDO = 0.3
# Transverse over axial inertia of the tumbling body (a prolate one, like the mock-up).
_TUMBLE_INERTIA_RATIO = 2.0
# Fixed angular momentum direction of the tumbling profile, sensor frame (near the vertical).
_TUMBLE_H = np.array([0.3, -1.0, 0.2]) / np.linalg.norm([0.3, -1.0, 0.2])

Background = tuple[tuple[trimesh.Trimesh, NDArray[np.float64]], ...]


def R_table_model(tilt_deg: float) -> Rotation:
    """Model +z (dish) towards the sensor, wings along sensor x, then the tilt about the wings."""
    return Rotation.from_euler("yx", [180.0, tilt_deg], degrees=True)


def ramp(profile: MotionProfile, frames: int, step: float) -> NDArray[np.float64]:
    """(N,) offsets of a slide or turntable whose per-frame step is ``step`` on average.

    ``constant`` and ``tumbling`` give ``c_k·step``, ``accelerating`` the quadratic ramp of the
    module notes; both span ``±step·(N − 1)/2``.
    """
    k = np.arange(frames, dtype=np.float64)
    if profile != "accelerating":
        return (k - 0.5 * (frames - 1)) * step
    span = max(frames - 1, 1)
    return step * (k**2 / span - 0.5 * (frames - 1))


def tumble_step_angle(alpha: float, cone_rad: float) -> float:
    """Angle (rad) of ``Rot(h, α) · Rot(e, ρα)`` with ``∠(h, e) = cone``, ρ as in the notes."""
    spin = math.cos(cone_rad) * (_TUMBLE_INERTIA_RATIO - 1.0) * alpha
    half = math.cos(0.5 * alpha) * math.cos(0.5 * spin)
    half -= math.sin(0.5 * alpha) * math.sin(0.5 * spin) * math.cos(cone_rad)
    return 2.0 * math.acos(min(1.0, abs(half)))


def tumbling_rotations(
    frames: int, step_deg: float, cone_deg: float, R_start: Rotation
) -> Rotation:
    """(N,) attitudes ``R_k`` of the tumbling profile (module notes), starting at ``R_start``.

    Parameters
    ----------
    frames
        N.
    step_deg
        Rotation angle of every frame-to-frame step, deg (0 to 90).
    cone_deg
        Angle between the spin axis and the angular momentum, deg (0 to below 90).
    R_start
        Attitude of frame 0 (target frame into sensor frame).
    """
    theta, cone = math.radians(step_deg), math.radians(cone_deg)
    alpha = 0.0
    if theta > 0:
        alpha = brentq(lambda a: tumble_step_angle(a, cone) - theta, 0.0, theta, xtol=1e-15)
    spin = math.cos(cone) * (_TUMBLE_INERTIA_RATIO - 1.0) * alpha
    side = np.cross(_TUMBLE_H, [0.0, 0.0, 1.0])
    e0 = Rotation.from_rotvec(cone * side / np.linalg.norm(side)).apply(_TUMBLE_H)
    k = np.arange(frames, dtype=np.float64)[:, None]
    precess = Rotation.from_rotvec(k * alpha * _TUMBLE_H)
    return precess * Rotation.from_rotvec(k * spin * e0) * R_start


def lab_poses(config: LabConfig) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """True poses of the lab run: ``T_sensor_table`` and ``T_sensor_target``, each (N, 4, 4)."""
    n = config.frames
    up = np.array([0.0, -1.0, 0.0])
    R_start = R_table_model(config.tilt_deg)
    if config.motion == "tumbling":
        R0 = Rotation.from_rotvec(math.radians(config.yaw_center_deg) * up) * R_start
        R_sensor_target = tumbling_rotations(n, config.tumble_deg, config.tumble_cone_deg, R0)
    else:
        yaw = np.radians(config.yaw_center_deg + ramp(config.motion, n, config.step_deg))
        R_sensor_target = Rotation.from_rotvec(yaw[:, None] * up) * R_start
    T_sensor_table = np.tile(np.eye(4), (n, 1, 1))
    T_sensor_table[:, 0, 3] = ramp(config.motion, n, config.step_m)
    T_sensor_table[:, 2, 3] = config.range_m
    T_sensor_target = T_sensor_table.copy()
    T_sensor_target[:, :3, :3] = R_sensor_target.as_matrix()
    return T_sensor_table, T_sensor_target


def table_scale(config: LabConfig) -> float:
    """Scale of the turntable and slide geometry: 1 for the mock-up's native size."""
    size = config.target_size_m
    return 1.0 if size is None else size / LAB_TARGET_EXTENT_M


def sized_target(target: Target, size_m: float | None, align: bool = False) -> Target:
    """``target`` scaled about its model origin so its largest extent is ``size_m`` (None: as is).

    With ``align``, the mesh is first turned so that its bounding box's longest side lies along
    model x (the mock-up's wing axis) and its shortest along model z (towards the sensor), so
    that a mesh file of any orientation shows its broad side to the sensor. The rectangle catalogue
    scales (and turns) with it; so do the parts, so hidden surface samples are still recognised.
    """
    if size_m is None:
        return target
    R = np.eye(3)
    if align:
        small, mid, large = np.argsort(target.mesh.extents, kind="stable")
        R = np.eye(3)[[large, mid, small]]
        R[2] *= np.linalg.det(R)  # a proper rotation
    factor = size_m / float(np.max(target.mesh.extents))
    if abs(factor - 1.0) < 1e-12 and not align:  # the size it has, up to rounding: keep its bits
        return target
    T = np.eye(4)
    T[:3, :3] = factor * R
    rects = tuple(
        Rectangle(r.name, factor * R @ r.center, R @ r.R_model_plane, factor * r.a, factor * r.b)
        for r in target.rectangles
    )
    parts = tuple(p.copy().apply_transform(T) for p in target.parts)
    return Target(target.name, target.mesh.copy().apply_transform(T), rects, parts)


def lab_background(
    config: LabConfig, target: Target, T_sensor_table: NDArray[np.float64]
) -> tuple[Background, tuple[float, ...]]:
    """The wall (fixed) and the turntable (on the slide; left out with ``config.turntable``
    False), and the albedo of target and parts.

    Returns
    -------
    background, albedo
        Each part with its (N, 4, 4) poses in the sensor frame; the reflectances of the target
        and of each part, in that order.
    """
    d = config.wall_distance_m
    wall = trimesh.creation.box(bounds=[(-1.5 * d, -1.0 * d, d), (1.5 * d, 1.0 * d, d + 0.05)])
    fixed = np.tile(np.eye(4), (config.frames, 1, 1))
    if not config.turntable:
        return ((wall, fixed),), (config.target_albedo, WALL_ALBEDO)
    s = table_scale(config)
    # Turning about the vertical keeps heights, so the lowest target point is the same in
    # every frame; the disc sits 5 cm below it (y is down). A tumbling target can turn any
    # point downwards: the disc then sits below its bounding sphere.
    if config.motion == "tumbling":
        low = float(np.linalg.norm(target.mesh.vertices, axis=1).max()) + 0.05 * s
    else:
        tilted = target.mesh.vertices @ R_table_model(config.tilt_deg).as_matrix().T
        low = float(tilted[:, 1].max()) + 0.05 * s
    disc_t = 0.02 * s
    post = trimesh.creation.cylinder(0.01 * s, segment=[(0.0, 0.0, 0.0), (0.0, low, 0.0)])
    disc = trimesh.creation.cylinder(
        0.25 * s, segment=[(0.0, low, 0.0), (0.0, low + disc_t, 0.0)], sections=64
    )
    plinth = trimesh.creation.box(
        bounds=[(-0.2 * s, low + disc_t, -0.2 * s), (0.2 * s, low + disc_t + 1.0 * s, 0.2 * s)]
    )
    table = trimesh.util.concatenate([post, disc, plinth])
    albedo = (config.target_albedo, WALL_ALBEDO, TABLE_ALBEDO)
    return ((wall, fixed), (table, T_sensor_table)), albedo
