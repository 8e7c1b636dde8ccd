"""ICP: Open3D equivalence, convergence, covariance consistency and bad input."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from spacepose.core import se3
from spacepose.core.cloud import PointCloud
from spacepose.core.config import validate_config
from spacepose.core.correspondences import (
    CorrespondenceSearch,
    FusedPlaneMatcher,
    find_correspondences,
)
from spacepose.core.grid import VoxelIndex
from spacepose.core.icp import ICPConfig, icp
from spacepose.core.icp_systems import point_to_plane_system, point_to_point_information
from spacepose.core.normals import NormalsConfig, estimate_normals
from spacepose.core.sim.targets import Target, sample_surface
from spacepose.errors import ConfigError, DegenerateGeometryError, InputError, RegistrationError

PLANE = ICPConfig(
    max_correspondence_distance=0.1,
    method="point_to_plane",
    max_iterations=50,
    relative_fitness=1e-9,
    relative_rmse=1e-9,
)


def asymmetric_target() -> Target:
    """A 0.8 m box with an off-centre cylinder and sphere: no symmetry, so the pose is unique."""
    box = trimesh.creation.box((0.8, 0.5, 0.3))
    cylinder = trimesh.creation.cylinder(0.1, 0.4)
    cylinder.apply_translation((0.3, 0.1, 0.3))
    sphere = trimesh.creation.icosphere(2, 0.12)
    sphere.apply_translation((-0.35, -0.2, 0.2))
    parts = [box, cylinder, sphere]
    return Target("asymmetric", trimesh.util.concatenate(parts), (), tuple(parts))


def perturbation(rng: np.random.Generator, deg: float = 5.0, metres: float = 0.05) -> np.ndarray:
    """A rigid transform rotating by ``deg`` about a random axis and moving ``metres``."""
    axis, direction = rng.normal(size=(2, 3))
    R = Rotation.from_rotvec(np.deg2rad(deg) * axis / np.linalg.norm(axis))
    return se3.make_transform(R, metres * direction / np.linalg.norm(direction))


def pose_error(T_est: np.ndarray, T_true: np.ndarray) -> tuple[float, float]:
    """Rotation error (deg) and translation error (m) of ``T_est · T_true⁻¹``."""
    dT = T_est @ se3.invert(T_true)
    return float(np.rad2deg(Rotation.from_matrix(dT[:3, :3]).magnitude())), float(
        np.linalg.norm(dT[:3, 3])
    )


@pytest.fixture(scope="module")
def shape() -> Target:
    return asymmetric_target()


@pytest.fixture(scope="module")
def dense_target(shape: Target) -> PointCloud:
    """Noise-free dense target with the true face normals."""
    return sample_surface(shape, 20000, seed=1)


def make_noisy_pair(
    shape: Target, seed: int, n_target: int, n_source: int, sample_seeds: tuple[int, int]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Noisy source and target (σ = 2 mm, different samples) and the true T_target_source."""
    rng = np.random.default_rng(seed)
    tgt = sample_surface(shape, n_target, seed=sample_seeds[0]).points
    src = sample_surface(shape, n_source, seed=sample_seeds[1]).points
    tgt = tgt + rng.normal(0, 0.002, tgt.shape)
    src = src + rng.normal(0, 0.002, src.shape)
    T_true = perturbation(rng)
    return se3.transform_points(se3.invert(T_true), src), tgt, T_true


@pytest.fixture(scope="module")
def noisy_pair(shape: Target) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    return make_noisy_pair(shape, 7, 4000, 3000, (2, 3))


