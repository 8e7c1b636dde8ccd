"""How far a tracker's pose covariance is from its errors over a run (docs/methods.md §2.4).

A filter fed registration poses assumes each pose's error is white with the tracker's
covariance. A tracker's errors are not white: on some targets they hold a bias over tens of
frames (the Hubble kit at 25 m: 0.3–0.9 σ over whole 50-frame blocks), on others they are white
and the covariance is cautious. A filter averages its poses over many frames, so what matters
is the variance of an error averaged over a window, not of one frame's: for whitened errors
``w_k = L_k⁻¹ e_k`` (``C_k = L_k L_kᵀ``) cut into batches of ``B`` frames, ``B · mean(w̄²)``
per axis is 1 for white errors that the covariance describes, below 1 for a cautious one, and
grows with ``B`` when the errors are correlated or biased (the batch-means estimate of the
long-run variance). Its largest axis, at least 1, is the factor the covariance needs in
variance: :func:`pose_noise_scale`.

The errors need a truth; :mod:`spacepose.core.pose_bootstrap` makes one by rendering the
target at the tracker's own poses and tracking the renders (a parametric bootstrap).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from spacepose.core import se3
from spacepose.core.health import covariance_at
from spacepose.errors import InputError

# Frames a filter's poses are averaged over, as a batch: the orbit run's filter follows its
# attitude and centre of mass over hundreds of 1-s frames; 50 frames is where the Hubble kit's
# bias shows (docs/results.md, "A bootstrap of the poses' σ").
BATCH_FRAMES = 50
# An error this many times the median squared whitened error is a gross failure (a twin, a
# slide), not noise: a filter's gate rejects such a pose, and its restart undoes a start on one.
GROSS_FACTOR = 100.0
# Largest whitened error whose square, summed over a batch, stays finite in float64.
_LARGEST_WHITENED = 1e150
# Batches a factor needs: each axis's ratio from k batches spreads as χ²ₖ/k (±0.7 at 4).
MIN_BATCHES = 4
# Standard errors a bias component must stand from zero to be taken off (translation_bias).
SIGNIFICANT_BIAS = 3.0
# The order of a pose covariance's axes (left perturbation about the sensor's origin, in the
# sensor frame): rotation, then translation.
POSE_NOISE_AXES = ("rotation x", "rotation y", "rotation z", "x", "y", "z")


@dataclass(frozen=True)
class PoseNoiseScale:
    """The factor a tracker's pose covariance needs over a run.

    Attributes
    ----------
    scale
        Factor on σ (the covariance times its square), at least 1.
    batch_ratios
        (6,) ``B · mean(w̄²)`` per axis of the whitened errors (rotation x, y, z, then
        translation, the covariance's order).
    frames
        Frames with an error, in whole batches.
    batch
        Frames per batch ``B``.
    gross
        Frames left out as gross failures (:data:`GROSS_FACTOR`).
    bias
        The poses' constant translation errors (:func:`translation_bias`), or None where they
        were not measured.
    target_ratios
        (6,) the batch ratios of the errors about the target's origin, the rotation and the
        translation each whitened by its own block there (:func:`target_origin_whitened`), or
        None where they were not measured.
    """

    scale: float
    batch_ratios: NDArray[np.float64]
    frames: int
    batch: int
    gross: int = 0
    bias: TranslationBias | None = None
    target_ratios: NDArray[np.float64] | None = None

    @property
    def rotation_scale(self) -> float:
        """Factor on the rotation's σ about the target's origin (``target_ratios``' largest
        rotation ratio's root, at least 1; ``scale`` where they were not measured)."""
        if self.target_ratios is None:
            return self.scale
        return float(np.sqrt(max(1.0, self.target_ratios[:3].max())))

    @property
    def translation_scale(self) -> float:
        """Factor on the translation's σ about the target's origin (as :attr:`rotation_scale`)."""
        if self.target_ratios is None:
            return self.scale
        return float(np.sqrt(max(1.0, self.target_ratios[3:].max())))

    def to_dict(self) -> dict:
        out = {
            "scale": self.scale,
            "batch_ratios": self.batch_ratios.tolist(),
            "frames": self.frames,
            "batch": self.batch,
            "gross": self.gross,
        }
        if self.bias is not None:
            out["bias"] = self.bias.to_dict()
        if self.target_ratios is not None:
            out |= {
                "target_origin_ratios": self.target_ratios.tolist(),
                "rotation_scale": self.rotation_scale,
                "translation_scale": self.translation_scale,
            }
        return out


def whitened_errors(
    T_est: ArrayLike, covariances: ArrayLike, T_ref: ArrayLike
) -> NDArray[np.float64]:
    """Each pose's error whitened by its covariance, ``L⁻¹ [log(T_est T_ref⁻¹)]``.

    Parameters
    ----------
    T_est, T_ref
        (N, 4, 4) estimated and reference poses (``T_sensor_target``).
    covariances
        (N, 6, 6) covariances of ``T_est`` (left perturbation, rotation first).

    Returns
    -------
    (N, 6) whitened errors; NaN rows where a pose or covariance is not finite or the covariance
    not positive definite.
    """
    T_est, T_ref, C = _poses_and_covariances(T_est, T_ref, covariances)
    n = len(T_est)
    out = np.full((n, 6), np.nan)
    for k in range(n):
        if not (np.isfinite(T_est[k]).all() and np.isfinite(T_ref[k]).all()):
            continue
        try:
            L = np.linalg.cholesky(C[k])
        except np.linalg.LinAlgError:  # NaN or not positive definite
            continue
        D = T_est[k] @ se3.invert(T_ref[k])
        e = np.r_[Rotation.from_matrix(D[:3, :3]).as_rotvec(), D[:3, 3]]
        out[k] = np.linalg.solve(L, e)
    return out


@dataclass(frozen=True)
class TranslationBias:
    """Constant translation errors of a run's poses: ``sensor`` (3,) in the sensor's frame and
    ``body`` (3,) in the target's, m (components that cannot be told from zero are zero), with
    their standard errors (:func:`translation_bias`)."""

    sensor: NDArray[np.float64]
    body: NDArray[np.float64]
    sensor_sigma: NDArray[np.float64]
    body_sigma: NDArray[np.float64]

    def correct(self, T_sensor_target: NDArray[np.float64]) -> NDArray[np.float64]:
        """Poses (..., 4, 4) with both biases taken off: ``S⁻¹ T B⁻¹``, S and B the
        translations by ``sensor`` and ``body``."""
        S = se3.make_transform(np.eye(3), -self.sensor)
        B = se3.make_transform(np.eye(3), -self.body)
        return S @ T_sensor_target @ B

    def to_dict(self) -> dict:
        return {
            "sensor_m": self.sensor.tolist(),
            "body_m": self.body.tolist(),
            "sensor_sigma_m": self.sensor_sigma.tolist(),
            "body_sigma_m": self.body_sigma.tolist(),
        }


def translation_bias(
    T_est: ArrayLike,
    T_ref: ArrayLike,
    covariances: ArrayLike,
    batch: int = BATCH_FRAMES,
    min_batches: int = MIN_BATCHES,
    significance: float = SIGNIFICANT_BIAS,
) -> TranslationBias:
    """The constant translation errors in the sensor's and the target's frames that best
    explain a run's errors, ``t_est − t_ref = b_s + R_ref b_b``, each frame weighed by the
    inverse covariance of its target origin's position; a component within ``significance``
    standard errors of zero is set to zero (it cannot be told from the noise, and taking it
    off would add the fit's own error to every pose).

    Two biases a tracker can hold: one in the sensor's frame (along the line of sight, where
    faces seen at a graze pull each frame alike) and one in the target's (its thin panels and
    sampled faces, which turn with it). The filter takes the first for the target's position
    and the second for its centre of mass, and grows sure of both; a white-noise factor sized
    on them widens every other axis. The target's turn tells them apart where its axis turns
    too; where it does not their components along it are split the least-norm way.

    Parameters
    ----------
    T_est, T_ref
        (N, 4, 4) estimated and reference poses ``T_sensor_target``; frames where either, or the
        covariance, is not finite are left out.
    covariances
        (N, 6, 6) covariances of ``T_est`` (left perturbation about the sensor's origin).
    batch, min_batches
        Standard errors: the sandwich ``N⁻¹ (Σ_b g_b g_bᵀ) N⁻¹`` over whole batches of ``batch``
        frames (``g_b`` the batch's sum of ``A_kᵀ W_k r_k``), as the errors are correlated
        from frame to frame; at least ``min_batches`` batches.

    Raises
    ------
    InputError
        Poses or covariances not of those shapes, or fewer usable frames than ``min_batches``
        batches.
    """
    T_est, T_ref, C = _poses_and_covariances(T_est, T_ref, covariances)
    batch = se3.whole_number(batch, "batch")
    min_batches = se3.whole_number(min_batches, "min_batches")
    if not significance >= 0.0:  # NaN too
        raise InputError(f"significance {significance} must be a number of standard errors >= 0")
    finite = (
        np.isfinite(T_est).all(axis=(1, 2))
        & np.isfinite(T_ref).all(axis=(1, 2))
        & np.isfinite(C).all(axis=(1, 2))
    )
    count = int(finite.sum()) // batch
    if count < min_batches:
        raise InputError(
            f"{int(finite.sum())} frames with an error: {min_batches} batches need "
            f"{min_batches * batch}"
        )
    keep = np.flatnonzero(finite)[: count * batch]
    R, t = T_ref[keep, :3, :3], T_ref[keep, :3, 3]
    d = T_est[keep, :3, 3] - t
    # The target origin's position covariance: the twist's moved there (v + ω × t).
    J = np.concatenate([-se3.skew(t), np.broadcast_to(np.eye(3), R.shape)], 2)
    W = np.linalg.pinv(J @ C[keep] @ np.transpose(J, (0, 2, 1)), hermitian=True)
    A = np.concatenate([np.broadcast_to(np.eye(3), R.shape), R], axis=2)  # (m, 3, 6)
    WA = W @ A
    normal = np.linalg.pinv(np.einsum("kji,kjl->il", A, WA), hermitian=True)
    x = normal @ np.einsum("kji,kj->i", WA, d)
    r = d - np.einsum("kij,j->ki", A, x)
    g = np.einsum("kji,kj->ki", WA, r).reshape(count, batch, 6).sum(axis=1)
    sigma = np.sqrt(np.clip(np.diag(normal @ (g.T @ g) @ normal), 0.0, None))
    x = np.where(np.abs(x) > significance * sigma, x, 0.0)
    return TranslationBias(x[:3], x[3:], sigma[:3], sigma[3:])


def batch_ratios(
    whitened: ArrayLike, batch: int = BATCH_FRAMES, min_batches: int = 1
) -> tuple[NDArray, int]:
    """``B · mean over batches of (batch mean)²`` per axis, and the frames it used.

    Rows with NaN are left out before batching (the frames a tracker did not call ``ok``);
    the remainder after the last whole batch is dropped.

    Raises
    ------
    InputError
        Not numbers in (N, 6), ``batch`` or ``min_batches`` not a whole number >= 1, or fewer
        finite rows than ``min_batches`` batches.
    """
    w = _error_rows(whitened)
    batch = se3.whole_number(batch, "batch")
    min_batches = se3.whole_number(min_batches, "min_batches")
    w = w[np.isfinite(w).all(axis=1)]
    count = len(w) // batch
    if count < min_batches:
        raise InputError(
            f"{len(w)} frames with an error: {min_batches} batches need {min_batches * batch}"
        )
    means = w[: count * batch].reshape(count, batch, 6).mean(axis=1)
    return batch * np.mean(means**2, axis=0), count * batch


def pose_noise_scale(
    whitened: ArrayLike, batch: int = BATCH_FRAMES, min_batches: int = MIN_BATCHES
) -> PoseNoiseScale:
    """The factor on σ that makes a run's poses as uncertain as their errors averaged over
    ``batch`` frames: ``sqrt(max(1, largest batch ratio))`` (see the module docstring), from
    at least ``min_batches`` batches.

    The largest of six noisy ratios leans high: white errors that their covariance describes
    give 1.6–1.8 in variance from 12 batches (a factor of about 1.3), a cautious side. Errors
    above :data:`GROSS_FACTOR` times the median squared error are left out first.
    """
    w = _error_rows(whitened).copy()
    finite_w = w[np.isfinite(w)]
    if finite_w.size and np.abs(finite_w).max() > _LARGEST_WHITENED:
        raise InputError(
            f"whitened errors up to {np.abs(finite_w).max():.3g}σ: their squares overflow"
        )
    gross = gross_failures(w)
    w[gross] = np.nan
    ratios, frames = batch_ratios(w, batch, min_batches)
    scale = float(np.sqrt(max(1.0, ratios.max())))
    return PoseNoiseScale(scale, ratios, frames, int(batch), int(gross.sum()))


def target_origin_whitened(
    T_est: ArrayLike, covariances: ArrayLike, T_ref: ArrayLike
) -> NDArray[np.float64]:
    """Each pose's error about the target's origin, its rotation and its translation each
    whitened by that block's own covariance there: (N, 6), NaN where not computable."""
    T_est, T_ref, C = _poses_and_covariances(T_est, T_ref, covariances)
    out = np.full((len(T_est), 6), np.nan)
    for k in range(len(T_est)):
        if not (np.isfinite(T_est[k]).all() and np.isfinite(T_ref[k]).all()):
            continue
        t = T_ref[k, :3, 3]
        rotation = Rotation.from_matrix(T_est[k, :3, :3] @ T_ref[k, :3, :3].T).as_rotvec()
        # The target's origin is where the pose puts it: its error is the difference.
        e = np.r_[rotation, T_est[k, :3, 3] - t]
        Ct = covariance_at(C[k], t)
        try:
            Lr, Lt = np.linalg.cholesky(Ct[:3, :3]), np.linalg.cholesky(Ct[3:, 3:])
        except np.linalg.LinAlgError:
            continue
        out[k] = np.r_[np.linalg.solve(Lr, e[:3]), np.linalg.solve(Lt, e[3:])]
    return out


def scaled_about_target(
    covariance: NDArray[np.float64],
    T_sensor_target: NDArray[np.float64],
    rotation_scale: float,
    translation_scale: float,
) -> NDArray[np.float64]:
    """A pose covariance (6, 6; left perturbation about the sensor's origin) whose rotation and
    translation σ about the target's origin are multiplied by the two factors.

    About the sensor 25 m away a rotation moves the target as much as a translation does, and
    the two blocks are nearly one; about the target's origin they are apart, and each can take
    its own factor (with equal factors the covariance is scaled by their square)."""
    t = T_sensor_target[:3, 3]
    D = np.diag([rotation_scale] * 3 + [translation_scale] * 3)
    # Scaled about the target's origin, then moved back about the sensor's (about −t).
    return covariance_at(D @ covariance_at(covariance, t) @ D, -t)


def gross_failures(whitened: NDArray[np.float64]) -> NDArray[np.bool_]:
    """(N,) rows of whitened errors (N, 6) whose squared norm is above :data:`GROSS_FACTOR`
    times the median of the finite rows'."""
    squared = np.sum(whitened**2, axis=1)
    finite = np.isfinite(squared)
    gross = np.zeros(len(whitened), dtype=bool)
    if finite.any():
        gross[finite] = squared[finite] > GROSS_FACTOR * np.median(squared[finite])
    return gross


def _poses_and_covariances(
    T_est: ArrayLike, T_ref: ArrayLike, covariances: ArrayLike
) -> tuple[NDArray[np.float64], NDArray[np.float64], NDArray[np.float64]]:
    """(N, 4, 4), (N, 4, 4) and (N, 6, 6) float64 arrays, or the package's error."""
    T_est, T_ref = as_numbers(T_est, "poses"), as_numbers(T_ref, "reference poses")
    C = as_numbers(covariances, "covariances")
    n = len(T_est) if T_est.ndim else -1
    if T_est.shape != (n, 4, 4) or T_ref.shape != (n, 4, 4) or C.shape != (n, 6, 6):
        raise InputError(
            f"poses must be (N, 4, 4) and covariances (N, 6, 6) alike, got {T_est.shape}, "
            f"{T_ref.shape} and {C.shape}"
        )
    return T_est, T_ref, C


def as_numbers(values: ArrayLike, name: str) -> NDArray[np.float64]:
    """``values`` as a float64 array, or the package's error naming them (numpy raises a
    ValueError or TypeError on text)."""
    se3.check_real(values, name)
    try:
        return np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name} are not numbers: {exc}") from None


def _error_rows(whitened: ArrayLike) -> NDArray[np.float64]:
    w = as_numbers(whitened, "whitened errors")
    if w.ndim != 2 or w.shape[1] != 6:
        raise InputError(f"whitened errors must be (N, 6), got {w.shape}")
    return w
