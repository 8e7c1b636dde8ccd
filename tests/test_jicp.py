"""J-ICP: the Eq. 9 average, its pose-graph form, drift reduction, 500 frames, tracker state."""

from __future__ import annotations

import numpy as np
import pytest

from spacepose.core import se3
from spacepose.core.config import validate_config
from spacepose.core.gicp import GICPConfig, gicp
from spacepose.core.icp import ICPConfig, icp
from spacepose.core.jicp import JICPConfig, JointICP, average_three
from spacepose.core.posegraph import PoseGraphEdge, optimize_pose_graph
from spacepose.core.sim.targets import sample_surface
from spacepose.errors import ConfigError, InputError, RegistrationError
from test_icp import asymmetric_target, pose_error

ICP_CFG = ICPConfig(max_correspondence_distance=0.05)
GICP_CFG = GICPConfig(max_correspondence_distance=0.05)


@pytest.fixture(scope="module")
def sequence() -> tuple[list[np.ndarray], list[np.ndarray]]:
    """10 noisy frames (1000 points, σ = 3 mm) of a target tumbling 1.5°/frame at 3 m.

    Returns the clouds in the sensor frame and the true motions ``T_k0``.
    """
    rng = np.random.default_rng(0)
    target = asymmetric_target()
    axis = rng.normal(size=3)
    xi = np.concatenate([np.deg2rad(1.5) * axis / np.linalg.norm(axis), rng.normal(0, 0.005, 3)])
    T_sensor_target0 = se3.make_transform(np.eye(3), (0.0, 0.0, 3.0))
    frames, truth = [], []
    for k in range(10):
        T_sensor_target = T_sensor_target0 @ se3.exp(k * xi)  # body-frame twist: spins in place
        truth.append(T_sensor_target @ se3.invert(T_sensor_target0))
        pts = sample_surface(target, 1000, seed=k).points
        frames.append(se3.transform_points(T_sensor_target, pts + rng.normal(0, 0.003, pts.shape)))
    return frames, truth


def _mean_errors(poses: list[np.ndarray], truth: list[np.ndarray]) -> np.ndarray:
    """Mean rotation (deg) and translation (m) error of ``T_k0`` over the sequence."""
    return np.mean([pose_error(T, G) for T, G in zip(poses, truth, strict=True)], axis=0)


def _chained(frames: list[np.ndarray], registration: str) -> list[np.ndarray]:
    """Frame-to-frame registration chained, with the same constant-velocity guess as JointICP."""
    poses = [np.eye(4)]
    for k in range(1, len(frames)):
        init = poses[-1] @ se3.invert(poses[-2]) if k >= 2 else np.eye(4)
        if registration == "icp":
            res = icp(frames[k - 1], frames[k], init, ICP_CFG, workers=1)
        else:
            res = gicp(frames[k - 1], frames[k], init, GICP_CFG, workers=1)
        poses.append(res.T_target_source @ poses[-1])
    return poses


def test_average_three_consistent_and_midpoint(rng: np.random.Generator) -> None:
    T_ji, T_kj = se3.exp(rng.normal(0, 0.2, 6)), se3.exp(rng.normal(0, 0.2, 6))
    # Consistent measurements: the indirect path equals the direct one.
    np.testing.assert_allclose(average_three(T_kj, T_kj @ T_ji, T_ji), T_kj, atol=1e-12)
    # Inconsistent: the result is the midpoint, equally far (in twist) from both estimates.
    T_ki = se3.exp(rng.normal(0, 0.05, 6)) @ T_kj @ T_ji
    M = average_three(T_kj, T_ki, T_ji)
    direct = se3.log(T_kj @ se3.invert(M))
    indirect = se3.log(T_ki @ se3.invert(T_ji) @ se3.invert(M))
    np.testing.assert_allclose(direct, -indirect, atol=1e-12)
    assert np.linalg.norm(direct) > 1e-3


def test_average_three_small_angle_form_of_eq9(rng: np.random.Generator) -> None:
    # Li's Eq. 9 in twist coordinates for small motions: (ξ_ki − ξ_ji + ξ_kj) / 2.
    s = 1e-4
    xi_ji, xi_kj, xi_ki = (s * rng.normal(size=6) for _ in range(3))
    M = average_three(se3.exp(xi_kj), se3.exp(xi_ki), se3.exp(xi_ji))
    first_order = 0.5 * (xi_ki - xi_ji + xi_kj)
    np.testing.assert_allclose(se3.log(M), first_order, atol=10 * s**2)
    assert np.abs(se3.log(M) - xi_kj).max() > 10 * s**2  # the average moved off T_kj


