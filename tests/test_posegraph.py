"""Pose-graph optimisation on SE(3): exact recovery, covariances, and bad input."""

from __future__ import annotations

import numpy as np
import pytest

from spacepose.core import se3
from spacepose.core.posegraph import (
    PoseGraphEdge,
    _normal_equations,
    edge_residual,
    optimize_pose_graph,
)
from spacepose.errors import DegenerateGeometryError, InputError


def _edge(i: int, j: int, X: np.ndarray, info: np.ndarray, noise: np.ndarray | None = None):
    """Edge (i, j) measuring X_j X_i⁻¹, optionally perturbed on the left by exp(noise)."""
    T = X[j] @ se3.invert(X[i])
    return PoseGraphEdge(i, j, T if noise is None else se3.exp(noise) @ T, info)


def test_exact_measurements_recover_truth(rng: np.random.Generator) -> None:
    truth = np.stack([np.eye(4)] + [se3.exp(rng.normal(0, 0.5, 6)) for _ in range(4)])
    edges = [_edge(i, j, truth, np.eye(6)) for i in range(5) for j in range(i + 1, 5)]
    start = np.stack([truth[0]] + [se3.exp(rng.normal(0, 0.05, 6)) @ T for T in truth[1:]])
    res = optimize_pose_graph(start, edges)
    np.testing.assert_allclose(res.poses, truth, atol=1e-10)
    assert res.converged and res.cost < 1e-20
    for e in edges:
        np.testing.assert_allclose(edge_residual(e, res.poses), 0.0, atol=1e-10)


def test_compiled_assembly_matches_the_edge_formula(rng: np.random.Generator) -> None:
    """H, b and the cost against a per-edge assembly from se3's log and adjoint, on edges of
    every size of rotation, those within 0.1 rad of a half turn included (the logarithm takes
    the axis from the quaternion there)."""
    X = np.stack([se3.exp(rng.normal(0, 1.0, 6)) for _ in range(4)])
    edges = []
    for n, (i, j) in enumerate([(0, 1), (1, 2), (2, 3), (3, 0), (0, 2), (1, 3)]):
        A = rng.normal(size=(6, 6))
        info = A @ A.T + np.eye(6)
        axis = rng.normal(size=3)
        angle = np.pi - 0.02 * n if n % 2 else 0.3 * n  # near a half turn, and small to 1.5 rad
        miss = se3.exp(np.concatenate([angle * axis / np.linalg.norm(axis), rng.normal(size=3)]))
        edges.append(PoseGraphEdge(i, j, miss @ X[j] @ se3.invert(X[i]), info))
    slot = {1: 0, 2: 6, 3: 12}  # node 0 fixed
    H = np.zeros((18, 18))
    b = np.zeros(18)
    cost = 0.0
    for e in edges:
        r = edge_residual(e, X)
        cost += r @ e.information @ r
        blocks = {e.j: -np.eye(6), e.i: se3.adjoint(X[e.j] @ se3.invert(X[e.i]))}
        for n, Jn in blocks.items():
            if n in slot:
                b[slot[n] : slot[n] + 6] += Jn.T @ e.information @ r
                for m, Jm in blocks.items():
                    if m in slot:
                        H[slot[n] : slot[n] + 6, slot[m] : slot[m] + 6] += Jn.T @ e.information @ Jm
    arrays = (
        np.array([e.T_j_i for e in edges]),
        np.array([e.information for e in edges]),
        np.array([e.i for e in edges]),
        np.array([e.j for e in edges]),
        np.array([-1, 0, 6, 12]),
    )
    H_c, b_c, cost_c = _normal_equations(X, *arrays, 18)
    np.testing.assert_allclose(H_c, H, rtol=1e-10, atol=1e-10)
    np.testing.assert_allclose(b_c, b, rtol=1e-9, atol=1e-9)
    assert cost_c == pytest.approx(cost, rel=1e-10)


def test_single_edge_covariance_is_inverse_information(rng: np.random.Generator) -> None:
    A = rng.normal(size=(6, 6))
    info = A @ A.T + 6 * np.eye(6)
    X = np.stack([np.eye(4), se3.exp(rng.normal(size=6))])
    res = optimize_pose_graph(X, [_edge(0, 1, X, info)])
    np.testing.assert_allclose(res.covariances[1], np.linalg.inv(info), atol=1e-12)
    np.testing.assert_array_equal(res.covariances[0], np.zeros((6, 6)))
    # Two independent measurements of the same edge add their information.
    info2 = np.diag(np.arange(1.0, 7.0))
    res2 = optimize_pose_graph(X, [_edge(0, 1, X, info), _edge(0, 1, X, info2)])
    np.testing.assert_allclose(res2.covariances[1], np.linalg.inv(info + info2), atol=1e-12)


