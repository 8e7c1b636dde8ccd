"""``spacepose evaluate``: table output, JSON output and the one-line error."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from spacepose.cli import main
from spacepose.core import se3
from spacepose.core.trajectory import Trajectory
from spacepose.errors import SpaceposeWarning
from spacepose.tools.trajectory_io import write_kitti, write_tum


@pytest.fixture
def files(tmp_path: Path, random_trajectory: Trajectory) -> tuple[Path, Path]:
    # Every estimate is off by +2 mm in x and 0.5° of yaw, applied on the left (ΔT).
    delta = se3.make_transform(Rotation.from_euler("z", 0.5, degrees=True), [0.002, 0, 0])
    est = Trajectory(random_trajectory.timestamps, delta @ random_trajectory.poses)
    return (
        write_tum(tmp_path / "est.tum", est),
        write_tum(tmp_path / "gt.tum", random_trajectory),
    )


def test_prints_table(files: tuple[Path, Path], capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["evaluate", str(files[0]), str(files[1])]) == 0
    out = capsys.readouterr().out
    assert "20 poses" in out
    lines = {line.split("│")[1].strip(): line for line in out.splitlines() if line.count("│") >= 3}
    assert "2.0000" in lines["x (mm)"]
    assert "0.5000" in lines["yaw (deg)"]
    assert "0.0000" in lines["pitch (deg)"]
    assert "0.5000" in lines["ATE rotation RMSE (deg)"]


def test_json_output(files: tuple[Path, Path], capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["evaluate", str(files[0]), str(files[1]), "--json"]) == 0
    data = json.loads(capsys.readouterr().out)
    assert data["n"] == 20
    assert data["mean"]["x_mm"] == pytest.approx(2.0, abs=1e-9)
    assert data["std"]["x_mm"] == pytest.approx(0.0, abs=1e-9)
    assert data["mean"]["y_mm"] == pytest.approx(0.0, abs=1e-9)
    assert data["mean"]["yaw_deg"] == pytest.approx(0.5, abs=1e-9)
    assert data["mean"]["pitch_deg"] == pytest.approx(0.0, abs=1e-9)
    assert data["ate_rotation_rmse_deg"] == pytest.approx(0.5, abs=1e-9)


def test_rebase_first_flag(
    tmp_path: Path, random_trajectory: Trajectory, capsys: pytest.CaptureFixture[str]
) -> None:
    # A constant offset on the right (T_k · C) cancels in T_k C (T_0 C)⁻¹ = T_k T_0⁻¹.
    offset = se3.exp([0.2, 0.1, -0.3, 0.5, -1.0, 2.0])
    est = write_tum(
        tmp_path / "est.tum",
        Trajectory(random_trajectory.timestamps, random_trajectory.poses @ offset),
    )
    gt = write_tum(tmp_path / "gt.tum", random_trajectory)
    assert main(["evaluate", str(est), str(gt), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["ate_translation_rmse_mm"] > 100.0
    assert main(["evaluate", str(est), str(gt), "--json", "--rebase-first"]) == 0
    data = json.loads(capsys.readouterr().out)
    assert data["ate_translation_rmse_mm"] == pytest.approx(0.0, abs=1e-6)
    assert data["ate_rotation_rmse_deg"] == pytest.approx(0.0, abs=1e-6)


def test_kitti_ground_truth_is_accepted(
    tmp_path: Path, random_trajectory: Trajectory, capsys: pytest.CaptureFixture[str]
) -> None:
    # KITTI has no timestamps (0, 1, 2, ...): the estimate must use the same times.
    gt = write_kitti(tmp_path / "gt.kitti", random_trajectory)
    est = write_tum(tmp_path / "est.tum", Trajectory(np.arange(20.0), random_trajectory.poses))
    assert main(["evaluate", str(est), str(gt), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["ate_translation_rmse_mm"] == pytest.approx(
        0.0, abs=1e-9
    )


def test_bad_file_is_one_line_error(
    tmp_path: Path, files: tuple[Path, Path], capsys: pytest.CaptureFixture[str]
) -> None:
    bad = tmp_path / "bad.tum"
    bad.write_text("0 0 0 0 0 0 0 1\n1 2 3\n")
    assert main(["evaluate", str(bad), str(files[1])]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert "bad.tum" in err and "line 2" in err
    assert main(["evaluate", str(tmp_path / "missing.tum"), str(files[1])]) == 1
    assert "missing.tum: no such file" in capsys.readouterr().err


def test_mismatched_timestamps_exit_1(
    tmp_path: Path, random_trajectory: Trajectory, capsys: pytest.CaptureFixture[str]
) -> None:
    late = Trajectory(random_trajectory.timestamps + 0.05, random_trajectory.poses)
    est = write_tum(tmp_path / "late.tum", late)
    gt = write_tum(tmp_path / "gt.tum", random_trajectory)
    assert main(["evaluate", str(est), str(gt)]) == 1
    assert "no ground truth within" in capsys.readouterr().err


def test_json_states_its_units_in_every_key(
    tmp_path: Path, random_trajectory: Trajectory, capsys: pytest.CaptureFixture[str]
) -> None:
    shift = se3.make_transform(np.eye(3), [0.002, 0.0, 0.0])  # every position 2 mm off in x
    est = write_tum(
        tmp_path / "est.tum",
        Trajectory(random_trajectory.timestamps, shift @ random_trajectory.poses),
    )
    gt = write_tum(tmp_path / "gt.tum", random_trajectory)
    assert main(["evaluate", str(est), str(gt), "--json"]) == 0
    out, err = capsys.readouterr()
    data = json.loads(out)
    assert err == ""
    assert data["units"] == {"translation": "mm", "rotation": "deg"}
    assert data["ate_translation_rmse_mm"] == pytest.approx(2.0, abs=1e-9)
    assert data["mean"]["x_mm"] == pytest.approx(2.0, abs=1e-9)
    for key in (*data["mean"], *data["std"]):
        assert key.endswith(("_mm", "_deg"))
    numbers = [k for k, v in data.items() if isinstance(v, float)]
    assert numbers and all(k.endswith(("_mm", "_deg")) for k in numbers)
    assert (data["n"], data["n_estimated"], data["n_ground_truth"]) == (20, 20, 20)
    assert data["warnings"] == []


def test_warns_on_a_shorter_estimate_and_repeated_timestamps(
    tmp_path: Path, random_trajectory: Trajectory, capsys: pytest.CaptureFixture[str]
) -> None:
    gt = write_tum(tmp_path / "gt.tum", random_trajectory)
    t, T = random_trajectory.timestamps, random_trajectory.poses
    short = write_tum(tmp_path / "short.tum", Trajectory(t[:15], T[:15]))
    assert main(["evaluate", str(short), str(gt)]) == 0
    captured = capsys.readouterr()
    assert "15 poses" in captured.out
    assert captured.err.strip() == (
        f"warning: {short}: 15 poses against 20 in gt.tum: only the 15 estimated ones are scored"
    )
    twice = write_tum(tmp_path / "twice.tum", Trajectory(np.r_[t, t[3]], np.r_[T, T[3:4]]))
    assert main(["evaluate", str(twice), str(gt), "--json"]) == 0
    captured = capsys.readouterr()
    assert json.loads(captured.out)["warnings"] == [
        "21 poses against 20 in gt.tum: only the 21 estimated ones are scored",
        "1 estimate(s) share a ground-truth pose with another (repeated timestamps, or a "
        "--max-dt wider than the spacing of the truth)",
    ]
    assert len(captured.err.strip().splitlines()) == 2


def test_warns_on_a_model_free_track_compared_without_rebase_first(
    tmp_path: Path, random_trajectory: Trajectory, capsys: pytest.CaptureFixture[str]
) -> None:
    # A perfect model-free track: frame 0 is the identity, every pose relative to it.
    est = write_tum(tmp_path / "free.tum", random_trajectory.rebased_first())
    gt = write_tum(tmp_path / "gt.tum", random_trajectory)
    assert main(["evaluate", str(est), str(gt), "--json"]) == 0
    captured = capsys.readouterr()
    assert json.loads(captured.out)["ate_translation_rmse_mm"] > 100.0  # the offset, not an error
    assert len(captured.err.strip().splitlines()) == 1
    assert captured.err.startswith(f"warning: {est}: the first pose is the identity")
    assert "--rebase-first" in captured.err
    assert main(["evaluate", str(est), str(gt), "--json", "--rebase-first"]) == 0
    captured = capsys.readouterr()
    assert captured.err == ""
    assert json.loads(captured.out)["ate_translation_rmse_mm"] == pytest.approx(0.0, abs=1e-6)


def test_warns_on_an_estimate_in_millimetres(
    tmp_path: Path, random_trajectory: Trajectory, capsys: pytest.CaptureFixture[str]
) -> None:
    """An estimate written in millimetres against metres scored the whole distance as error,
    silently. It now warns in one line with the factor (1000); the same file in metres does
    not. With --rebase-first too, where the motions are compared: there the factor must be a
    unit's and both must turn alike, since a nearly static truth against an estimate's noise
    can differ by any factor with no unit wrong."""
    mm = random_trajectory.poses.copy()
    mm[:, :3, 3] *= 1e3
    est = write_tum(tmp_path / "mm.tum", Trajectory(random_trajectory.timestamps, mm))
    gt = write_tum(tmp_path / "gt.tum", random_trajectory)
    assert main(["evaluate", str(est), str(gt), "--json"]) == 0
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and err.startswith(f"warning: {est}: its poses lie "), err
    assert "1e+03 times as far: are both in metres?" in err, err
    assert main(["evaluate", str(gt), str(gt), "--json"]) == 0
    assert capsys.readouterr().err == ""
    assert main(["evaluate", str(est), str(gt), "--json", "--rebase-first"]) == 0
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "from its first pose" in err and "1e+03 times" in err, err
    # A static truth against an estimate's noise: distances 1000 times apart, turns not alike.
    rng = np.random.default_rng(3)
    n = len(random_trajectory)
    static = np.repeat(random_trajectory.poses[:1], n, axis=0)
    noisy = static.copy()
    noisy[:, :3, 3] += rng.normal(0.0, 1e-3, (n, 3))
    for k in range(n):
        noisy[k, :3, :3] = (
            Rotation.from_rotvec(rng.normal(0.0, 1e-3, 3)).as_matrix() @ static[k, :3, :3]
        )
    static[:, :3, 3] += rng.normal(0.0, 1e-6, (n, 3))
    est = write_tum(tmp_path / "noisy.tum", Trajectory(random_trajectory.timestamps, noisy))
    gt = write_tum(tmp_path / "static.tum", Trajectory(random_trajectory.timestamps, static))
    assert main(["evaluate", str(est), str(gt), "--json", "--rebase-first"]) == 0
    assert capsys.readouterr().err == ""


def test_lost_frames_of_the_health_table_are_left_out(
    tmp_path: Path, random_trajectory: Trajectory, capsys: pytest.CaptureFixture[str]
) -> None:
    """A lost frame's pose in EST.tum is the motion model's prediction; scored, it counted as
    the tracker's error. The frames EST.health.csv marks lost are left out, with a warning."""
    gt = write_tum(tmp_path / "gt.tum", random_trajectory)
    poses = random_trajectory.poses.copy()
    poses[2] = np.eye(4)  # a placeholder far from the truth
    est = write_tum(tmp_path / "e.tum", Trajectory(random_trajectory.timestamps, poses))
    status = ["ok"] * len(poses)
    status[2] = "lost"
    (tmp_path / "e.health.csv").write_text(
        "frame,status\n" + "".join(f"{k},{s}\n" for k, s in enumerate(status))
    )
    assert main(["evaluate", str(est), str(gt), "--json"]) == 0
    captured = capsys.readouterr()
    out = json.loads(captured.out)
    assert out["ate_translation_rmse_mm"] == pytest.approx(0.0, abs=1e-6)
    assert out["n"] == len(poses) - 1
    assert "1 frame(s) lost in e.health.csv left out" in captured.err
    # A table that does not match the poses leaves every pose scored, and says so.
    (tmp_path / "e.health.csv").write_text("frame,status\n0,lost\n")
    assert main(["evaluate", str(est), str(gt), "--json"]) == 0
    captured = capsys.readouterr()
    assert json.loads(captured.out)["ate_translation_rmse_mm"] > 1.0
    assert "has 1 rows for" in captured.err


