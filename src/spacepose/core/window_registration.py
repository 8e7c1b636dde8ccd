"""A frame's pose from its registrations onto the keyframe window (docs/methods.md §1.6, §5.5).

Each estimate takes the :class:`~spacepose.core.frame_registration.FrameRegistrar` that
registers the frame onto one reference, and the window of references, oldest first:
:func:`single` registers onto one reference (ICP, GICP, or any method against a model),
:func:`li_step` averages the registrations onto the two frames before by Li's Eq. 9 (method
``jicp``), and :func:`joint` solves the registrations onto every keyframe of the window as a pose
graph (method ``keyframe``, ours). Each returns a
:class:`~spacepose.core.keyframes.FineEstimate`: ``T_k0`` (4, 4), ``T_sensor_target`` at frame k
(m), with its (6, 6) covariance (twist order (omega, v), left perturbation in the sensor frame at
frame k; rad², m²), which adds the references' own covariance and the drift a chain of keyframes
builds up (:func:`chain_drift`, rad and m), spread over the directions by
:func:`~spacepose.core.pose_covariance.shaped_drift`.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
from numpy.typing import NDArray

from spacepose.core import se3
from spacepose.core.frame_registration import FrameRegistrar
from spacepose.core.jicp import average_three, average_three_covariance
from spacepose.core.keyframes import FineEstimate, Keyframe, PreparedCloud, moved_covariance
from spacepose.core.motion import rigid
from spacepose.core.pose_covariance import shaped_drift
from spacepose.core.posegraph import PoseGraphEdge, optimize_pose_graph
from spacepose.core.registration import RegistrationResult
from spacepose.errors import SpaceposeError


def single(
    registrar: FrameRegistrar,
    prepared: PreparedCloud,
    ref: Keyframe,
    T_init: NDArray[np.float64],
    robust: bool = False,
) -> FineEstimate:
    """One registration onto ``ref`` (ICP, GICP, or any method against a model);
    ``robust``: :meth:`FrameRegistrar.register`'s."""
    pair = registrar.register(prepared, ref, T_init, robust=robust)
    res, cov_ref_k = pair.result, pair.covariance
    T_k_ref = se3.invert(res.T_target_source)
    Ad = se3.adjoint(T_k_ref)
    own = Ad @ cov_ref_k @ Ad.T
    cov = Ad @ (cov_ref_k + ref.covariance) @ Ad.T
    T = rigid(T_k_ref @ ref.T_ref_target)
    bias = chain_drift(registrar, prepared, res, ref)
    drift = shaped_drift(prepared, bias, own)
    return FineEstimate(
        T,
        cov + drift,
        own,
        res,
        ref,
        pair.step,
        bias=bias,
        drift=drift,
        structure=pair.structure,
        influence=pair.influence,
    )


def li_step(
    registrar: FrameRegistrar,
    prepared: PreparedCloud,
    window: list[Keyframe],
    T_init: NDArray[np.float64],
) -> FineEstimate:
    """Li's J-ICP: the frame k onto the two frames j, i before it, averaged by Eq. 9.

    ``window`` holds the references, oldest first (the last two are i and j). The direct
    ``T_kj`` and the indirect ``T_ki · T_ji⁻¹`` (``T_ji`` being frame j's own registration
    onto i, stored as its edge) are averaged on SE(3) and chained, ``T_k0 = ΔT_kj T_j0``;
    the earlier poses stay as they were output. With one reference, or when frame k does
    not register onto i, the direct estimate stands alone.
    """
    j = window[-1]
    latest = registrar.register(prepared, j, T_init)
    res, cov_j_k = latest.result, latest.covariance
    T_kj = se3.invert(res.T_target_source)
    own = _moved(cov_j_k, T_kj)
    delta, cov_delta = T_kj, own
    through = _edge_onto(j, window[-2]) if len(window) >= 2 else None
    if through is not None:
        T_start = rigid(T_kj @ j.T_ref_target)
        try:
            onto_i = registrar.register(prepared, window[-2], T_start, measure=False)
        except SpaceposeError:
            onto_i = None
        if onto_i is not None:
            T_ji, cov_ji = through
            T_ki = se3.invert(onto_i.result.T_target_source)
            delta = average_three(T_kj, T_ki, T_ji)
            cov_delta = average_three_covariance(
                T_ki, T_ji, own, _moved(onto_i.covariance, T_ki), cov_ji
            )
    T_k0 = rigid(delta @ j.T_ref_target)
    cov = cov_delta + _moved(j.covariance, delta)
    bias = chain_drift(registrar, prepared, res, j)
    drift = shaped_drift(prepared, bias, own)
    cov = cov + drift
    edge = (j.index, res.T_target_source, np.linalg.pinv(cov_j_k, hermitian=True))
    return FineEstimate(
        T_k0,
        cov,
        own,
        res,
        j,
        latest.step,
        (edge,),
        (),
        bias,
        drift,
        latest.structure,
        latest.influence,
    )


