"""Relative orbital and attitude dynamics (methods.md §2.4, Yu §3): pure functions.

Frames and conventions (shared with the simulator)
--------------------------------------------------
* O, the target's orbital frame: x along the flight direction, z towards the Earth's centre,
  y = z × x (against the orbital angular momentum). O rotates relative to the inertial frame I
  about −y_O at the mean motion n; I coincides with O at t = 0.
* A relative state ``state6 = (x, y, z, vx, vy, vz)`` is ρ = target CoM − chaser CoM and its
  time derivative, both in O (Clohessy–Wiltshire / Hill equations).
* Attitude ``q_I_B`` is a scalar-last quaternion (x, y, z, w) mapping target body coordinates B
  into I; ``omega_B`` is the target's angular rate in B.
* Inertia ratios ``k = ((Iyy−Izz)/Ixx, (Izz−Ixx)/Iyy, (Ixx−Iyy)/Izz)``; Euler's torque-free
  equations read ``ω̇ = (k_x ω_y ω_z, k_y ω_z ω_x, k_z ω_x ω_y)``.
"""

from __future__ import annotations

from collections.abc import Callable

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from spacepose.core import se3
from spacepose.errors import InputError


def _vector(values: ArrayLike, size: int, name: str) -> NDArray[np.float64]:
    arr = se3.real_array(values, name)
    if arr.shape != (size,):
        raise InputError(f"{name} must have shape ({size},), got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise InputError(f"{name} has non-finite entries")
    return arr


def cw_matrix(n: float) -> NDArray[np.float64]:
    """System matrix A (6, 6) of the CW equations in O: ``d/dt state6 = A @ state6``."""
    A = np.zeros((6, 6))
    A[:3, 3:] = np.eye(3)
    A[3, 5] = 2.0 * n  # ẍ = 2n ż
    A[4, 1] = -(n**2)  # ÿ = −n² y
    A[5, 3] = -2.0 * n  # z̈ = −2n ẋ + 3n² z
    A[5, 2] = 3.0 * n**2
    return A


def cw_derivative(state6: ArrayLike, n: float) -> NDArray[np.float64]:
    """Time derivative (6,) of the relative state ``(ρ, ρ̇)`` in O under the CW equations."""
    return cw_matrix(n) @ _vector(state6, 6, "state6")


# Hill frame (radial out, along-track, orbit normal) -> O: x_O = along, y_O = −normal,
# z_O = −radial. The classical CW solution is written in the Hill frame and mapped once.
_HILL_TO_O = np.array([[0.0, 1.0, 0.0], [0.0, 0.0, -1.0], [-1.0, 0.0, 0.0]])


def cw_stm(n: float, t: float) -> NDArray[np.float64]:
    """State-transition matrix Φ(t) (6, 6) of the CW equations in O: ``state(t) = Φ state(0)``.

    The classical closed-form solution (Clohessy & Wiltshire 1960) in the Hill frame, rotated
    into O. For ``n == 0`` it is the free-flight matrix.
    """
    n, t = se3.real_number(n, "n (mean motion)"), se3.real_number(t, "t")
    if n < 0.0:
        raise InputError(f"n (mean motion) must be >= 0 rad/s, got {n}")
    if n == 0.0:
        phi = np.eye(6)
        phi[:3, 3:] = t * np.eye(3)
        return phi
    s, c, nt = np.sin(n * t), np.cos(n * t), n * t
    # Hill order (x radial, y along, z normal): [[Φrr, Φrv], [Φvr, Φvv]].
    rr = np.array([[4 - 3 * c, 0, 0], [6 * (s - nt), 1, 0], [0, 0, c]])
    rv = np.array(
        [[s / n, 2 * (1 - c) / n, 0], [-2 * (1 - c) / n, (4 * s - 3 * nt) / n, 0], [0, 0, s / n]]
    )
    vr = np.array([[3 * n * s, 0, 0], [-6 * n * (1 - c), 0, 0], [0, 0, -n * s]])
    vv = np.array([[c, 2 * s, 0], [-2 * s, 4 * c - 3, 0], [0, 0, c]])
    P = np.zeros((6, 6))
    P[:3, :3] = P[3:, 3:] = _HILL_TO_O
    return P @ np.block([[rr, rv], [vr, vv]]) @ P.T


def cw_closed_form(state6_0: ArrayLike, n: float, t: float) -> NDArray[np.float64]:
    """Relative state (6,) in O at time t from the state at 0, by the analytic CW solution."""
    return cw_stm(n, t) @ _vector(state6_0, 6, "state6_0")


def R_I_O(n: float, t: float) -> NDArray[np.float64]:
    """Rotation (3, 3) mapping O coordinates into I at time t (O turns about −y_O at rate n)."""
    return Rotation.from_rotvec([0.0, -n * t, 0.0]).as_matrix()


def inertia_ratios(inertia_diag: ArrayLike) -> NDArray[np.float64]:
    """Inertia ratios ``k = (k_x, k_y, k_z)`` (3,) from the principal moments (Ixx, Iyy, Izz)."""
    Ixx, Iyy, Izz = _vector(inertia_diag, 3, "inertia_diag")
    if min(Ixx, Iyy, Izz) <= 0:
        raise InputError(f"principal moments of inertia must be positive, got {inertia_diag}")
    return np.array([(Iyy - Izz) / Ixx, (Izz - Ixx) / Iyy, (Ixx - Iyy) / Izz])


def euler_derivative(omega_B: ArrayLike, inertia_diag: ArrayLike) -> NDArray[np.float64]:
    """Torque-free Euler equations: ω̇ (3,) in B for rate ``omega_B`` and moments (Ixx, Iyy, Izz).

    Only the ratios of the moments matter, so ``inertia_diag`` may be given up to a scale.
    """
    w = np.asarray(omega_B, dtype=np.float64)
    k = inertia_ratios(inertia_diag)
    return k * np.array([w[1] * w[2], w[2] * w[0], w[0] * w[1]])


def quat_rate_matrix(omega_B: ArrayLike) -> NDArray[np.float64]:
    """Matrix Ω (4, 4) with ``q ⊗ (ω, 0) = Ω(ω) @ q`` for scalar-last quaternions (Hamilton)."""
    wx, wy, wz = np.asarray(omega_B, dtype=np.float64)
    return np.array(
        [
            [0.0, wz, -wy, wx],
            [-wz, 0.0, wx, wy],
            [wy, -wx, 0.0, wz],
            [-wx, -wy, -wz, 0.0],
        ]
    )


def quat_derivative(q_xyzw: ArrayLike, omega_B: ArrayLike) -> NDArray[np.float64]:
    """q̇ (4,) = ½ q ⊗ (ω, 0): kinematics of ``q = q_I_B`` (scalar last) with ω in B."""
    return 0.5 * quat_rate_matrix(omega_B) @ np.asarray(q_xyzw, dtype=np.float64)


def rk4_step(
    f: Callable[[NDArray[np.float64]], NDArray[np.float64]], x: ArrayLike, dt: float
) -> NDArray[np.float64]:
    """One classical Runge–Kutta step of the autonomous system ``ẋ = f(x)``."""
    x = np.asarray(x, dtype=np.float64)
    k1 = f(x)
    k2 = f(x + 0.5 * dt * k1)
    k3 = f(x + 0.5 * dt * k2)
    k4 = f(x + dt * k3)
    return x + (dt / 6.0) * (k1 + 2.0 * k2 + 2.0 * k3 + k4)


def propagate_attitude(
    q_I_B_xyzw: ArrayLike,
    omega_B: ArrayLike,
    inertia_diag: ArrayLike,
    dt: float,
    substeps: int = 10,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """Propagate torque-free attitude and rate over ``dt`` by RK4 in ``substeps`` steps.

    Parameters
    ----------
    q_I_B_xyzw
        (4,) attitude, B -> I, scalar last; need not be exactly unit.
    omega_B
        (3,) angular rate in B, rad/s.
    inertia_diag
        (3,) principal moments (any common scale).
    dt
        Time step, s (may be negative).
    substeps
        RK4 steps inside ``dt``; the quaternion is renormalised after each.

    Returns
    -------
    q, omega
        (4,) unit quaternion (sign kept continuous with the input) and (3,) rate at ``t + dt``.
    """
    return propagate_attitude_k(q_I_B_xyzw, omega_B, inertia_ratios(inertia_diag), dt, substeps)


def propagate_attitude_k(
    q_I_B_xyzw: ArrayLike,
    omega_B: ArrayLike,
    k: ArrayLike,
    dt: float,
    substeps: int = 10,
) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
    """As :func:`propagate_attitude`, with the inertia given as the ratios ``k`` (3,)."""
    q = _vector(q_I_B_xyzw, 4, "q_I_B_xyzw")
    w = _vector(omega_B, 3, "omega_B")
    k = _vector(k, 3, "k")
    substeps = se3.whole_number(substeps, "substeps")
    dt = se3.real_number(dt, "dt")
    if not q.any():
        raise InputError("q_I_B_xyzw is a quaternion of zeros: no attitude")

    def f(x: NDArray[np.float64]) -> NDArray[np.float64]:
        wx, wy, wz = x[4:]
        return np.concatenate(
            [0.5 * quat_rate_matrix(x[4:]) @ x[:4], k * np.array([wy * wz, wz * wx, wx * wy])]
        )

    x = np.concatenate([q / np.linalg.norm(q), w])
    h = dt / substeps
    for _ in range(substeps):
        x = rk4_step(f, x, h)
        x[:4] /= np.linalg.norm(x[:4])
    return x[:4], x[4:]
