"""Frame preparation: the finer, surface-smoothed keyframe cloud (methods.md §5.4)."""

from __future__ import annotations

import numpy as np
import pytest

from spacepose.core import se3
from spacepose.core.cloud import PointCloud
from spacepose.core.frame_preparation import FramePreparer
from spacepose.core.sim.grid import grid_scenario
from spacepose.core.sim.scenarios import simulate
from spacepose.core.tracker import Tracker
from spacepose.core.tracker_config import TrackerConfig
from spacepose.errors import InputError
from spacepose.tools.experiments.robustness_cells import mesh_path


def _noisy_plane(seed: int, sigma: float) -> tuple[np.ndarray, np.ndarray, float]:
    """A 0.6 m square tilted 30° at 1.2 m, 2.5 mm grid, noise ``sigma`` m along its normal."""
    rng = np.random.default_rng(seed)
    u = np.arange(-0.3, 0.3, 0.0025)
    g = np.stack(np.meshgrid(u, u), -1).reshape(-1, 2)
    c, s = np.cos(np.radians(30.0)), np.sin(np.radians(30.0))
    R = np.array([[1.0, 0.0, 0.0], [0.0, c, -s], [0.0, s, c]])
    normal = R[:, 2]
    pts = np.c_[g, np.zeros(len(g))] @ R.T + [0.0, 0.0, 1.2]
    pts += rng.normal(0.0, sigma, len(pts))[:, None] * normal
    return pts, normal, float(normal @ [0.0, 0.0, 1.2])


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_keyframe_cloud_is_finer_and_nearer_the_surface(seed):
    sigma = 0.002
    pts, normal, offset = _noisy_plane(seed, sigma)
    frames = FramePreparer(TrackerConfig(keyframe_density=3.0), None, workers=1)
    prepared = frames.prepare(pts, None)
    dense = frames.keyframe_cloud(prepared)
    assert dense is not None and dense.cloud.has_normals
    # Finer than the frame's voxel cloud (about 3,000 points), never finer than the spacing.
    assert len(dense.cloud) > 2 * len(prepared.cloud)
    assert len(dense.cloud) <= len(pts)
    # Each point moved onto its neighbourhood's plane. Measured (seeds 0-2): 0.35 σ from the
    # true plane; the frame's voxel centroids 1.00-1.04 σ, no nearer than a raw point: which
    # voxel a point falls in depends on its noise, so a centroid averages a selection, not the
    # noise. The bound is the measured 0.35 σ with a margin; what the test guards is that the
    # finer cloud stays well below both the raw noise and the voxel centroids.
    dist = dense.cloud.points @ normal - offset
    rms_voxel = np.sqrt(np.mean((prepared.cloud.points @ normal - offset) ** 2))
    rms = np.sqrt(np.mean(dist**2))
    assert rms < 0.45 * sigma and rms < 0.5 * rms_voxel


@pytest.mark.parametrize("stray_share", [1 / 16, 0.0])
def test_flying_pixels_are_dropped_from_frame_and_keyframe_or_left_in_place(stray_share):
    # Points 5-20 cm in front of the plane, far from each other: by default neither the
    # frame's voxels nor the keyframe's finer ones keep them. Kept (stray_share 0), they have
    # no neighbourhood within the search's bound, so no plane to move onto. Either way the
    # plane's points are smoothed as without them.
    pts, normal, offset = _noisy_plane(0, 0.002)
    rng = np.random.default_rng(5)
    stray = pts[rng.choice(len(pts), 40, replace=False)] - rng.uniform(0.05, 0.2, (40, 1)) * normal
    config = TrackerConfig(keyframe_density=3.0, isolate_target=False, stray_share=stray_share)
    frames = FramePreparer(config, None, workers=1)
    prepared = frames.prepare(np.vstack([pts, stray]), None)
    dense = frames.keyframe_cloud(prepared)
    d = dense.cloud.points @ normal - offset
    on_plane = np.abs(d) < 0.02
    off_frame = np.abs(prepared.cloud.points @ normal - offset) >= 0.02
    if stray_share > 0:
        assert on_plane.all() and not off_frame.any()
    else:
        assert np.count_nonzero(off_frame) == len(stray)
        kept = {tuple(p) for p in dense.cloud.points[~on_plane]}
        assert kept == {tuple(p) for p in stray}
    assert np.sqrt(np.mean(d[on_plane] ** 2)) < 0.45 * 0.002