def test_marginal_covariances_match_monte_carlo_errors() -> None:
    """A 4-node loop with noisy edges: each free node's normalised error has mean 6."""
    rng = np.random.default_rng(3)
    truth = np.stack([np.eye(4)] + [se3.exp(rng.normal(0, 0.3, 6)) for _ in range(3)])
    pairs = [(0, 1), (1, 2), (2, 3), (3, 0), (0, 2)]
    sig = np.array([0.01, 0.01, 0.01, 0.002, 0.002, 0.002])  # rad, m
    info = np.diag(1 / sig**2)
    nees = []
    for _ in range(200):
        edges = [_edge(i, j, truth, info, rng.normal(0, sig)) for i, j in pairs]
        res = optimize_pose_graph(truth, edges)
        errs = {n: se3.log(res.poses[n] @ se3.invert(truth[n])) for n in (1, 2, 3)}
        nees.append([e @ np.linalg.solve(res.covariances[n], e) for n, e in errs.items()])
    # Each column ~ χ²(6): mean 6, std of the mean of 200 = 0.24. Measured 6.27, 6.11, 6.02.
    means = np.mean(nees, axis=0)
    assert np.all((5.2 < means) & (means < 6.8)), means


def test_bad_input(rng: np.random.Generator) -> None:
    X = np.stack([np.eye(4), se3.exp(rng.normal(size=6)), se3.exp(rng.normal(size=6))])
    e01 = _edge(0, 1, X, np.eye(6))
    with pytest.raises(InputError, match="fixed"):
        optimize_pose_graph(X, [e01], fixed=())
    with pytest.raises(InputError, match="distinct nodes"):
        optimize_pose_graph(X, [PoseGraphEdge(0, 5, X[1], np.eye(6))])
    with pytest.raises(InputError, match="information"):
        optimize_pose_graph(X, [PoseGraphEdge(0, 1, X[1], np.full((6, 6), np.nan))])
    with pytest.raises(InputError, match="node 1"):
        optimize_pose_graph(np.stack([np.eye(4), 2 * np.eye(4)]), [])
    for bad in ((1e-6, 1e-6, 1e-6), 0.0, (1e-6, -1.0), "tight", None):
        with pytest.raises(InputError, match="tolerance"):
            optimize_pose_graph(X, [e01], tolerance=bad)
    with pytest.raises(InputError, match="measurement"):
        optimize_pose_graph(X, [PoseGraphEdge(0, 1, np.diag([1, 1, -1, 1.0]), np.eye(6))])
    # Node 2 has no edge: its pose is not determined.
    with pytest.raises(DegenerateGeometryError, match="unconstrained"):
        optimize_pose_graph(X, [e01])


def test_a_tolerance_per_part_stops_a_graph_in_other_units_alike(rng: np.random.Generator) -> None:
    """The same noisy graph in metres and in millimetres: with a (rotation, translation)
    tolerance whose translation follows the unit, both stop after the same iterations at the
    same poses (× 1000); one scalar tolerance lets the graph in millimetres run longer."""
    truth = np.stack([np.eye(4)] + [se3.exp(rng.normal(0, 0.3, 6)) for _ in range(3)])
    noise = [rng.normal(0, 0.01, 6) for _ in range(6)]
    pairs = [(i, j) for i in range(4) for j in range(i + 1, 4)]
    start = np.stack([truth[0]] + [se3.exp(rng.normal(0, 0.05, 6)) @ T for T in truth[1:]])

    def in_mm(T: np.ndarray) -> np.ndarray:
        T = T.copy()
        T[..., :3, 3] *= 1000.0
        return T

    info = np.diag([1.0, 1.0, 1.0, 1e-6, 1e-6, 1e-6])  # the same weights per mm²
    m_edges = [_edge(i, j, truth, np.eye(6), n) for (i, j), n in zip(pairs, noise, strict=True)]
    mm_edges = [PoseGraphEdge(e.i, e.j, in_mm(e.T_j_i), info) for e in m_edges]
    m = optimize_pose_graph(start, m_edges, tolerance=(1e-9, 1e-9))
    mm = optimize_pose_graph(in_mm(start), mm_edges, tolerance=(1e-9, 1e-6))
    assert m.converged and mm.converged and m.iterations == mm.iterations
    np.testing.assert_allclose(mm.poses, in_mm(m.poses), atol=1e-9)
    assert optimize_pose_graph(in_mm(start), mm_edges, tolerance=1e-9).iterations > m.iterations
