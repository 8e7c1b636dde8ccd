"""Trajectory type and TUM / KITTI files: round trips, evo agreement and bad input."""

from __future__ import annotations

import re
import warnings
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from spacepose.core import se3
from spacepose.core.trajectory import Trajectory
from spacepose.errors import FileFormatError, InputError, SpaceposeWarning
from spacepose.tools.trajectory_io import (
    read_kitti,
    read_trajectory,
    read_tum,
    write_kitti,
    write_tum,
)


def _raises_naming(path: Path, match: str):
    return pytest.raises(FileFormatError, match=rf"^{re.escape(str(path))}: .*{match}")


# ---------------------------------------------------------------------------- Trajectory


def test_trajectory_properties(random_trajectory: Trajectory) -> None:
    traj = random_trajectory
    assert len(traj) == 20
    np.testing.assert_array_equal(traj.positions, traj.poses[:, :3, 3])
    assert not traj.poses.flags.writeable


def test_rebased_first_is_motion_since_first_frame(random_trajectory: Trajectory) -> None:
    rebased = random_trajectory.rebased_first()
    np.testing.assert_allclose(rebased.poses[0], np.eye(4), atol=1e-15)
    # pose_k · pose_0⁻¹ recovers pose_k when multiplied back by pose_0.
    np.testing.assert_allclose(
        rebased.poses @ random_trajectory.poses[0], random_trajectory.poses, atol=1e-12
    )
    np.testing.assert_array_equal(rebased.timestamps, random_trajectory.timestamps)


@pytest.mark.parametrize(
    ("timestamps", "poses", "match"),
    [
        (np.zeros(0), np.zeros((0, 4, 4)), "empty"),
        (np.zeros(2), np.tile(np.eye(4), (3, 1, 1)), "2 timestamps for 3 poses"),
        (np.zeros(1), np.eye(3)[None], r"shape \(N, 4, 4\)"),
        (np.array([np.nan]), np.eye(4)[None], "non-finite timestamps"),
        (np.zeros(2), np.stack([np.eye(4), np.full((4, 4), np.inf)]), "pose 1 has non-finite"),
        (np.zeros(1), np.diag([1.0, 1.0, -1.0, 1.0])[None], "pose 0 is not a rigid"),
        (np.zeros(1), np.diag([2.0, 1.0, 1.0, 1.0])[None], "pose 0 is not a rigid"),
    ],
)
def test_trajectory_rejects_bad_data(timestamps, poses, match: str) -> None:
    with pytest.raises(InputError, match=match):
        Trajectory(timestamps, poses)


# ---------------------------------------------------------------------------- files


def test_tum_round_trip(tmp_path: Path, random_trajectory: Trajectory) -> None:
    back = read_tum(write_tum(tmp_path / "a.tum", random_trajectory))
    np.testing.assert_allclose(back.timestamps, random_trajectory.timestamps, rtol=0, atol=1e-9)
    np.testing.assert_allclose(back.poses, random_trajectory.poses, rtol=0, atol=1e-9)
    assert back.source == str(tmp_path / "a.tum")


def test_tum_line_format_matches_scipy(tmp_path: Path) -> None:
    R = Rotation.from_euler("ZYX", [30, -10, 5], degrees=True)
    traj = Trajectory([12.5], se3.make_transform(R, [1.0, -2.0, 0.25])[None])
    line = write_tum(tmp_path / "one.tum", traj).read_text().splitlines()[-1]
    values = np.array(line.split(), dtype=float)
    q = R.as_quat()
    q = q if q[3] >= 0 else -q
    np.testing.assert_allclose(values, [12.5, 1.0, -2.0, 0.25, *q], rtol=0, atol=1e-15)


def test_tum_matches_evo_reader(tmp_path: Path, random_trajectory: Trajectory) -> None:
    file_interface = pytest.importorskip("evo.tools.file_interface")
    path = write_tum(tmp_path / "e.tum", random_trajectory)
    evo_traj = file_interface.read_tum_trajectory_file(str(path))
    np.testing.assert_allclose(np.stack(evo_traj.poses_se3), random_trajectory.poses, atol=1e-12)
    np.testing.assert_allclose(evo_traj.timestamps, random_trajectory.timestamps, atol=1e-9)


def test_tum_reads_comments_and_unnormalised_quaternions(tmp_path: Path) -> None:
    path = tmp_path / "c.tum"
    path.write_text("# header\n\n1.0 1 2 3 0 0 0 2  # identity, scaled quaternion\n")
    # Read as its rotation, with a warning naming the file and line: a quaternion this far
    # from unit length is more often columns in another order than a scaled rotation.
    with pytest.warns(
        SpaceposeWarning, match=r"c\.tum: 1 quaternions are not of unit length \(line 3: 2\)"
    ):
        traj = read_tum(path)
    np.testing.assert_allclose(traj.poses[0], se3.make_transform(np.eye(3), [1, 2, 3]))
    # Written to 4 decimals, a unit quaternion is within the tolerance: no warning.
    path.write_text("1.0 0 0 0 0.7071 0 0 0.7071\n")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        read_tum(path)


def test_kitti_round_trip_and_timestamps(tmp_path: Path, random_trajectory: Trajectory) -> None:
    path = write_kitti(tmp_path / "a.kitti", random_trajectory)
    back = read_kitti(path)
    np.testing.assert_allclose(back.poses, random_trajectory.poses, rtol=0, atol=1e-15)
    np.testing.assert_array_equal(back.timestamps, np.arange(20.0))
    timed = read_kitti(path, timestamps=random_trajectory.timestamps)
    np.testing.assert_array_equal(timed.timestamps, random_trajectory.timestamps)


