"""Tests of the simulator (methods.md §3): targets, sensor noise, scenario motion, orbit truth."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh
from scipy import ndimage
from scipy.spatial import cKDTree
from scipy.spatial.transform import Rotation

from spacepose.core import dynamics, se3
from spacepose.core.sim import (
    TRUTH_COLUMNS,
    LabConfig,
    OrbitConfig,
    Target,
    lab_target,
    load_mesh,
    mean_motion,
    orbit_target,
    sample_surface,
    scenario_config,
    sensor_config,
    simulate_lab,
    simulate_orbit,
    symmetric_orbit_target,
)
from spacepose.core.sim.sensors import scan, sigma_at
from spacepose.errors import ConfigError, FileFormatError, InputError

SMALL_TOF = {"width": 320, "height": 240, "focal_px": 241.8}  # same field of view, 1/4 the rays
HUBBLE = str(Path(__file__).resolve().parents[1] / "data" / "models" / "hubble_model_kit.obj")


def _wall(distance: float) -> trimesh.Trimesh:
    """A 40 m square wall facing the sensor, its front face at z = distance (sensor frame)."""
    return trimesh.creation.box(bounds=[(-20.0, -20.0, distance), (20.0, 20.0, distance + 0.1)])


# --------------------------------------------------------------------------------------------
# Targets


@pytest.mark.parametrize("make", [lab_target, orbit_target, symmetric_orbit_target])
def test_rectangle_corners_are_mesh_vertices_and_normals_point_out(make) -> None:
    target = make()
    vertices = cKDTree(target.mesh.vertices)
    for rect in target.rectangles:
        R = rect.R_model_plane
        assert np.allclose(R.T @ R, np.eye(3), atol=1e-12) and np.linalg.det(R) > 0
        assert rect.a <= rect.b
        signs = np.array([[1, 1], [1, -1], [-1, 1], [-1, -1]]) * 0.5
        corners = rect.center + signs[:, :1] * rect.a * R[:, 0] + signs[:, 1:] * rect.b * R[:, 1]
        dist, _ = vertices.query(corners)
        assert dist.max() < 1e-9, rect.name
        # Outward normal: 1 mm behind the face is inside a part, 1 mm in front is outside all.
        probe = rect.center + 0.25 * rect.a * R[:, 0] + 0.25 * rect.b * R[:, 1]
        behind = [p.contains([probe - 1e-3 * R[:, 2]])[0] for p in target.parts]
        front = [p.contains([probe + 1e-3 * R[:, 2]])[0] for p in target.parts]
        assert any(behind) and not any(front), rect.name


@pytest.mark.parametrize("make", [orbit_target, symmetric_orbit_target])
def test_orbit_catalogue_sizes_are_distinct_and_match_the_spec(make) -> None:
    rects = make().rectangles
    sizes = {r.name: (round(r.a, 9), round(r.b, 9)) for r in rects}
    assert sizes["bus+z"] == sizes["bus-z"] == (1.8, 2.4)
    assert sizes["bus+y"] == sizes["bus-y"] == (1.4, 2.4)
    assert sizes["bus+x"] == sizes["bus-x"] == (1.4, 1.8)
    assert sizes["wing_front"] == sizes["wing_back"] == (2.0, 6.0)
    front = next(r for r in rects if r.name == "wing_front")
    assert np.allclose(front.R_model_plane[:, 2], (0, 0, 1))
    if make is symmetric_orbit_target:
        assert len(set(sizes.values())) == 4 and len(rects) == 8
        return
    # The default target adds the antenna panel's two faces, a fifth size.
    assert sizes["antenna_front"] == sizes["antenna_back"] == (0.8, 1.2)
    assert len(set(sizes.values())) == 5 and len(rects) == 10
    panel = next(r for r in rects if r.name == "antenna_front")
    np.testing.assert_allclose(panel.center, (0.02, -1.9, 0.5), atol=1e-12)
    np.testing.assert_allclose(panel.R_model_plane[:, 2], (1, 0, 0))


def test_lab_target_is_not_symmetric() -> None:
    # A symmetric body maps onto itself under a 180° turn about a principal axis through its
    # centroid. Compare a second, independent sample with the first: unturned, no point is 1 cm
    # from the first sample; turned about each principal axis, a large share must be.
    target = lab_target()
    a = sample_surface(target, 20000, seed=1).points
    b = sample_surface(target, 20000, seed=2).points
    centroid = a.mean(axis=0)
    _, axes = np.linalg.eigh((a - centroid).T @ (a - centroid))
    tree = cKDTree(a - centroid)
    assert np.mean(tree.query(b - centroid)[0] > 0.01) == 0.0
    for axis in axes.T:
        turned = (b - centroid) @ Rotation.from_rotvec(np.pi * axis).as_matrix().T
        assert np.mean(tree.query(turned)[0] > 0.01) > 0.3


def test_sample_surface_drops_points_hidden_inside_another_part() -> None:
    big = trimesh.creation.box((1.0, 1.0, 1.0))
    small = trimesh.creation.box((0.5, 0.5, 0.5)).apply_translation((0.5, 0.0, 0.0))
    target = Target("two boxes", trimesh.util.concatenate([big, small]), parts=(big, small))
    cloud = sample_surface(target, 40000, seed=3)
    p = cloud.points
    inside_big = np.all(np.abs(p) < 0.5 - 1e-9, axis=1)
    inside_small = np.all(np.abs(p - (0.5, 0, 0)) < 0.25 - 1e-9, axis=1)
    assert not inside_big.any() and not inside_small.any()
    # Hidden: the big box's +x patch under the small box (0.25 m²), the small box's −x face
    # (0.25) and the inner halves of its four sides (4 × 0.125). Visible 6.5 of 7.5 m².
    share = len(cloud) / 40000
    assert share == pytest.approx(6.5 / 7.5, abs=4 * np.sqrt(share * (1 - share) / 40000))


def test_load_mesh_scales_and_centres() -> None:
    raw = trimesh.load(HUBBLE, force="mesh")
    target = load_mesh(HUBBLE, scale=0.005)
    assert np.allclose(target.mesh.extents, raw.extents * 0.005, rtol=1e-9)
    assert np.allclose(target.mesh.bounds.mean(axis=0), 0.0, atol=1e-12)
    assert target.rectangles == ()


def test_load_mesh_bad_input(tmp_path) -> None:
    with pytest.raises(FileFormatError, match="cannot read the mesh: no such file"):
        load_mesh(tmp_path / "missing.obj")
    with pytest.raises(FileFormatError, match="unknown mesh extension"):
        load_mesh(tmp_path / "model.xyz")
    empty = tmp_path / "empty.obj"
    empty.write_text("# nothing here\n")
    with pytest.raises(FileFormatError, match=r"empty\.obj"):
        load_mesh(empty)
    with pytest.raises(InputError, match="scale"):
        load_mesh(HUBBLE, scale=-1.0)
    with pytest.raises(InputError, match="count"):
        sample_surface(lab_target(), 0)


@pytest.mark.parametrize(
    "corners",
    [
        "v 0 0 0\nv 1 0 0\nv 2 0 0\n",  # on one line
        "v 0 0 0\nv 0.1 0.2 0.3\nv 0.3 0.6 0.9\n",  # on one line, up to rounding
        "v 1 1 1\nv 1 1 1\nv 1 1 1\n",  # one point
    ],
)
def test_a_mesh_of_zero_area_triangles_is_refused_up_front(tmp_path, corners) -> None:
    """Every triangle of zero area: `simulate lab --model` failed at frame 0 with "the sensor
    sees nothing", which pointed at the range and the scale, not at the mesh."""
    path = tmp_path / "degen.obj"
    path.write_text(corners + "f 1 2 3\nf 3 2 1\n")
    with pytest.raises(FileFormatError) as info:
        load_mesh(path)
    assert str(info.value) == f"{path}: all 2 triangles have zero area: no surface to render"
    # One triangle with an area is a surface, however small.
    path.write_text(corners + "v 0 1e-6 0\nv 1e-6 0 0\nf 1 2 3\nf 4 5 1\n")
    assert len(load_mesh(path).mesh.faces) == 2