def joint(
    registrar: FrameRegistrar,
    prepared: PreparedCloud,
    window: list[Keyframe],
    T_init: NDArray[np.float64],
    equal_weights: bool,
) -> FineEstimate:
    """Keyframe graph (ours): register the frame to each keyframe of the window, solve it.

    Nodes are the window's keyframes (the oldest fixed) and the new frame; edges are the
    stored keyframe-to-keyframe registrations and the new frame's registrations to every
    keyframe, each weighted by its information (or equally).

    How it differs from Li's J-ICP (:func:`li_step`, docs/methods.md §5.5): its references
    are keyframes, not the two frames before, so frames between keyframes do not chain;
    the earlier keyframe poses are re-estimated, not fixed once output; the edges include
    the keyframes' own registrations and are weighted by their inverse covariance, not
    equally; its pairs are point-to-plane ICP, not Li's point-to-point.
    """
    node = {kf.index: n for n, kf in enumerate(window)}
    k = len(window)
    graph_edges: list[PoseGraphEdge] = []
    new_edges = []
    for kf in window:
        for ref_index, T_j_i, info in kf.edges:
            if ref_index in node:
                graph_edges.append(PoseGraphEdge(node[kf.index], node[ref_index], T_j_i, info))
    # The latest keyframe must register (its failure fails the frame); an older one out of
    # reach is no reason to.
    latest = registrar.register(prepared, window[-1], T_init)
    pairs = [(window[-1], latest)]
    # The latest registration is a better start for the older pairs than the prediction.
    T_start = se3.invert(latest.result.T_target_source) @ window[-1].T_ref_target
    poses = [kf.T_ref_target for kf in window] + [T_start]
    for kf in window[:-1]:
        try:
            pairs.append((kf, registrar.register(prepared, kf, T_start, measure=False)))
        except SpaceposeError:
            continue
    for kf, pair in pairs:
        T_kf_k = pair.result.T_target_source
        info = np.eye(6) if equal_weights else np.linalg.pinv(pair.covariance, hermitian=True)
        graph_edges.append(PoseGraphEdge(k, node[kf.index], T_kf_k, info))
        new_edges.append((kf.index, T_kf_k, info))
    # Gauge: the oldest keyframe keeps its pose; its covariance is added to the result.
    graph = optimize_pose_graph(
        np.array(poses), graph_edges, fixed=(0,), tolerance=registrar.graph_tolerance
    )
    oldest = window[0]
    T_k0 = rigid(graph.poses[k])
    cov = graph.covariances[k] + moved_covariance(oldest, T_k0)
    res = latest.result
    Ad_own = se3.adjoint(se3.invert(res.T_target_source))
    own = Ad_own @ latest.covariance @ Ad_own.T
    bias = chain_drift(registrar, prepared, res, window[-1])
    drift = shaped_drift(prepared, bias, own)
    cov = cov + drift
    # Node n < k is window[n]; the oldest (n = 0) is fixed.
    updated = tuple(
        (
            window[n],
            rigid(graph.poses[n]),
            graph.covariances[n] + moved_covariance(oldest, graph.poses[n]),
        )
        for n in range(1, k)
    )
    return FineEstimate(
        T_k0,
        cov,
        own,
        res,
        window[-1],
        latest.step,
        tuple(new_edges),
        updated,
        bias,
        drift,
        latest.structure,
        latest.influence,
    )