def test_a_panel_thinner_than_the_model_cells_is_seen_from_both_sides():
    """A closed 0.5 m panel 10 µm thick, sampled on both faces: the model the tracker culls
    keeps each face wherever it was sampled, so from either side the visible model is that
    whole face (one point per cell kept one of the two faces and hid the panel in places)."""
    pts, _, _ = _noisy_plane(0, 0.002)
    frames = FramePreparer(TrackerConfig(), None, workers=1)
    frames.prepare(pts, None)  # sets the lengths: both faces lie in one row of model cells
    rng = np.random.default_rng(2)
    faces = {}
    for side in (1.0, -1.0):
        xy = rng.uniform(-0.25, 0.25, size=(8000, 2))
        normals = np.tile([0.0, 0.0, side], (8000, 1))
        faces[side] = PointCloud(np.c_[xy, np.full(8000, 1.5e-5 + 0.5e-5 * side)], normals)
    both = [np.vstack([getattr(f, a) for f in faces.values()]) for a in ("points", "normals")]
    model = frames.sensor_model(PointCloud(*both))
    for side, face in faces.items():
        alone = len(frames.sensor_model(face))
        assert np.count_nonzero(model.normals[:, 2] == side) == alone
        # The sensor 1.2 m off this face: it sees the face's points, none of the other's.
        T_sensor_target = se3.invert(se3.make_transform(np.eye(3), [0.0, 0.0, 1.2 * side]))
        seen = frames.visible_model(model, T_sensor_target).prepared.cloud
        assert len(seen) == alone and np.all(seen.points[:, 2] == face.points[0, 2])


def test_keyframe_cloud_needs_a_density_and_a_frame_finer_than_its_voxel():
    pts, _, _ = _noisy_plane(0, 0.002)
    own = FramePreparer(TrackerConfig(keyframe_density=1.0), None, workers=1)
    assert own.keyframe_cloud(own.prepare(pts, None)) is None
    # A voxel at the spacing (a sparse flash-LiDAR frame): nothing finer to give.
    sparse = FramePreparer(
        TrackerConfig(keyframe_density=3.0, points_per_frame=len(pts)), None, workers=1
    )
    prepared = sparse.prepare(pts, None)
    assert sparse.scale.voxel <= 2.0 * sparse.scale.spacing
    assert sparse.keyframe_cloud(prepared) is None


def test_li_jicp_registers_onto_the_frames_as_they_are():
    """Li's J-ICP registers a frame onto the two frames before it at their voxel (Li §2.3.2).
    Onto the finer keyframe clouds the default tracker uses, its point-to-point pairs drifted:
    over the lab run's 10 seeds (`spacepose experiment li-l3 --seeds 10`) its mean x error went
    from 3.97 to 12.1 mm, and y from 1.41 to 17.3 mm. The keyframe graph keeps its finer cloud."""
    pts, _, _ = _noisy_plane(0, 0.002)
    li = FramePreparer(TrackerConfig(method="jicp"), None, workers=1)
    assert li.keyframe_cloud(li.prepare(pts, None)) is None
    ours = FramePreparer(TrackerConfig(), None, workers=1)
    assert ours.keyframe_cloud(ours.prepare(pts, None)) is not None


def test_finer_keyframes_follow_the_panel_satellite_at_6_m_and_noise_x3():
    """The solar-panel satellite at 6 m, noise ×3, sliding 155 mm a frame (the robustness
    grid's worst clean cell before finer keyframes were the default): onto keyframes at its own
    voxel the registration stops short of the steps while flagged ok; onto finer keyframes it
    follows."""
    cell = grid_scenario(
        target=mesh_path("panels"),
        range_m=6.0,
        noise_scale=3.0,
        seed=0,
        frames=5,
    )
    sim = simulate(cell)
    frames = list(sim.frames())
    T0 = frames[0].T_sensor_target
    centroid = frames[0].cloud.points[frames[0].on_target].mean(axis=0)

    def errors(config: TrackerConfig) -> tuple[np.ndarray, np.ndarray, float]:
        """(centroid error m, rotation error deg) of frames 1-4, and the voxel."""
        tracker = Tracker(config, workers=1)
        t, r = [], []
        for f in frames:
            res = tracker.track_frame(f.cloud, f.timestamp)
            D = res.T_sensor_target @ se3.invert(f.T_sensor_target @ se3.invert(T0))
            t.append(np.linalg.norm(se3.transform_points(D, centroid[None])[0] - centroid))
            r.append(np.degrees(np.linalg.norm(se3.log(D)[:3])))
        return np.array(t[1:]), np.array(r[1:]), tracker.scale.voxel

    # Measured: the range noise (60 mm) grows the voxel from the spacing's 60 mm to 90 mm. Onto
    # finer keyframes: 8-12 mm and 0.15-0.26° off; at density 1: 5-32 mm and 0.66-2.0°. (At the
    # 60 mm voxel: 0.6-6.1 mm but 0.63-1.12° with finer keyframes, 38-183 mm at density 1.)
    coarse_t, coarse_r, _ = errors(TrackerConfig(keyframe_density=1.0))
    fine_t, fine_r, voxel = errors(TrackerConfig())
    assert voxel > 0.085
    assert fine_t.max() < 0.015 and fine_r.max() < 0.35
    assert coarse_r.max() > 1.5 and coarse_t.max() > 0.025


