"""What a sensor's systematic range error does to a pose registered against a model
(docs/methods.md §5.3): a constant offset, stated, and its change with range, measured.

A ToF camera or LiDAR measures every range a little long or short. Against a model this moves
the pose, and the registration's own covariance (from the residuals' spread) does not see it:

- a constant offset ``b₀`` moves every return along its own ray alike, mostly a shift of the
  target along the line of sight; the fit at the shifted pose is as good as at the true one, so
  no residual shows it, and its σ is stated (a multiple of the range noise);
- an offset that changes with range (an AMCW ToF camera's *wiggling*: a few mm, periodic over
  a metre or two of range) stretches and bends the cloud along the rays. The rigid fit turns
  and shifts to follow it part of the way, and the rest stays in the residuals, where it is
  measured: a polynomial ``Σₖ bₖ xᵏ`` (k = 1…5, ``x`` the range about its mean in units of its
  spread) fitted to the residuals left after the pose (the registration's columns projected
  out), with a cluster-robust variance.

Both act on the pose through its sensitivity ``j = −H⁻¹ Σ hᵢ ∂eᵢ/∂b`` (``hᵢ = (qᵢ × nᵢ, nᵢ)``,
``eᵢ = nᵢ·(qᵢ − mᵢ)`` the point-to-plane residual). The measured terms' covariance
``J (b̂ b̂ᵀ + var b̂) Jᵀ`` is the fitted error's effect plus the variance a fit with the terms
free would have added (the Schur complement of the joint system).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy.stats import chi2

from spacepose.core import se3
from spacepose.core.cell_hash import group_cells
from spacepose.core.correspondences import find_correspondences
from spacepose.core.keyframes import PreparedCloud
from spacepose.core.voxel import cell_keys

# Powers of the range (about its mean) the measured part of the offset is made of: a period of
# wiggling across the target's range needs five (three left 0.5 mm of a 6 mm one on a
# satellite 1.9 m deep).
RANGE_TERMS = 5
# Chance that residuals without a range error show range terms this strong (their χ²).
SIGNIFICANCE = 0.99
_CHI2_BOUND = float(chi2.ppf(SIGNIFICANCE, RANGE_TERMS))
# Shift (Mahalanobis, in the pose's own σ) below which measured terms are not added: there the
# residuals' structure is mostly the model's and the frame's sampling, which the registration's
# own covariance carries. On the lab's noisy frames without a range error the terms shift the
# pose by 0-2.4 of its σ (seed 0, 8 frames), with 2 mm of wiggling 1.5-2.8, with 4 mm 3.6-5.
# It does not hold on sampled CAD meshes: the Hubble kit at 5 m without a range error reached
# 8.9 (9 of 20 frames above 3), its rotation σ 1.8-4.7 times wider on third-party renders.
SHIFT_BOUND = 3.0


@dataclass(frozen=True)
class RangeBiasEffect:
    """A range error's effect on one pose: twists (omega, v), left perturbation, sensor frame.

    Attributes
    ----------
    offset
        (6, 6) covariance of the stated constant offset.
    measured
        (6, 6) covariance of the measured range terms; zeros when the residuals show none.
    shift
        (6,) the pose's shift by the measured terms (zeros when not measured).
    """

    offset: NDArray[np.float64]
    measured: NDArray[np.float64]
    shift: NDArray[np.float64]

    def covariance(self, own: NDArray[np.float64]) -> NDArray[np.float64]:
        """(6, 6) ``own`` (the registration's covariance, sensor frame) with the offset's
        term, and the measured terms' when they shift the pose by more than
        :data:`SHIFT_BOUND` of its own σ."""
        total = own + self.offset
        if float(self.shift @ np.linalg.pinv(own, hermitian=True) @ self.shift) > SHIFT_BOUND**2:
            total = total + self.measured
        return total


def range_bias_effect(
    points: NDArray[np.float64],
    model: PreparedCloud,
    T_sensor_target: NDArray[np.float64],
    gate: float,
    sigma: float,
    cell: float,
    workers: int = -1,
) -> RangeBiasEffect:
    """A sensor's range error's effect on a pose registered against a model (module
    docstring): the stated constant offset of σ ``sigma`` (m) and the frame's measured change
    with range, kept when its terms are significant at :data:`SIGNIFICANCE`. Zero when fewer
    than 7 pairs are found within ``gate`` or the pairs leave a direction of the pose free.

    Parameters
    ----------
    points
        (N, 3) the frame's points, sensor frame (the sensor at its origin).
    model
        The model, with normals (target frame).
    T_sensor_target
        (4, 4) the registered pose.
    gate
        Largest distance (m) of a pair.
    sigma
        1-σ (m) of the constant offset.
    cell
        Edge (m) of the cells whose residuals are taken as one correlated group
        (:func:`~spacepose.core.pose_covariance.clustered_covariance`).
    """
    none = RangeBiasEffect(np.zeros((6, 6)), np.zeros((6, 6)), np.zeros(6))
    T_target_sensor = se3.invert(T_sensor_target)
    moved = se3.transform_points(T_target_sensor, points)
    s, t, _ = find_correspondences(model.tree, moved, gate, workers)
    if len(s) < 7:
        return none
    q, n = moved[s], model.cloud.normals[t]
    rays = q - T_target_sensor[:3, 3]
    ranges = np.linalg.norm(rays, axis=1)
    along = np.einsum("ij,ij->i", n, rays / ranges[:, None])
    h = np.hstack([np.cross(q, n), n])
    H = h.T @ h
    ev = np.linalg.eigvalsh(H)
    if ev[0] <= 1e-12 * ev[-1]:
        return none
    # ∂e/∂b of the offset (each return one unit along its ray) and of the range terms.
    scaled = (ranges - ranges.mean()) / max(float(np.std(ranges)), 1e-12)
    terms = scaled[:, None] ** np.arange(1, RANGE_TERMS + 1)
    d_terms = along[:, None] * terms
    j_offset = -np.linalg.solve(H, h.T @ along)
    j_terms = -np.linalg.solve(H, h.T @ d_terms)
    residuals = np.einsum("ij,ij->i", n, q - model.cloud.points[t])
    # The terms' columns with the pose's projected out; the residuals left after the pose.
    terms_left = d_terms + h @ j_terms
    left = residuals - h @ np.linalg.solve(H, h.T @ residuals)
    W_inv = np.linalg.pinv(terms_left.T @ terms_left, hermitian=True)
    b = W_inv @ (terms_left.T @ left)
    # Cluster-robust variance of the terms: a model's sampling leaves residuals correlated over
    # a few voxels, which white noise's variance would read as range terms.
    # Hashed cell keys: numpy's unique over rows took 37 ms of a lab frame's 5,000 pairs.
    cells, occupied, _, _ = group_cells(cell_keys(q, cell)[0])
    groups = len(occupied)
    sums = np.zeros((groups, RANGE_TERMS))
    np.add.at(sums, cells, terms_left * (left - terms_left @ b)[:, None])
    b_var = groups / max(groups - 1, 1) * (W_inv @ (sums.T @ sums) @ W_inv)
    # The twist of T_target_sensor in the target frame, as one of T_sensor_target in the sensor
    # frame: exp(ξ) T_ts ↔ exp(−Ad(T_st) ξ) T_st.
    Ad = se3.adjoint(T_sensor_target)
    offset = sigma**2 * np.outer(j_offset, j_offset)
    if float(b @ np.linalg.pinv(b_var, hermitian=True) @ b) <= _CHI2_BOUND:
        return RangeBiasEffect(Ad @ offset @ Ad.T, np.zeros((6, 6)), np.zeros(6))
    # A range error that changes this much across the target: its mean, the offset no residual
    # shows, is not known better than its spread.
    measured = float(np.var(terms @ b)) * np.outer(j_offset, j_offset)
    measured += j_terms @ (np.outer(b, b) + b_var) @ j_terms.T
    return RangeBiasEffect(Ad @ offset @ Ad.T, Ad @ measured @ Ad.T, -Ad @ (j_terms @ b))