def test_lost_frames_are_counted_in_the_estimate_they_were_left_out_of(
    tmp_path: Path, random_trajectory: Trajectory, capsys: pytest.CaptureFixture[str]
) -> None:
    """Two of three frames lost: the estimate was counted without them, "1 poses against 3 in
    gt.tum: only the 1 estimated ones are scored", though it holds 3 as the truth does."""
    three = Trajectory(random_trajectory.timestamps[:3], random_trajectory.poses[:3])
    est = write_tum(tmp_path / "est.tum", three)
    gt = write_tum(tmp_path / "gt.tum", three)
    (tmp_path / "est.health.csv").write_text("frame,status\n0,ok\n1,lost\n2,lost\n")
    assert main(["evaluate", str(est), str(gt), "--json"]) == 0
    captured = capsys.readouterr()
    assert captured.err.splitlines() == [
        f"warning: {est}: 2 frame(s) lost in est.health.csv left out (their poses are the "
        "motion model's predictions)"
    ]
    out = json.loads(captured.out)
    assert (out["n"], out["n_estimated"], out["n_ground_truth"]) == (1, 3, 3)
    # Against a longer truth, the count is the file's and the scored ones are named apart.
    gt = write_tum(tmp_path / "gt.tum", random_trajectory)
    assert main(["evaluate", str(est), str(gt), "--json"]) == 0
    assert (
        f"warning: {est}: 3 poses against 20 in gt.tum: only the 1 estimated ones not lost are "
        "scored"
    ) in capsys.readouterr().err.splitlines()
    # A status none of ok, degraded, lost is named with its file, and every frame scored.
    (tmp_path / "est.health.csv").write_text("frame,status\n0,ok\n1,banana\n2,lost\n")
    assert main(["evaluate", str(est), str(gt), "--json"]) == 0
    assert (
        f"warning: {est}: est.health.csv row 2 has status 'banana', not one of ok, degraded, "
        "lost: lost frames, if any, are scored"
    ) in capsys.readouterr().err.splitlines()


