"""What every registration returns, and the closed-form rigid fit they share."""

from __future__ import annotations

from dataclasses import dataclass, field, replace

import numpy as np
from numpy.typing import ArrayLike, NDArray

from spacepose.core import se3
from spacepose.core.cloud import check_peak
from spacepose.core.scale import rms_radius
from spacepose.core.se3 import real_array
from spacepose.errors import DegenerateGeometryError, InputError


@dataclass(frozen=True)
class RegistrationResult:
    """Outcome of aligning a source cloud to a target cloud.

    Attributes
    ----------
    T_target_source
        (4, 4) transform mapping source coordinates into the target frame.
    fitness
        Share of source points with a correspondence within the maximum distance, in [0, 1].
    inlier_rmse
        RMS distance of those correspondences, metres.
    iterations
        Iterations run (RANSAC: hypotheses evaluated).
    converged
        Whether the stopping criterion was met before the iteration limit.
    information
        (6, 6) information matrix ``JᵀWJ`` of the final residuals, twist order ``(omega, v)``,
        left perturbation of ``T_target_source``; in units of 1/σ² when the residuals are
        weighted by their noise, otherwise of 1/m² (scale by 1/σ² for a covariance).
    n_correspondences
        Number of inlier correspondences behind ``fitness`` and ``information``.
    residual_sigma
        Residual standard deviation (m) the registration estimated for its (unweighted-unit)
        ``information``, e.g. the weighted σ of a robust kernel's inliers; None: the inlier
        RMSE stands in for it (see :meth:`covariance`).
    centred_information
        ``(centre (3,), information (6, 6) of the twist about it)`` when the registration was
        solved about a centre far from the origin (:func:`moved_back`): ``information`` about
        the origin has then lost digits (at 40,000 km, every one of its rotation block), and
        :meth:`covariance` inverts this one instead. None otherwise.

    Raises
    ------
    InputError
        A transform that is not rigid, a fitness outside [0, 1] or a negative RMSE.
    """

    T_target_source: NDArray[np.float64]
    fitness: float
    inlier_rmse: float
    iterations: int
    converged: bool
    information: NDArray[np.float64] = field(default_factory=lambda: np.zeros((6, 6)))
    n_correspondences: int = 0
    residual_sigma: float | None = None
    centred_information: tuple[NDArray[np.float64], NDArray[np.float64]] | None = None

    def __post_init__(self) -> None:
        se3.as_transform(self.T_target_source, "T_target_source")
        fitness, rmse = (
            _number_or_nan(v, n)
            for v, n in ((self.fitness, "fitness"), (self.inlier_rmse, "inlier_rmse"))
        )
        # NaN passes: a registration with no correspondence has no RMSE.
        if not 0.0 <= fitness <= 1.0 and not np.isnan(fitness):
            raise InputError(f"fitness must lie in [0, 1], got {fitness}")
        if rmse < 0.0:
            raise InputError(f"inlier_rmse must not be negative, got {rmse}")

    def covariance(self, sigma: float | None = None) -> NDArray[np.float64]:
        """6×6 covariance ``σ² · information⁻¹`` (pseudo-inverse where unconstrained).

        It is the covariance the final correspondences give: it does not judge whether the
        surfaces constrain every direction (a plate sliding in its own plane pairs its points
        anyway, and GICP's regularised covariances put information on the slide);
        :func:`~spacepose.tools.register.register` and the tracker do
        (:func:`~spacepose.core.degeneracy.surface_degeneracy`).

        Inverted about the clouds' centre (:func:`information_centre`) and moved back: about an
        origin far from the clouds (10 km and more) each rotation is a lever arm of that
        distance, and the pseudo-inverse of the information there gave a rotation σ 10⁵ times
        too small at 10 km and 1e-14 rad at 7,000 km, which the information itself, moved to
        the centre, does not.

        Parameters
        ----------
        sigma
            Residual standard deviation (m) when ``information`` is unweighted; defaults to
            ``residual_sigma`` when set, else the inlier RMSE. Pass 1.0 when the information is
            already noise-weighted.

        Raises
        ------
        InputError
            ``sigma`` not a number of 0 or more; ``information`` holds NaN or inf, or is not
            positive semi-definite (a negative variance would come out).
        """
        s = sigma if sigma is not None else self.residual_sigma
        s = self.inlier_rmse if s is None else s
        s = se3.real_number(s, "sigma")
        if s < 0.0:
            raise InputError(f"sigma must not be negative, got {s}")
        if not np.isfinite(self.information).all():
            # numpy's "SVD did not converge in Linear Least Squares" named neither.
            raise InputError("the registration's information holds NaN or inf: no covariance")
        if self.centred_information is not None:
            centre, information = self.centred_information
        else:
            centre = information_centre(self.information)
            # A twist about the centre -> about the origin; the information moves by the
            # transpose.
            back = se3.adjoint(se3.make_transform(np.eye(3), centre))
            information = back.T @ self.information @ back
        ev = np.linalg.eigvalsh(information)
        if ev[0] < -1e-9 * max(ev[-1], 0.0) or ev[-1] < 0.0:
            raise InputError(
                f"the registration's information has a negative eigenvalue ({ev[0]:.3g}): not "
                "an information matrix"
            )
        back = se3.adjoint(se3.make_transform(np.eye(3), centre))
        return s**2 * (back @ np.linalg.pinv(information, hermitian=True) @ back.T)

    @property
    def condition_number(self) -> float:
        """Ratio of the largest to the smallest eigenvalue of ``information`` (inf if singular)."""
        ev = np.linalg.eigvalsh(self.information)
        return float(ev[-1] / ev[0]) if ev[0] > 0 else float("inf")


