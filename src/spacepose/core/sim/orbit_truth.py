"""Truth of the orbit run from physics the navigation filter does not share (methods.md §3).

The filter (:mod:`spacepose.core.ekf`) models the relative translation with the linear
Clohessy–Wiltshire equations in a frame O turning uniformly at the mean motion n, and the
target's attitude with torque-free Euler equations in the inertia ratios, integrated by its own
RK4. The truth here is made independently:

* **Orbits.** Chaser and target are propagated in Earth-centred inertial coordinates (ECI, z the
  Earth's pole) under two-body gravity, the J2 zonal term and optionally drag (a constant density
  and a ballistic coefficient ``C_D A / m`` per spacecraft; the atmosphere does not rotate), by
  scipy's DOP853 with tight tolerances. The state integrated is the chaser's ``(r, v)`` and the
  target's offset ``(δr, δv)`` from it, the offset's acceleration being ``a(r + δr) − a(r)``:
  the error control then acts on the 25 m offset itself, not on 7000 km.
* **Attitude.** ``R_I_B`` and ω are integrated as a rotation matrix ``Ṙ = R [ω]×`` and the full
  Euler equations ``I ω̇ = −ω × I ω`` in the principal moments (DOP853), not the filter's
  quaternion and ratio form.

Frames handed to the filter
---------------------------
The filter's inertial frame I is the chaser's LVLH frame at t = 0 (x along-track, z to the
Earth's centre, y against the orbital angular momentum); its O is I turned about −y by ``n t``
with ``n = √(μ / a³)`` of the chaser's initial osculating orbit. The chaser keeps its sensor
attitude ``R_O_C`` fixed in that uniformly turning frame (a constant-rate pitch its attitude
control commands in inertial terms, so the filter's ``R_I_O(n, t) R_O_C`` is its true inertial
attitude). The relative state is ``ρ = R_O_I(t) (r_T − r_C)`` and ``ρ̇ = dρ/dt`` (components
in O), exactly what the filter estimates. On a near-circular orbit O stays within a few
millidegrees of the chaser's true LVLH frame over a run; on an eccentric one they part by up to
``2e`` rad, and the CW model's error grows accordingly (what the filter misses, as process
noise: :mod:`spacepose.core.sim.process_noise`).

Knowledge errors: the filter is handed the chaser attitude and the rectangle catalogue with
seeded errors (:func:`misaligned`, :func:`perturbed_catalogue`); the truth uses the exact ones.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.integrate import solve_ivp
from scipy.spatial.transform import Rotation

from spacepose.core import se3
from spacepose.core.sim.targets import Rectangle
from spacepose.errors import InputError

EARTH_MU = 3.986004418e14  # m³/s², WGS-84
EARTH_RADIUS = 6378137.0  # m, WGS-84 equatorial
EARTH_J2 = 1.08262668e-3  # EGM2008 / WGS-84 second zonal harmonic
RTOL = 1e-12  # relative tolerance of every truth integration


@dataclass(frozen=True)
class ForceModel:
    """Forces on both spacecraft.

    Attributes
    ----------
    j2
        Include the Earth's J2 term.
    drag_density
        Constant air density, kg/m³ (0: no drag).
    ballistic_chaser, ballistic_target
        ``C_D A / m`` of each spacecraft, m²/kg.
    """

    j2: bool = True
    drag_density: float = 0.0
    ballistic_chaser: float = 0.0
    ballistic_target: float = 0.0


def mean_motion(altitude_m: float) -> float:
    """Mean motion n (rad/s) of a circular Earth orbit at the given altitude."""
    return math.sqrt(EARTH_MU / (EARTH_RADIUS + altitude_m) ** 3)


def acceleration(
    r: NDArray[np.float64], v: NDArray[np.float64], ballistic: float, force: ForceModel
) -> NDArray[np.float64]:
    """Acceleration (3,) in ECI, m/s², of a spacecraft under ``force``.

    Parameters
    ----------
    r, v
        (3,) ECI position (m) and velocity (m/s).
    ballistic
        The spacecraft's ``C_D A / m``, m²/kg (used only with drag).
    force
        Which forces act.
    """
    rn2 = float(r @ r)
    rn = math.sqrt(rn2)
    a = -EARTH_MU / (rn2 * rn) * r
    if force.j2:
        z2 = r[2] ** 2 / rn2
        c = -1.5 * EARTH_J2 * EARTH_MU * EARTH_RADIUS**2 / rn2**2 / rn
        a = a + c * r * np.array([1.0 - 5.0 * z2, 1.0 - 5.0 * z2, 3.0 - 5.0 * z2])
    if force.drag_density > 0 and ballistic > 0:
        a = a - 0.5 * force.drag_density * ballistic * math.sqrt(float(v @ v)) * v
    return a


def keplerian_state(
    a: float, e: float, inclination: float, raan: float, arg_perigee: float, true_anomaly: float
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """ECI position (3,, m) and velocity (3,, m/s) from Keplerian elements.

    Parameters
    ----------
    a, e
        Semi-major axis (m) and eccentricity (0 <= e < 1).
    inclination, raan, arg_perigee, true_anomaly
        Angles, rad (ECI: z the Earth's pole, x the node reference).
    """
    if not (a > 0 and 0 <= e < 1):
        raise InputError(f"orbit needs a > 0 and 0 <= e < 1, got a={a}, e={e}")
    p = a * (1.0 - e**2)
    c, s = math.cos(true_anomaly), math.sin(true_anomaly)
    r_pf = p / (1.0 + e * c) * np.array([c, s, 0.0])
    v_pf = math.sqrt(EARTH_MU / p) * np.array([-s, e + c, 0.0])
    R = Rotation.from_euler("ZXZ", [raan, inclination, arg_perigee]).as_matrix()
    return R @ r_pf, R @ v_pf


def lvlh_basis(r: ArrayLike, v: ArrayLike) -> NDArray[np.float64]:
    """``R_ECI_O`` (3, 3): columns x (along-track), y (−orbit normal), z (nadir) of the LVLH."""
    r, v = np.asarray(r, dtype=np.float64), np.asarray(v, dtype=np.float64)
    z = -r / np.linalg.norm(r)
    h = np.cross(r, v)
    y = -h / np.linalg.norm(h)
    return np.column_stack([np.cross(y, z), y, z])


def propagate_pair(
    r_chaser: ArrayLike,
    v_chaser: ArrayLike,
    dr: ArrayLike,
    dv: ArrayLike,
    t: ArrayLike,
    force: ForceModel | None = None,
) -> NDArray[np.float64]:
    """Chaser and target in ECI at times ``t`` (N,), s, the initial state being at ``t[0]``.

    Parameters
    ----------
    r_chaser, v_chaser
        (3,) the chaser's ECI position (m) and velocity (m/s) at ``t[0]``.
    dr, dv
        (3,) the target's offset from the chaser, ECI, m and m/s, at ``t[0]``.
    t
        (N,) increasing output times, s.
    force
        Forces on both spacecraft.

    Returns
    -------
    (N, 12) rows ``(r_C, v_C, δr, δv)``: the chaser's position and velocity and the target's
    offset ``r_T − r_C``, ``v_T − v_C``, ECI, SI. ``force`` defaults to two-body + J2.
    """
    force = force or ForceModel()
    t = np.asarray(t, dtype=np.float64)
    y0 = np.concatenate([r_chaser, v_chaser, dr, dv]).astype(np.float64)
    bc, bt = force.ballistic_chaser, force.ballistic_target

    def f(_: float, y: NDArray[np.float64]) -> NDArray[np.float64]:
        a_c = acceleration(y[:3], y[3:6], bc, force)
        a_t = acceleration(y[:3] + y[6:9], y[3:6] + y[9:12], bt, force)
        return np.concatenate([y[3:6], a_c, y[9:12], a_t - a_c])

    scale = np.repeat([1.0, 1e-3, 1e-6, 1e-9], 3)  # m, m/s, and the offset's smaller scale
    return _integrate(f, y0, t, RTOL * scale)


def _integrate(
    f: Callable[[float, NDArray[np.float64]], NDArray[np.float64]],
    y0: NDArray[np.float64],
    t: NDArray[np.float64],
    atol: float | NDArray[np.float64],
) -> NDArray[np.float64]:
    """DOP853 from ``y0`` at ``t[0]``, states (N, len(y0)) at ``t``."""
    if t.ndim != 1 or len(t) == 0 or np.any(np.diff(t) <= 0):
        raise InputError("truth times must be a non-empty increasing 1-D array")
    if t[-1] == t[0]:
        return y0[None, :].copy()
    sol = solve_ivp(f, (t[0], t[-1]), y0, method="DOP853", t_eval=t, rtol=RTOL, atol=atol)
    if not sol.success:  # pragma: no cover - DOP853 on a smooth field does not fail
        raise InputError(f"truth integration failed: {sol.message}")
    return sol.y.T


@dataclass(frozen=True, eq=False)
class RelativeTruth:
    """Relative translation of the run in the filter's frames.

    Attributes
    ----------
    t
        (N,) s since the epoch where I and O coincide.
    rho_O, v_O
        (N, 3) ρ = target CoM − chaser CoM and its time derivative, components in O.
    eci
        (N, 12) the integrated ECI states (see :func:`propagate_pair`).
    R_eci_I
        (3, 3) the filter's inertial frame I in ECI (the chaser's LVLH at t = 0).
    mean_motion
        n, rad/s, of the chaser's initial osculating orbit: O turns about −y at n.
    """

    t: NDArray[np.float64]
    rho_O: NDArray[np.float64]
    v_O: NDArray[np.float64]
    eci: NDArray[np.float64]
    R_eci_I: NDArray[np.float64]
    mean_motion: float


def relative_truth(
    r_chaser: ArrayLike,
    v_chaser: ArrayLike,
    rho0_O: ArrayLike,
    v0_O: ArrayLike,
    t: ArrayLike,
    force: ForceModel | None = None,
) -> RelativeTruth:
    """Propagate chaser and target and express ρ, ρ̇ in the filter's O frame.

    Parameters
    ----------
    r_chaser, v_chaser
        (3,) the chaser's ECI position (m) and velocity (m/s) at t = 0.
    rho0_O, v0_O
        (3,) the target's position (m) in the chaser's LVLH at t = 0 (= O = I then), and its
        velocity (m/s) relative to that frame turning at the chaser's true orbital rate
        ``|r × v| / r²`` (so ``v0_O = 0`` keeps station to first order).
    t
        (N,) increasing times, s, from ``t[0] = 0`` (the epoch where I and O coincide).
    force
        Forces on both spacecraft (default two-body + J2).
    """
    r_c, v_c = np.asarray(r_chaser, dtype=np.float64), np.asarray(v_chaser, dtype=np.float64)
    rho0, v0 = np.asarray(rho0_O, dtype=np.float64), np.asarray(v0_O, dtype=np.float64)
    R_eci_I = lvlh_basis(r_c, v_c)
    rate = np.linalg.norm(np.cross(r_c, v_c)) / float(r_c @ r_c)
    dr = R_eci_I @ rho0
    dv = R_eci_I @ (v0 + np.cross([0.0, -rate, 0.0], rho0))
    t = np.asarray(t, dtype=np.float64)
    if t.ndim != 1 or len(t) == 0 or t[0] != 0.0:
        raise InputError("relative_truth needs times starting at the epoch t = 0")
    eci = propagate_pair(r_c, v_c, dr, dv, t, force)
    a = 1.0 / (2.0 / np.linalg.norm(r_c) - float(v_c @ v_c) / EARTH_MU)
    n = math.sqrt(EARTH_MU / a**3)
    R_O_I = Rotation.from_rotvec(np.outer(n * t, [0.0, -1.0, 0.0])).inv().as_matrix()
    rho = np.einsum("nij,nj->ni", R_O_I, eci[:, 6:9] @ R_eci_I)
    # d/dt of O components of an inertial vector u: R_O_I u̇ − ω × u_O, ω = (0, −n, 0) in O.
    v = np.einsum("nij,nj->ni", R_O_I, eci[:, 9:12] @ R_eci_I) - np.cross([0.0, -n, 0.0], rho)
    return RelativeTruth(t, rho, v, eci, R_eci_I, n)


def torque_free_attitude(
    R_I_B0: ArrayLike, omega_B0: ArrayLike, inertia_diag: ArrayLike, t: ArrayLike
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Torque-free rotation of a rigid body at times ``t`` (N,), s, the initial state at ``t[0]``.

    Integrates ``Ṙ_I_B = R_I_B [ω]×`` and ``I ω̇ = −ω × (I ω)`` by DOP853.

    Parameters
    ----------
    R_I_B0
        (3, 3) initial attitude, body B -> inertial I.
    omega_B0
        (3,) initial rate in B, rad/s.
    inertia_diag
        (3,) principal moments (any common scale), B's axes.
    t
        (N,) increasing times, s.

    Returns
    -------
    q_I_B (N, 4) scalar-last, sign kept continuous, and ω_B (N, 3), rad/s.
    """
    inertia = np.asarray(inertia_diag, dtype=np.float64)
    if inertia.shape != (3,) or np.any(inertia <= 0):
        raise InputError(f"principal moments must be 3 positive numbers, got {inertia_diag}")
    y0 = np.concatenate([np.asarray(R_I_B0, dtype=np.float64).ravel(), omega_B0])

    def f(_: float, y: NDArray[np.float64]) -> NDArray[np.float64]:
        R, w = y[:9].reshape(3, 3), y[9:]
        return np.concatenate([(R @ se3.skew(w)).ravel(), -np.cross(w, inertia * w) / inertia])

    y = _integrate(f, y0, np.asarray(t, dtype=np.float64), RTOL * 1e-3)
    q = Rotation.from_matrix(y[:, :9].reshape(-1, 3, 3)).as_quat()
    flip = np.cumprod(np.where(np.einsum("ni,ni->n", q[1:], q[:-1]) < 0, -1.0, 1.0))
    q[1:] *= flip[:, None]
    return q, y[:, 9:]


def misaligned(R: ArrayLike, sigma_rad: float, rng: np.random.Generator) -> NDArray[np.float64]:
    """``R · exp([φ]×)`` (3, 3) with φ ~ N(0, σ² I) (3,): a rotation known to σ per axis."""
    phi = sigma_rad * rng.standard_normal(3)
    return np.asarray(R, dtype=np.float64) @ Rotation.from_rotvec(phi).as_matrix()


def perturbed_catalogue(
    rectangles: Sequence[Rectangle], sigma_m: float, rng: np.random.Generator
) -> list[Rectangle]:
    """The catalogue as the filter knows it: centres and sides off by N(0, σ²) each, metres.

    The orientation is kept (a face's normal is known far better than its extent); the sides
    stay ordered ``a <= b``.
    """
    known = []
    for r in rectangles:
        dc = sigma_m * rng.standard_normal(3)
        da, db = sigma_m * rng.standard_normal(2)
        a, b = r.a + da, r.b + db
        known.append(Rectangle(r.name, r.center + dc, r.R_model_plane, min(a, b), max(a, b)))
    return known