@pytest.mark.peers
@pytest.mark.parametrize("max_iterations", [3, 30])
def test_point_to_point_equals_open3d(noisy_pair, max_iterations: int) -> None:
    o3d = pytest.importorskip("open3d")
    reg = o3d.pipelines.registration
    src, tgt, T_true = noisy_pair
    # A start 1° / 1 cm from the truth exercises the non-identity init path.
    init = perturbation(np.random.default_rng(3), 1.0, 0.01) @ T_true
    cfg = ICPConfig(max_correspondence_distance=0.08, max_iterations=max_iterations)
    ours = icp(src, tgt, init, cfg, workers=1)
    pc_src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(src.copy()))
    pc_tgt = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(tgt.copy()))
    theirs = reg.registration_icp(
        pc_src,
        pc_tgt,
        0.08,
        init,
        reg.TransformationEstimationPointToPoint(),
        reg.ICPConvergenceCriteria(1e-6, 1e-6, max_iterations),
    )
    # Measured: entries within 4e-15 (12 iterations when converged), fitness identical, RMSE
    # within 2e-17.
    np.testing.assert_allclose(ours.T_target_source, theirs.transformation, rtol=0, atol=1e-6)
    assert abs(ours.fitness - theirs.fitness) < 1e-6
    assert abs(ours.inlier_rmse - theirs.inlier_rmse) < 1e-6
    assert ours.n_correspondences == len(theirs.correspondence_set)
    assert ours.iterations <= max_iterations
    # Open3D's information uses J = [−skew(q) I] at the matched *target* points, ours at the
    # moved source points; they differ by the residuals only (measured relative difference
    # 1.4e-3 after 3 iterations, 1.1e-4 after convergence).
    o3d_info = reg.get_information_matrix_from_point_clouds(
        pc_src, pc_tgt, 0.08, ours.T_target_source
    )
    rel = np.linalg.norm(ours.information - o3d_info) / np.linalg.norm(o3d_info)
    assert rel < 1e-2, rel


def test_point_to_plane_noise_free_converges(shape: Target, dense_target: PointCloud) -> None:
    tree = cKDTree(dense_target.points)
    for trial in range(5):
        rng = np.random.default_rng(100 + trial)
        T_true = perturbation(rng)
        src = se3.transform_points(se3.invert(T_true), sample_surface(shape, 1500, trial).points)
        res = icp(src, dense_target, config=PLANE, workers=1, target_tree=tree)
        rot, trans = pose_error(res.T_target_source, T_true)
        # Measured: worst of 30 trials 0.020° / 0.09 mm (facet edges, distinct samples).
        assert rot < 0.05 and trans < 0.5e-3, (trial, rot, trans)
        assert res.converged


@pytest.mark.parametrize("kernel", ["none", "geman_mcclure"])
def test_point_to_plane_error_matches_information(
    shape: Target, dense_target: PointCloud, kernel: str
) -> None:
    """Normalised squared error over 30 seeded trials ~ χ²(6): the covariance is honest.

    Without a kernel the information is scaled by the true σ; with one, the result's own
    covariance (weighted information, σ estimated from the residuals) is used."""
    sigma = 0.003
    tree = cKDTree(dense_target.points)
    cfg = PLANE.model_copy(update={"robust_kernel": kernel})
    nees = []
    for trial in range(30):
        rng = np.random.default_rng(trial)
        src = sample_surface(shape, 1500, seed=1000 + trial).points
        src = src + rng.normal(0, sigma, src.shape)
        T_true = perturbation(rng)
        src = se3.transform_points(se3.invert(T_true), src)
        res = icp(src, dense_target, config=cfg, workers=1, target_tree=tree)
        e = se3.log(res.T_target_source @ se3.invert(T_true))
        if kernel == "none":
            nees.append(e @ res.information @ e / sigma**2)
        else:
            nees.append(e @ np.linalg.solve(res.covariance(), e))
    # χ²(6) has mean 6; the mean of 30 has std 0.63. Measured 6.37 (none) and 6.13
    # (Geman-McClure, Huber's M-estimator variance; holding the final weights fixed instead
    # gave 7.12).
    assert 4.5 < np.mean(nees) < 8.0, np.mean(nees)


