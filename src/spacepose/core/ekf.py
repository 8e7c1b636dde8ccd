"""Relative-navigation error-state EKF for a tumbling target (methods.md §2.4, Yu §3).

Nominal state
-------------
``rho`` (3) target CoM − chaser CoM in O, ``v`` (3) its derivative in O, ``q_I_B`` (4) target
attitude B -> I (scalar last), ``omega_B`` (3) rate in B, ``p`` (2) inertia parameters
``(k_x, k_y)``, ``com`` (3) = Δ, the offset B' origin -> B origin in B, and one
``δ_j`` (3) per tracked rectangle (location error of its catalogue centroid, in B).

Consider state
--------------
``φ`` (3), the error of the chaser attitude the filter is given (a star tracker's knowledge
error), in C: ``R_O_C(given) = R_O_C(true) · exp([φ]×)``, so ``R_C_O(true) = exp([φ]×) R_C_O``.
It is a constant bias no measurement can separate from ρ and the attitude (it turns the whole
scene about the sensor), so it is held as a Schmidt *consider* state: prior σ
(``sigma_chaser_attitude_deg``), never corrected (zero gain rows), but its covariance and its
cross-covariances enter every update, so that P of the estimated states carries its effect.
It sits after the fixed part (indices 17–19) when its σ is positive; rectangles follow.

The error state, ``(δρ, δv, δθ, δω, δp, δΔ, δ_1, δ_2, ...)`` with the attitude error on the
right, in B, its slices, the inertia parametrisation and the discretisation of its propagation
are :mod:`spacepose.core.nav_state`'s.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation
from scipy.stats import chi2

from spacepose.core import dynamics, se3
from spacepose.core.config import stage_config
from spacepose.core.ekf_config import EKFConfig
from spacepose.core.nav_state import (
    ATT,
    CHASER,
    COM,
    INERTIA,
    N_FIXED,
    RATE,
    RHO,
    VEL,
    NavState,
    discretise,
    dk_dp,
    finite,
    k_from_params,
    measurement_covariance,
    params_from_k,
    seconds,
)
from spacepose.errors import InputError, PredictionGapError

# Largest turn (rad) of the body or the orbit in one RK4 step of a prediction.
_STEP_RAD = 0.05
# Largest turn (rad) a prediction is carried over: 160 turns (20,000 steps; a 3,000 s eclipse at
# the orbit run's 2.7 °/s is 141 rad). Beyond it the state is a guess and costs minutes.
_LONGEST_TURN_RAD = 1000.0
# Largest mean motion taken (rad/s): a circular orbit grazing a body of density ρ turns at
# √(4πGρ/3), 0.0012 rad/s about the Earth and 0.0025 about a body of 20 t/m³.
_FASTEST_ORBIT_RAD_S = 0.01


class RelativeNavEKF:
    """Multiplicative error-state EKF of relative translation, attitude, rate, inertia, CoM.

    Parameters
    ----------
    mean_motion
        Orbital mean motion n, rad/s (at most 0.01).
    R_O_C
        (3, 3) constant chaser-body (= sensor) attitude in O.
    initial
        Initial estimate; ``initial.k`` gives the inertia parameters.
    config
        Noise, initial σ's and gate.
    """

    def __init__(
        self,
        mean_motion: float,
        R_O_C: ArrayLike,
        initial: NavState,
        config: EKFConfig | None = None,
    ) -> None:
        self.config = EKFConfig() if config is None else stage_config(config, EKFConfig)
        self.n = seconds(mean_motion, "mean_motion")
        if self.n < 0:
            raise InputError(f"mean_motion must be >= 0 rad/s, got {self.n}")
        if self.n > _FASTEST_ORBIT_RAD_S:
            # 1e300 rad/s ended in Python's OverflowError squaring it.
            raise InputError(
                f"mean_motion {self.n:.6g} rad/s: no orbit turns faster than about 0.0025 rad/s "
                "(one grazing the densest body); in degrees or revolutions?"
            )
        R = se3.real_array(R_O_C, "R_O_C")
        # A reflection passed RᵀR = I and ended in scipy's "non-positive determinant".
        if (
            R.shape != (3, 3)
            or not np.all(np.isfinite(R))
            or not np.allclose(R.T @ R, np.eye(3), atol=1e-6)
            or np.linalg.det(R) < 0
        ):
            raise InputError(f"R_O_C must be a 3x3 rotation matrix, got shape {R.shape}")
        if not isinstance(initial, NavState):
            raise InputError(f"initial must be a NavState, got {type(initial).__name__}")
        self.R_C_O = R.T
        self.t = seconds(initial.t, "initial.t")
        self.rho = finite(initial.rho, (3,), "initial.rho").copy()
        self.v = finite(initial.v, (3,), "initial.v").copy()
        self.q = Rotation.from_quat(_quaternion(initial.q_I_B, "initial.q_I_B")).as_quat()
        self.w = finite(initial.omega_B, (3,), "initial.omega_B").copy()
        self.p = params_from_k(initial.k)
        self.com = finite(initial.com, (3,), "initial.com").copy()
        self.features: dict[str, NDArray[np.float64]] = {}
        self._feature_index: dict[str, int] = {}
        c = self.config
        sig = np.concatenate(
            [
                np.full(3, c.init_sigma_position),
                np.full(3, c.init_sigma_velocity),
                np.full(3, np.deg2rad(c.init_sigma_attitude_deg)),
                np.full(3, np.deg2rad(c.init_sigma_rate_deg_s)),
                np.full(2, c.init_sigma_inertia),
                np.full(3, c.init_sigma_com),
            ]
        )
        if c.sigma_chaser_attitude_deg > 0:
            sig = np.append(sig, np.full(3, np.deg2rad(c.sigma_chaser_attitude_deg)))
        self.P = np.diag(sig**2)
        self.n_accepted = 0
        self.n_rejected = 0
        self.last_nis: float = float("nan")
        # The last update's innovation (m,) and its prediction covariance H P Hᵀ (m, m), before
        # the update: what an innovation-based noise estimate needs (innovation_scale).
        self.last_innovation: NDArray[np.float64] = np.zeros(0)
        self.last_HPHt: NDArray[np.float64] = np.zeros((0, 0))

    # ----------------------------------------------------------------- state access
    @property
    def dim(self) -> int:
        """Size of the error state."""
        return len(self.P)

    @property
    def has_consider(self) -> bool:
        """Whether the chaser-attitude consider state φ is part of the error state."""
        return self.config.sigma_chaser_attitude_deg > 0

    @property
    def k(self) -> NDArray[np.float64]:
        """Inertia ratios (3,) derived from the two estimated parameters."""
        return k_from_params(self.p)

    @property
    def R_I_B(self) -> NDArray[np.float64]:
        return Rotation.from_quat(self.q).as_matrix()

    def R_O_B(self) -> NDArray[np.float64]:
        """Target attitude in O at the filter time (O turns relative to I)."""
        return dynamics.R_I_O(self.n, self.t).T @ self.R_I_B

    def state(self) -> NavState:
        """The current estimate."""
        return NavState(
            self.t,
            self.rho.copy(),
            self.v.copy(),
            self.q.copy(),
            self.w.copy(),
            self.k,
            self.com.copy(),
        )

    def sigmas(self) -> dict[str, NDArray[np.float64]]:
        """1-σ of the estimate: rho, v, att (rotation vector, rad), omega, k, com."""
        d = np.sqrt(np.clip(np.diag(self.P), 0, None))
        J = dk_dp(self.p)
        sig_k = np.sqrt(np.clip(np.diag(J @ self.P[INERTIA, INERTIA] @ J.T), 0, None))
        return {
            "rho": d[RHO],
            "v": d[VEL],
            "att": d[ATT],
            "omega": d[RATE],
            "k": sig_k,
            "com": d[COM],
        }

    def error_state(self, truth: NavState) -> NDArray[np.float64]:
        """Error ``truth ⊟ estimate`` (fixed part, 17,) in the filter's error coordinates."""
        if abs(truth.t - self.t) > 1e-9:
            raise InputError(f"truth at t={truth.t} compared with an estimate at t={self.t}")
        datt = (Rotation.from_quat(self.q).inv() * Rotation.from_quat(truth.q_I_B)).as_rotvec()
        return np.concatenate(
            [
                truth.rho - self.rho,
                truth.v - self.v,
                datt,
                truth.omega_B - self.w,
                params_from_k(truth.k) - self.p,
                truth.com - self.com,
            ]
        )

    def nees(self, truth: NavState) -> float:
        """Normalised estimation error squared of the fixed part of the state (17 dof)."""
        e = self.error_state(truth)
        return float(e @ np.linalg.solve(self.P[:N_FIXED, :N_FIXED], e))

    # ----------------------------------------------------------------- propagation
    def _jacobian(self, w: NDArray[np.float64], p: NDArray[np.float64]) -> NDArray[np.float64]:
        """Jacobian F (17, 17) of the fixed error state at rate ``w`` and parameters ``p``.

        The consider state and the rectangle location errors are constant and enter no other
        derivative, so their rows and columns of the full Jacobian are zero and are left out.
        """
        F = np.zeros((N_FIXED, N_FIXED))
        F[:6, :6] = dynamics.cw_matrix(self.n)
        F[ATT, ATT] = -se3.skew(w)
        F[ATT, RATE] = np.eye(3)
        k = k_from_params(p)
        wx, wy, wz = w
        F[RATE, RATE] = np.array(
            [[0, k[0] * wz, k[0] * wy], [k[1] * wz, 0, k[1] * wx], [k[2] * wy, k[2] * wx, 0]]
        )
        F[RATE, INERTIA] = np.array([wy * wz, wz * wx, wx * wy])[:, None] * dk_dp(p)
        return F

    def _process_noise_density(self) -> NDArray[np.float64]:
        c = self.config
        Qc = np.zeros((N_FIXED, N_FIXED))
        Qc[VEL, VEL] = c.sigma_accel**2 * np.eye(3)
        Qc[RATE, RATE] = c.sigma_angular_accel**2 * np.eye(3)
        Qc[INERTIA, INERTIA] = c.sigma_inertia_walk**2 * np.eye(2)
        return Qc

    def predict(self, t: float) -> None:
        """Propagate the nominal state (RK4) and the covariance (Φ P Φᵀ + Q) to time ``t``."""
        dt = seconds(t, "t") - self.t
        if dt < 0:
            raise InputError(f"cannot predict backwards from t={self.t} to t={t}")
        if dt == 0:
            return
        F0 = self._jacobian(self.w, self.p)
        # Each RK4 step turns the body and the orbit by at most _STEP_RAD: a fixed count over
        # a 3,000 s gap (an eclipse without frames) was 300 s steps, and the state overflowed.
        turn = dt * max(float(np.linalg.norm(self.w)), self.n)
        if turn > _LONGEST_TURN_RAD:
            raise PredictionGapError(
                f"a gap of {dt:.6g} s from t={self.t:.6g} s: the target turns {turn:.3g} rad in "
                f"it, too far to predict across (at most {_LONGEST_TURN_RAD:g})"
            )
        steps = max(self.config.substeps, math.ceil(turn / _STEP_RAD))
        h = dt / steps
        x = np.concatenate([self.rho, self.v])
        for _ in range(steps):
            x = dynamics.rk4_step(lambda s: dynamics.cw_derivative(s, self.n), x, h)
        q, w = dynamics.propagate_attitude_k(self.q, self.w, self.k, dt, steps)
        # Jacobian averaged over the interval.
        F = 0.5 * (F0 + self._jacobian(w, self.p))
        with np.errstate(over="ignore", invalid="ignore"):
            Phi, Q = discretise(F, self._process_noise_density(), dt)
        if not (np.isfinite(Phi).all() and np.isfinite(Q).all() and np.isfinite(x).all()):
            # A target that does not turn passes the turn's bound at any gap, and the rate's
            # σ carried over 10³⁰⁰ s overflowed into a state of NaN. The filter stays as it was.
            raise PredictionGapError(
                f"a gap of {dt:.6g} s from t={self.t:.6g} s: the covariance overflows across it"
            )
        self.rho, self.v, self.q, self.w = x[:3], x[3:], q, w
        m = N_FIXED
        # Φ is the identity on the consider state and the rectangle location errors: only the
        # fixed block moves.
        P = self.P.copy()
        P[:m, :m] = Phi @ self.P[:m, :m] @ Phi.T + 0.5 * (Q + Q.T)
        P[:m, m:] = Phi @ self.P[:m, m:]
        P[m:, :m] = P[:m, m:].T
        self.P = 0.5 * (P + P.T)
        self.t = float(t)

    # ----------------------------------------------------------------- measurement updates
    def add_feature(self, feature_id: str) -> int:
        """Add rectangle ``feature_id``'s location error δ (0, prior σ) if new; its state index."""
        if feature_id in self._feature_index:
            return self._feature_index[feature_id]
        i = self.dim
        P = np.zeros((i + 3, i + 3))
        P[:i, :i] = self.P
        P[i:, i:] = self.config.sigma_feature**2 * np.eye(3)
        self.P = P
        self.features[feature_id] = np.zeros(3)
        self._feature_index[feature_id] = i
        return i

    def predict_centroid(self, feature_id: str, d_Bp: ArrayLike) -> NDArray[np.float64]:
        """Predicted centroid (3,) in C of rectangle ``feature_id`` with catalogue centre d (B').

        Raises
        ------
        InputError
            ``d_Bp`` is not a finite (3,) vector (a NaN centre came out as a NaN centroid).
        """
        d_Bp = finite(d_Bp, (3,), "catalogue centre d_Bp")
        r_B = d_Bp + self.features.get(feature_id, 0.0) - self.com
        return self.R_C_O @ (self.rho + self.R_O_B() @ r_B)

    def update_centroid(
        self,
        feature_id: str,
        d_Bp: ArrayLike,
        c_C: ArrayLike,
        cov: ArrayLike | None = None,
    ) -> bool:
        """Update with a rectangle centroid measured in C.

        Parameters
        ----------
        feature_id
            Name of the rectangle in the catalogue (adds its δ state on first sight).
        d_Bp
            (3,) catalogue centre of the rectangle in B'.
        c_C
            (3,) measured centroid in the sensor frame C.
        cov
            (3, 3) measurement covariance; ``sigma_centroid² I`` when omitted.

        Returns
        -------
        Whether the measurement passed the gate and was used.
        """
        c_C = finite(c_C, (3,), "centroid")
        # A NaN centre passed the gate (NaN > bound is false) and turned the state into NaN.
        d_Bp = finite(d_Bp, (3,), "catalogue centre d_Bp")
        if not isinstance(feature_id, str):
            raise InputError(f"feature_id must be a rectangle's name, got {feature_id!r}")
        i = self.add_feature(feature_id)
        R_O_B = self.R_O_B()
        r_B = d_Bp + self.features[feature_id] - self.com
        z_hat = self.R_C_O @ (self.rho + R_O_B @ r_B)
        H = np.zeros((3, self.dim))
        A = self.R_C_O @ R_O_B
        H[:, RHO] = self.R_C_O
        H[:, ATT] = -A @ se3.skew(r_B)
        H[:, COM] = -A
        H[:, i : i + 3] = A
        if self.has_consider:
            H[:, CHASER] = -se3.skew(z_hat)  # exp([φ]×) ẑ ≈ ẑ − [ẑ]× φ
        sigma = self.config.sigma_centroid
        Rm = sigma**2 * np.eye(3) if cov is None else measurement_covariance(cov, 3)
        return self._update(c_C - z_hat, H, Rm)

    def update_attitude(self, q_I_B_meas: ArrayLike, cov: ArrayLike | None = None) -> bool:
        """Update with a measured attitude q_I_B (scalar last); residual is a body rotation vector.

        ``cov`` (3, 3) is the covariance of that rotation vector, in B (rad²).
        """
        q = _quaternion(q_I_B_meas, "attitude quaternion")
        r = (Rotation.from_quat(self.q).inv() * Rotation.from_quat(q)).as_rotvec()
        H = np.zeros((3, self.dim))
        H[:, ATT] = np.eye(3)
        if self.has_consider:
            # R_I_B(meas) = R_I_O R_O_C exp([φ]×) R_C_B = R_I_B exp([R_C_Bᵀ φ]×).
            H[:, CHASER] = (self.R_C_O @ self.R_O_B()).T
        s = np.deg2rad(self.config.sigma_attitude_deg)
        Rm = s**2 * np.eye(3) if cov is None else measurement_covariance(cov, 3)
        return self._update(r, H, Rm)

    def predict_pose(self) -> NDArray[np.float64]:
        """Predicted ``T_sensor_model`` (4, 4): the nominal body frame B' seen from C."""
        R_C_B = self.R_C_O @ self.R_O_B()
        return se3.make_transform(R_C_B, self.R_C_O @ self.rho - R_C_B @ self.com)

    def update_pose(self, T_sensor_model: ArrayLike, cov6: ArrayLike) -> bool:
        """Fuse a full pose ``T_sensor_model`` (C <- B') with its 6×6 covariance.

        ``cov6`` is ordered (omega, v) for a left perturbation ``T ← exp(ξ) T`` (the package's
        registration convention); the residual is ``log(T_meas · T̂⁻¹)``.
        """
        T = se3.as_transform(T_sensor_model, "T_sensor_model")
        T_hat = self.predict_pose()
        r = se3.log(T @ se3.invert(T_hat))
        return self._update(r, self._pose_jacobian(T_hat), measurement_covariance(cov6, 6))

    def pose_covariance(self) -> NDArray[np.float64]:
        """Covariance (6, 6) of :meth:`predict_pose`, ``H P Hᵀ``: twist (ω, v), left
        perturbation in the sensor frame C (the registration convention)."""
        H = self._pose_jacobian(self.predict_pose())
        C = H @ self.P @ H.T
        return 0.5 * (C + C.T)

    def _pose_jacobian(self, T_hat: NDArray[np.float64]) -> NDArray[np.float64]:
        """Jacobian (6, dim) of the left twist of ``T_sensor_model`` about ``T_hat``."""
        R_C_B = T_hat[:3, :3]
        H = np.zeros((6, self.dim))
        H[:3, ATT] = R_C_B
        # Left twist: η_v = δt + [t̂]× η_ω with t = R_C_O (ρ − R_O_B Δ).
        H[3:, RHO] = self.R_C_O
        H[3:, COM] = -R_C_B
        H[3:, ATT] = R_C_B @ se3.skew(self.com) + se3.skew(T_hat[:3, 3]) @ R_C_B
        if self.has_consider:
            H[:3, CHASER] = np.eye(3)  # a turn of C about its origin: η = (φ, 0)
        return H

    def _update(
        self, residual: NDArray[np.float64], H: NDArray[np.float64], Rm: NDArray[np.float64]
    ) -> bool:
        HPHt = H @ self.P @ H.T
        S = HPHt + Rm
        nis = float(residual @ np.linalg.solve(S, residual))
        self.last_nis, self.last_innovation, self.last_HPHt = nis, residual, HPHt
        gate = self.config.gate_probability
        if gate < 1.0 and nis > chi2.ppf(gate, len(residual)):
            self.n_rejected += 1
            return False
        K = np.linalg.solve(S, H @ self.P).T  # P Hᵀ S⁻¹ with S, P symmetric
        if self.has_consider:
            K[CHASER] = 0.0  # Schmidt: the consider state is never corrected
        IKH = np.eye(self.dim) - K @ H
        # Joseph form: stays symmetric positive definite even with a sub-optimal gain.
        self.P = IKH @ self.P @ IKH.T + K @ Rm @ K.T
        self.P = 0.5 * (self.P + self.P.T)
        self._inject(K @ residual)
        self.n_accepted += 1
        return True

    def _inject(self, dx: NDArray[np.float64]) -> None:
        """Fold an error-state correction into the nominal state (attitude on the right)."""
        self.rho = self.rho + dx[RHO]
        self.v = self.v + dx[VEL]
        self.q = (Rotation.from_quat(self.q) * Rotation.from_rotvec(dx[ATT])).as_quat()
        self.w = self.w + dx[RATE]
        self.p = self.p + dx[INERTIA]
        self.com = self.com + dx[COM]
        for fid, i in self._feature_index.items():
            self.features[fid] = self.features[fid] + dx[i : i + 3]


def _quaternion(values: ArrayLike, name: str) -> NDArray[np.float64]:
    """A finite (4,) quaternion of finite, non-zero norm (scipy's "zero norm" error otherwise)."""
    q = finite(values, (4,), name)
    with np.errstate(over="ignore"):
        norm = float(np.linalg.norm(q))
    if not (0.0 < norm < np.inf):
        raise InputError(f"{name} must have a finite, non-zero norm, got {q}")
    return q