# --------------------------------------------------------------------------------------------
# Sensors


@pytest.mark.parametrize("distance", [1.0, 2.0, 4.0])
def test_tof_range_noise_on_a_flat_wall_matches_sigma_r(distance: float) -> None:
    cfg = sensor_config("tof", **SMALL_TOF)
    s = scan(_wall(distance), cfg, np.random.default_rng(7))
    d = s.points / np.linalg.norm(s.points, axis=1, keepdims=True)
    true_range = distance / d[:, 2]
    residual = np.linalg.norm(s.points, axis=1) - true_range
    sigma_model = 0.5e-3 + 0.5e-3 * true_range**2
    assert np.std(residual / sigma_model) == pytest.approx(1.0, rel=0.05)
    centre = true_range < distance * 1.01  # near the boresight, where r ≈ distance
    assert centre.sum() > 1000
    assert np.std(residual[centre]) == pytest.approx(0.5e-3 * (1 + distance**2), rel=0.05)
    assert np.allclose(s.sigma, sigma_at(cfg, true_range), rtol=1e-9)
    assert abs(np.mean(residual / sigma_model)) < 4 / np.sqrt(len(residual))
    # 1 % dropouts: binomial, 4 standard deviations.
    n_pix = cfg.width * cfg.height
    assert abs(1 - len(s.points) / n_pix - 0.01) < 4 * np.sqrt(0.01 * 0.99 / n_pix)
    assert not s.flying.any()