def test_kitti_low_precision_is_reorthonormalised(
    tmp_path: Path, random_trajectory: Trajectory
) -> None:
    # 6 decimals, as many KITTI tools print: RᵀR is off the identity by ~1e-6.
    path = tmp_path / "six.kitti"
    np.savetxt(path, random_trajectory.poses[:, :3, :].reshape(-1, 12), fmt="%.6f")
    R = np.loadtxt(path).reshape(-1, 3, 4)[:, :, :3]
    assert np.abs(np.swapaxes(R, 1, 2) @ R - np.eye(3)).max() > 1e-7
    back = read_kitti(path)
    np.testing.assert_allclose(
        np.swapaxes(back.poses[:, :3, :3], 1, 2) @ back.poses[:, :3, :3],
        np.tile(np.eye(3), (20, 1, 1)),
        atol=1e-14,
    )
    np.testing.assert_allclose(back.poses, random_trajectory.poses, atol=2e-6)


def test_read_trajectory_dispatch(tmp_path: Path, random_trajectory: Trajectory) -> None:
    tum_txt = write_tum(tmp_path / "t.txt", random_trajectory)
    kitti_txt = write_kitti(tmp_path / "k.txt", random_trajectory)
    np.testing.assert_allclose(read_trajectory(tum_txt).timestamps, random_trajectory.timestamps)
    np.testing.assert_array_equal(read_trajectory(kitti_txt).timestamps, np.arange(20.0))
    for path in (tum_txt, kitti_txt):
        np.testing.assert_allclose(read_trajectory(path).poses, random_trajectory.poses, atol=1e-9)
    bad = tmp_path / "five.txt"
    bad.write_text("1 2 3 4 5\n")
    with _raises_naming(bad, "first data line has 5 values"):
        read_trajectory(bad)
    with _raises_naming(tmp_path / "none.txt", "no such file"):
        read_trajectory(tmp_path / "none.txt")


# ---------------------------------------------------------------------------- bad input


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("0 0 0 0 0 0 0 1\n0 0 0 0 0 0 1\n", "line 2: expected 8 values for TUM, got 7"),
        ("# c\n0 0 0 0 0 0 0 1\n1 0 0 x 0 0 0 1\n", r"line 3: not a number"),
        ("0 0 0 0 0 0 0 1\n1 0 nan 0 0 0 0 1\n", "line 2: non-finite value"),
        ("0 0 0 0 0 0 0 1\n\n1 0 0 0 0 0 0 0\n", "line 3: zero quaternion"),
        ("# only comments\n", "no TUM poses"),
    ],
)
def test_bad_tum_lines(tmp_path: Path, text: str, match: str) -> None:
    path = tmp_path / "bad.tum"
    path.write_text(text)
    with _raises_naming(path, match):
        read_tum(path)


def test_bad_kitti(tmp_path: Path) -> None:
    path = tmp_path / "bad.kitti"
    path.write_text("1 0 0 0 0 1 0 0 0 0 1 0\n2 0 0 0 0 1 0 0 0 0 1 0\n")
    with _raises_naming(path, "line 2: pose 1 is not a rigid transform"):
        read_kitti(path)
    path.write_text("1 0 0 0 0 1 0 0 0 0 1 0\n")
    with _raises_naming(path, "2 timestamps for 1 poses"):
        read_kitti(path, timestamps=[0.0, 1.0])


def test_kitti_rotations_near_orthonormal_warn_and_far_ones_say_how_far(
    tmp_path: Path, random_trajectory: Trajectory
) -> None:
    """A file written to 4 decimals was refused as "pose 7 is not a rigid transform", saying
    neither how far off it was nor that a TUM quaternion as far off is read with a warning."""
    path = tmp_path / "est.kitti"
    identity = "1 0 0 0 0 1 0 0 0 0 1 0\n"
    # cos 30° written 0.8664: RᵀR off the identity by 6.5e-4, within 1e-3.
    path.write_text(identity + "0.8664 -0.5 0 1 0.5 0.866 0 2 0 0 1 3\n")
    with pytest.warns(SpaceposeWarning) as caught:
        traj = read_kitti(path)
    assert [str(w.message) for w in caught] == [
        f"{path}: 1 rotation blocks are off orthonormal (line 2: RᵀR off the identity by "
        "0.00065, over 0.0001: too few digits written?); read as their nearest rotations"
    ]
    R = traj.poses[1, :3, :3]
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-14)
    np.testing.assert_allclose(R, Rotation.from_euler("z", 30, degrees=True).as_matrix(), atol=1e-3)
    # Beyond 1e-3 no rounding explains it: refused, saying how far off.
    path.write_text(identity * 7 + "0.8760 -0.5 0 1 0.5 0.866 0 2 0 0 1 3\n")
    with pytest.raises(FileFormatError) as info:
        read_kitti(path)
    assert str(info.value) == (
        f"{path}: line 8: pose 7 is not a rigid transform: its rotation block is not a proper "
        "rotation (RᵀR off the identity by 0.017, det 1.009; a rotation has 0 and 1); up to "
        "0.001 is read as rounding"
    )
    # 6 decimals, as KITTI's tools print: read without a word.
    np.savetxt(path, random_trajectory.poses[:, :3, :].reshape(-1, 12), fmt="%.6f")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        read_kitti(path)


def test_missing_tum(tmp_path: Path) -> None:
    with _raises_naming(tmp_path / "absent.tum", "no such file"):
        read_tum(tmp_path / "absent.tum")
