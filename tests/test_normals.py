"""Normals against Open3D and closed-form surfaces."""

from __future__ import annotations

import numpy as np
import pytest

from spacepose.core.cloud import PointCloud
from spacepose.core.config import validate_config
from spacepose.core.neighbors import hybrid, knn
from spacepose.core.normals import (
    NormalsConfig,
    estimate_normals,
    normals_from_covariances,
    plane_offsets,
)
from spacepose.errors import ConfigError, DegenerateGeometryError, InputError


def _noisy_sphere(n: int, seed: int, sigma: float = 0.002) -> np.ndarray:
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    return 0.5 * d + rng.normal(0, sigma, (n, 3))


@pytest.mark.peers
@pytest.mark.parametrize("radius", [None, 0.08])
def test_normals_match_open3d(radius):
    o3d = pytest.importorskip("open3d")
    pts = _noisy_sphere(1500, seed=1) + np.array([0.3, -0.2, 2.0])
    cloud = estimate_normals(PointCloud(pts), NormalsConfig(k=15, radius=radius), workers=1)
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    param = (
        o3d.geometry.KDTreeSearchParamKNN(15)
        if radius is None
        else o3d.geometry.KDTreeSearchParamHybrid(radius, 15)
    )
    pcd.estimate_normals(param, fast_normal_computation=False)
    ref = np.asarray(pcd.normals)
    # Points with < 3 neighbours in the radius have no plane; the two libraries fall back
    # differently (Open3D: an axis; here: the line of sight), so they are compared elsewhere.
    ok = np.ones(len(pts), dtype=bool)
    if radius is not None:
        ok = (hybrid(pts, pts, radius, 15)[0] >= 0).sum(axis=1) >= 3
        assert ok.sum() > 1490
    sign = np.sign(np.einsum("ij,ij->i", cloud.normals, ref))
    assert np.max(np.abs(cloud.normals - sign[:, None] * ref)[ok]) < 1e-6


def test_plane_and_sphere_closed_form():
    rng = np.random.default_rng(2)
    plane = np.column_stack([rng.uniform(-1, 1, (500, 2)), np.full(500, 3.0)])
    n = estimate_normals(PointCloud(plane), NormalsConfig(k=10)).normals
    # Sensor at the origin looks along +z: the normals of the plane z = 3 point back at it.
    np.testing.assert_allclose(n, np.tile([0.0, 0.0, -1.0], (500, 1)), atol=1e-12)

    sphere = _noisy_sphere(20000, seed=4, sigma=0.0)
    n = estimate_normals(PointCloud(sphere), NormalsConfig(k=12), viewpoint=(0, 0, 10)).normals
    radial = sphere / np.linalg.norm(sphere, axis=1, keepdims=True)
    facing = sphere[:, 2] > 0.1  # the side that sees the viewpoint gets outward normals
    cos = np.einsum("ij,ij->i", n, radial)
    assert np.min(cos[facing]) > 0.999
    # Every normal has a non-negative component towards the viewpoint.
    assert np.all(np.einsum("ij,ij->i", n, (0, 0, 10) - sphere) >= 0)


def test_isolated_point_gets_line_of_sight():
    pts = np.array([[0, 0, 2.0], [0.01, 0, 2.0], [0, 0.01, 2.0], [0.01, 0.01, 2.0], [5, 5, 5.0]])
    n = estimate_normals(PointCloud(pts), NormalsConfig(k=4, radius=0.1)).normals
    np.testing.assert_allclose(n[4], -np.array([5, 5, 5.0]) / np.sqrt(75), atol=1e-12)
    np.testing.assert_allclose(n[:4], np.tile([0, 0, -1.0], (4, 1)), atol=1e-12)


def test_bad_input_raises():
    with pytest.raises(InputError, match="at least 3"):
        estimate_normals(PointCloud(np.zeros((2, 3))))
    with pytest.raises(ConfigError, match="k"):
        validate_config(NormalsConfig, {"k": 2})
    with pytest.raises(ConfigError, match="radius"):
        validate_config(NormalsConfig, {"radius": -1.0})
    # A cloud on one line, or at one place, has no surface: its normals were an arbitrary
    # axis ([1, 0, 0] and [0, -1, 0] here), returned without a word.
    line = np.c_[np.linspace(0, 1, 100), np.zeros(100), np.ones(100)]
    for cloud in (line, np.tile([[0.1, 0.2, 1.0]], (100, 1))):
        with pytest.raises(DegenerateGeometryError, match="all 100 points lie on a line"):
            estimate_normals(cloud)
    # A thin strip (1 mm across 1 m) is a surface still.
    strip = (
        line + np.c_[np.zeros(100), np.random.default_rng(0).uniform(0, 1e-3, 100), np.zeros(100)]
    )
    assert np.all(np.isfinite(estimate_normals(strip).normals))