def test_gaussian_sensor_is_isotropic() -> None:
    cfg = sensor_config("gaussian", sigma_const=2e-3, **SMALL_TOF)
    s = scan(_wall(1.5), cfg, np.random.default_rng(8))
    directions = s.points / np.linalg.norm(s.points, axis=1, keepdims=True)
    # The true point is on the wall along the ray; the noise is everything else. Recover it from
    # the z error alone is impossible, so re-cast noise-free and compare pixel by pixel.
    clean = scan(_wall(1.5), cfg.model_copy(update={"noise_scale": 0.0}), None)
    errors = s.points - clean.points[np.searchsorted(clean.pixel, s.pixel)]
    assert np.allclose(np.std(errors, axis=0), 2e-3, rtol=0.05)
    assert len(s.points) == len(clean.points) == cfg.width * cfg.height
    assert directions.shape == s.points.shape


def test_noise_scale_zero_gives_exact_points_without_artefacts() -> None:
    cfg = sensor_config("tof", noise_scale=0.0, **SMALL_TOF)
    s = scan(_wall(2.0), cfg, None)
    assert len(s.points) == cfg.width * cfg.height
    assert np.abs(s.points[:, 2] - 2.0).max() < 1e-12
    assert np.all(s.sigma == 0)
    with pytest.raises(ConfigError, match="seeded random generator"):
        scan(_wall(2.0), sensor_config("tof", **SMALL_TOF), None)


def test_flying_pixels_mix_the_two_depths_at_edges_only() -> None:
    # A 1 m square plate at 1.5 m in front of the wall at 2 m: a 0.5 m jump along its outline.
    scene = trimesh.util.concatenate(
        [_wall(2.0), trimesh.creation.box(bounds=[(-0.5, -0.5, 1.5), (0.5, 0.5, 1.6)])]
    )
    cfg = sensor_config("tof", dropout=0.0, sigma_const=0.0, sigma_quad=0.0, **SMALL_TOF)
    s = scan(scene, cfg, np.random.default_rng(9))
    z = s.points[:, 2]
    flat = ~s.flying
    assert np.all(np.isclose(z[flat], 1.5, atol=1e-12) | np.isclose(z[flat], 2.0, atol=1e-12))
    # Edge pixels: their 3×3 window of true ranges spans the jump; a flying pixel's range lies
    # between the window's nearest and farthest range, and about half the edge pixels fly.
    clean = scan(scene, cfg.model_copy(update={"noise_scale": 0.0}), None)
    img = np.linalg.norm(clean.points, axis=1).reshape(cfg.height, cfg.width)
    near = ndimage.minimum_filter(img, 3).ravel()
    far = ndimage.maximum_filter(img, 3).ravel()
    edge = far - near > 0.05
    fly = s.pixel[s.flying]
    r_fly = np.linalg.norm(s.points[s.flying], axis=1)
    assert np.all(edge[fly]) and np.all((r_fly >= near[fly]) & (r_fly <= far[fly]))
    n_edge = int(edge.sum())
    assert abs(len(fly) - 0.5 * n_edge) < 4 * np.sqrt(0.25 * n_edge)
    assert np.mean((z[s.flying] > 1.51) & (z[s.flying] < 1.99)) > 0.9  # off both surfaces