def test_information_matches_numerical_jacobian(rng: np.random.Generator) -> None:
    p = rng.normal(size=(5, 3))
    n = rng.normal(size=(5, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    q = p + 0.01 * rng.normal(size=(5, 3))
    h = 1e-7
    J_plane = np.empty((5, 6))
    J_point = np.empty((5, 3, 6))
    for a in range(6):
        d = np.zeros(6)
        d[a] = h
        moved = [se3.transform_points(se3.exp(s * d), p) for s in (1, -1)]
        J_point[:, :, a] = (moved[0] - moved[1]) / (2 * h)
        r = [np.einsum("ni,ni->n", m - q, n) for m in moved]
        J_plane[:, a] = (r[0] - r[1]) / (2 * h)
    r0 = np.einsum("ni,ni->n", p - q, n)
    H, g, sse = point_to_plane_system(p, q, n)
    np.testing.assert_allclose(H, J_plane.T @ J_plane, atol=1e-6)
    np.testing.assert_allclose(g, J_plane.T @ r0, atol=1e-8)
    assert sse == pytest.approx(r0 @ r0, rel=1e-12)
    np.testing.assert_allclose(
        point_to_point_information(p), np.einsum("nai,naj->ij", J_point, J_point), atol=1e-6
    )


def test_estimates_missing_normals_and_reuses_tree(shape: Target, dense_target: PointCloud) -> None:
    rng = np.random.default_rng(5)
    T_true = perturbation(rng)
    src = se3.transform_points(se3.invert(T_true), sample_surface(shape, 1500, 5).points)
    bare = dense_target.points  # no normals: icp estimates them
    res = icp(src, bare, config=PLANE, workers=1)
    rot, trans = pose_error(res.T_target_source, T_true)
    assert rot < 0.05 and trans < 0.5e-3, (rot, trans)
    again = icp(src, bare, config=PLANE, workers=1, target_tree=VoxelIndex(bare))
    np.testing.assert_array_equal(again.T_target_source, res.T_target_source)
    # A cKDTree takes the generic (numpy) path: the same matches, sums in another order.
    generic = icp(src, bare, config=PLANE, workers=1, target_tree=cKDTree(bare))
    np.testing.assert_allclose(generic.T_target_source, res.T_target_source, atol=1e-12)
    np.testing.assert_allclose(generic.information, res.information, rtol=1e-10)
    assert (generic.fitness, generic.iterations) == (res.fitness, res.iterations)


@pytest.mark.parametrize("kernel", ["none", "geman_mcclure"])
@pytest.mark.parametrize("method", ["point_to_point", "point_to_plane"])
def test_same_result_for_any_workers(noisy_pair, method: str, kernel: str) -> None:
    src, tgt, _ = noisy_pair
    cfg = ICPConfig(max_correspondence_distance=0.1, method=method, robust_kernel=kernel)
    one = icp(src, tgt, config=cfg, workers=1)
    two = icp(src, tgt, config=cfg, workers=2)
    np.testing.assert_array_equal(one.T_target_source, two.T_target_source)
    np.testing.assert_array_equal(one.information, two.information)
    assert one.fitness == two.fitness and one.inlier_rmse == two.inlier_rmse


def test_bad_input(noisy_pair) -> None:
    src, tgt, _ = noisy_pair
    with pytest.raises(InputError, match="at least 3 points"):
        icp(src[:2], tgt)
    with pytest.raises(RegistrationError, match="correspondences"):
        icp(src + 10.0, tgt)
    nan_init = np.eye(4)
    nan_init[0, 3] = np.nan
    with pytest.raises(InputError, match="init_T_target_source"):
        icp(src, tgt, nan_init)
    with pytest.raises(InputError, match="init_T_target_source"):
        icp(src, tgt, np.diag([2.0, 2.0, 2.0, 1.0]))
    with pytest.raises(InputError, match="target_tree"):
        icp(src, tgt, target_tree=cKDTree(tgt[:100]))
    with pytest.raises(ConfigError, match="max_correspondence_distance"):
        validate_config(ICPConfig, {"max_correspondence_distance": -1.0})


def test_single_plane_is_degenerate_for_point_to_plane(rng: np.random.Generator) -> None:
    plane = np.column_stack([rng.uniform(-1, 1, (500, 2)), np.zeros(500)])
    target = PointCloud(plane, np.tile([0.0, 0.0, 1.0], (500, 1)))
    with pytest.raises(DegenerateGeometryError, match="degrees of freedom"):
        icp(plane + np.array([0.0, 0.0, 0.01]), target, config=ICPConfig(method="point_to_plane"))


def test_correspondence_search_equals_tree_search(noisy_pair) -> None:
    # Steps shrinking from 5 cm / 5° (most points searched again) to micrometres (most
    # certified), with a gate that leaves points unmatched, then a jump back: every call must give
    # the plain tree search's answer.
    src, tgt, T_true = noisy_pair
    tree = cKDTree(tgt)
    searched = []

    class CountingTree:  # the tree, recording how many points each call searches again
        data, n = tree.data, tree.n

        def query(self, x, **kwargs):
            searched.append(len(x))
            return tree.query(x, **kwargs)

    search = CorrespondenceSearch(CountingTree(), 0.02, workers=1)
    # Poses closing in on the truth (errors 3 cm .. 3 µm), from and back to the identity.
    closing = [
        se3.exp(np.random.default_rng(k).normal(0, 10.0 ** -(k / 2 + 1.5), 6)) @ T_true
        for k in range(10)
    ]
    counts = []
    for T in [np.eye(4), *closing, np.eye(4)]:
        moved = se3.transform_points(T, src)
        s, t, d2 = search(moved)
        s_ref, t_ref, d2_ref = find_correspondences(tree, moved, 0.02, workers=1)
        np.testing.assert_array_equal(s, s_ref)
        np.testing.assert_array_equal(t, t_ref)
        np.testing.assert_allclose(d2, d2_ref, rtol=1e-12, atol=1e-30)
        counts.append(len(s))
    # Both regimes occur: few matches early (gate 2 cm, offsets up to 5 cm), nearly all later;
    # the first call searches every point, the micrometre steps almost none.
    assert min(counts) < 0.5 * len(src) and max(counts) > 0.85 * len(src)  # measured 0.42, 0.91
    assert searched[0] == len(src) and min(searched) < 0.05 * len(src), searched  # min 1 point


@pytest.mark.parametrize(
    ("gate", "clutter"), [(0.004, 0), (0.02, 0), (0.06, 0), (0.1, 0), (0.1, 300)]
)
def test_fused_plane_matcher_equals_tree_search(noisy_pair, gate: float, clutter: int) -> None:
    # The compiled point-to-plane pass skips a point's search while its certificate holds:
    # along poses closing in on the truth (and a jump back) its matches and sums must be the
    # tree's, with the gate within two of the index's 4 cm cells (own cell, then the box) or
    # beyond (rings).
    # Clutter: source points 25 cm off the surface, unmatched, certified by a ring search.
    src, tgt, T_true = noisy_pair
    rng = np.random.default_rng(5)
    away = rng.normal(size=(clutter, 3))
    away *= 0.25 / np.linalg.norm(away, axis=1, keepdims=True)
    src = np.concatenate([src, src[rng.choice(len(src), clutter)] + away])
    tree, index = cKDTree(tgt), VoxelIndex(tgt)
    normals = estimate_normals(PointCloud(tgt), NormalsConfig(k=15), workers=1).normals
    matcher = FusedPlaneMatcher(index, normals, src, gate, ICPConfig(), workers=2)
    closing = [
        se3.exp(np.random.default_rng(k).normal(0, 10.0 ** -(k / 2 + 1.5), 6)) @ T_true
        for k in range(10)
    ]
    kept = []
    for T in [np.eye(4), *closing, np.eye(4)]:
        anchors = matcher.anchors.copy()
        moved = se3.transform_points(T, src)
        s_ref, t_ref, _ = find_correspondences(tree, moved, gate, workers=1)
        if len(s_ref) < 3:
            with pytest.raises(RegistrationError):
                matcher(T)
            continue
        matches = matcher(T)
        np.testing.assert_array_equal(matches.src_idx, s_ref)
        np.testing.assert_array_equal(matches.tgt_idx, t_ref)
        H, g, sse = point_to_plane_system(moved[s_ref], tgt[t_ref], normals[t_ref])
        np.testing.assert_allclose(matches.system[0], H, rtol=1e-10)
        np.testing.assert_allclose(matches.system[1], g, rtol=1e-8, atol=1e-12 * np.abs(g).max())
        assert matches.system[2] == pytest.approx(sse, rel=1e-10)
        kept.append(float(np.mean((matcher.anchors == anchors).all(axis=1))))
    # Micrometre steps: nearly every point keeps its last search's certificate (measured
    # 0.9996, 0.9993, 0.9996; 0.9997 with clutter); the first and the jump back search every
    # point again but clutter far enough from every target to stay unmatched (measured 38).
    assert max(kept) > 0.99 and kept[0] == 0.0 and kept[-1] <= clutter / len(src), kept


def test_a_ring_search_certifies_its_answers(noisy_pair) -> None:
    # Without hints and with a gate over two cells, a pass searches ring by ring; its answers
    # carry certificates, so a nanometre step later searches (almost) no point again. (Before,
    # a nearest found ring by ring had none: every matched point was searched twice.)
    src, tgt, T_true = noisy_pair
    index = VoxelIndex(tgt)
    normals = estimate_normals(PointCloud(tgt), NormalsConfig(k=15), workers=1).normals
    gate = 2.5 * index.cell_size
    matcher = FusedPlaneMatcher(index, normals, src, gate, ICPConfig(), workers=1)
    first = matcher(T_true)
    anchors = matcher.anchors.copy()
    step = se3.exp(np.full(6, 1e-9)) @ T_true
    matches = matcher(step)
    moved = se3.transform_points(step, src)
    s_ref, t_ref, _ = find_correspondences(cKDTree(tgt), moved, gate, workers=1)
    np.testing.assert_array_equal(matches.src_idx, s_ref)
    np.testing.assert_array_equal(matches.tgt_idx, t_ref)
    # A searched point's anchor moves with it; a certified one keeps the first pass's.
    kept = float(np.mean((matcher.anchors == anchors).all(axis=1)))
    assert first.fitness > 0.9 and kept > 0.99, (first.fitness, kept)


def test_correspondence_search_single_target_and_new_size() -> None:
    # One target point: no second neighbour exists, so the bound is twice the gate.
    tree = cKDTree(np.zeros((1, 3)))
    search = CorrespondenceSearch(tree, 1.0, workers=1)
    pts = np.array([[0.5, 0, 0], [1.5, 0, 0], [0.0, 0.9, 0.0]])
    for shift in (0.0, 0.3, 0.45, -0.5):
        moved = pts + np.array([shift, 0.0, 0.0])
        s, t, d2 = search(moved)
        expect = np.flatnonzero(np.linalg.norm(moved, axis=1) < 1.0)
        np.testing.assert_array_equal(s, expect)
        np.testing.assert_array_equal(t, 0)
        np.testing.assert_allclose(d2, (moved[expect] ** 2).sum(axis=1), rtol=1e-15)
    # A different number of query points starts afresh.
    s, _, _ = search(np.array([[0.1, 0.0, 0.0]]))
    np.testing.assert_array_equal(s, [0])


def test_point_to_plane_system_sums_in_fixed_chunks(rng: np.random.Generator) -> None:
    # 5000 rows span ten chunks: the same bits on one and two threads, and the sums of
    # numpy's rows to rounding.
    p = rng.normal(size=(5000, 3))
    n = rng.normal(size=(5000, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    q = p + 0.01 * rng.normal(size=(5000, 3))
    one, two = point_to_plane_system(p, q, n, workers=1), point_to_plane_system(p, q, n, workers=2)
    for a, b in zip(one, two, strict=True):
        np.testing.assert_array_equal(a, b)
    rows = np.concatenate([np.cross(p, n), n], axis=1)
    r = np.einsum("ni,ni->n", p - q, n)
    np.testing.assert_allclose(one[0], rows.T @ rows, rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(one[1], rows.T @ r, rtol=1e-10, atol=1e-12)
    # Rows that do not line up are refused before the kernel reads past an array.
    with pytest.raises(InputError, match="one row count"):
        point_to_plane_system(p, q[:-1], n)
    with pytest.raises(InputError, match="one row count"):
        point_to_plane_system(p[:, :2], q[:, :2], n[:, :2])


def ghost_pair(shape: Target, trial: int, share: float = 0.4) -> tuple[np.ndarray, np.ndarray]:
    """A noisy source (σ = 2 mm) of which ``share`` are gross outliers inside a 5 cm gate: a
    ghost copy of the surface shifted 3 cm along x (a second return, a neighbour's surface).
    Returns the source points and the true T_target_source."""
    rng = np.random.default_rng(trial)
    src = sample_surface(shape, 1500, seed=1000 + trial).points
    src = src + rng.normal(0, 0.002, src.shape)
    n_ghost = round(share / (1 - share) * len(src))
    ghost = sample_surface(shape, n_ghost, seed=2000 + trial).points + np.array([0.03, 0, 0])
    T_true = perturbation(rng, 2.0, 0.01)
    return se3.transform_points(se3.invert(T_true), np.vstack([src, ghost])), T_true


@pytest.mark.parametrize("share", [0.3, 0.5])
def test_robust_kernel_rejects_gross_outliers(
    shape: Target, dense_target: PointCloud, share: float
) -> None:
    # 30 % and 50 % of the source on a ghost surface 15σ off: plain point-to-plane ICP is pulled
    # along x by tens of σ of its own covariance, Geman-McClure with the adaptive scale lands
    # within a few σ. Measured over trials 0-2 and both shares: plain 7.8-15.3 mm (18-40σ in
    # tx), robust 0.10-0.26 mm (at most 3.1σ on any axis, residual σ 1.35-1.72 mm).
    cfg = PLANE.model_copy(update={"max_correspondence_distance": 0.05, "max_iterations": 60})
    tree = cKDTree(dense_target.points)
    for trial in range(3):
        src, T_true = ghost_pair(shape, trial, share)
        for kernel in ("none", "geman_mcclure"):
            res = icp(
                src,
                dense_target,
                config=cfg.model_copy(update={"robust_kernel": kernel}),
                workers=1,
                target_tree=tree,
            )
            e = se3.log(res.T_target_source @ se3.invert(T_true))
            z = np.abs(e) / np.sqrt(np.diag(res.covariance()))
            if kernel == "none":
                assert z[3] > 10 and np.linalg.norm(e[3:]) > 5e-3, (trial, z, e)
            else:
                assert z.max() < 4 and np.linalg.norm(e[3:]) < 1e-3, (trial, z, e)
                assert res.residual_sigma < 0.003


def test_huge_fixed_scale_is_least_squares(noisy_pair) -> None:
    # A kernel width far beyond every residual weighs every pair ~1: plain least squares.
    src, tgt, _ = noisy_pair
    for method in ("point_to_point", "point_to_plane"):
        plain = ICPConfig(max_correspondence_distance=0.1, method=method)
        wide = plain.model_copy(update={"robust_kernel": "cauchy", "robust_scale": 1e6})
        a, b = icp(src, tgt, config=plain, workers=1), icp(src, tgt, config=wide, workers=1)
        np.testing.assert_allclose(a.T_target_source, b.T_target_source, atol=1e-9)
        np.testing.assert_allclose(b.information, a.information, rtol=1e-8)
        assert a.iterations == b.iterations


def test_weighted_plane_system_matches_numpy(rng: np.random.Generator) -> None:
    p = rng.normal(size=(1200, 3))
    n = rng.normal(size=(1200, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    q = p + 0.01 * rng.normal(size=(1200, 3))
    w = rng.uniform(0, 1, 1200)
    H, g, sse = point_to_plane_system(p, q, n, weights=w)
    rows = np.concatenate([np.cross(p, n), n], axis=1)
    r = np.einsum("ni,ni->n", p - q, n)
    np.testing.assert_allclose(H, rows.T @ (w[:, None] * rows), rtol=1e-12, atol=1e-9)
    np.testing.assert_allclose(g, rows.T @ (w * r), rtol=1e-10, atol=1e-12)
    assert sse == pytest.approx(w @ r**2, rel=1e-12)
    # Unit weights give the unweighted sums to the bit.
    ones = point_to_plane_system(p, q, n, weights=np.ones(1200))
    for a, b in zip(ones, point_to_plane_system(p, q, n), strict=True):
        np.testing.assert_array_equal(a, b)
