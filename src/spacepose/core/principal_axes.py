"""Principal axes and inertia ratios of a tumbling target from its tracked attitudes (model-free).

A model-free tracker reports the target's motion in the frame F of its first view (methods.md §0.7);
the navigation filter needs the body's principal axes B. A torque-free body keeps its angular
momentum in inertial space: with ``J`` the inertia tensor in F (unknown, up to scale) and
``ω_F`` the body rate in F,

    R_I_F(t) J ω_F(t) = h   (constant),

linear in the six entries of ``J`` and the three of ``h``. Stacking every pair of tracked
attitudes gives a homogeneous system whose null vector (smallest right singular vector) is
``(J, h)``; the eigenvectors of ``J`` are the principal axes in F and its eigenvalues the
moments up to scale. Axes are ordered by decreasing moment (x the largest) and signed to a
right-handed frame; each axis keeps a sign ambiguity that no motion resolves (a half turn about
a principal axis leaves the dynamics unchanged).

Rates come from attitude differences ``m`` frames apart (central, at the mid attitude), so the
tracker's per-frame attitude noise is divided by the baseline. A batch estimate: the filter does
not yet carry the rotation F → B as a state (see :mod:`spacepose.core.fused_navigation`).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial.transform import Rotation

from spacepose.core.dynamics import inertia_ratios
from spacepose.errors import InputError

__all__ = ["PrincipalAxes", "principal_axes"]


@dataclass(frozen=True)
class PrincipalAxes:
    """Result of :func:`principal_axes`.

    Attributes
    ----------
    R_F_B
        (3, 3) principal axes (columns, decreasing moment) in the tracked frame F.
    moments
        (3,) principal moments, normalised to sum 1.
    k
        (3,) inertia ratios of :func:`spacepose.core.dynamics.inertia_ratios` in that order
        (NaN when a moment is not positive).
    h_I
        (3,) angular momentum direction in I (unit, same scale as ``moments``).
    residual
        RMS of ``R_I_F J ω_F − h`` over the samples relative to ``|h|`` (0 for exact data).
    """

    R_F_B: NDArray[np.float64]
    moments: NDArray[np.float64]
    k: NDArray[np.float64]
    h_I: NDArray[np.float64]
    residual: float

    @property
    def physical(self) -> bool:
        """Whether the moments can be a rigid body's: positive, each at most the sum of the
        other two (too short a batch can give neither)."""
        m = self.moments
        return bool(np.all(m > 0) and np.all(2 * m <= m.sum() + 1e-12))


def principal_axes(t: ArrayLike, R_I_F: ArrayLike, baseline: int = 5) -> PrincipalAxes:
    """Principal axes of a torque-free body from its attitudes ``R_I_F`` (N, 3, 3) at times
    ``t`` (N,), s; ``baseline`` frames between the two attitudes of each rate sample.

    Raises
    ------
    InputError
        Shapes disagree, times not finite and increasing, an attitude that is not a rotation
        (NaN, zero, scaled or reflected; NaN ended in numpy's 'SVD did not converge', a scaled
        matrix was taken as its rotation without a word), a baseline that is not a whole
        number >= 1, or fewer than 4 rate samples.
    """
    t = np.asarray(t, dtype=np.float64)
    R = np.asarray(R_I_F, dtype=np.float64)
    if t.ndim != 1:
        raise InputError(f"principal_axes: t must be (N,) times, got shape {t.shape}")
    if R.shape != (len(t), 3, 3):
        raise InputError(f"principal_axes: R_I_F must be ({len(t)}, 3, 3), got {R.shape}")
    if not np.isfinite(t).all() or np.any(np.diff(t) <= 0):
        raise InputError("principal_axes: the times t must be finite and increasing")
    bad = _not_rotations(R)
    if len(bad):
        raise InputError(
            f"principal_axes: R_I_F[{bad[0]}] is not a rotation (finite, orthonormal, det +1); "
            f"{len(bad)} of {len(R)} attitudes are not"
        )
    if isinstance(baseline, bool) or not float(baseline).is_integer():
        raise InputError(
            f"principal_axes: baseline must be a whole number of frames, got {baseline}"
        )
    m = int(baseline)
    if len(t) - m < 4 or m < 1:
        raise InputError(f"{len(t)} attitudes give fewer than 4 rate samples at baseline {m}")
    rot = Rotation.from_matrix(R)
    step = (rot[:-m].inv() * rot[m:]).as_rotvec()  # body-frame rotation over the baseline
    w_F = step / (t[m:] - t[:-m])[:, None]
    R_mid = (rot[:-m] * Rotation.from_rotvec(0.5 * step)).as_matrix()
    # R J ω - h = 0, J symmetric: columns for J11, J22, J33, J12, J13, J23, then -h.
    wx, wy, wz = w_F.T
    basis = np.zeros((len(w_F), 3, 6))
    basis[:, 0, 0], basis[:, 1, 1], basis[:, 2, 2] = wx, wy, wz
    basis[:, 0, 3], basis[:, 1, 3] = wy, wx
    basis[:, 0, 4], basis[:, 2, 4] = wz, wx
    basis[:, 1, 5], basis[:, 2, 5] = wz, wy
    A = np.concatenate([R_mid @ basis, np.broadcast_to(-np.eye(3), (len(w_F), 3, 3))], axis=2)
    A = A.reshape(-1, 9)
    x = np.linalg.svd(A, full_matrices=False)[2][-1]
    J = np.array([[x[0], x[3], x[4]], [x[3], x[1], x[5]], [x[4], x[5], x[2]]])
    if np.trace(J) < 0:
        J, x = -J, -x
    lam, V = np.linalg.eigh(J)
    order = np.argsort(lam)[::-1]
    lam, V = lam[order], V[:, order]
    if np.linalg.det(V) < 0:
        V[:, 2] = -V[:, 2]
    scale = lam.sum()
    h = x[6:] / scale
    residual = float(np.linalg.norm(A @ x) / np.sqrt(len(w_F)) / np.linalg.norm(x[6:]))
    k = inertia_ratios(lam) if lam.min() > 0 else np.full(3, np.nan)
    return PrincipalAxes(V, lam / scale, k, h, residual)


def _not_rotations(R: NDArray[np.float64]) -> NDArray[np.intp]:
    """Indices of the (N, 3, 3) matrices that are not rotations to 1e-3: the attitudes come
    from products of validated rotations, each off orthonormal by up to 1e-6."""
    with np.errstate(invalid="ignore", over="ignore"):
        off = np.abs(np.einsum("nji,njk->nik", R, R) - np.eye(3)).max(axis=(1, 2))
        det = np.linalg.det(np.where(np.isfinite(R), R, 0.0))
    return np.flatnonzero(~(off <= 1e-3) | ~(det > 0))