def test_sensor_presets_and_bad_names() -> None:
    lidar = sensor_config("flash-lidar")
    assert (lidar.width, lidar.height) == (160, 160)
    assert lidar.fov_deg[0] == pytest.approx(30.0, abs=1e-12)
    assert sensor_config("tof").fov_deg[0] == pytest.approx(67.0, abs=0.5)
    with pytest.raises(ConfigError, match="unknown sensor 'sonar'"):
        sensor_config("sonar")
    with pytest.raises(ConfigError, match="noise_scale"):
        sensor_config("tof", noise_scale=-1.0)


# --------------------------------------------------------------------------------------------
# Lab scenario


def test_lab_motion_is_570_mm_and_57_degrees_about_the_vertical() -> None:
    sim = simulate_lab()
    assert len(sim) == 58
    assert np.array_equal(sim.timestamps, np.arange(58.0))
    T0, T1 = sim.T_sensor_target[0], sim.T_sensor_target[-1]
    assert np.linalg.norm(T1[:3, 3] - T0[:3, 3]) == pytest.approx(0.570, abs=1e-12)
    assert np.allclose(T1[:3, 3] - T0[:3, 3], (0.570, 0, 0), atol=1e-12)
    rotvec = Rotation.from_matrix(T1[:3, :3] @ T0[:3, :3].T).as_rotvec()
    assert np.degrees(np.linalg.norm(rotvec)) == pytest.approx(57.0, abs=1e-9)
    assert np.allclose(rotvec / np.linalg.norm(rotvec), (0, -1, 0), atol=1e-12)
    # Centred travel: the middle of the slide is on the boresight.
    assert np.mean(sim.T_sensor_target[:, 0, 3]) == pytest.approx(0.0, abs=1e-12)


def test_lab_target_stays_in_view_in_every_frame() -> None:
    sim = simulate_lab()
    cfg = sim.sensor
    for T in sim.T_sensor_target:
        v = se3.transform_points(T, sim.target.mesh.vertices)
        u = v[:, 0] / v[:, 2] * cfg.focal_px + 0.5 * (cfg.width - 1)
        w = v[:, 1] / v[:, 2] * cfg.focal_px + 0.5 * (cfg.height - 1)
        assert u.min() > 0 and u.max() < cfg.width - 1 and w.min() > 0 and w.max() < cfg.height - 1


def test_noise_free_lab_points_lie_on_the_posed_mesh() -> None:
    o3d = pytest.importorskip("open3d")
    full = simulate_lab(LabConfig(sensor=sensor_config("tof", noise_scale=0.0)))
    small = simulate_lab(LabConfig(sensor=sensor_config("tof", noise_scale=0.0, **SMALL_TOF)))
    for sim, k in ((full, 57), (small, 0)):
        frame = sim.frame(k)
        points = frame.cloud.points
        assert frame.on_target.all() and len(points) > 4000
        mesh = sim.target.mesh.copy().apply_transform(frame.T_sensor_target)
        # Open3D (float32) names the nearest triangle of each point; the distance to that
        # triangle, computed in float64 by trimesh, bounds the distance to the mesh from above.
        scene = o3d.t.geometry.RaycastingScene()
        scene.add_triangles(
            o3d.core.Tensor(mesh.vertices.astype(np.float32)),
            o3d.core.Tensor(mesh.faces.astype(np.uint32)),
        )
        nearest = scene.compute_closest_points(o3d.core.Tensor(points.astype(np.float32)))
        tri = mesh.triangles[nearest["primitive_ids"].numpy().astype(np.int64)]
        on_tri = trimesh.triangles.closest_point(tri, points)
        assert np.linalg.norm(points - on_tri, axis=1).max() <= 1e-6


def test_model_cloud_lands_on_the_frame_under_the_true_pose() -> None:
    sim = simulate_lab(LabConfig(sensor=sensor_config("tof", noise_scale=0.0)))
    model = sim.model_cloud()
    assert model.has_normals and np.allclose(np.linalg.norm(model.normals, axis=1), 1.0)
    spacing = np.sqrt(sim.target.mesh.area / len(model))  # mean sample spacing, ~4.3 mm
    frame = sim.frame(20)

    def distances(T_sensor_target):
        posed = model.transformed(T_sensor_target)
        dist, idx = cKDTree(posed.points).query(frame.cloud.points)
        offset = frame.cloud.points - posed.points[idx]
        return dist, np.abs(np.einsum("ij,ij->i", offset, posed.normals[idx]))

    dist, plane = distances(frame.T_sensor_target)
    assert np.median(dist) < 0.6 * spacing and np.percentile(dist, 99) < 1.5 * spacing
    # The nearest sample is on the same flat facet for most points: zero point-to-plane gap.
    assert np.percentile(plane, 90) < 1e-9
    # 1 mm off along each axis: the facets no longer coincide.
    shifted = se3.make_transform(np.eye(3), (0.001, 0.001, 0.001)) @ frame.T_sensor_target
    assert np.median(distances(shifted)[1]) > 3e-4


