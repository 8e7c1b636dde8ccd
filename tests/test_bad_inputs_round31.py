"""Round 31 of bad inputs: a depth.txt naming images of another folder, tracks without the
scenario.json a report reads runs by, an initial transform that moves the source clear of the
target, and a lopsided measurement covariance the filter averaged."""

from __future__ import annotations

import warnings

import numpy as np
import pytest
from tests.cli_errors import error_line

from spacepose.cli import main
from spacepose.errors import InputError, SpaceposeWarning


@pytest.mark.parametrize("listed", ["../other/000002.png", "depth/../../other/000002.png"])
def test_a_depth_list_naming_an_image_outside_its_folder_is_refused(tmp_path, listed):
    """``1.2 ../other/000002.png`` in depth.txt read another folder's image as this sequence's
    third frame, without a word."""
    from spacepose.tools.depth_folder import read_tum_depth_list

    listed_path = tmp_path / "run" / "depth.txt"
    listed_path.parent.mkdir()
    listed_path.write_text(f"1.0 depth/000000.png\n1.1 depth/000001.png\n1.2 {listed}\n")
    with pytest.raises(InputError) as info:
        read_tum_depth_list(listed_path)
    assert str(info.value) == (
        f"{listed_path}: line 3: {listed} lies outside the list's folder: a depth list "
        "names the images of its own sequence"
    )
    inside = "depth/./sub/../000002.png"
    listed_path.write_text(f"1.0 depth/000000.png\n1.1 depth/000001.png\n1.2 {inside}\n")
    paths, _ = read_tum_depth_list(listed_path)
    assert paths[-1] == listed_path.parent / inside
    # An absolute path within the folder names one of its own images.
    within = listed_path.parent / "depth" / "000002.png"
    listed_path.write_text(f"1.0 depth/000000.png\n1.1 depth/000001.png\n1.2 {within}\n")
    paths, _ = read_tum_depth_list(listed_path)
    assert paths[-1] == within
    elsewhere = tmp_path / "other" / "000002.png"
    listed_path.write_text(f"1.0 depth/000000.png\n1.1 depth/000001.png\n1.2 {elsewhere}\n")
    with pytest.raises(InputError, match="lies outside the list's folder"):
        read_tum_depth_list(listed_path)


def test_tracks_without_a_scenario_are_named_by_the_report(tmp_path, capsys):
    """A folder of track.tum (and groundtruth.tum) but no scenario.json was "nothing to report:
    no run, experiment or benchmark output found", as if it held nothing."""
    root = tmp_path / "run"
    root.mkdir()
    for name in ("track.tum", "groundtruth.tum"):
        (root / name).write_text("0 0 0 0 0 0 0 1\n1 0.1 0 0 0 0 0 1\n")
    assert main(["report", str(root)]) == 1
    assert error_line(capsys) == (
        f"error: {root}: nothing to report: groundtruth.tum, track.tum found, but no "
        "scenario.json: the report reads run folders as `spacepose simulate` writes them "
        "(scenario.json, groundtruth.tum, tracks)"
    )
    assert not (root / "report.html").exists()


def test_an_init_transform_that_moves_the_source_clear_of_the_target_names_init(tmp_path):
    """A translation of 1e20 m (or 5 m, of a 1 m cloud) failed as "a.ply onto b.ply: GICP found
    0 correspondences within 0.247 m ...", the --init file unnamed."""
    from spacepose.tools.cloud_io import write_cloud
    from spacepose.tools.register_io import register_files

    rng = np.random.default_rng(0)
    points = rng.uniform(-0.5, 0.5, (500, 3))
    points[:, 2] = 0.2 * points[:, 0] ** 2 + 0.1 * points[:, 1] ** 2
    source, target, init = tmp_path / "a.ply", tmp_path / "b.ply", tmp_path / "init.txt"
    write_cloud(source, points)
    write_cloud(target, points)
    T = np.eye(4)
    T[0, 3] = 1e20
    np.savetxt(init, T)
    with pytest.raises(InputError) as info:
        register_files(source, target, init)
    assert str(info.value).startswith(
        f"{init}: the initial transform (--init) moves {source} 1e+20 m clear of {target} "
        "(their bounding boxes do not meet), and registration failed: GICP found 0 "
        "correspondences within"
    )
    T[0, 3] = 0.01
    np.savetxt(init, T)
    with warnings.catch_warnings():  # the bowl leaves directions free: warned of, and fitted
        warnings.simplefilter("ignore", SpaceposeWarning)
        assert register_files(source, target, init).result.fitness > 0.9


def _ekf():
    from spacepose.core.dynamics import inertia_ratios
    from spacepose.core.ekf import RelativeNavEKF
    from spacepose.core.nav_state import NavState

    state = NavState(
        0.0, np.array([0.0, 0.0, 10.0]), np.zeros(3), np.array([0.0, 0.0, 0.0, 1.0]),
        np.array([0.01, 0.02, 0.03]), inertia_ratios([3.0, 2.0, 4.0]), np.zeros(3),
    )  # fmt: skip
    return RelativeNavEKF(1.1e-3, np.eye(3), state)


def test_a_lopsided_measurement_covariance_is_refused():
    """cov6 with C[0, 1] 0.5 and C[1, 0] 0 was averaged into another matrix (0.25 both) and
    fused without a word."""
    ekf = _ekf()
    lopsided = np.eye(6)
    lopsided[0, 1] = 0.5
    with pytest.raises(InputError) as info:
        ekf.update_pose(ekf.predict_pose(), lopsided)
    assert str(info.value) == (
        "measurement covariance is not symmetric (C[0, 1] 0.5, C[1, 0] 0): no covariance"
    )
    with pytest.raises(InputError, match=r"not symmetric \(C\[0, 2\] 0\.001, C\[2, 0\] 0\)"):
        ekf.update_centroid("f", [0, 0, 0], [0, 0, 10], [[1, 0, 1e-3], [0, 1, 0], [0, 0, 1]])
    assert ekf.n_accepted == 0
    symmetric = 0.5 * (lopsided + lopsided.T)
    assert ekf.update_pose(ekf.predict_pose(), symmetric)


def test_a_measurement_covariance_whose_sums_overflow_is_refused():
    """cov6 of 1e308 printed numpy's "overflow encountered in add" and ended in numpy's
    LinAlgError "Eigenvalues did not converge"."""
    ekf = _ekf()
    with pytest.raises(InputError) as info:
        ekf.update_pose(ekf.predict_pose(), 1e308 * np.eye(6))
    assert str(info.value) == (
        "measurement covariance reaches 1e+308, beyond 9.75e+288: its sums overflow float64 "
        "(wrong units?)"
    )
    assert ekf.n_accepted == 0 and ekf.update_attitude([0, 0, 0, 1], 1e288 * np.eye(3))