def test_a_ground_truth_with_two_poses_at_one_time_is_refused(
    tmp_path: Path, random_trajectory: Trajectory, capsys: pytest.CaptureFixture[str]
) -> None:
    """A ground truth holding two different poses at t[3] was used as it came: the estimate
    there scored against one of them, without a word, exit 0."""
    est = write_tum(tmp_path / "est.tum", random_trajectory)
    t, T = random_trajectory.timestamps, random_trajectory.poses
    other = se3.make_transform(np.eye(3), [0.5, 0.0, 0.0]) @ T[3:4]
    gt = write_tum(tmp_path / "gt.tum", Trajectory(np.r_[t, t[3]], np.r_[T, other]))
    assert main(["evaluate", str(est), str(gt)]) == 1
    err = capsys.readouterr().err.strip()
    assert err == (
        f"error: {gt}: two ground-truth poses at t = {float(t[3])!r}: which one is the truth? "
        "(one pose a time)"
    ), err


def test_a_fast_ground_truth_paired_within_a_wide_tolerance_is_scored(tmp_path: Path) -> None:
    """Poses apart in time are no ambiguity: a 100 Hz truth (TUM RGB-D's motion capture) with
    a 30 Hz estimate paired within 20 ms was refused as "two poses within 0.02 s"."""
    from spacepose.tools.evaluation import compare_trajectory_files

    t_gt = np.arange(0.0, 2.0, 0.01)
    gt = np.stack([se3.make_transform(np.eye(3), [0.1 * t, 0.0, 1.0]) for t in t_gt])
    t_est = np.arange(0.0, 1.9, 1 / 30) + 0.004  # 4 ms late: paired with the nearest
    est = np.stack([se3.make_transform(np.eye(3), [0.1 * t, 0.0, 1.0]) for t in t_est])
    gt_path = write_tum(tmp_path / "gt.tum", Trajectory(t_gt, gt))
    est_path = write_tum(tmp_path / "est.tum", Trajectory(t_est, est))
    with pytest.warns(SpaceposeWarning, match="only the 57 estimated ones are scored"):
        result = compare_trajectory_files(est_path, gt_path, tolerance=0.02)
    # Each estimate is off by 0.1 m/s times its time from the nearest truth (0-5 ms).
    nearest = t_gt[np.abs(t_gt[None] - t_est[:, None]).argmin(axis=1)]
    expected = np.sqrt(np.mean((0.1 * (nearest - t_est)) ** 2))  # 0.28 mm
    assert result.table.ate_translation_rmse == pytest.approx(expected, rel=1e-9)