def test_lab_background_adds_wall_and_turntable_but_target_points_are_unchanged() -> None:
    clean = sensor_config("tof", noise_scale=0.0, **SMALL_TOF)
    plain = simulate_lab(LabConfig(sensor=clean)).frame(3)
    busy = simulate_lab(LabConfig(sensor=clean, background=True)).frame(3)
    assert busy.on_target.sum() == len(plain.cloud)
    assert np.array_equal(busy.cloud.points[busy.on_target], plain.cloud.points)
    back = busy.cloud.points[~busy.on_target]
    assert np.isclose(back[:, 2], 2.0, atol=1e-12).sum() > 0.5 * len(back)  # the wall
    assert (back[:, 2] < 2.0 - 1e-6).sum() > 500  # turntable and plinth in front of the wall


def test_frames_are_reproducible_and_depend_on_the_seed() -> None:
    small = sensor_config("tof", **SMALL_TOF)
    a = simulate_lab(LabConfig(sensor=small, frames=4, seed=5))
    b = simulate_lab(LabConfig(sensor=small, frames=4, seed=5))
    c = simulate_lab(LabConfig(sensor=small, frames=4, seed=6))
    assert np.array_equal(a.frame(2).cloud.points, b.frame(2).cloud.points)
    assert not np.array_equal(a.frame(2).cloud.points, c.frame(2).cloud.points)
    assert not np.array_equal(a.frame(1).cloud.points, a.frame(2).cloud.points)
    with pytest.raises(ConfigError, match="out of range"):
        a.frame(4)


def test_frame_crlb_matches_an_independent_fisher_matrix() -> None:
    sim = simulate_lab(LabConfig(sensor=sensor_config("tof", **SMALL_TOF), frames=2))
    frame = sim.frame(0)
    keep = frame.on_target & ~frame.flying
    p, n = frame.cloud.points[keep], frame.true_normals[keep]
    r = np.linalg.norm(p, axis=1)
    # methods.md §4: σ_i = σ_r(r)·|cos θ_i|; σ_r at the measured range (≈ true range to 1e-3).
    sigma = (0.5e-3 + 0.5e-3 * r**2) * np.abs(np.einsum("ij,ij->i", p / r[:, None], n))
    h = np.hstack([np.cross(p, n), n])
    fisher = np.einsum("ni,nj->ij", h / sigma[:, None] ** 2, h)
    bound = frame.crlb()
    assert bound.rank == 6
    assert np.allclose(bound.std, np.sqrt(np.diag(np.linalg.inv(fisher))), rtol=1e-2)
    assert np.allclose(frame.crlb(frame_to_frame=True).std, np.sqrt(2) * bound.std, rtol=1e-9)
    clean = simulate_lab(
        LabConfig(sensor=sensor_config("tof", noise_scale=0.0, **SMALL_TOF), frames=1)
    )
    with pytest.raises(ConfigError, match="noise-free"):
        clean.frame(0).crlb()


# --------------------------------------------------------------------------------------------
# Orbit scenario


