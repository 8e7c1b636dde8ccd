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
    assert data["ate_rotation_rmse"] == pytest.approx(0.5, abs=1e-9)


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
    assert json.loads(capsys.readouterr().out)["ate_translation_rmse"] > 0.1
    assert main(["evaluate", str(est), str(gt), "--json", "--rebase-first"]) == 0
    data = json.loads(capsys.readouterr().out)
    assert data["ate_translation_rmse"] == pytest.approx(0.0, abs=1e-9)
    assert data["ate_rotation_rmse"] == pytest.approx(0.0, abs=1e-6)


def test_kitti_ground_truth_is_accepted(
    tmp_path: Path, random_trajectory: Trajectory, capsys: pytest.CaptureFixture[str]
) -> None:
    # KITTI has no timestamps (0, 1, 2, ...): the estimate must use the same times.
    gt = write_kitti(tmp_path / "gt.kitti", random_trajectory)
    est = write_tum(tmp_path / "est.tum", Trajectory(np.arange(20.0), random_trajectory.poses))
    assert main(["evaluate", str(est), str(gt), "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["ate_translation_rmse"] == pytest.approx(
        0.0, abs=1e-12
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