def _spectra_stack(rng: np.random.Generator) -> np.ndarray:
    """Random rotations of hard spectra: distinct, plane (0, 1, 1), line (0, 0, 1), near-double
    smallest pair, triple, rank 0, at scales 1e-8..1e3 and 1e6 m from the origin's scale."""
    spectra = [
        lambda: np.sort(rng.uniform(0, 1, 3)),
        lambda: np.array([0.0, 1.0, 1.0]),
        lambda: np.array([0.0, 0.0, 1.0]),
        lambda: np.array([1e-9, 1e-9 + 1e-15, 1.0]),
        lambda: np.array([1e-6, 0.3, 0.3 + 1e-12]),
        lambda: np.full(3, 2.0),
        lambda: np.zeros(3),
    ]
    out = []
    for m in range(1400):
        Q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        lam = spectra[m % len(spectra)]() * 10 ** rng.uniform(-8, 3)
        A = (Q * lam) @ Q.T
        out.append(0.5 * (A + A.T))
    return np.array(out)


def test_closed_form_eigen_matches_eigh_on_hard_spectra():
    A = _spectra_stack(np.random.default_rng(8))
    normals, ev = normals_from_covariances(A)
    ref_ev, ref_vec = np.linalg.eigh(A)
    scale = np.maximum(np.abs(ref_ev).max(axis=1), 1e-300)
    # Eigenvalues to rounding relative to ‖A‖, as eigh (measured 1.6e-15).
    assert np.max(np.abs(ev - ref_ev) / scale[:, None]) < 1e-13
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-14)
    # The normal is an eigenvector of λ0 even where the eigenspace is a plane (measured 7e-16).
    residual = np.einsum("mij,mj->mi", A, normals) - ev[:, :1] * normals
    assert np.max(np.linalg.norm(residual, axis=1) / scale) < 1e-13
    # Where λ0 is isolated (gap > 1e-6 ‖A‖) it is eigh's vector up to sign (measured 9e-16).
    isolated = (ref_ev[:, 1] - ref_ev[:, 0]) > 1e-6 * scale
    assert isolated.sum() > 500
    cos = np.abs(np.einsum("mi,mi->m", normals, ref_vec[:, :, 0]))[isolated]
    np.testing.assert_allclose(cos, 1.0, atol=1e-9)
    # Multiples of the identity (zero included) get the x axis, as from eigh.
    iso, _ = normals_from_covariances(np.array([np.zeros((3, 3)), 2.0 * np.eye(3)]))
    np.testing.assert_array_equal(iso, [[1.0, 0.0, 0.0], [1.0, 0.0, 0.0]])


def test_prebuilt_tree_gives_the_same_normals_and_is_checked() -> None:
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(11)
    pts = rng.normal(size=(400, 3)) * np.array([0.2, 0.1, 0.01]) + np.array([0.0, 0.0, 1.0])
    cloud = PointCloud(pts)
    own = estimate_normals(cloud, NormalsConfig(k=12))
    reused = estimate_normals(cloud, NormalsConfig(k=12), tree=cKDTree(pts))
    np.testing.assert_array_equal(reused.normals, own.normals)
    with pytest.raises(InputError, match="tree holds 10 points"):
        estimate_normals(cloud, NormalsConfig(k=12), tree=cKDTree(pts[:10]))


def _stress_stack(rng: np.random.Generator, m: int) -> np.ndarray:
    """m random symmetric PSD matrices, one kind in six: distinct spectra, multiples of the
    identity (zero included), rank 1, rank 2, a huge isotropic offset (1 + 1e-9 spreads) and a
    double smallest eigenvalue; random rotations, scales 1e-8..1e3."""
    from scipy.spatial.transform import Rotation

    lam = np.sort(rng.uniform(0.0, 1.0, (m, 3)), axis=1)
    kind = np.arange(m) % 6
    lam[kind == 2, :2] = 0.0
    lam[kind == 3, 0] = 0.0
    lam[kind == 4] = 1.0 + 1e-9 * lam[kind == 4]
    lam[kind == 5, 0] = lam[kind == 5, 1]
    lam *= 10 ** rng.uniform(-8, 3, (m, 1))
    Q = Rotation.random(m, random_state=rng).as_matrix()
    A = np.einsum("mij,mj,mkj->mik", Q, lam, Q)
    A = 0.5 * (A + np.swapaxes(A, 1, 2))
    # Multiples c·I exactly, not rotated, with short mantissas so that trace / 3 == c (an
    # inexact trace / 3 leaves ~1-ulp diagonal differences, which pick some other unit vector).
    iso = np.flatnonzero(kind == 1)
    c = rng.integers(0, 2**20, len(iso)) * 2.0 ** rng.integers(-60, 0, len(iso))
    c[::50] = 0.0
    A[iso] = c[:, None, None] * np.eye(3)
    return A