def _number_or_nan(value: object, name: str) -> float:
    """``value`` as a finite float or NaN (a registration with no correspondence has no RMSE),
    or the package's error naming it: text or None compared with 0 raised a raw TypeError."""
    if isinstance(value, float | np.floating) and np.isnan(value):
        return float("nan")
    return se3.real_number(value, name)


def information_centre(information: ArrayLike) -> NDArray[np.float64]:
    """The point (3,) about which a registration's (6, 6) information (twist ``(omega, v)``
    about the origin) couples rotation and translation least: for point-to-plane rows
    ``(p × n, n)`` the cross block about ``c`` is ``B - [c]ₓ D`` (``B`` the cross block, ``D``
    the translation block), made smallest in the least-squares sense; for point-to-point rows
    it is the centroid. Directions the rows leave undetermined (along a plane's normal) do not
    change the rows."""
    information = np.asarray(information, dtype=np.float64)
    B, D = information[:3, 3:], information[3:, 3:]
    # Column j of [c]ₓ D is c × D_j = -[D_j]ₓ c: B - [c]ₓ D = B + [D_j]ₓ c, column by column.
    K = np.vstack([se3.skew(D[:, j]) for j in range(3)])
    return -np.linalg.lstsq(K, B.T.reshape(-1), rcond=None)[0]


# A cloud whose centre lies further from its origin than this many RMS radii is solved about its
# centre: about its origin each rotation is a lever arm of that distance (a tracker's frames lie
# within tens of radii of their sensor, and are solved as they are).
FAR_RADII = 100.0
_FAR_SAMPLE = 1024


