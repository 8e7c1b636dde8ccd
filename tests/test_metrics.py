"""Pose errors: hand-computed cases for Li's per-axis table, evo for the ATE."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from spacepose.core import se3
from spacepose.core.metrics import associate, evaluate, pose_errors
from spacepose.core.trajectory import Trajectory
from spacepose.errors import InputError
from spacepose.tools.trajectory_io import write_tum


def _perturbed(traj: Trajectory, rng: np.random.Generator, scale: float) -> Trajectory:
    deltas = [se3.exp(rng.normal(scale=scale, size=6)) for _ in range(len(traj))]
    return Trajectory(traj.timestamps, np.stack(deltas) @ traj.poses)


def test_pose_errors_pure_offsets() -> None:
    T_gt = se3.make_transform(Rotation.from_euler("ZYX", [40, 10, -20], degrees=True), [1, 2, 3])
    offset = se3.make_transform(np.eye(3), [0.002, 0.0, 0.0])
    dt, euler = pose_errors(offset @ T_gt, T_gt)
    np.testing.assert_allclose(dt, [[0.002, 0, 0]], atol=1e-12)
    np.testing.assert_allclose(euler, 0.0, atol=1e-12)
    yaw = se3.make_transform(Rotation.from_euler("z", 0.5, degrees=True), [0, 0, 0])
    dt, euler = pose_errors(yaw @ T_gt, T_gt)
    np.testing.assert_allclose(dt, 0.0, atol=1e-12)
    np.testing.assert_allclose(euler, [[np.radians(0.5), 0, 0]], atol=1e-12)


def test_error_table_hand_computed() -> None:
    # Frame 0: +2 mm along x. Frame 1: yaw of -0.5° and −1 mm along z. Frame 2: perfect.
    # Ground truth at the origin, so Δt is the position difference too.
    gt = Trajectory([0.0, 1.0, 2.0], np.tile(np.eye(4), (3, 1, 1)))
    yaw = Rotation.from_euler("z", -0.5, degrees=True)
    est = Trajectory(
        [0.0, 1.0, 2.0],
        np.stack(
            [
                se3.make_transform(np.eye(3), [0.002, 0, 0]),
                se3.make_transform(yaw, [0, 0, -0.001]),
                np.eye(4),
            ]
        ),
    )
    table = evaluate(est, gt)
    assert table.n == 3
    # |x| errors (2, 0, 0) mm: mean 2/3, population std sqrt(8/9).
    np.testing.assert_allclose(table.translation_mean_mm, [2 / 3, 0, 1 / 3], atol=1e-12)
    np.testing.assert_allclose(
        table.translation_std_mm, [np.sqrt(8) / 3, 0, np.sqrt(2) / 3], atol=1e-12
    )
    # Rotation rows are pitch, yaw, roll: only yaw, |−0.5°| in one of three frames.
    np.testing.assert_allclose(table.rotation_mean_deg, [0, 0.5 / 3, 0], atol=1e-12)
    np.testing.assert_allclose(table.rotation_std_deg, [0, np.sqrt(2) * 0.5 / 3, 0], atol=1e-12)
    np.testing.assert_allclose(table.ate_translation_rmse, np.sqrt((0.002**2 + 0.001**2) / 3))
    np.testing.assert_allclose(table.ate_rotation_rmse, np.sqrt(0.25 / 3), rtol=1e-12)
    d = table.to_dict()
    assert d["n"] == 3
    assert list(d["mean"]) == ["x_mm", "y_mm", "z_mm", "pitch_deg", "yaw_deg", "roll_deg"]
    assert d["mean"]["x_mm"] == pytest.approx(2 / 3)
    assert d["std"]["yaw_deg"] == pytest.approx(np.sqrt(2) * 0.5 / 3)
    assert d["ate_translation_rmse"] == pytest.approx(np.sqrt((0.002**2 + 0.001**2) / 3))
    assert d["ate_rotation_rmse"] == pytest.approx(np.sqrt(0.25 / 3))
    assert [r[0] for r in table.rows()] == ["x", "y", "z", "pitch", "yaw", "roll"]


def test_translation_error_includes_rotation_lever_arm() -> None:
    # Li Eq. 10: Δt = t_est − ΔR t_gt, unlike evo's position difference.
    gt = Trajectory([0.0], se3.make_transform(np.eye(3), [1.0, 0, 0])[None])
    dR = Rotation.from_euler("z", 90, degrees=True)
    est = Trajectory([0.0], se3.make_transform(dR, [1.0, 0, 0])[None])
    dt, _ = pose_errors(est.poses, gt.poses)
    np.testing.assert_allclose(dt, [[1.0, -1.0, 0.0]], atol=1e-15)
    assert evaluate(est, gt).ate_translation_rmse == pytest.approx(0.0, abs=1e-15)


@pytest.mark.parametrize("rebase_first", [False, True])
def test_ate_matches_evo(
    tmp_path: Path, rng: np.random.Generator, random_trajectory: Trajectory, rebase_first: bool
) -> None:
    pytest.importorskip("evo")
    from evo.core import metrics as evo_metrics
    from evo.tools import file_interface

    est = _perturbed(random_trajectory, rng, scale=0.01)
    if rebase_first:
        est, gt = est.rebased_first(), random_trajectory.rebased_first()
    else:
        gt = random_trajectory
    ref_path = write_tum(tmp_path / "ref.tum", gt)
    est_path = write_tum(tmp_path / "est.tum", est)
    ref_evo = file_interface.read_tum_trajectory_file(str(ref_path))
    est_evo = file_interface.read_tum_trajectory_file(str(est_path))
    table = evaluate(est, gt)
    for relation, ours in (
        (evo_metrics.PoseRelation.translation_part, table.ate_translation_rmse),
        (evo_metrics.PoseRelation.rotation_angle_deg, table.ate_rotation_rmse),
    ):
        ape = evo_metrics.APE(relation)
        ape.process_data((ref_evo, est_evo))
        evo_rmse = ape.get_statistic(evo_metrics.StatisticsType.rmse)
        assert ours == pytest.approx(evo_rmse, abs=1e-6)
        assert evo_rmse > 1e-3  # the perturbation is visible, so agreement means something


def test_rebase_first_removes_constant_offset(random_trajectory: Trajectory) -> None:
    offset = se3.exp([0.1, -0.2, 0.3, 1.0, 2.0, 3.0])
    shifted = Trajectory(random_trajectory.timestamps, random_trajectory.poses @ offset)
    assert evaluate(shifted, random_trajectory).ate_translation_rmse > 0.1
    table = evaluate(shifted, random_trajectory, rebase_first=True)
    assert table.ate_translation_rmse == pytest.approx(0.0, abs=1e-12)
    assert table.ate_rotation_rmse == pytest.approx(0.0, abs=1e-6)


def test_association_by_timestamp(rng: np.random.Generator, random_trajectory: Trajectory) -> None:
    # Estimate on every other frame, shuffled, with 1e-7 s jitter: pairs follow the times.
    keep = rng.permutation(np.arange(0, 20, 2))
    est = Trajectory(random_trajectory.timestamps[keep] + 1e-7, random_trajectory.poses[keep])
    i_est, i_gt = associate(est.timestamps, random_trajectory.timestamps)
    np.testing.assert_array_equal(i_gt, keep)
    np.testing.assert_array_equal(i_est, np.arange(10))
    table = evaluate(est, random_trajectory)
    assert table.n == 10
    assert table.ate_translation_rmse == 0.0


def test_unmatched_timestamps_raise(random_trajectory: Trajectory) -> None:
    est = Trajectory(random_trajectory.timestamps + 1e-3, random_trajectory.poses)
    with pytest.raises(InputError, match=r"20 of 20 estimated timestamps have no ground truth"):
        evaluate(est, random_trajectory)


def test_align_by_index(random_trajectory: Trajectory) -> None:
    est = Trajectory(random_trajectory.timestamps + 5.0, random_trajectory.poses)
    assert evaluate(est, random_trajectory, align_by="index").ate_rotation_rmse == 0.0
    short = Trajectory(est.timestamps[:5], est.poses[:5])
    with pytest.raises(InputError, match="equal lengths, got 5 estimated and 20"):
        evaluate(short, random_trajectory, align_by="index")
    with pytest.raises(InputError, match="align_by must be"):
        evaluate(est, random_trajectory, align_by="nearest")  # type: ignore[arg-type]


def test_pose_errors_bad_shapes() -> None:
    with pytest.raises(InputError, match=r"matching non-empty \(N, 4, 4\)"):
        pose_errors(np.tile(np.eye(4), (2, 1, 1)), np.tile(np.eye(4), (3, 1, 1)))
    with pytest.raises(InputError, match="non-finite"):
        pose_errors(np.full((4, 4), np.nan), np.eye(4))


def test_navigation_errors_per_group_and_attitude_in_body_frame() -> None:
    from spacepose.core.metrics import NAV_GROUPS, navigation_errors

    n = 10
    q_true = Rotation.from_euler("ZYX", [30.0, -20.0, 45.0], degrees=True)
    # The estimate is off by 0.2° about body x: R_true = R_est · exp(δθ) with δθ = (0.2°, 0, 0).
    q_est = q_true * Rotation.from_rotvec(np.radians([-0.2, 0.0, 0.0]))
    truth = {"t": np.arange(n, dtype=float)}
    nav = {"t": np.arange(n, dtype=float)}
    pairs = zip(q_true.as_quat(), q_est.as_quat(), strict=True)
    for axis, (qt, qe) in zip("xyzw", pairs, strict=True):
        truth[f"q{axis}"] = np.full(n, qt)
        nav[f"q{axis}"] = np.full(n, qe)
    for _, cols, _, _ in NAV_GROUPS:
        for c in cols:
            truth[c] = np.zeros(n)
            nav[c] = np.zeros(n)
            nav[f"sig_{c}"] = np.full(n, 1e-3)
    for a in "xyz":
        nav[f"sig_att_{a}"] = np.full(n, 1e-3)
    nav["rho_y"] = np.full(n, 0.004)  # 4 mm along y
    nav["qx"][:3] = np.nan  # filter not started on the first three frames
    errors = navigation_errors(nav, truth)
    rms = errors.rms(0.5)
    np.testing.assert_allclose(rms["position"], [0.0, 4.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(rms["attitude"], [0.2, 0.0, 0.0], atol=1e-9)
    assert np.isnan(errors.groups["attitude"][2][:3]).all()
    np.testing.assert_allclose(errors.groups["velocity"][3], 1.0)  # σ of 1 mm/s shown in mm/s
    del nav["com_z"]
    with pytest.raises(InputError, match="com_z"):
        navigation_errors(nav, truth)
