"""Rectangle measurement and recognition, the 4-fold fix and the coarse target pose."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from spacepose.core import se3
from spacepose.core.attitude_fix import (
    FOUR_FOLD_FLIPS,
    coarse_target_pose,
    consistent_rectangles,
    fix_four_fold,
)
from spacepose.core.rectangle_measurement import fill_ratio, measure_rectangle
from spacepose.core.rectangles import (
    CatalogueEntry,
    RectangleConfig,
    candidates,
    recognise,
    rejection_reason,
)
from spacepose.errors import DegenerateGeometryError, InputError

CM2 = 1e-4  # m² per cm²


def _grid(a, b, n_a, n_b, z=0.065):
    """Cell centres of an n_a × n_b grid over [−a/2, a/2] × [−b/2, b/2] at height z (m)."""
    x = (np.arange(n_a) + 0.5) / n_a * a - a / 2
    y = (np.arange(n_b) + 0.5) / n_b * b - b / 2
    X, Y = np.meshgrid(x, y, indexing="ij")
    return np.column_stack([X.ravel(), Y.ravel(), np.full(X.size, z)])


def _uniform(rng, n, a, b, z=0.065):
    return np.column_stack(
        [rng.uniform(-a / 2, a / 2, n), rng.uniform(-b / 2, b / 2, n), np.full(n, z)]
    )


def _entry(name, a, b, R=np.eye(3), center=(0.0, 0.0, 0.0)):
    return CatalogueEntry(name=name, center=center, R_model_plane=R.tolist(), a=a, b=b)


BOX = (2.4, 1.8, 1.4)  # the orbit bus, m


def _box_face(name, axis, sign):
    """Catalogue entry of a face of the box BOX centred at the model origin."""
    others = [i for i in range(3) if i != axis]
    short, long_ = sorted(others, key=lambda i: BOX[i])
    z = sign * np.eye(3)[axis]
    y = np.eye(3)[long_]
    R = np.column_stack([np.cross(y, z), y, z])
    return _entry(name, BOX[short], BOX[long_], R, tuple(0.5 * BOX[axis] * z))


def _face_points(entry, T_sensor_model, spacing=0.03):
    """Grid points on a catalogue face, seen in the sensor frame (m)."""
    n_a, n_b = round(entry.a / spacing), round(entry.b / spacing)
    local = _grid(entry.a, entry.b, n_a, n_b, z=0.0)
    model = local @ entry.rotation.T + entry.centre
    return se3.transform_points(T_sensor_model, model)


def _angle_deg(R1, R2):
    return np.degrees(Rotation.from_matrix(R1.T @ R2).magnitude())


# A target 25 m down the boresight, turned so that its +z and +x faces look at the sensor.
T_SENSOR_MODEL = se3.make_transform(
    Rotation.from_euler("xyz", [180.0 - 30.0, 35.0, 10.0], degrees=True), [0.3, -0.2, 25.0]
)


def test_dense_grid_gives_paper_eigenvalues_closed_form():
    # Yu's check: a 10×18 cm rectangle has λ = a²/12, b²/12, 0 = 8.3333, 27, 0 cm².
    m = measure_rectangle(_grid(0.10, 0.18, 300, 540))
    # A grid of n cell centres has variance exactly (s²/12)(1 − 1/n²): 1e-5 relative here.
    exact = [0.0, 0.10**2 / 12 * (1 - 1 / 300**2), 0.18**2 / 12 * (1 - 1 / 540**2)]
    np.testing.assert_allclose(m.eigenvalues, exact, rtol=1e-9, atol=1e-15)
    np.testing.assert_allclose(m.eigenvalues / CM2, [0.0, 8.3333333, 27.0], rtol=2e-5, atol=1e-9)
    assert m.a == pytest.approx(0.10, rel=1e-5)
    assert m.b == pytest.approx(0.18, rel=1e-5)
    np.testing.assert_allclose(m.centroid, [0.0, 0.0, 0.065], atol=1e-12)
    # E[u⁴]/E[u²]² of n equally spaced values: 3(3n² − 7) / (5(n² − 1)) → 1.8.
    n = np.array([300, 540])
    np.testing.assert_allclose(m.kurtosis, 3 * (3 * n**2 - 7) / (5 * (n**2 - 1)), rtol=1e-9)
    # The quantile extent of a grid is right to within one cell, s / n.
    assert np.all(np.abs(m.extent - [0.10, 0.18]) <= np.array([0.10, 0.18]) / n + 1e-12)


def test_plane_frame_is_right_handed_and_faces_the_sensor():
    m = measure_rectangle(_grid(0.10, 0.18, 50, 90))
    R = m.R_sensor_plane
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)
    assert np.linalg.det(R) == pytest.approx(1.0, abs=1e-12)
    # Short side along sensor x, long side along y, normal back towards the origin (−z).
    np.testing.assert_allclose(np.abs(R[:, 0]), [1, 0, 0], atol=1e-9)
    np.testing.assert_allclose(np.abs(R[:, 1]), [0, 1, 0], atol=1e-9)
    np.testing.assert_allclose(R[:, 2], [0, 0, -1], atol=1e-9)
    np.testing.assert_array_equal(m.normal, R[:, 2])


def test_noise_correction_recovers_sides():
    rng = np.random.default_rng(11)
    sigma = 0.01
    pts = _uniform(rng, 20000, 0.10, 0.18) + rng.normal(0.0, sigma, (20000, 3))
    m = measure_rectangle(pts, sigma)
    # Standard error of a here ≈ 0.4 mm, of b ≈ 0.6 mm.
    assert abs(m.a - 0.10) < 1.5e-3
    assert abs(m.b - 0.18) < 2.5e-3
    # Without the σ² term the sides come out far too long.
    raw = measure_rectangle(pts, 0.0)
    assert raw.a - 0.10 > 4e-3
    np.testing.assert_allclose(m.kurtosis, 1.8, atol=0.06)
    assert recognise(m, [_entry("r", 0.10, 0.18)], RectangleConfig(sigma=sigma)) == "r"


def test_recognise_picks_the_entry_of_matching_size():
    rng = np.random.default_rng(12)
    catalogue = [_entry("small", 0.10, 0.18), _entry("big", 0.20, 0.30), _entry("sq", 0.15, 0.15)]
    for name, a, b in (("small", 0.10, 0.18), ("big", 0.20, 0.30)):
        m = measure_rectangle(_uniform(rng, 2500, a, b))
        assert recognise(m, catalogue) == name
        assert rejection_reason(m, catalogue) is None
    # A square's in-plane eigenvectors are arbitrary, so it cannot give an attitude.
    m = measure_rectangle(_uniform(rng, 2500, 0.15, 0.15))
    assert recognise(m, catalogue) is None
    assert "near-square" in rejection_reason(m, catalogue)


def test_partial_rectangle_cut_to_60_percent_is_rejected():
    rng = np.random.default_rng(13)
    catalogue = [_entry("small", 0.10, 0.18), _entry("big", 0.20, 0.30)]
    pts = _uniform(rng, 2500, 0.10, 0.18)
    cut = pts[pts[:, 1] <= -0.09 + 0.6 * 0.18]  # field of view cuts the long side at 60 %
    m = measure_rectangle(cut)
    assert m.b == pytest.approx(0.6 * 0.18, abs=3e-3)
    # Its centroid is 3.6 cm off the rectangle's centre: matching it would bias the pose.
    assert abs(m.centroid[1] + 0.2 * 0.18) < 2e-3
    assert recognise(m, catalogue) is None
    assert "near-square" in rejection_reason(m, catalogue)  # 0.10 x 0.108 m is left
    # Cut across the short side instead: a 6 x 18 cm strip matches no entry.
    m = measure_rectangle(pts[pts[:, 0] <= -0.05 + 0.6 * 0.10])
    assert recognise(m, catalogue) is None
    assert "match no catalogue rectangle" in rejection_reason(m, catalogue)


def test_occluded_corner_and_ellipse_are_rejected_by_shape():
    rng = np.random.default_rng(14)
    catalogue = [_entry("r", 0.10, 0.18)]
    pts = _uniform(rng, 4000, 0.10, 0.18)
    l_shape = pts[~((pts[:, 0] > 0) & (pts[:, 1] > 0))]  # a quarter hidden behind another part
    m = measure_rectangle(l_shape)
    assert recognise(m, catalogue) is None
    assert "fourth-moment" in rejection_reason(m, catalogue)
    # A uniform ellipse (semi-axes 5 and 9 cm): ratio 2.0 along both axes.
    r = np.sqrt(rng.uniform(0, 1, 4000))
    t = rng.uniform(0, 2 * np.pi, 4000)
    ellipse = np.column_stack([0.05 * r * np.cos(t), 0.09 * r * np.sin(t), np.full(4000, 0.065)])
    m = measure_rectangle(ellipse)
    np.testing.assert_allclose(m.kurtosis, 2.0, atol=0.08)
    assert recognise(m, catalogue) is None
    # A triangle: extents and moments disagree.
    u, v = rng.uniform(0, 1, (2, 4000))
    flip = u + v > 1
    u[flip], v[flip] = 1 - u[flip], 1 - v[flip]
    tri = np.column_stack([0.1 * u, 0.18 * v, np.full(4000, 0.065)])
    assert recognise(measure_rectangle(tri), catalogue) is None


def _camera_view(a, b, focal_px, z, hole=None):
    """A rectangle facing a range camera at depth z, one point per pixel ray (m)."""
    step = z / focal_px  # pixel footprint on a fronto-parallel plane
    x = np.arange(-a / 2 + step / 2, a / 2, step)
    y = np.arange(-b / 2 + step / 2, b / 2, step)
    X, Y = (v.ravel() for v in np.meshgrid(x, y, indexing="ij"))
    keep = np.ones(X.size, bool) if hole is None else ~hole(X, Y)
    return np.column_stack([X[keep], Y[keep], np.full(keep.sum(), z)])


def test_fill_ratio_and_hidden_parts():
    f, z = 300.0, 25.0  # flash-LiDAR-like: 8.3 cm pixels at 25 m
    catalogue = [_entry("face", 1.4, 2.4)]
    # A loose moment check, so that each of the other two checks is seen on its own.
    config = RectangleConfig(focal_px=f, kurtosis_tolerance=0.2)
    whole = measure_rectangle(_camera_view(1.4, 2.4, f, z))
    assert fill_ratio(whole, f) == pytest.approx(1.0, abs=0.02)
    assert recognise(whole, catalogue, config) == "face"
    np.testing.assert_allclose(whole.centre_offset, 0.0, atol=1e-9)
    # A 0.4 m band hidden 0.5 m off-centre (a boom in front): 17 % of the points are missing.
    band = measure_rectangle(_camera_view(1.4, 2.4, f, z, hole=lambda x, y: abs(y - 0.5) < 0.2))
    assert fill_ratio(band, f) < 0.9
    assert "part of it is hidden" in rejection_reason(band, catalogue, config)
    # Without the camera model the band still moves the centroid off the extent's middle.
    assert band.centre_offset[1] < -0.07
    loose = RectangleConfig(kurtosis_tolerance=0.2)
    assert "centroid off the middle" in rejection_reason(band, catalogue, loose)


def test_random_sampling_mode_accepts_small_independent_samples():
    # 625 independent points scatter more than a pixel grid: in 100 draws the grid-mode
    # tolerances reject some whole rectangles, the random mode none.
    rng = np.random.default_rng(16)
    catalogue = [_entry("r", 0.10, 0.18)]
    draws = [measure_rectangle(_uniform(rng, 625, 0.10, 0.18)) for _ in range(100)]
    grid = sum(recognise(m, catalogue) is None for m in draws)
    random = sum(recognise(m, catalogue, RectangleConfig(sampling="random")) is None for m in draws)
    assert grid >= 5 and random == 0


def test_too_few_points_and_thick_planes_are_rejected():
    rng = np.random.default_rng(15)
    catalogue = [_entry("r", 0.10, 0.18)]
    m = measure_rectangle(_uniform(rng, 30, 0.10, 0.18))
    assert "min_points" in rejection_reason(m, catalogue)
    thick = _uniform(rng, 2500, 0.10, 0.18) + [0, 0, 1] * rng.uniform(-0.05, 0.05, (2500, 1))
    assert "max_thickness" in rejection_reason(measure_rectangle(thick), catalogue)


def test_faces_of_equal_size_need_a_prediction():
    plus_z, minus_z = _box_face("bus+z", 2, 1.0), _box_face("bus-z", 2, -1.0)
    catalogue = [plus_z, minus_z, _box_face("bus+x", 0, 1.0)]
    m = measure_rectangle(_face_points(plus_z, T_SENSOR_MODEL))
    assert sorted(e.name for e in candidates(m, catalogue)) == ["bus+z", "bus-z"]
    assert recognise(m, catalogue) is None
    assert "predicted attitude" in rejection_reason(m, catalogue)
    R_pred = Rotation.from_rotvec([0.3, -0.2, 0.1]).as_matrix() @ T_SENSOR_MODEL[:3, :3]  # ~21°
    assert recognise(m, catalogue, predicted_R_sensor_model=R_pred) == "bus+z"
    m_x = measure_rectangle(_face_points(catalogue[2], T_SENSOR_MODEL))
    assert recognise(m_x, catalogue) == "bus+x"


@pytest.mark.parametrize("k", range(4))
def test_four_fold_fix_returns_true_frame_for_each_flip(k):
    rng = np.random.default_rng(20 + k)
    R_true = Rotation.random(random_state=rng).as_matrix()
    R_measured = R_true @ FOUR_FOLD_FLIPS[k]
    for _ in range(20):
        axis = rng.normal(size=3)
        axis /= np.linalg.norm(axis)
        # Predictions up to ±20° from the truth, the edge included.
        angle = np.radians(rng.choice([20.0, -20.0, rng.uniform(-20.0, 20.0)]))
        R_pred = Rotation.from_rotvec(angle * axis).as_matrix() @ R_true
        np.testing.assert_allclose(fix_four_fold(R_measured, R_pred), R_true, atol=1e-12)
    # Without the fix, the three flipped frames are 180° off.
    assert _angle_deg(R_measured, R_true) == pytest.approx(0.0 if k == 0 else 180.0, abs=1e-6)


def test_coarse_pose_from_one_face_with_and_without_fix():
    entry = _box_face("bus+z", 2, 1.0)
    m = measure_rectangle(_face_points(entry, T_SENSOR_MODEL))
    R_true = T_SENSOR_MODEL[:3, :3]
    R_pred = Rotation.from_rotvec(np.radians(15.0) * np.array([0.6, 0.8, 0.0])).as_matrix() @ R_true
    errors_without = []
    for flip in FOUR_FOLD_FLIPS:
        flipped = dataclasses.replace(m, R_sensor_plane=m.R_sensor_plane @ flip)
        T = coarse_target_pose(flipped, entry, predicted_R_sensor_model=R_pred)
        assert _angle_deg(T[:3, :3], R_true) < 1e-6
        np.testing.assert_allclose(T[:3, 3], T_SENSOR_MODEL[:3, 3], atol=1e-9)
        errors_without.append(_angle_deg(coarse_target_pose(flipped, entry)[:3, :3], R_true))
    # Without a prediction the attitude is 180° off for the wrong eigenvector signs.
    assert sorted(np.round(errors_without)) == [0.0, 180.0, 180.0, 180.0]


def test_consistent_rectangles_settle_the_normal_turn_without_prediction():
    top, side = _box_face("bus+z", 2, 1.0), _box_face("bus+x", 0, 1.0)
    m_top = measure_rectangle(_face_points(top, T_SENSOR_MODEL))
    m_side = measure_rectangle(_face_points(side, T_SENSOR_MODEL))
    turn = FOUR_FOLD_FLIPS[3]  # 180° about the normal: what the normal-towards-sensor rule leaves
    for f_top in (np.eye(3), turn):
        for f_side in (np.eye(3), turn):
            pairs = [
                (dataclasses.replace(m_top, R_sensor_plane=m_top.R_sensor_plane @ f_top), top),
                (dataclasses.replace(m_side, R_sensor_plane=m_side.R_sensor_plane @ f_side), side),
            ]
            T = consistent_rectangles(pairs)
            assert _angle_deg(T[:3, :3], T_SENSOR_MODEL[:3, :3]) < 1e-6
            np.testing.assert_allclose(T[:3, 3], T_SENSOR_MODEL[:3, 3], atol=1e-9)
    # With a prediction 20° off, the flipped frames are fixed the same way.
    R_pred = Rotation.from_rotvec(np.radians(20.0) * np.array([0, 0, 1.0])).as_matrix()
    T = consistent_rectangles(pairs, predicted_R_sensor_model=R_pred @ T_SENSOR_MODEL[:3, :3])
    assert _angle_deg(T[:3, :3], T_SENSOR_MODEL[:3, :3]) < 1e-6


def test_bad_input_raises_package_errors():
    with pytest.raises(InputError, match="at least 3"):
        measure_rectangle(np.zeros((2, 3)))
    with pytest.raises(InputError, match="NaN"):
        measure_rectangle([[0, 0, 1], [1, 0, 1], [0, 1, np.nan]])
    with pytest.raises(DegenerateGeometryError, match="collinear"):
        measure_rectangle(np.outer(np.linspace(0, 1, 20), [1.0, 1.0, 0.0]))
    with pytest.raises(InputError, match="3x3"):
        fix_four_fold(np.eye(4), np.eye(3))
    with pytest.raises(InputError, match="rotation"):
        fix_four_fold(np.diag([1.0, 1.0, -1.0]), np.eye(3))
    with pytest.raises(InputError, match="at least one"):
        consistent_rectangles([])


def test_simulated_orbit_frame_end_to_end():
    sim_mod = pytest.importorskip("spacepose.core.sim")
    from spacepose.core.planes import PlaneConfig
    from spacepose.core.rectangle_search import find_rectangles
    from spacepose.tools.catalogue import parse_catalogue

    # The scene this test was written for: the box-and-wing target (the default one adds an
    # antenna panel and an instrument, which change what frame 0 shows).
    sim = sim_mod.simulate_orbit(sim_mod.OrbitConfig(frames=1))
    sim = dataclasses.replace(sim, target=sim_mod.symmetric_orbit_target())
    frame = sim.frame(0)
    catalogue = parse_catalogue(sim.scenario())
    T_true = frame.T_sensor_target
    R_pred = Rotation.from_rotvec(np.radians(15.0) * np.array([0.6, 0.0, 0.8])).as_matrix()
    R_pred = R_pred @ T_true[:3, :3]
    found = find_rectangles(
        frame.cloud,
        catalogue,
        PlaneConfig(distance_threshold=0.03, min_inliers=100, cluster_radius=0.25),
        RectangleConfig(sigma=0.01, focal_px=sim.sensor.focal_px),
        predicted_R_sensor_model=R_pred,
    )
    # Frame 0 shows the wing (partly behind the bus), bus+y (a band hidden by the boom and wing)
    # and bus-x whole: only bus-x may be recognised.
    assert len(found) == 3
    assert [f.name for f in found if f.name] == ["bus-x"]
    hit = next(f for f in found if f.name)
    entry = next(e for e in catalogue if e.name == "bus-x")
    T = coarse_target_pose(hit.measurement, entry, R_pred)
    # 8 cm pixels at 25 m, σ = 1 cm, a 1.4 x 1.8 m face (in-plane eigenvalues only 0.11 m²
    # apart): measured 1.0° and 25 mm here; over 100 frames bus-x had a median of 1.4°.
    assert _angle_deg(T[:3, :3], T_true[:3, :3]) < 2.0
    assert np.linalg.norm(T[:3, 3] - T_true[:3, 3]) < 0.05


def _y1_cloud(seed: int) -> np.ndarray:
    """Y1-style scene (m): a 10 x 18 cm rectangle of 1,250 uniform points at z = 6.5 cm and
    1,250 uniform outliers in a 20 x 30 x 13 cm box around it."""
    rng = np.random.default_rng(seed)
    face = np.column_stack(
        [rng.uniform(-0.05, 0.05, 1250), rng.uniform(-0.09, 0.09, 1250), np.full(1250, 0.065)]
    )
    out = rng.uniform([-0.10, -0.15, 0.0], [0.10, 0.15, 0.13], (1250, 3))
    return np.vstack([face, out])


def test_y1_rectangle_with_outliers_in_its_slab():
    from spacepose.core.planes import PlaneConfig
    from spacepose.core.rectangle_search import measure_planes

    errors = {}
    for mode in ("support", "slab"):
        config = RectangleConfig(sampling="random", support=mode == "support")
        rows = []
        for seed in range(10):
            m = measure_planes(_y1_cloud(seed), PlaneConfig(max_planes=1), config)[0].measurement
            rows.append([m.a - 0.10, m.b - 0.18, np.linalg.norm(m.centroid - [0, 0, 0.065])])
        errors[mode] = 1e3 * np.array(rows)  # mm
    # Measured, mean ± std over the 10 seeds (mm): short side 0.51 ± 0.43, long side
    # -0.20 ± 0.63 (at most 1.2), centroid 0.37 ± 0.20 (at most 0.79). The moments of the
    # whole slab, as before, gave 8.4 ± 2.0, 10.6 ± 4.0 and 1.7 ± 0.8.
    support = errors["support"]
    assert np.all(np.abs(support[:, :2]) < 3.0), support
    assert np.all(support[:, 2] < 1.0), support
    # The edges of the whole slab (its strays included): sides 61 and 76 mm too long.
    assert np.all(errors["slab"][:, :2] > 30.0)


def test_random_sampling_measures_the_edges_not_the_moments():
    # 1,250 uniform points on 10 x 18 cm without outliers: the mean scatters by 1.5 mm along
    # the long side and the side from the variance by 2.3 mm; the edges by a tenth of that.
    rows = []
    for seed in range(20):
        pts = _y1_cloud(seed)[:1250]
        grid, rand = measure_rectangle(pts), measure_rectangle(pts, sampling="random")
        np.testing.assert_array_equal(grid.eigenvalues, rand.eigenvalues)
        np.testing.assert_allclose(rand.moment_sides, [grid.a, grid.b])
        rows.append([grid.b - 0.18, rand.b - 0.18, grid.centroid[1], rand.centroid[1]])
    spread = 1e3 * np.std(rows, axis=0)
    # Theory: 0.18 √(0.2 / 1250) = 2.28 mm and 0.18 / √(12 · 1250) = 1.47 mm for the moments;
    # measured 2.90 and 1.37 mm, against 0.74 and 0.37 mm from the edges.
    assert 1.4 < spread[0] < 3.3 and 0.9 < spread[2] < 2.1
    assert spread[1] < 0.5 * spread[0] and spread[3] < 0.5 * spread[2]


def test_pixel_area_weights_measure_a_tilted_face_as_a_surface() -> None:
    from spacepose.core.nav_measurements import pixel_area_weights

    # A 2 x 6 m face at 25 m, turned 60/30/30° (x, y, z), sampled by a regular pinhole grid:
    # the samples crowd where the face is nearer and thin out off the axis.
    R = Rotation.from_euler("xyz", [60, 30, 30], degrees=True).as_matrix()
    centre = np.array([0.3, 4.4, 25.0])
    u, v = np.meshgrid(np.linspace(-0.3, 0.3, 900), np.linspace(-0.15, 0.5, 1000))
    rays = np.stack([u.ravel(), v.ravel(), np.ones(u.size)], axis=1)
    pts = rays * ((centre @ R[:, 2]) / (rays @ R[:, 2]))[:, None]
    local = (pts - centre) @ R
    pts = pts[(np.abs(local[:, 0]) <= 1.0) & (np.abs(local[:, 1]) <= 3.0)]
    errors = {}
    for name, w in (("plain", None), ("weighted", pixel_area_weights(pts))):
        m = measure_rectangle(pts, weights=w)
        spin = np.degrees(np.arccos(min(1.0, abs(m.R_sensor_plane[:, 1] @ R[:, 1]))))
        sides = np.abs([m.a - 2.0, m.b - 6.0])
        errors[name] = (spin, sides.max(), np.linalg.norm(m.centroid - centre))
    # Measured: plain 0.038°, 36 mm on the long side, 270 mm; weighted 0.0016°, 1.5 mm, 0.7 mm.
    assert errors["plain"][0] > 0.02 and errors["plain"][1] > 0.02 and errors["plain"][2] > 0.1
    assert errors["weighted"][0] < 0.005
    assert errors["weighted"][1] < 0.003 and errors["weighted"][2] < 0.002


def test_pixel_area_weights_fall_back_to_range_cubed_off_a_pinhole_image() -> None:
    from spacepose.core.nav_measurements import pixel_area_weights

    pts = np.array([[3.0, 0.0, 4.0], [0.0, 1.0, 2.0]])
    np.testing.assert_allclose(pixel_area_weights(pts), [64.0, 8.0])  # depth³
    # A point behind the image plane: no pinhole image, so range³ (a scanner's solid angle).
    behind = np.array([[3.0, 0.0, 4.0], [0.0, 2.0, -1.0]])
    np.testing.assert_allclose(pixel_area_weights(behind), [125.0, 5.0**1.5])


@pytest.mark.parametrize(
    "weights, message",
    [
        (np.ones(3), r"weights must be \(4,\)"),
        (np.array([1.0, -1.0, 1.0, 1.0]), "non-negative"),
        (np.array([1.0, np.nan, 1.0, 1.0]), "finite"),
        (np.zeros(4), "all 0"),
    ],
)
def test_bad_weights_raise_input_errors(weights, message) -> None:
    from spacepose.core.rectangle_search import measure_planes

    square = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 1.0], [0.0, 1.0, 1.0], [1.0, 1.0, 1.0]])
    with pytest.raises(InputError, match=message):
        measure_rectangle(square, weights=weights)
    with pytest.raises(InputError, match=message):
        measure_planes(square, weights=weights)
