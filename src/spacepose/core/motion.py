"""The tracker's motion model (docs/methods.md §5.2): constant velocity, and how wrong it has been.

The prediction of frame k is the last accepted pose moved on by the last inter-frame motion,
scaled to the elapsed time. What the model cannot foresee (acceleration, a hand-held jerk, a
tumble about a changing axis) shows as the *model error*: the disagreement between each
prediction and the pose the registration then accepted. Its RMS over recent frames, as in
KISS-ICP's adaptive threshold, sizes the first registration stage's gate and widens the health
check's prediction bounds, so that motion that is not constant is input, not a fault.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from spacepose.core import se3
from spacepose.errors import InputError

# Recent model errors kept: enough for a stable RMS, few enough to follow a change of motion.
_ERROR_WINDOW = 20
# Predictions of one velocity measured before its model error counts as known: from n errors
# the RMS's 95 % upper bound is sqrt(n / chi2.ppf(0.05, n)) times the RMS, within a factor of
# two from six on (2.09 at five).
SETTLED_TESTS = 6


# Latest time read as seconds since the Unix epoch: 1e11 s is the year 5138, so a larger time
# counts milliseconds, microseconds or nanoseconds (1.7e12, 1.7e15, 1.7e18 in 2024).
LATEST_S = 1e11
TIME_UNIT = "(times are seconds; milliseconds, microseconds or nanoseconds given?)"


def next_timestamp(timestamp: float, last: float) -> float:
    """``timestamp`` as seconds, checked to come after ``last`` (s).

    Raises
    ------
    InputError
        Not a number, not finite, past :data:`LATEST_S` (another unit), or not after ``last``:
        two frames at one time leave the motion between them undefined (the motion model
        divided by a step of zero).
    """
    # Text and yes/no are no times: float() reads "2.0" and True (as track_sequence does not).
    t = se3.real_number(timestamp, "frame timestamp (s)")
    if abs(t) > LATEST_S:
        raise InputError(f"a frame time of {t:.4g} s is past the year 5000 {TIME_UNIT}")
    if t <= last:
        what = "repeats" if t == last else "comes before"
        raise InputError(f"frame timestamps must increase: {t} {what} the last frame's {last}")
    return t


def order_problem(timestamps: ArrayLike) -> str | None:
    """Why a sequence's timestamps (s) cannot time its frames, or None: each must come after
    the one before (two frames at one time leave the motion between them undefined)."""
    stamps = np.asarray(timestamps, dtype=np.float64).reshape(-1)
    steps = np.diff(stamps)
    if not np.any(steps <= 0):
        return None
    k = int(np.argmax(steps <= 0))
    what = "repeats" if steps[k] == 0 else "goes back to"
    return f"timestamps must increase: frame {k + 1} {what} {stamps[k + 1]}"


def predict_pose(
    history: list[tuple[float, NDArray[np.float64]]], timestamp: float
) -> NDArray[np.float64] | None:
    """Constant-velocity prediction of ``T_sensor_target`` at ``timestamp``.

    Parameters
    ----------
    history
        Up to the last two accepted ``(timestamp, T_sensor_target)``, oldest first.

    Returns
    -------
    The last pose moved on by the last inter-frame motion ``T_b T_a⁻¹`` scaled to the elapsed
    time (on the Lie algebra); the last pose itself with one entry; None with none.
    """
    if not history:
        return None
    t_b, T_b = history[-1]
    if len(history) < 2:
        return T_b.copy()
    t_a, T_a = history[-2]
    dt = t_b - t_a
    # Equal or missing timestamps: assume one frame period per frame.
    scale = (timestamp - t_b) / dt if dt > 0 else 1.0
    return rigid(se3.exp(scale * se3.log(T_b @ se3.invert(T_a))) @ T_b)


def rigid(T: NDArray[np.float64]) -> NDArray[np.float64]:
    """``T`` with its rotation block projected back onto SO(3).

    Long chains of products (keyframe poses, predictions, registrations started from them) let
    rounding errors grow; without this the rotation drifts measurably off orthonormal.
    """
    return se3.make_transform(Rotation.from_matrix(T[:3, :3]), T[:3, 3])


@dataclass(frozen=True)
class Prediction:
    """The motion model's guess for one frame.

    Attributes
    ----------
    T_sensor_target
        (4, 4) predicted pose.
    covariance
        (6, 6) its covariance (left perturbation, twist (ω, v), about the origin).
    velocity_known
        False when it is only the last pose (one pose in the history).
    """

    T_sensor_target: NDArray[np.float64]
    covariance: NDArray[np.float64]
    velocity_known: bool

    @classmethod
    def given(cls, T_sensor_target: ArrayLike, covariance: ArrayLike) -> Prediction:
        """A prediction made outside the tracker (e.g. a navigation filter's), trusted as a
        constant-velocity one.

        Parameters
        ----------
        T_sensor_target
            (4, 4) predicted pose (model-free: ``T_k0``, as the tracker reports it).
        covariance
            (6, 6) its covariance, twist (ω, v), left perturbation in the sensor frame.

        Raises
        ------
        InputError
            Not a rigid transform, or a covariance of the wrong shape, not finite, with a
            negative eigenvalue or zero.
        """
        T = se3.as_transform(T_sensor_target, "prior T_sensor_target")
        try:
            cov = np.asarray(covariance, dtype=np.float64)
        except (TypeError, ValueError):
            raise InputError("prior covariance must be a 6x6 matrix of numbers") from None
        if cov.shape != (6, 6) or not np.all(np.isfinite(cov)):
            raise InputError(f"prior covariance must be a finite 6x6 matrix, got {cov.shape}")
        cov = 0.5 * (cov + cov.T)
        eig = np.linalg.eigvalsh(cov)
        # A covariance has no negative variance and is not zero: a certain prior cannot be
        # weighed against anything.
        if eig[-1] <= 0.0 or eig[0] < -1e-9 * eig[-1]:
            raise InputError(
                "prior covariance must be positive semi-definite and not zero, got "
                f"eigenvalues {eig[0]:.3g}..{eig[-1]:.3g}"
            )
        return cls(rigid(T), cov, True)


@dataclass
class MotionModel:
    """Accepted poses and the model's recent errors.

    Attributes
    ----------
    history
        The last two accepted ``(timestamp, T_sensor_target, covariance)``.
    errors
        Recent model errors: (centroid displacement m, rotation rad) per accepted frame.
    tests
        Frames the present velocity's model has predicted and seen measured since the first
        pose or the last restart (the errors kept from before a restart are of another
        velocity).
    """

    history: list[tuple[float, NDArray[np.float64], NDArray[np.float64]]] = field(
        default_factory=list
    )
    errors: list[tuple[float, float]] = field(default_factory=list)
    tests: int = 0

    @property
    def tested(self) -> bool:
        """Whether the model has predicted a frame since the first pose or the last restart:
        until then nothing has confirmed the step it extrapolates."""
        return self.tests > 0

    @property
    def settled(self) -> bool:
        """Whether its error is known within a factor of two (:data:`SETTLED_TESTS`)."""
        return self.tests >= SETTLED_TESTS

    def predict(
        self, timestamp: float, frames_missed: int, fallback_error: tuple[float, float]
    ) -> Prediction | None:
        """The prediction at ``timestamp``, or None before the first accepted pose.

        Its covariance is the last pose's plus the model error (or ``fallback_error`` while
        none is measured) per axis, growing with the frames since the last accepted pose.
        """
        T = predict_pose([(t, T) for t, T, _ in self.history[-2:]], timestamp)
        if T is None:
            return None
        e_t, e_r = self.model_error() or fallback_error
        q = np.array([e_r] * 3 + [e_t] * 3) / np.sqrt(3.0)
        cov = self.history[-1][2] + (1 + frames_missed) ** 2 * np.diag(q**2)
        return Prediction(T, cov, len(self.history) >= 2)

    def model_error(self) -> tuple[float, float] | None:
        """RMS (displacement m, rotation rad) of the recent prediction errors, None if none."""
        if not self.errors:
            return None
        e = np.asarray(self.errors)
        return float(np.sqrt((e[:, 0] ** 2).mean())), float(np.sqrt((e[:, 1] ** 2).mean()))

    def accept(
        self,
        timestamp: float,
        T_sensor_target: NDArray[np.float64],
        covariance: NDArray[np.float64],
        error: tuple[float, float] | None,
        restart: bool,
    ) -> None:
        """Record an accepted pose.

        ``error`` is its disagreement with a constant-velocity prediction (displacement m,
        rotation rad; None when there was no velocity to predict with); ``restart`` drops the
        old velocity (after a re-initialisation it is meaningless).
        """
        kept = [] if restart else self.history[-1:]
        self.history = [*kept, (timestamp, T_sensor_target, covariance)]
        if error is not None:
            self.errors = [*self.errors[-(_ERROR_WINDOW - 1) :], error]
        self.tests = (0 if restart else self.tests) + int(error is not None)