def test_orbit_truth_is_near_cw_but_not_cw_and_rotates_torque_free() -> None:
    config = OrbitConfig(frames=20)
    sim = simulate_orbit(config)
    truth = sim.truth
    assert truth.shape == (20, 20)
    assert ",".join(TRUTH_COLUMNS) == (
        "t,rho_x,rho_y,rho_z,v_x,v_y,v_z,qx,qy,qz,qw,w_x,w_y,w_z,k_x,k_y,k_z,com_x,com_y,com_z"
    )
    n = mean_motion(500e3)
    assert n == pytest.approx(1.107e-3, rel=1e-3)
    assert np.allclose(truth[0, 1:4], (25.0, 0.0, 0.0))
    assert np.linalg.norm(truth[0, 4:7]) == pytest.approx(0.002, rel=1e-9, abs=0)
    assert sim.scenario()["mean_motion"] == pytest.approx(n, rel=1e-12, abs=0)
    # Not the filter's model: J2's differential pull takes ρ off CW, by about ½ (∂a/∂r) ρ t²
    # (∂a/∂r ≈ 6.7e-9 s⁻² at 500 km); without J2 only CW's second-order term is left.
    t19 = truth[19, 0]
    gap = np.linalg.norm(truth[19, 1:4] - (dynamics.cw_stm(n, t19) @ truth[0, 1:7])[:3])
    assert 1e-6 < gap < 6.7e-9 * 25.0 * t19**2
    kepler = simulate_orbit(OrbitConfig(frames=20, j2=False)).truth
    gap = np.linalg.norm(kepler[19, 1:4] - (dynamics.cw_stm(n, t19) @ kepler[0, 1:7])[:3])
    assert gap < 1e-6
    # Torque-free: kinetic energy and |angular momentum| are conserved.
    inertia = np.array(config.inertia)
    w = truth[:, 11:14]
    energy = 0.5 * np.einsum("ni,i,ni->n", w, inertia, w)
    momentum = np.linalg.norm(w * inertia, axis=1)
    assert np.ptp(energy) / energy[0] < 1e-9 and np.ptp(momentum) / momentum[0] < 1e-9
    # The inertial angular momentum vector R_I_B (I ω) is constant too.
    h_I = Rotation.from_quat(truth[:, 7:11]).apply(w * inertia)
    assert np.abs(h_I - h_I[0]).max() / momentum[0] < 1e-8
    assert np.allclose(w[0], np.radians([1.0, -2.0, 1.5]), atol=1e-15)
    assert np.allclose(truth[:, 14:17], [1 / 6, -0.4, 0.25], atol=1e-15)
    assert np.allclose(truth[:, 17:20], [0.02, -0.03, 0.05], atol=1e-15)


def test_eccentric_orbit_run_gives_the_filter_its_mean_motion() -> None:
    sim = simulate_orbit(OrbitConfig(frames=5, eccentricity=0.05))
    a = (6378137.0 + 500e3) / 0.95
    n = np.sqrt(3.986004418e14 / a**3)
    assert sim.scenario()["mean_motion"] == pytest.approx(n, rel=1e-12, abs=0)
    assert np.allclose(sim.truth[0, 1:4], (25.0, 0.0, 0.0), atol=1e-12)
    assert sim.scenario()["process_noise"]["sigma_accel"] > 0


def test_orbit_filter_knows_chaser_attitude_and_catalogue_with_seeded_errors() -> None:
    s = simulate_orbit(OrbitConfig(frames=2, seed=4)).scenario()
    R_known, R_true = np.array(s["R_O_C"]), np.array(s["R_O_C_true"])
    angle = np.degrees(Rotation.from_matrix(R_true.T @ R_known).magnitude())
    assert 0 < angle < 5 * 0.01 * np.sqrt(3)  # 0.01° 1σ per axis
    assert s == simulate_orbit(OrbitConfig(frames=2, seed=4)).scenario()  # seeded
    assert s["rectangles_true"] == [r.to_dict() for r in orbit_target().rectangles]
    for known, true in zip(s["rectangles"], s["rectangles_true"], strict=True):
        offsets = np.r_[np.subtract(known["center"], true["center"]), known["a"] - true["a"]]
        assert known["name"] == true["name"] and 0 < np.abs(offsets).max() < 5 * 0.002
    exact = simulate_orbit(OrbitConfig(frames=2, chaser_attitude_sigma_deg=0, catalogue_sigma_m=0))
    assert exact.scenario()["R_O_C"] == exact.scenario()["R_O_C_true"]
    assert exact.scenario()["rectangles"] == exact.scenario()["rectangles_true"]


