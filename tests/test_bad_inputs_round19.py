"""Nineteenth hostile round: trajectories from other conventions, scored without a word."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from spacepose.core.trajectory import Trajectory
from spacepose.errors import InputError, SpaceposeWarning
from spacepose.tools.evaluation import compare_trajectory_files
from spacepose.tools.trajectory_io import write_tum


def _w_first_tum(path, traj: Trajectory) -> None:
    """``traj`` written as TUM with each quaternion in the order w x y z (a common mix-up)."""
    q = Rotation.from_matrix(traj.poses[:, :3, :3]).as_quat()  # x y z w
    rows = np.column_stack([traj.timestamps, traj.poses[:, :3, 3], np.roll(q, 1, axis=1)])
    path.write_text("".join(" ".join(f"{v:.17g}" for v in row) + "\n" for row in rows))


def test_a_truth_written_w_first_is_said_to_be(tmp_path, random_trajectory):
    """A truth whose quaternions are written w first scored 160° of rotation error beside
    0.17 mm of translation, without a word. Now a warning says that read w first the
    rotations agree; a truth written right says nothing of it."""
    est = write_tum(tmp_path / "est.tum", random_trajectory)
    _w_first_tum(tmp_path / "gt.tum", random_trajectory)
    with pytest.warns(SpaceposeWarning, match=r"agree within .* when gt\.tum's quaternions are"):
        result = compare_trajectory_files(est, tmp_path / "gt.tum")
    assert result.table.ate_rotation_rmse > 60.0
    right = write_tum(tmp_path / "right.tum", random_trajectory)
    result = compare_trajectory_files(est, right)
    assert not [w for w in result.warnings if "quaternions" in w]


def test_a_clock_offset_let_through_by_a_wide_max_dt_is_said(tmp_path, random_trajectory):
    """Every estimate 0.03 s after its truth, scored with ``--max-dt 0.04``: the errors
    compared poses 0.03 s apart and nothing said so. Now a warning names the offset."""
    gt = write_tum(tmp_path / "gt.tum", random_trajectory)
    late = Trajectory(random_trajectory.timestamps + 0.03, random_trajectory.poses)
    est = write_tum(tmp_path / "est.tum", late)
    with pytest.warns(SpaceposeWarning, match=r"gt\.tum -0\.03 s from it: a clock offset"):
        compare_trajectory_files(est, gt, tolerance=0.04)


def test_poses_left_out_before_a_refusal_are_counted_in_it(tmp_path, random_trajectory):
    """Estimates 0.05 s late, the last past the truth's end: the refusal counted the 19 left
    ("5 of 5 estimated timestamps have no ground truth" of a file of 6); the one left out
    first is now named in the same line."""
    gt = write_tum(tmp_path / "gt.tum", random_trajectory)
    late = Trajectory(random_trajectory.timestamps + 0.05, random_trajectory.poses)
    est = write_tum(tmp_path / "est.tum", late)
    with pytest.raises(
        InputError, match=r"1 of 20 estimated poses lie outside gt\.tum's times .*; 19 of 19"
    ):
        compare_trajectory_files(est, gt)