def far_centre(points: NDArray[np.float64]) -> NDArray[np.float64] | None:
    """The centroid (3,) of (N, 3) ``points`` when it lies more than :data:`FAR_RADII` RMS radii
    from their origin, else None. Both from an even stride of about a thousand points: the
    test has a hundredfold margin, any centre near the cloud serves the solve, and ICP asks
    once a call (0.55 ms over a 20,000-point keyframe, a few per tracked frame)."""
    sample = points[:: max(1, len(points) // _FAR_SAMPLE)]
    centre = sample.mean(axis=0)
    return centre if np.linalg.norm(centre) > FAR_RADII * rms_radius(sample) else None


def moved_back(result: RegistrationResult, S: NDArray[np.float64]) -> RegistrationResult:
    """``result`` of clouds both moved by the shift ``S`` (4, 4), for the clouds where they
    were: the pose ``S⁻¹ T S``, the information of the twist about the original origin, and
    the information about the point the shift took to the origin, which keeps its digits
    (:attr:`RegistrationResult.centred_information`)."""
    T = se3.invert(S) @ result.T_target_source @ S  # S is a shift: R is kept to the bit
    Ad = se3.adjoint(S)
    information = Ad.T @ result.information @ Ad
    centre = -S[:3, 3]
    centred = (centre, result.information)
    return replace(result, T_target_source=T, information=information, centred_information=centred)


def kabsch(
    source: ArrayLike, target: ArrayLike, weights: ArrayLike | None = None
) -> NDArray[np.float64]:
    """Least-squares rigid transform ``T_target_source`` from paired points (Kabsch/Umeyama).

    Batched: ``source`` and ``target`` are (..., M, 3) with matching shapes, ``weights`` (..., M);
    returns (..., 4, 4). Minimises ``Σ w_i ‖R s_i + t − d_i‖²`` with ``det R = +1``.

    Raises
    ------
    InputError
        On mismatched shapes, fewer than 3 pairs, non-finite points or ones whose squares
        overflow float64, or weights that are not one finite value >= 0 per pair with a
        positive sum.
    DegenerateGeometryError
        When a (single, unbatched) set of pairs is collinear, so the rotation is undetermined.
    """
    src = real_array(source, "kabsch: the source points")
    dst = real_array(target, "kabsch: the target points")
    if src.shape != dst.shape or src.ndim < 2 or src.shape[-1] != 3:
        raise InputError(f"kabsch needs matching (..., M, 3) arrays, got {src.shape}, {dst.shape}")
    if src.shape[-2] < 3:
        raise InputError(f"kabsch needs at least 3 point pairs, got {src.shape[-2]}")
    for name, values in (("source", src), ("target", dst)):
        peak = float(max(values.max(initial=0.0), -values.min(initial=0.0)))  # NaN, inf: any
        if not np.isfinite(peak):
            raise InputError(f"kabsch: the {name} points have non-finite entries (NaN or inf)")
        # Their squares overflowed: numpy's "SVD did not converge" (LinAlgError) at 1e200.
        check_peak(peak, f"kabsch: the {name} points")
    w = np.ones(src.shape[:-1]) if weights is None else _pair_weights(weights, src.shape[:-1])
    wsum = w.sum(axis=-1, keepdims=True)
    mu_s = np.einsum("...m,...mi->...i", w, src) / wsum
    mu_d = np.einsum("...m,...mi->...i", w, dst) / wsum
    cs = src - mu_s[..., None, :]
    cd = dst - mu_d[..., None, :]
    H = np.einsum("...m,...mi,...mj->...ij", w, cs, cd)
    U, S, Vt = np.linalg.svd(H)
    if src.ndim == 2 and S[1] <= 1e-12 * max(S[0], 1e-300):
        raise DegenerateGeometryError("kabsch: the point pairs are collinear or coincident")
    # Reflection guard: flip the last singular direction when det(V Uᵀ) < 0.
    d = np.sign(np.linalg.det(np.swapaxes(Vt, -1, -2) @ np.swapaxes(U, -1, -2)))
    d = np.where(d == 0, 1.0, d)
    D = np.zeros((*d.shape, 3, 3))
    D[..., 0, 0] = 1.0
    D[..., 1, 1] = 1.0
    D[..., 2, 2] = d
    R = np.swapaxes(Vt, -1, -2) @ D @ np.swapaxes(U, -1, -2)
    T = np.zeros((*src.shape[:-2], 4, 4))
    T[..., :3, :3] = R
    T[..., :3, 3] = mu_d - np.einsum("...ij,...j->...i", R, mu_s)
    T[..., 3, 3] = 1.0
    return T


def _pair_weights(weights: ArrayLike, shape: tuple[int, ...]) -> NDArray[np.float64]:
    """``weights`` as one finite value >= 0 per pair of ``shape``, each set summing above 0:
    a NaN or a zero sum ended in numpy's "SVD did not converge", and a negative weight
    turned the fit into a reflection's without a word."""
    try:
        w = np.asarray(weights, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"kabsch: the weights are not numeric: {exc}") from None
    try:
        w = np.broadcast_to(w, shape)
    except ValueError:
        raise InputError(
            f"kabsch needs one weight per point pair {shape}, got {np.shape(weights)}"
        ) from None
    if not np.isfinite(w).all():
        raise InputError("kabsch: the weights have non-finite entries (NaN or inf)")
    if (w < 0).any():
        raise InputError(f"kabsch: weights must be >= 0, got {float(w.min()):.6g}")
    with np.errstate(over="ignore"):
        total = w.sum(axis=-1)
    if (total <= 0).any():
        raise InputError("kabsch: the weights of a set of pairs are all zero")
    if not np.isfinite(total).all():
        # Their sum overflowed to inf: numpy's "SVD did not converge" followed.
        raise InputError("kabsch: the weights of a set of pairs sum past float64's range")
    return w