def chain_drift(
    registrar: FrameRegistrar, prepared: PreparedCloud, res: RegistrationResult, ref: Keyframe
) -> tuple[float, float]:
    """1-σ (rad, m at the centroid) of the drift a keyframe chain has built up to the frame.

    A registration between two views is biased in proportion to the motion between them
    (sampling and normals differ), and the bias keeps its sign along a chain of keyframes,
    so it adds up linearly: the reference's drift plus ``floor_motion`` times the rotation
    angle and the centroid's displacement from the reference. A model has none.
    """
    if ref.index < 0:
        return 0.0, 0.0
    kappa = registrar.lengths.floor_motion
    c_ref = se3.transform_points(res.T_target_source, prepared.centroid[None])[0]
    angle = float(np.linalg.norm(se3.log(res.T_target_source)[:3]))
    shift = float(np.linalg.norm(c_ref - prepared.centroid))
    return ref.drift[0] + kappa * angle, ref.drift[1] + kappa * shift


def _moved(cov: NDArray[np.float64], T_b_a: NDArray[np.float64]) -> NDArray[np.float64]:
    """A covariance (6, 6) left in frame a carried into frame b by ``T_b_a``'s adjoint."""
    Ad = se3.adjoint(T_b_a)
    return Ad @ cov @ Ad.T


def _edge_onto(
    frame: Keyframe, earlier: Keyframe
) -> tuple[NDArray[np.float64], NDArray[np.float64]] | None:
    """``T_frame_earlier`` and its covariance (left, in ``frame``) from ``frame``'s stored
    registration onto ``earlier``, or None when it has none."""
    for index, T_earlier_frame, info in frame.edges:
        if index == earlier.index:
            T = se3.invert(T_earlier_frame)
            return T, _moved(np.linalg.pinv(info, hermitian=True), T)
    return None


def with_grid_spread(
    registrar: FrameRegistrar,
    shifted: PreparedCloud,
    estimate: FineEstimate,
    robust: bool = False,
) -> FineEstimate:
    """``estimate`` with the voxel grid's share of its error in its covariance.

    The frame, downsampled on a grid shifted by half a voxel (``shifted``,
    :meth:`~spacepose.core.frame_preparation.FramePreparer.shifted_source`), is registered
    onto the estimate's reference from the estimate's own registration there. The two
    samplings' errors are independent draws of the sampling error, so their difference ``d``
    (a twist, sensor frame at frame k) has twice its covariance: ``d dᵀ / 2`` is added. The
    pose is left as it is: its error and ``d`` are correlated (a sampling far from the
    surface's own pose moves ``d`` with it), which a mean of the two would lose.

    ``robust``: the shifted frame weighed as the estimate's registration was (against a
    model, by a redescending kernel). A registration of the shifted frame that fails leaves
    the estimate as it is.
    """
    ref = estimate.reference
    T_k_ref = se3.invert(estimate.result.T_target_source)
    try:
        pair = registrar.register(
            shifted, ref, T_k_ref @ ref.T_ref_target, measure=False, robust=robust
        )
    except SpaceposeError:
        return estimate
    T_ref_k_shifted = pair.result.T_target_source
    # T_shifted = exp(d) T: both at frame k, seen from the one reference.
    d = se3.log(se3.invert(T_ref_k_shifted) @ se3.invert(T_k_ref))
    spread = 0.5 * np.outer(d, d)
    return replace(estimate, covariance=estimate.covariance + spread)
