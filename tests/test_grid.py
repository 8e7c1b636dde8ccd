"""VoxelIndex against brute force and cKDTree; voxel downsampling against numpy, to the bit."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree

from spacepose.core.cloud import PointCloud
from spacepose.core.grid import VoxelIndex
from spacepose.core.segmentation import crop_sphere
from spacepose.core.threads import numba_threads
from spacepose.core.voxel import bounds, cell_keys, voxel_cells, voxel_downsample
from spacepose.errors import InputError


def _surface(n: int, seed: int) -> np.ndarray:
    """A noisy curved sheet about 1.2 m in front of the sensor (a scanned surface)."""
    rng = np.random.default_rng(seed)
    uv = rng.uniform(-0.3, 0.3, (n, 2))
    z = 1.2 + 0.2 * np.sin(4 * uv[:, 0]) * np.cos(3 * uv[:, 1]) + rng.normal(0, 0.002, n)
    return np.column_stack([uv, z])


def _brute(points: np.ndarray, queries: np.ndarray, k: int, bound: float = np.inf):
    """(d2, idx) of the k nearest strictly within ``bound``, ties by index, padded (inf, -1)."""
    d2 = ((queries[:, None, :] - points[None, :, :]) ** 2).sum(axis=2)
    d2 = np.where(d2 < bound**2, d2, np.inf)
    order = np.lexsort((np.broadcast_to(np.arange(len(points)), d2.shape), d2), axis=1)[:, :k]
    best = np.take_along_axis(d2, order, axis=1)
    return best, np.where(np.isfinite(best), order, -1)


@pytest.mark.parametrize("cell_size", [None, 0.004, 0.05])
@pytest.mark.parametrize("k", [1, 2, 15])
def test_knn_matches_brute_force(cell_size, k):
    pts = _surface(1500, seed=1)
    rng = np.random.default_rng(2)
    # Queries on the sheet, off it, and far outside the indexed box.
    queries = np.vstack([pts[:200], pts[:100] + rng.normal(0, 0.03, (100, 3)), [[5, -3, 9]]])
    index = VoxelIndex(pts, cell_size)
    dist, idx = index.query(queries, k=k, workers=1)
    ref_d2, ref_idx = _brute(pts, queries, k)
    dist, idx = dist.reshape(len(queries), k), idx.reshape(len(queries), k)
    np.testing.assert_array_equal(idx, ref_idx)
    np.testing.assert_allclose(dist**2, ref_d2, rtol=1e-12)


@pytest.mark.parametrize("bound", [0.003, 0.01, 0.2])
def test_bounded_query_matches_ckdtree(bound):
    pts = _surface(3000, seed=3)
    queries = pts + np.random.default_rng(4).normal(0, 0.004, pts.shape)
    index, tree = VoxelIndex(pts), cKDTree(pts)
    for k in (1, 4):
        d, i = index.query(queries, k=k, distance_upper_bound=bound, workers=2)
        d_ref, i_ref = tree.query(queries, k=k, distance_upper_bound=bound)
        np.testing.assert_array_equal(i, i_ref)
        np.testing.assert_array_equal(np.isinf(d), np.isinf(d_ref))
        np.testing.assert_allclose(d[np.isfinite(d)], d_ref[np.isfinite(d_ref)], rtol=1e-12)
        # Some queries have fewer than k neighbours in the smallest bound: padding is exercised.
        if bound == 0.003 and k == 4:
            assert np.any(i == len(pts))


def test_ties_are_broken_by_index_and_duplicates_survive():
    # A lattice: many neighbours at exactly equal distances, plus exact duplicates.
    g = np.arange(6) * 0.01
    lattice = np.stack(np.meshgrid(g, g, g, indexing="ij"), axis=-1).reshape(-1, 3)
    pts = np.vstack([lattice, lattice[:20]])
    index = VoxelIndex(pts, 0.013)
    dist, idx = index.query(lattice, k=8, workers=1)
    ref_d2, ref_idx = _brute(pts, lattice, 8)
    np.testing.assert_array_equal(idx, ref_idx)
    np.testing.assert_allclose(dist**2, ref_d2, atol=1e-18)
    # A duplicated point has its twin at distance zero as its second neighbour.
    assert idx[0, 1] == len(lattice) and dist[0, 1] == 0.0


def test_nearest_within_is_exact_whatever_the_hint():
    pts = _surface(4000, seed=5)
    queries = pts[::3] + np.random.default_rng(6).normal(0, 0.003, (len(pts[::3]), 3))
    index = VoxelIndex(pts)
    ref_d2, ref_idx = _brute(pts, queries, 1, 0.005)
    cold_idx, cold_d2 = index.nearest_within(queries, 0.005, workers=1)
    np.testing.assert_array_equal(cold_idx, ref_idx[:, 0])
    np.testing.assert_allclose(cold_d2, ref_d2[:, 0], rtol=1e-12)
    # Warm starts: the right answer, a wrong point, a far point, nothing.
    rng = np.random.default_rng(7)
    for hint in (cold_idx, rng.integers(0, len(pts), len(queries)), np.full(len(queries), -1)):
        idx, d2 = index.nearest_within(queries, 0.005, hint=hint, workers=2)
        np.testing.assert_array_equal(idx, cold_idx)
        np.testing.assert_array_equal(d2, cold_d2)


@pytest.mark.parametrize("k", [1, 15, 40])
def test_query_self_equals_query_of_the_points(k):
    # A scanned sheet with a sparse fringe: the fringe's k-th neighbours lie beyond the 27
    # cells around them and take the per-point search; the rest the shared-cell one.
    rng = np.random.default_rng(10)
    fringe = rng.uniform(-1, 1, (40, 3)) + np.array([0.0, 0.0, 1.2])
    pts = np.vstack([_surface(3000, seed=11), fringe])
    index = VoxelIndex(pts)
    dist, idx = index.query_self(k, workers=2)
    ref_d2, ref_idx = _brute(pts, pts, k)
    np.testing.assert_array_equal(idx, ref_idx)
    np.testing.assert_allclose(dist**2, ref_d2, rtol=1e-12)
    with pytest.raises(InputError, match="k must be"):
        index.query_self(len(pts) + 1)


@pytest.mark.parametrize("k", [2, 15])
def test_query_self_within_a_bound_equals_brute_force(k):
    # The fringe's points have nothing within the bound: their rows come back missing
    # (inf, n) instead of reaching across the empty cells; the sheet's rows are exact.
    rng = np.random.default_rng(13)
    fringe = rng.uniform(-1, 1, (40, 3)) + np.array([0.0, 0.0, 1.2])
    pts = np.vstack([_surface(3000, seed=14), fringe])
    index, bound = VoxelIndex(pts), 0.05
    dist, idx = index.query_self(k, workers=2, distance_upper_bound=bound)
    ref_d2, ref_idx = _brute(pts, pts, k, bound)
    np.testing.assert_array_equal(idx, np.where(ref_idx < 0, len(pts), ref_idx))
    np.testing.assert_allclose(dist**2, ref_d2, rtol=1e-12)
    # Most fringe points are alone within 5 cm; every sheet point has its k there.
    assert np.isinf(dist[3000:, -1]).mean() > 0.9 and np.isfinite(dist[:3000]).all()
    with pytest.raises(InputError, match="distance_upper_bound"):
        index.query_self(k, distance_upper_bound=-1.0)


@pytest.mark.parametrize("k", [8, 30])
def test_query_self_breaks_ties_by_index_on_a_lattice_and_duplicates(k):
    # Equal distances everywhere: the squared-distance bands the search sorts into hold many
    # points each, and the k-th often ties with points beyond it.
    lattice = np.stack(np.meshgrid(*[np.arange(12.0)] * 2, np.arange(3.0)), -1).reshape(-1, 3)
    rng = np.random.default_rng(12)
    dups = np.repeat(rng.normal(0.5, 0.02, (60, 3)), 5, axis=0)
    for pts in (0.01 * lattice, dups):
        dist, idx = VoxelIndex(pts).query_self(k, workers=2)
        ref_d2, ref_idx = _brute(pts, pts, k)
        np.testing.assert_array_equal(idx, ref_idx)
        np.testing.assert_allclose(dist**2, ref_d2, rtol=1e-12, atol=1e-18)


def test_thread_count_does_not_change_the_answer():
    # With a fringe of 400 stray points: more unsure rows than the one-thread pass takes.
    fringe = np.random.default_rng(9).uniform(-1, 1, (400, 3)) + np.array([0.0, 0.0, 1.2])
    pts = np.vstack([_surface(20000, seed=8), fringe])
    index = VoxelIndex(pts)
    for search in (
        lambda w: index.query(pts, k=10, workers=w),
        lambda w: index.query_self(10, w),
        lambda w: index.query_self(10, w, distance_upper_bound=0.05),
    ):
        one, two = search(1), search(2)
        np.testing.assert_array_equal(one[1], two[1])
        np.testing.assert_array_equal(one[0], two[0])
    # And the many unsure rows are exact: brute force on the fringe's rows.
    dist, idx = index.query_self(10, 2, distance_upper_bound=0.05)
    ref_d2, ref_idx = _brute(pts, pts[20000:], 10, 0.05)
    np.testing.assert_array_equal(idx[20000:], np.where(ref_idx < 0, len(pts), ref_idx))
    np.testing.assert_allclose(dist[20000:] ** 2, ref_d2, rtol=1e-12)


def test_degenerate_clouds():
    # One point, and many copies of one point (zero extent).
    single = VoxelIndex([[1.0, 2.0, 3.0]])
    d, i = single.query([[1.0, 2.0, 4.0]], k=1)
    assert i[0] == 0 and d[0] == pytest.approx(1.0)
    d, i = single.query([[1.0, 2.0, 4.0]], k=3)
    np.testing.assert_array_equal(i[0], [0, 1, 1])
    assert np.isinf(d[0, 1:]).all()
    same = VoxelIndex(np.ones((50, 3)))
    d, i = same.query(np.zeros((2, 3)), k=5)
    np.testing.assert_array_equal(i, np.tile(np.arange(5), (2, 1)))
    np.testing.assert_allclose(d, np.sqrt(3.0))
    # A cloud kilometres wide gets cells large enough for its keys.
    wide = VoxelIndex([[0.0, 0.0, 0.0], [5e3, 0.0, 0.0], [0.0, 0.0, 1e-3]], cell_size=1e-3)
    assert wide.cell_size >= 5e3 / (1 << 20)
    assert wide.query([[4e3, 0, 0]], k=1)[1][0] == 1


def test_bad_input_is_reported():
    with pytest.raises(InputError, match="at least 1 point"):
        VoxelIndex(np.empty((0, 3)))
    with pytest.raises(InputError):
        VoxelIndex([[0.0, np.nan, 1.0]])
    with pytest.raises(InputError):
        VoxelIndex(np.zeros((4, 2)))
    with pytest.raises(InputError, match="cell_size"):
        VoxelIndex(np.zeros((4, 3)), cell_size=-1.0)
    index = VoxelIndex(_surface(100, seed=9))
    with pytest.raises(InputError, match="k must be"):
        index.query(np.zeros((1, 3)), k=0)
    with pytest.raises(InputError, match="distance_upper_bound"):
        index.query(np.zeros((1, 3)), distance_upper_bound=0.0)
    with pytest.raises(InputError, match="hints"):
        index.nearest_within(np.zeros((3, 3)), 0.01, hint=np.zeros(2, dtype=np.int64))
    # A hint the kernel would look up out of range, a float hint, bad points and gates.
    with pytest.raises(InputError, match="hints must lie"):
        index.nearest_within(np.zeros((2, 3)), 0.01, hint=np.array([0, 100]))
    with pytest.raises(InputError, match="hints must lie"):
        index.nearest_within(np.zeros((2, 3)), 0.01, hint=np.array([0, -2]))
    with pytest.raises(InputError, match="integers"):
        index.nearest_within(np.zeros((2, 3)), 0.01, hint=np.zeros(2))
    with pytest.raises(InputError):
        index.nearest_within(np.full((2, 3), np.nan), 0.01)
    for gate in (0.0, -1.0, np.nan):
        with pytest.raises(InputError, match="max_distance"):
            index.nearest_within(np.zeros((2, 3)), gate)
    with pytest.raises(InputError, match="workers"), numba_threads(0):
        pass


def test_voxel_primitives_refuse_bad_input():
    # Empty, non-finite or misshaped points and non-positive cells: the compiled passes would
    # otherwise read points[0] of an empty array or index cells from NaN coordinates.
    for bad in (np.empty((0, 3)), np.array([[0.0, np.inf, 1.0]]), np.zeros((3, 2))):
        with pytest.raises(InputError):
            bounds(bad)
        with pytest.raises(InputError):
            cell_keys(bad, 0.01)
        with pytest.raises(InputError):
            voxel_cells(bad, 0.01)
    for size in (0.0, -0.01, np.nan, np.inf):
        with pytest.raises(InputError, match="cell size"):
            cell_keys(np.zeros((3, 3)), size)
    # And the right answer on good input: min/max as numpy, keys that order cells as the
    # lexicographic (x, y, z) cell indices do.
    pts = _surface(500, seed=12)
    low, high = bounds(pts)
    np.testing.assert_array_equal(low, pts.min(axis=0))
    np.testing.assert_array_equal(high, pts.max(axis=0))
    keys, dims, offset = cell_keys(pts, 0.05)
    cells = np.floor(pts / 0.05).astype(np.int64)
    np.testing.assert_array_equal(offset, cells.min(axis=0))
    np.testing.assert_array_equal(dims, cells.max(axis=0) - cells.min(axis=0) + 1)
    lexical = np.lexsort(((cells - offset)[:, 2], (cells - offset)[:, 1], (cells - offset)[:, 0]))
    np.testing.assert_array_equal(np.sort(keys), keys[lexical])


# A coarse voxel leaves few cells in the box (a slot per cell), a fine one many (the hash).
@pytest.mark.parametrize("voxel", [0.002, 0.01, 0.1])
def test_voxel_downsample_equals_a_numpy_reference_to_the_bit(voxel):
    rng = np.random.default_rng(3)
    # Scan order (rows of the sheet) as a camera delivers them, then shuffled: the shortcut
    # for a point in the previous point's cell must not change the sums' order.
    pts = _surface(4000, seed=4)
    pts = np.vstack([pts[np.argsort(pts[:, 1], kind="stable")], pts[rng.permutation(4000)]])
    sigma = rng.uniform(0.001, 0.003, len(pts))
    cells = np.floor(pts / voxel).astype(np.int64)
    # np.unique orders rows lexicographically (x, y, z), the order of the keys.
    _, cell, counts = np.unique(cells, axis=0, return_inverse=True, return_counts=True)
    sums = np.column_stack([np.bincount(cell, weights=pts[:, a]) for a in range(3)])
    down = voxel_downsample(PointCloud(pts, sigma=sigma), voxel)
    np.testing.assert_array_equal(down.points, sums / counts[:, None])
    np.testing.assert_array_equal(down.sigma, np.bincount(cell, weights=sigma) / counts)
    centroids, of_point = voxel_cells(pts, voxel)
    np.testing.assert_array_equal(centroids, down.points)
    np.testing.assert_array_equal(of_point, cell)


@pytest.mark.parametrize("voxel", [0.002, 0.01, 0.1])
def test_a_moved_grid_groups_as_a_numpy_reference_does(voxel):
    # Cells aligned to origin + k·voxel: the points grouped by ⌊(p − origin) / voxel⌋, their
    # centroids summed from the points themselves; a zero origin is the default to the bit.
    pts = _surface(4000, seed=9)
    origin = np.array([0.5, -0.25, 0.375]) * voxel
    cells = np.floor((pts - origin) / voxel).astype(np.int64)
    _, cell, counts = np.unique(cells, axis=0, return_inverse=True, return_counts=True)
    sums = np.column_stack([np.bincount(cell, weights=pts[:, a]) for a in range(3)])
    moved = voxel_downsample(pts, voxel, origin=origin)
    np.testing.assert_array_equal(moved.points, sums / counts[:, None])
    default = voxel_downsample(pts, voxel)
    np.testing.assert_array_equal(
        voxel_downsample(pts, voxel, origin=np.zeros(3)).points, default.points
    )
    assert len(moved) != len(default) or not np.array_equal(moved.points, default.points)
    with pytest.raises(InputError, match="origin"):
        voxel_downsample(pts, voxel, origin=[0.0, np.nan, 0.0])


def test_crop_sphere_keeps_what_numpy_keeps_to_the_bit():
    # The compiled crop sums the squared distance as numpy sums a row ((dx² + dy²) + dz²): a
    # point whose squared distance is the radius squared to the bit is kept, as numpy keeps it.
    # Tiled past several chunks of its passes, with no-returns (points at the origin) among
    # them, the indices are numpy's on every thread count.
    pts = np.tile(_surface(6000, seed=6), (30, 1))
    pts[::7] = 0.0
    center = pts[1:6000].mean(axis=0) + np.array([0.05, -0.02, 0.0])
    d2 = ((pts - center) ** 2).sum(axis=1)
    on = next(i for i in np.argsort(d2)[len(pts) // 2 :] if np.sqrt(d2[i]) ** 2 == d2[i])
    radius = float(np.sqrt(d2[on]))
    expected = np.flatnonzero((d2 <= radius**2) & np.any(pts != 0.0, axis=1))
    kept = crop_sphere(pts, center, radius)
    np.testing.assert_array_equal(kept, expected)
    assert on in kept and 0.2 * len(pts) < len(kept) < 0.9 * len(pts)
    # No return is kept, though the sphere holds the origin.
    assert not np.isin(np.arange(0, len(pts), 7), crop_sphere(pts, [0.0, 0.0, 0.0], 100.0)).any()
    np.testing.assert_array_equal(crop_sphere(pts, center, radius, workers=2), kept)
    # A cloud, lists and a column centre are points and a centre too.
    np.testing.assert_array_equal(crop_sphere(PointCloud(pts), center, radius), kept)
    np.testing.assert_array_equal(crop_sphere(pts.tolist(), center[:, None], radius), kept)
    # A negative radius, squared, used to crop as its opposite; a short centre crashed in
    # numpy's reshape: both are refused by name now, as are NaN and a text radius.
    for bad_center, bad_radius in (
        (center, -radius),
        (center[:2], radius),
        (center, float("nan")),
        ([np.inf, 0.0, 0.0], radius),
        (center, "far"),
    ):
        with pytest.raises(InputError, match="a crop needs"):
            crop_sphere(pts, bad_center, bad_radius)


def test_voxel_downsample_options_are_keywords():
    # A call written for the old third positional (a crop sphere) must not bind it to
    # stray_share: positional options are refused, and a share that is not a number is named.
    pts = _surface(2000, seed=3)
    with pytest.raises(TypeError):
        voxel_downsample(pts, 0.01, 0.1)  # type: ignore[misc]
    with pytest.raises(InputError, match="stray_share must be a number"):
        voxel_downsample(pts, 0.01, stray_share=(np.zeros(3), 0.1))  # type: ignore[arg-type]


@pytest.mark.parametrize("voxel", [0.03, 0.05])
def test_stray_voxels_are_those_a_numpy_block_count_finds(voxel):
    # A sheet and 60 lone returns between it and the sensor (flying pixels): a voxel goes when
    # its 3×3×3 block holds fewer points than a sixteenth of the median block.
    rng = np.random.default_rng(7)
    sheet = _surface(20000, seed=8)
    lone = np.column_stack([rng.uniform(-0.3, 0.3, (60, 2)), rng.uniform(0.5, 0.9, 60)])
    pts = np.vstack([sheet, lone])
    cells = np.floor(pts / voxel).astype(np.int64)
    occupied, cell, counts = np.unique(cells, axis=0, return_inverse=True, return_counts=True)
    assert len(occupied) < 1024  # every block enters the median (one in every 1024 // 512)
    near = np.abs(occupied[:, None, :] - occupied[None, :, :]).max(axis=2) <= 1
    block = near @ counts
    solid = block >= np.median(block) / 16
    kept = voxel_downsample(PointCloud(pts), voxel, stray_share=1 / 16)
    every = voxel_downsample(PointCloud(pts), voxel)
    np.testing.assert_array_equal(kept.points, every.points[solid])
    # Every lone return dropped, every voxel of the sheet kept.
    assert not solid[cell[len(sheet) :]].any() and solid[cell[: len(sheet)]].all()
    for share in (float("nan"), 1.0, -0.1):
        with pytest.raises(InputError, match="stray_share"):
            voxel_downsample(PointCloud(pts), voxel, stray_share=share)


def test_fuller_cells_give_the_same_self_search():
    from spacepose.core.grid import self_knn_occupancy

    pts = _surface(3000, seed=13)
    ref_d2, ref_idx = _brute(pts, pts, 30)
    for occupancy in (self_knn_occupancy(30), 25.0):
        index = VoxelIndex(pts, occupancy=occupancy)
        assert len(pts) / len(index._cell_keys) > 0.5 * occupancy
        dist, idx = index.query_self(30, workers=2)
        np.testing.assert_array_equal(idx, ref_idx)
        np.testing.assert_allclose(dist**2, ref_d2, rtol=1e-12)
    with pytest.raises(InputError, match="occupancy"):
        VoxelIndex(pts, occupancy=0.5)