def test_warns_on_a_model_free_track_in_millimetres_of_a_target_turning_at_range(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """A model-free track (T_k0, first pose the identity) written in millimetres against a
    truth in metres of a target 2 m away turning in place: rebased as the scores are, the
    motions are 1000 times apart; rebased the other way the truth barely moved, the factor
    came out thousands, no unit's, and the 100 m errors went unflagged."""
    n = 12
    gt_poses = np.repeat(np.eye(4)[None], n, axis=0)
    for k in range(n):
        gt_poses[k, :3, :3] = Rotation.from_rotvec([0.0, 0.05 * k, 0.01 * k]).as_matrix()
        gt_poses[k, :3, 3] = [0.01 * k, 0.0, 2.0]
    free = gt_poses @ np.linalg.inv(gt_poses[0])
    free[:, :3, 3] *= 1e3
    times = np.arange(n, dtype=float)
    est = write_tum(tmp_path / "free_mm.tum", Trajectory(times, free))
    gt = write_tum(tmp_path / "gt.tum", Trajectory(times, gt_poses))
    assert main(["evaluate", str(est), str(gt), "--json", "--rebase-first"]) == 0
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "from its first pose" in err and "1e+03 times" in err, err


def test_ground_truth_of_the_sensor_in_a_world_frame_is_scored_inverted(
    files: tuple[Path, Path], tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    """TUM RGB-D's groundtruth.txt holds T_world_sensor; the estimate, the still scene's pose
    in the sensor frame. The file of the inverses, written here through scipy's quaternions,
    scored with --gt-sensor-poses, gives the numbers of the file of the poses themselves."""
    est, gt = files
    lines = []
    for row in np.loadtxt(gt):
        R_sensor_world = Rotation.from_quat(row[4:8])
        R_world_sensor = R_sensor_world.inv()
        t = -R_world_sensor.apply(row[1:4])
        lines.append(" ".join(f"{v:.17g}" for v in [row[0], *t, *R_world_sensor.as_quat()]))
    (tmp_path / "camera.tum").write_text("\n".join(lines) + "\n")
    assert main(["evaluate", str(est), str(gt), "--json"]) == 0
    reference = json.loads(capsys.readouterr().out)
    args = ["evaluate", str(est), str(tmp_path / "camera.tum"), "--json"]
    assert main([*args, "--gt-sensor-poses"]) == 0
    inverted = json.loads(capsys.readouterr().out)
    for key in ("ate_translation_rmse_mm", "ate_rotation_rmse_deg"):
        assert inverted[key] == pytest.approx(reference[key], abs=1e-9)
    assert main(args) == 0  # taken as the scene's poses: far off
    assert json.loads(capsys.readouterr().out)["ate_translation_rmse_mm"] > 100.0
