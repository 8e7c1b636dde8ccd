"""Model-free start of the navigation filter: where the body's principal axes and centre of mass
sit in the frame F of the first tracked view, from a batch of model-free tracked poses.

The model-free tracker reports ``T_C_F(k)`` (``T_k0``, methods.md §0.7). With the chaser attitude
``R_O_C`` and O turning at the mean motion, each pose gives the attitude ``R_I_F(k)``; the
principal axes ``R_F_B`` and the inertia ratios follow from the conservation of angular momentum
(:func:`spacepose.core.principal_axes.principal_axes`). The centre of mass ``p_F`` (in F) is the
body point that moves as the Clohessy–Wiltshire equations say: with ``Φ(t)`` their transition
matrix and ``x0`` its initial state in O,

    R_O_C (R_C_F(k) p_F + t_C_F(k)) = Φ_ρ(t_k − t_0) x0,

linear in ``(p_F, x0)`` and solved by least squares. The filter then navigates the frame
``B' = [R_F_B, p_F]`` in F, whose axes are the estimated principal axes and whose origin the
estimated centre of mass; its Δ absorbs what the batch left. The batch is not revised later (the
alignment is not a filter state).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from spacepose.core import dynamics, se3
from spacepose.core.principal_axes import PrincipalAxes, principal_axes
from spacepose.errors import InputError

__all__ = ["ModelFreeStart", "model_free_start"]


@dataclass(frozen=True)
class ModelFreeStart:
    """Result of :func:`model_free_start`.

    Attributes
    ----------
    T_F_B
        (4, 4) estimated body frame (principal axes, origin at the centre of mass) in F.
    axes
        The principal-axes estimate (inertia ratios in ``axes.k``).
    state0
        (6,) CW state ``(ρ, ρ̇)`` of the centre of mass in O at the first time, m and m/s.
    residual_m
        RMS of the CW fit's position residuals, m.
    """

    T_F_B: NDArray[np.float64]
    axes: PrincipalAxes
    state0: NDArray[np.float64]
    residual_m: float


def model_free_start(
    t: ArrayLike,
    T_C_F: ArrayLike,
    mean_motion: float,
    R_O_C: ArrayLike,
    baseline: int = 5,
) -> ModelFreeStart:
    """Body frame in F from model-free poses ``T_C_F`` (N, 4, 4) at times ``t`` (N,), s.

    ``t`` counts from the epoch where I and O coincide; ``R_O_C`` (3, 3) is the chaser's
    attitude in O; ``baseline`` as for :func:`principal_axes`.

    Raises
    ------
    InputError
        Shapes disagree or too few poses.
    """
    t = np.asarray(t, dtype=np.float64)
    T = np.asarray(T_C_F, dtype=np.float64)
    R_O_C = np.asarray(R_O_C, dtype=np.float64)
    if T.shape != (len(t), 4, 4) or len(t) < 10:
        raise InputError(f"need at least 10 poses (N, 4, 4) with their times, got {T.shape}")
    R_I_F = np.array(
        [dynamics.R_I_O(mean_motion, tk) @ R_O_C @ Tk[:3, :3] for tk, Tk in zip(t, T, strict=True)]
    )
    axes = principal_axes(t, R_I_F, baseline)
    # [R_O_C R_C_F(k), −Φ_ρ(t_k)] (p_F, x0) = −R_O_C t_C_F(k)
    rows = [np.hstack([R_O_C @ Tk[:3, :3], -dynamics.cw_stm(mean_motion, tk - t[0])[:3]])
            for tk, Tk in zip(t, T, strict=True)]  # fmt: skip
    A = np.concatenate(rows)
    b = -np.concatenate([R_O_C @ Tk[:3, 3] for Tk in T])
    x, *_ = np.linalg.lstsq(A, b, rcond=None)
    residual = float(np.sqrt(np.mean((A @ x - b) ** 2)))
    return ModelFreeStart(se3.make_transform(axes.R_F_B, x[:3]), axes, x[3:], residual)