def test_pose_graph_with_equal_weights_is_eq9(rng: np.random.Generator) -> None:
    """Window i, j, k; i and j fixed with X_j = T_ji X_i; equal weights: X_k X_j⁻¹ = Eq. 9."""
    T_ji = se3.exp(rng.normal(0, 0.1, 6))
    T_kj = se3.exp(rng.normal(0, 0.1, 6))
    T_ki = se3.exp(rng.normal(0, 0.02, 6)) @ T_kj @ T_ji  # inconsistent loop
    X_i = se3.exp(rng.normal(0, 0.3, 6))
    X_j = T_ji @ X_i
    edges = [
        PoseGraphEdge(0, 1, T_ji, np.eye(6)),
        PoseGraphEdge(0, 2, T_ki, np.eye(6)),
        PoseGraphEdge(1, 2, T_kj, np.eye(6)),
    ]
    res = optimize_pose_graph(np.stack([X_i, X_j, T_kj @ X_j]), edges, fixed=(0, 1))
    np.testing.assert_allclose(
        res.poses[2] @ se3.invert(X_j), average_three(T_kj, T_ki, T_ji), atol=1e-9
    )


@pytest.mark.parametrize("method", ["point_to_point", "point_to_plane"])
def test_each_step_is_eq9_of_its_pairwise_registrations(sequence, method: str) -> None:
    """Frame k against k-1 and k-2; T_ji is frame j's own registration onto i (Li's Eq. 9)."""
    frames, _ = sequence
    icp_cfg = ICP_CFG.model_copy(update={"method": method})
    tracker = JointICP(JICPConfig(icp=icp_cfg), workers=1)
    steps = [tracker.step(f) for f in frames[:5]]
    assert steps[0].index == 0 and np.array_equal(steps[0].T_k0, np.eye(4))
    assert len(steps[1].pairwise) == 1 and all(len(s.pairwise) == 2 for s in steps[2:])
    np.testing.assert_allclose(steps[1].T_k0, steps[1].pairwise[0].T_target_source, atol=1e-12)
    for j, k in ((1, 2), (2, 3), (3, 4)):
        T_ki, T_kj = (r.T_target_source for r in steps[k].pairwise)
        T_ji = steps[j].pairwise[-1].T_target_source  # the direct registration of j onto i
        expected = average_three(T_kj, T_ki, T_ji)
        got = steps[k].T_k0 @ se3.invert(steps[j].T_k0)
        np.testing.assert_allclose(got, expected, atol=1e-9)


@pytest.mark.parametrize(
    ("registration", "ratio"),
    # Measured mean (rotation °, translation mm at 3 m range), chained -> J-ICP, this seed:
    #   ICP:  1.53 / 78.5 -> 0.30 / 9.6 (ratios 0.19, 0.12)
    #   GICP: 0.40 / 19.3 -> 0.30 / 12.0 (ratios 0.76, 0.62)
    [("icp", 0.4), ("gicp", 0.85)],
)
def test_joint_icp_reduces_drift(sequence, registration: str, ratio: float) -> None:
    frames, truth = sequence
    chained = _mean_errors(_chained(frames, registration), truth)
    cfg = JICPConfig(registration=registration, icp=ICP_CFG, gicp=GICP_CFG)
    tracker = JointICP(cfg, workers=1)
    joint = _mean_errors([tracker.step(f).T_k0 for f in frames], truth)
    assert np.all(joint < ratio * chained), (chained, joint)


def test_500_frames_stay_rigid_and_bounded() -> None:
    """A long run: every pose a proper rigid transform, the error bounded, σ growing slowly.

    200 points of the asymmetric target re-noised (σ = 3 mm) at every frame, tumbling 1.5° a
    frame (750° in all) at 3 m. Before the poses were projected back onto SE(3) the rotation
    lost orthonormality fourfold a frame and the run stopped at frame 15.
    """
    clouds, truth = _tumbling_run(500, 200, seed=3)
    tracker = JointICP(JICPConfig(icp=ICP_CFG), workers=1)
    errors, orthonormality, sigmas = [], [], []
    for cloud, T_k0 in zip(clouds, truth, strict=True):
        step = tracker.step(cloud)
        R = step.T_k0[:3, :3]
        orthonormality.append(np.abs(R.T @ R - np.eye(3)).max())
        errors.append(pose_error(step.T_k0, T_k0))
        sigmas.append(np.sqrt(np.diag(step.covariance)))
    assert step.index == 499
    assert max(orthonormality) < 1e-12
    errors = np.array(errors)
    # Measured: at most 0.47° and 20.7 mm, mean 0.21° and 7.4 mm (frame-to-frame ICP chained:
    # 0.55° and 24.7 mm, mean 0.26° and 11.0 mm): a slow drift, as any chain of frames has.
    assert errors[:, 0].max() < 0.6 and errors[:, 1].max() < 0.03
    assert errors[:, 0].mean() < 0.25 and errors[:, 1].mean() < 0.009
    # The chained covariance grows as a random walk (σ ∝ √k: measured 2.7-4.0× from frame 50
    # to 499, √10 = 3.2), never explodes.
    sigmas = np.array(sigmas)
    assert np.all(np.isfinite(sigmas)) and np.all(sigmas[-1] > 2 * sigmas[50])
    assert np.all(sigmas[-1] < 2 * np.sqrt(499 / 50) * sigmas[50])


