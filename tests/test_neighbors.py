"""Neighbour searches against brute force and Open3D; covariances against numpy."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree
from scipy.spatial.distance import cdist

from spacepose.core.neighbors import as_tree, hybrid, knn, local_covariances, weighted_moments
from spacepose.errors import InputError


@pytest.fixture
def clouds() -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(3)
    return rng.uniform(-1, 1, (400, 3)), rng.uniform(-1, 1, (50, 3))


def test_knn_matches_brute_force(clouds):
    pts, q = clouds
    dist, idx = knn(pts, q, k=7, workers=1)
    d_all = cdist(q, pts)
    order = np.argsort(d_all, axis=1)[:, :7]
    np.testing.assert_array_equal(idx, order)
    np.testing.assert_allclose(dist, np.take_along_axis(d_all, order, axis=1), atol=1e-12)
    # k = 1 keeps the (M, 1) shape; a prebuilt tree gives the same answer.
    d1, i1 = knn(as_tree(pts), q, k=1, workers=2)
    assert i1.shape == (50, 1)
    np.testing.assert_array_equal(i1[:, 0], order[:, 0])
    np.testing.assert_allclose(d1[:, 0], dist[:, 0])
    # No queries: the searched points themselves, on either kind of index.
    d_self = cdist(pts, pts)
    self_order = np.argsort(d_self, axis=1, kind="stable")[:, :5]
    for index in (as_tree(pts), cKDTree(pts)):
        dist, idx = knn(index, None, k=5, workers=2)
        np.testing.assert_array_equal(idx, self_order)
        np.testing.assert_allclose(dist, np.take_along_axis(d_self, self_order, axis=1), atol=1e-12)
    # Within a bound: the neighbours beyond it missing (inf, N), on either kind of index.
    within = np.take_along_axis(d_self, self_order, axis=1) < 0.3
    assert 0.2 < within.mean() < 0.9
    for index in (as_tree(pts), cKDTree(pts)):
        dist, idx = knn(index, None, k=5, workers=2, distance_upper_bound=0.3)
        np.testing.assert_array_equal(idx, np.where(within, self_order, len(pts)))
        assert np.isinf(dist[~within]).all() and np.isfinite(dist[within]).all()


def test_hybrid_matches_brute_force(clouds):
    pts, q = clouds
    idx, dist = hybrid(pts, q, radius=0.35, max_nn=12, workers=2)
    d_all = cdist(q, pts)
    for m in range(len(q)):
        inside = np.flatnonzero(d_all[m] < 0.35)
        expect = inside[np.argsort(d_all[m, inside])][:12]
        got = idx[m][idx[m] >= 0]
        np.testing.assert_array_equal(got, expect)
        assert np.all(np.isinf(dist[m][idx[m] < 0]))
    # Some queries are capped at max_nn and some have fewer neighbours: both cases exercised.
    counts = (idx >= 0).sum(axis=1)
    assert counts.max() == 12 and counts.min() < 12


@pytest.mark.peers
def test_hybrid_matches_open3d(clouds):
    o3d = pytest.importorskip("open3d")
    pts, q = clouds
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(pts))
    tree = o3d.geometry.KDTreeFlann(pcd)
    idx, _ = hybrid(pts, q, radius=0.3, max_nn=9)
    for m in range(len(q)):
        _, o3d_idx, _ = tree.search_hybrid_vector_3d(q[m], 0.3, 9)
        np.testing.assert_array_equal(idx[m][idx[m] >= 0], np.asarray(o3d_idx))


def test_local_covariances_match_numpy(clouds):
    pts, _ = clouds
    _, idx = knn(pts, pts[:20], k=10)
    cov = local_covariances(pts, idx)
    for m in range(20):
        np.testing.assert_allclose(cov[m], np.cov(pts[idx[m]].T, bias=True), atol=1e-14)
    # Padding (-1) and an explicit mask drop neighbours the same way.
    padded = idx.copy()
    padded[:, 6:] = -1
    masked = np.ones_like(idx, dtype=bool)
    masked[:, 6:] = False
    np.testing.assert_allclose(local_covariances(pts, padded), local_covariances(pts, idx, masked))
    np.testing.assert_allclose(
        local_covariances(pts, padded)[0], np.cov(pts[idx[0, :6]].T, bias=True), atol=1e-14
    )


def test_weighted_moments_far_from_origin():
    # Centred sums keep full precision 1e6 m from the origin (cumulant sums would not).
    rng = np.random.default_rng(0)
    local = rng.normal(0, 1e-3, (30, 3))
    w = rng.uniform(0.1, 1.0, (1, 30))
    idx = np.arange(30)[None]
    mean, cov, total = weighted_moments(local + 1e6, idx, w)
    mean0, cov0, _ = weighted_moments(local, idx, w)
    np.testing.assert_allclose(cov, cov0, rtol=1e-6)
    np.testing.assert_allclose(mean - 1e6, mean0, atol=1e-9)
    assert total[0] == pytest.approx(w.sum())


@pytest.mark.parametrize(
    ("call", "message"),
    [
        (lambda p: knn(p, p, k=0), "k must be"),
        (lambda p: knn(p, p, k=11), "k must be"),
        (lambda p: knn(p, np.full((2, 3), np.nan), k=2), "NaN"),
        (lambda p: knn(p[:, :2], p, k=2), "shape"),
        (lambda p: hybrid(p, p, radius=0.0, max_nn=3), "radius"),
        (lambda p: hybrid(p, p, radius=float("nan"), max_nn=3), "radius"),
        (lambda p: hybrid(p, p, radius=1.0, max_nn=0), "max_nn"),
        (lambda p: knn(np.zeros((0, 3)), p, k=1), "non-empty"),
        (lambda p: knn(cKDTree(p), p, k=2, distance_upper_bound=float("nan")), "upper_bound"),
        (lambda p: knn(p, None, k=2, distance_upper_bound=0.0), "upper_bound"),
    ],
)
def test_bad_input_raises(call, message):
    pts = np.random.default_rng(1).uniform(size=(10, 3))
    with pytest.raises(InputError, match=message):
        call(pts)


def test_weighted_moments_across_blocks_match_per_row_numpy():
    # More rows than one block (256), with padding, zero-weight rows and varying weights: every
    # row must equal numpy's weighted mean and biased weighted covariance of its own neighbours.
    rng = np.random.default_rng(7)
    pts = rng.normal(size=(500, 3)) + np.array([0.0, 0.0, 20.0])
    idx = rng.integers(0, 500, size=(700, 9))
    idx[rng.uniform(size=idx.shape) < 0.3] = -1
    idx[5] = -1  # a row with no neighbour at all
    w = rng.uniform(0.0, 2.0, size=idx.shape)
    w[11] = 0.0  # neighbours, but zero total weight
    mean, cov, total = weighted_moments(pts, idx, w)
    for m in range(len(idx)):
        ok = idx[m] >= 0
        wm = w[m][ok]
        np.testing.assert_allclose(total[m], wm.sum(), rtol=1e-14)
        if wm.sum() == 0:
            np.testing.assert_array_equal(mean[m], 0.0)
            np.testing.assert_array_equal(cov[m], 0.0)
            continue
        ref_mean = np.average(pts[idx[m][ok]], axis=0, weights=wm)
        np.testing.assert_allclose(mean[m], ref_mean, rtol=1e-13, atol=1e-13)
        if ok.sum() > 1:
            ref = np.cov(pts[idx[m][ok]].T, aweights=wm, bias=True)
            np.testing.assert_allclose(cov[m], ref, atol=1e-13)


def test_weighted_moments_same_on_any_thread_count():
    # Several parallel chunks (256 rows each) with padding: bit-identical on 1, 2 and all threads.
    rng = np.random.default_rng(12)
    pts = rng.normal(size=(2000, 3)) * 0.05 + np.array([0.0, 0.0, 1.2])
    idx = rng.integers(0, 2000, size=(3000, 15))
    idx[rng.uniform(size=idx.shape) < 0.2] = -1
    w = rng.uniform(0.0, 1.0, size=idx.shape)
    one = weighted_moments(pts, idx, w, workers=1)
    for workers in (2, -1):
        for a, b in zip(one, weighted_moments(pts, idx, w, workers=workers), strict=True):
            np.testing.assert_array_equal(a, b)
    np.testing.assert_array_equal(
        local_covariances(pts, idx, workers=1), local_covariances(pts, idx, workers=2)
    )


@pytest.mark.parametrize(
    ("idx", "weights", "workers", "message"),
    [
        (np.array([[0, 1, 10]]), np.ones((1, 3)), 1, "1 neighbour indices are >= the number"),
        (np.array([0, 1, 2]), np.ones(3), 1, r"\(M, k\) integer array"),
        (np.array([[0.0, 1.0]]), np.ones((1, 2)), 1, r"\(M, k\) integer array"),
        (np.array([[0, 1, 2]]), np.ones((1, 2)), 1, "weights must have the shape"),
        (np.array([[0, 1, 2]]), np.ones((1, 3)), 0, "workers must be"),
    ],
)
def test_weighted_moments_bad_input_raises(idx, weights, workers, message):
    pts = np.random.default_rng(2).uniform(size=(10, 3))
    with pytest.raises(InputError, match=message):
        weighted_moments(pts, idx, weights, workers=workers)
