"""Process noise of the navigation filter from what its model misses on a truth run.

The filter (:mod:`spacepose.core.ekf`) adds white noise of spectral density q to ρ̈ and ω̇.
Here q is measured, not tuned: the truth is carried one frame interval at a time by the filter's
own model, and what is left over is the unmodelled acceleration; its spectral density at the
frequencies the filter responds to is q (see :func:`model_defect`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from spacepose.core import dynamics
from spacepose.errors import InputError


@dataclass(frozen=True)
class ModelDefect:
    """What the filter's motion model misses on a truth run, as process noise.

    Attributes
    ----------
    sigma_accel
        √q of the unmodelled relative acceleration, m/s²/√Hz (worst O axis), for
        ``EKFConfig.sigma_accel``.
    sigma_angular_accel
        √q of the unmodelled angular acceleration, rad/s²/√Hz (worst B axis), for
        ``EKFConfig.sigma_angular_accel``.
    rms_accel
        (3,) RMS per O axis of the mean unmodelled acceleration over one step, m/s².
    rms_angular_accel
        (3,) the same per B axis, rad/s².
    memory_s
        The filter memory T the translational density was summed over, s.
    dt
        The step the defect was measured over, s.
    """

    sigma_accel: float
    sigma_angular_accel: float
    rms_accel: NDArray[np.float64]
    rms_angular_accel: NDArray[np.float64]
    memory_s: float
    dt: float

    def to_dict(self) -> dict[str, float | list[float]]:
        """JSON-ready form (the orbit scenario's ``process_noise``)."""
        return {
            "sigma_accel": self.sigma_accel,
            "sigma_angular_accel": self.sigma_angular_accel,
            "rms_accel": self.rms_accel.tolist(),
            "rms_angular_accel": self.rms_angular_accel.tolist(),
            "memory_s": self.memory_s,
            "dt": self.dt,
        }


@dataclass(frozen=True)
class Density:
    """Spectral density ``q`` ((m/s²)²/Hz or (rad/s²)²/Hz) and the memory (s) it covers."""

    q: float
    memory_s: float


def spectral_density(defect: ArrayLike, dt: float, sigma_measurement: float) -> Density:
    """Low-frequency spectral density of a sampled unmodelled acceleration, over a filter memory.

    Parameters
    ----------
    defect
        (N,) mean unmodelled acceleration over each step, one axis (m/s² or rad/s²).
    dt
        Step, s.
    sigma_measurement
        1σ of one measurement of the matching position (m) or angle (rad) per step.

    Notes
    -----
    A sampled process of variance σ² and autocorrelation ρ_k has the low-frequency density
    ``q = σ² Δt (1 + 2 Σ_{k=1..K} ρ_k)``: ``σ² Δt`` for white noise, ``≈ 2 σ² T`` for a bias
    over ``T = K Δt``. The sum runs over the filter's memory only, since the filter forgets
    older errors: a position filter driven by a density q and measured with a density
    ``r = σ_m² Δt`` has the bandwidth ``(q / r)^¼``, hence the memory ``T = (r / q)^¼``.
    q and T are solved together: K is the fewest lags with ``K >= ⌊T(q_K) / Δt⌋`` (q grows
    and T shrinks with K while the defect stays correlated). σ² and ρ_k are taken about zero, not
    about the mean: a steady unmodelled acceleration counts in full.
    """
    d = np.asarray(defect, dtype=np.float64)
    power = float(np.mean(d**2))
    if power == 0.0:
        return Density(0.0, float("inf"))
    N = len(d)
    rho = np.array([np.mean(d[: N - k] * d[k:]) for k in range(N)]) / power
    # q_K over K lags; the memory T_K it implies; the K that T_K itself spans.
    q = power * dt * np.maximum(1.0, 1.0 + 2.0 * np.concatenate([[0.0], np.cumsum(rho[1:])]))
    memory = np.maximum(dt, (sigma_measurement**2 * dt / q) ** 0.25)
    consistent = np.flatnonzero(np.floor(memory / dt) <= np.arange(N))
    K = int(consistent[0]) if len(consistent) else N - 1
    return Density(float(q[K]), float(memory[K]))


def model_defect(
    truth: ArrayLike,
    mean_motion: float,
    sigma_position: float = 0.01,
    sigma_attitude: float = math.radians(0.1),
    substeps: int = 10,
) -> ModelDefect:
    """Process noise of the filter from the one-step defect of its model on the truth.

    For each frame interval ``Δt`` the true state at ``t_k`` is carried to ``t_k+1`` by the
    filter's own model: CW (its exact transition matrix) for ``(ρ, ρ̇)``, and the filter's RK4
    with ``substeps`` steps for the attitude and rate with the true inertia ratios. The velocity
    and rate left over, ``δv_k = v(t_k+1) − v̂(t_k+1)`` and ``δω_k``, are what the model does not
    explain; ``d_k = δv_k / Δt`` is the mean unmodelled acceleration over the step. The filter
    treats it as white noise of density q, which adds ``q Δt`` to the velocity variance over
    one step; a white ``d`` needs ``q = E[d²] Δt``, a slowly varying one more, summed over the
    filter's memory (:func:`spectral_density`). The worst axis is kept. Only these two numbers
    of the truth reach the filter.

    Parameters
    ----------
    truth
        (N >= 2, 20) truth table (columns of ``spacepose.core.sim.TRUTH_COLUMNS``), equal steps.
    mean_motion
        The n the filter uses, rad/s.
    sigma_position, sigma_attitude
        1σ of one frame's position (m) and attitude (rad) measurement: they set the filter's
        memory (defaults: a rectangle centroid in the flash LiDAR's 8 cm pixels, a face's
        attitude).
    substeps
        The filter's RK4 steps per interval (``EKFConfig.substeps``).
    """
    truth = np.asarray(truth, dtype=np.float64)
    if truth.ndim != 2 or truth.shape[1] != 20 or len(truth) < 2:
        raise InputError(f"truth must be (N >= 2, 20), got {truth.shape}")
    steps = np.diff(truth[:, 0])
    dt = float(steps[0])
    if not np.allclose(steps, dt, rtol=1e-9):
        raise InputError("model_defect needs equally spaced truth rows")
    phi = dynamics.cw_stm(mean_motion, dt)
    accel = (truth[1:, 4:7] - truth[:-1, 1:7] @ phi[3:].T) / dt
    w_model = [
        dynamics.propagate_attitude_k(row[7:11], row[11:14], row[14:17], dt, substeps)[1]
        for row in truth[:-1]
    ]
    angular = (truth[1:, 11:14] - np.array(w_model)) / dt
    trans = [spectral_density(accel[:, i], dt, sigma_position) for i in range(3)]
    rot = [spectral_density(angular[:, i], dt, sigma_attitude) for i in range(3)]
    worst = max(trans, key=lambda d: d.q)
    return ModelDefect(
        sigma_accel=math.sqrt(worst.q),
        sigma_angular_accel=math.sqrt(max(d.q for d in rot)),
        rms_accel=np.sqrt(np.mean(accel**2, axis=0)),
        rms_angular_accel=np.sqrt(np.mean(angular**2, axis=0)),
        memory_s=worst.memory_s,
        dt=dt,
    )