def test_same_result_for_any_workers(sequence) -> None:
    frames, _ = sequence
    runs = []
    for workers in (1, 2):
        tracker = JointICP(JICPConfig(icp=ICP_CFG), workers=workers)
        runs.append(np.stack([tracker.step(f).T_k0 for f in frames[:4]]))
    np.testing.assert_array_equal(runs[0], runs[1])


def test_bad_frames_leave_the_tracker_unchanged(sequence) -> None:
    frames, _ = sequence
    clean = JointICP(JICPConfig(icp=ICP_CFG), workers=1)
    expected = [clean.step(f).T_k0 for f in frames[:4]]
    tracker = JointICP(JICPConfig(icp=ICP_CFG), workers=1)
    got = [tracker.step(f).T_k0 for f in frames[:3]]
    with pytest.raises(InputError, match="at least 3 points"):
        tracker.step(frames[3][:2])
    with pytest.raises(RegistrationError, match="correspondences"):
        tracker.step(frames[3] + 5.0)
    with pytest.raises(InputError, match="init_T_k_prev"):
        tracker.step(frames[3], init_T_k_prev=np.full((4, 4), np.nan))
    got.append(tracker.step(frames[3]).T_k0)
    np.testing.assert_array_equal(np.stack(got), np.stack(expected))
    with pytest.raises(ConfigError, match="registration"):
        validate_config(JICPConfig, {"registration": "ndt"})


def _tumbling_run(frames: int, points: int, seed: int) -> tuple[list[np.ndarray], np.ndarray]:
    """``points`` points of the asymmetric target re-noised (σ = 3 mm) at every frame, tumbling
    1.5° a frame about a random axis at 3 m; the clouds and the true ``T_k0`` (frames, 4, 4)."""
    rng = np.random.default_rng(seed)
    base = sample_surface(asymmetric_target(), points, seed=0).points
    axis = rng.normal(size=3)
    xi = np.concatenate([np.deg2rad(1.5) * axis / np.linalg.norm(axis), rng.normal(0, 0.005, 3)])
    T_sensor_target0 = se3.make_transform(np.eye(3), (0.0, 0.0, 3.0))
    clouds, truth = [], []
    for k in range(frames):
        T_sensor_target = T_sensor_target0 @ se3.exp(k * xi)
        clouds.append(
            se3.transform_points(T_sensor_target, base + rng.normal(0, 0.003, base.shape))
        )
        truth.append(T_sensor_target @ se3.invert(T_sensor_target0))
    return clouds, np.array(truth)


@pytest.mark.parametrize("frames", [40, pytest.param(500, marks=pytest.mark.slow)])
def test_tracker_method_jicp_chains_every_frame_with_health_and_sigma(frames: int) -> None:
    """The tracker's ``jicp``: each frame registered onto the frame before it (and the one
    before that), every pose rigid, health flags and σ that cover the error."""
    from spacepose.core.tracker import TrackerConfig, track_sequence

    clouds, truth = _tumbling_run(frames, 400, seed=3)
    out = track_sequence(clouds, 0.1 * np.arange(frames), TrackerConfig(method="jicp"), workers=1)
    assert [r.reference_index for r in out.results[1:]] == list(range(frames - 1))
    R = out.trajectory.poses[:, :3, :3]
    assert np.abs(np.swapaxes(R, 1, 2) @ R - np.eye(3)).max() < 1e-12
    statuses = [r.status for r in out.results]
    # Measured, 500 frames: 496 ok, 4 degraded; at most 1.19° and 58 mm off (mean 0.49° and
    # 23 mm: 400 points of a 0.8 m target at 3 m), every frame within 3σ.
    assert statuses.count("lost") == 0 and statuses.count("ok") >= 0.95 * frames
    errors = np.array(
        [pose_error(r.T_sensor_target, G) for r, G in zip(out.results, truth, strict=True)]
    )
    assert errors[:, 0].max() < 1.5 and errors[:, 1].max() < 0.075
    within = [
        np.all(np.abs(se3.log(r.T_sensor_target @ se3.invert(G))) <= 3 * r.sigma)
        for r, G in zip(out.results[1:], truth[1:], strict=True)
    ]
    assert np.mean(within) >= 0.95