def test_orbit_pose_is_consistent_with_rho_q_com_offset_and_R_O_C() -> None:
    sim = simulate_orbit(OrbitConfig(frames=20))
    R_O_C = np.array(sim.scenario()["R_O_C_true"])  # the truth's; the filter's is off a little
    assert np.allclose(R_O_C @ (0, 0, 1), (1, 0, 0))  # boresight along the flight direction
    assert np.allclose(R_O_C @ (0, 1, 0), (0, 0, 1))  # image down towards the Earth
    n = sim.scenario()["mean_motion"]
    for k in (0, 7, 19):
        t, rho = sim.truth[k, 0], sim.truth[k, 1:4]
        R_I_B = Rotation.from_quat(sim.truth[k, 7:11]).as_matrix()
        R_O_B = dynamics.R_I_O(n, t).T @ R_I_B
        delta = sim.truth[k, 17:20]
        for rect in sim.target.rectangles:
            expected = R_O_C.T @ (rho + R_O_B @ (rect.center - delta))
            got = se3.transform_points(sim.T_sensor_target[k], rect.center[None])[0]
            assert np.allclose(got, expected, atol=1e-12)


def test_orbit_frames_see_the_target() -> None:
    sim = simulate_orbit(OrbitConfig(frames=20))
    counts = []
    for k in (0, 10, 19):
        frame = sim.frame(k)
        assert frame.on_target.all()
        counts.append(len(frame.cloud))
        # Range noise 1 cm along the ray at 25 m.
        assert np.allclose(frame.cloud.sigma, 0.01)
        assert np.linalg.norm(frame.cloud.points, axis=1).mean() == pytest.approx(25.0, abs=4.0)
    # Yu's Y4 has ~1800 points on the target; 160×160 px over 30° gives ~8.4 cm pixels at 25 m.
    assert 600 < min(counts) and max(counts) < 2500


def test_scenario_config_errors() -> None:
    with pytest.raises(ConfigError, match="unknown scenario 'moon'"):
        scenario_config("moon")
    with pytest.raises(ConfigError, match="background"):
        scenario_config("orbit", background=True)
    with pytest.raises(ConfigError, match="frames"):
        scenario_config("lab", frames=0)
    cfg = scenario_config("orbit", sensor="tof", noise_scale=0.5, frames=3)
    assert cfg.sensor.model == "tof" and cfg.sensor.noise_scale == 0.5 and cfg.frames == 3


def test_cast_rays_recasts_a_ray_that_embree_puts_on_the_wrong_face(monkeypatch) -> None:
    # Embree works in float32 and can name a face the ray only grazes. Simulate that by an
    # intersector that answers face 0 for every ray: rays that miss face 0 in float64 must be
    # re-cast exactly (and then hit the face they really hit, or nothing).
    from spacepose.core.sim import sensors

    scene = trimesh.util.concatenate([_wall(2.0), _wall(1.0).apply_translation((25.0, 0, 0))])

    class WrongFace:
        def __init__(self, mesh):
            self.mesh = mesh

        def intersects_first(self, origins, directions):
            return np.zeros(len(directions), dtype=np.int64)

    cfg = sensor_config("tof", width=40, height=30, focal_px=30.225)
    directions = sensors.pixel_directions(cfg)
    expected = sensors.cast_rays(scene, directions)
    monkeypatch.setattr(sensors, "RayMeshIntersector", WrongFace)
    face, ranges, normals = sensors.cast_rays(scene, directions)
    assert np.array_equal(face >= 0, expected[0] >= 0)
    assert np.allclose(ranges, expected[1], rtol=1e-12)
    assert np.allclose(ranges * directions[:, 2], 2.0, atol=1e-12)  # all on the wall's front
    assert np.allclose(normals, (0, 0, -1))


def test_an_orbit_model_in_millimetres_is_named_as_such(tmp_path) -> None:
    """A 1 m box written in millimetres was told to "stand off farther" than its 866 m."""
    import trimesh

    from spacepose.core.sim import OrbitConfig, simulate_orbit
    from spacepose.errors import ConfigError

    trimesh.creation.box(extents=(1000.0, 1000.0, 1000.0)).export(tmp_path / "box_mm.obj")
    config = OrbitConfig(frames=2, model=str(tmp_path / "box_mm.obj"))
    with pytest.raises(ConfigError, match=r"\(866 m from its centre\); a model in millimetres\?"):
        simulate_orbit(config)


@pytest.mark.parametrize("config", [None, {"frames": 3}, "lab"])
def test_simulate_refuses_what_is_no_scenario_config(config) -> None:
    """None, a dict or a name ran the default orbit run (600 frames) without a word."""
    from spacepose.core.sim import simulate

    with pytest.raises(ConfigError, match="needs a LabConfig or an OrbitConfig"):
        simulate(config)