def test_finer_keyframes_on_the_real_lidar_pair():
    """The real LiDAR pair of data/real (a room, 57 mm voxels, 12 mm spacing): the source
    tracked after the target, model-free, with the whole frame (no target to isolate), against
    small_gicp's reference transform. Measured: 15.2 mm / 0.365° with finer keyframes (the
    default), 15.5 mm / 0.369° without; small_gicp's own test asks for 0.05 m and 0.05 rad.
    (With the finer cloud's own normals, 11.3 mm / 0.158°: methods.md §5.4 says why not.)"""
    from pathlib import Path

    from scipy.spatial.transform import Rotation

    from spacepose.tools.cloud_io import read_cloud

    pair = Path(__file__).resolve().parents[1] / "data" / "real" / "small_gicp"
    T_ref = np.loadtxt(pair / "T_target_source.txt")

    def error(density: float) -> tuple[float, float]:
        tracker = Tracker(TrackerConfig(keyframe_density=density, isolate_target=False), workers=1)
        tracker.track_frame(read_cloud(pair / "target.ply"), 0.0)
        result = tracker.track_frame(read_cloud(pair / "source.ply"), 1.0)
        D = se3.invert(result.T_sensor_target) @ se3.invert(T_ref)
        return float(np.linalg.norm(D[:3, 3])), float(Rotation.from_matrix(D[:3, :3]).magnitude())

    fine, coarse = error(3.0), error(1.0)
    assert fine[0] < 0.02 and np.degrees(fine[1]) < 0.4
    # Finer keyframes cost no accuracy on a real scanner's frames.
    assert fine[0] <= coarse[0] and fine[1] <= coarse[1]


def test_a_raw_frame_keeps_its_surfaces_and_not_its_flying_pixels():
    """The lab mock-up before its wall at 640×480, every pixel a point: after the first frame
    the crop is a sphere around the predicted target, and the flying pixels at its silhouette
    (mixed between the mock-up and the wall) fall in it. Measured (seeds 0-2): 0.09-0.19 %
    (frame) and 0.03-0.07 % (keyframe) of the points farther than a voxel from every true
    surface point, against 9.0-9.4 % and 2.9-3.1 % with every voxel kept."""
    from scipy.spatial import cKDTree

    from spacepose.tools.bench_fullres import raw_frames

    first, _, frame = raw_frames(640, 480, 3, seed=0)
    frames = FramePreparer(TrackerConfig(), None, workers=1)
    frames.prepare(first.cloud, None)
    T_predicted = frame.T_sensor_target @ se3.invert(first.T_sensor_target)
    prepared = frames.prepare(frame.cloud, T_predicted)
    surface = cKDTree(frame.cloud.points[~frame.flying])
    voxel = frames.lengths.voxel
    for cloud in (prepared.cloud, frames.keyframe_cloud(prepared).cloud):
        off = surface.query(cloud.points, distance_upper_bound=voxel)[0] > voxel
        assert off.mean() < 0.005


def test_a_frame_with_nothing_where_the_target_is_predicted_is_refused_by_name():
    # The crop keeps only the points within the target's sphere carried by the prediction: a
    # frame whose points all lie elsewhere is unusable (a typed error naming the frame), and
    # the frame after it, back where the target is, is prepared as before.
    plane, _, _ = _noisy_plane(0, 0.002)
    # A wall 1 m behind it: the frame holds more than the object, so later frames are cropped.
    wall = np.c_[np.random.default_rng(1).uniform(-1.5, 1.5, (20000, 2)), np.full(20000, 2.5)]
    pts = np.r_[plane, wall]
    frames = FramePreparer(TrackerConfig(), None, workers=1)
    first = frames.prepare(pts, None)
    assert first.cloud.points[:, 2].max() < 2.0  # the plane, not the wall
    away = se3.make_transform(np.eye(3), [5.0, 0.0, 0.0])
    elsewhere = PointCloud(se3.transform_points(away, pts), source="frame_0042.ply")
    with pytest.raises(InputError, match=r"frame_0042\.ply.*no point within .* m of where"):
        frames.prepare(elsewhere, np.eye(4))
    again = frames.prepare(pts, np.eye(4))
    np.testing.assert_array_equal(again.cloud.points, first.cloud.points)


def test_an_earth_far_behind_the_target_leaves_the_track_as_it_was():
    """The lab mock-up at 1.2 m with a renderer's Earth 400 km behind it in 40 % of the view:
    every frame was lost ("cells of 0.0101 m are too many to number ... 1.04e+06 m"); now the
    poses and statuses are those of the frames without it, to the bit."""
    from test_segmentation import earth_behind

    config = grid_scenario(target=mesh_path("lab"), range_m=1.2, frames=4)
    frames = [simulate(config).frame(k) for k in range(4)]
    rng = np.random.default_rng(0)
    alone, with_earth = Tracker(TrackerConfig(), workers=2), Tracker(TrackerConfig(), workers=2)
    for frame in frames:
        pts = frame.cloud.points
        earth = earth_behind(pts, 0.4, rng)
        assert len(earth) > 0.3 * len(pts)
        seen = PointCloud(np.r_[pts, earth])
        got = with_earth.track_frame(seen, frame.timestamp)
        want = alone.track_frame(frame.cloud, frame.timestamp)
        assert got.status == want.status != "lost"
        np.testing.assert_array_equal(got.T_sensor_target, want.T_sensor_target)