def test_closed_form_eigen_stress_one_million_against_eigh():
    A = _stress_stack(np.random.default_rng(21), 1_000_000)
    normals, ev = normals_from_covariances(A, workers=2)
    ref_ev, ref_vec = np.linalg.eigh(A)
    scale = np.maximum(np.abs(ref_ev).max(axis=1), 1e-300)
    assert np.all(np.diff(ev, axis=1) >= 0)
    assert np.max(np.abs(ev - ref_ev) / scale[:, None]) < 1e-13
    np.testing.assert_allclose(np.linalg.norm(normals, axis=1), 1.0, atol=1e-14)
    residual = np.einsum("mij,mj->mi", A, normals) - ev[:, :1] * normals
    assert np.max(np.linalg.norm(residual, axis=1) / scale) < 1e-13
    isolated = (ref_ev[:, 1] - ref_ev[:, 0]) > 1e-6 * scale
    assert isolated.sum() > 330_000  # distinct spectra and rank 2: two kinds in six
    cos = np.abs(np.einsum("mi,mi->m", normals, ref_vec[:, :, 0]))[isolated]
    assert np.min(cos) > 1.0 - 1e-9
    # Multiples of the identity get the x axis exactly.
    identity = np.arange(len(A)) % 6 == 1
    np.testing.assert_array_equal(normals[identity], np.tile([1.0, 0.0, 0.0], (identity.sum(), 1)))


def test_closed_form_eigen_same_on_any_thread_count_and_checks_shape():
    A = _stress_stack(np.random.default_rng(22), 5000)
    one = normals_from_covariances(A, workers=1)
    for workers in (2, -1):
        for a, b in zip(one, normals_from_covariances(A, workers=workers), strict=True):
            np.testing.assert_array_equal(a, b)
    with pytest.raises(InputError, match=r"\(M, 3, 3\)"):
        normals_from_covariances(np.zeros((4, 3)))
    with pytest.raises(InputError, match="workers must be"):
        normals_from_covariances(A, workers=0)


def test_neighbourhood_normals_equal_the_two_step_route():
    # One compiled pass must give the bits of local_covariances -> normals_from_covariances,
    # padding and sparse rows included, on any thread count.
    from spacepose.core.neighbors import local_covariances
    from spacepose.core.normals import neighbourhood_normals

    pts = _noisy_sphere(3000, seed=12) + np.array([0.1, 0.2, 1.5])
    idx, _ = hybrid(pts, pts, 0.03, 12)
    assert (idx < 0).any() and ((idx >= 0).sum(axis=1) < 3).any()
    two_step, _ = normals_from_covariances(local_covariances(pts, idx))
    for workers in (1, 2):
        np.testing.assert_array_equal(neighbourhood_normals(pts, idx, workers), two_step)
    with pytest.raises(InputError, match="beyond"):
        neighbourhood_normals(pts, np.array([[0, len(pts)]]))
    with pytest.raises(InputError, match="integer"):
        neighbourhood_normals(pts, np.zeros((2, 3)))


def test_estimate_normals_takes_an_n_by_3_array() -> None:
    pts = _noisy_sphere(800, seed=21)
    from_array = estimate_normals(pts, NormalsConfig(k=20))
    from_cloud = estimate_normals(PointCloud(pts), NormalsConfig(k=20))
    np.testing.assert_array_equal(from_array.normals, from_cloud.normals)
    np.testing.assert_array_equal(from_array.points, pts)
    # A sphere about the viewpoint: every normal points back to the centre, -p / |p|.
    radial = -pts / np.linalg.norm(pts, axis=1, keepdims=True)
    assert np.median(np.einsum("ij,ij->i", from_array.normals, radial)) > 0.99
    with pytest.raises(InputError, match=r"^cloud: points must have shape \(N, 3\)"):
        estimate_normals(pts[:, :2])


def test_plane_offsets_match_the_neighbourhood_mean_and_flag_missing_neighbours():
    """Each point's signed distance from the plane through its k neighbours' centroid, as
    numpy computes it from the gathered neighbours; NaN where the bounded search came short."""
    rng = np.random.default_rng(11)
    xy = rng.uniform(0.0, 0.3, size=(4000, 2))
    pts = np.c_[xy, 0.5 * xy[:, 0] ** 2 + rng.normal(0.0, 1e-3, 4000)]
    pts[:5] += 1.0  # isolated: fewer than k neighbours within the bound
    n = rng.normal(size=(4000, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    _, idx = knn(pts, None, 12, 1, distance_upper_bound=0.05)
    off = plane_offsets(pts, n, idx, workers=2)
    local = idx[:, -1] < len(pts)
    assert not local[:5].any() and np.isnan(off[:5]).all() and np.isfinite(off[local]).all()
    expected = np.einsum("ij,ij->i", pts[local] - pts[idx[local]].mean(axis=1), n[local])
    np.testing.assert_allclose(off[local], expected, rtol=0, atol=1e-15)
    # Mismatched shapes or indices out of range: the package's error, not numba's.
    with pytest.raises(InputError, match="normals for"):
        plane_offsets(pts, n[:10], idx)
    with pytest.raises(InputError, match=r"0\.\.4000"):
        plane_offsets(pts, n, idx - 1)
    with pytest.raises(InputError, match="integer array"):
        plane_offsets(pts, n, idx[:, 0])
