"""Bad inputs found by a seventh hostile round: each ends in one line naming the file (or the
parameter) and the problem, never a traceback or a silently wrong result."""

from __future__ import annotations

import numpy as np
import pytest

from spacepose.cli import main
from spacepose.core import se3
from spacepose.core.cloud import PointCloud
from spacepose.core.cloud_quality import normal_consistency
from spacepose.core.fpfh import FPFHConfig, compute_fpfh
from spacepose.core.gicp import gicp
from spacepose.core.icp import icp
from spacepose.core.mls import mpp_mls
from spacepose.core.normals import estimate_normals
from spacepose.core.planes import PlaneConfig, extract_planes
from spacepose.core.ransac import global_registration
from spacepose.core.rectangle_search import find_rectangles
from spacepose.core.registration import kabsch
from spacepose.core.trajectory import Trajectory
from spacepose.errors import ConfigError, InputError, SpaceposeWarning
from spacepose.tools.cloud_io import read_cloud, write_cloud
from spacepose.tools.runs import read_run
from spacepose.tools.trajectory_io import write_kitti, write_tum


def _plane(n: int = 400, seed: int = 0) -> np.ndarray:
    """``n`` points on a 0.4 m square plate 1 m in front of the sensor, slightly noisy."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-0.2, 0.2, (n, 2))
    return np.column_stack([xy, 1.0 + 1e-4 * rng.normal(size=n)])


# -- PointCloud: normals without a direction, a negative noise sigma ------------------------------


def test_a_cloud_with_zero_normals_is_refused_naming_the_row():
    """A (0, 0, 0) normal has no direction: the cloud was made, and a point-to-plane residual
    weighed by it is zero whatever the pose."""
    points = _plane(5)
    normals = np.tile([0.0, 0.0, -1.0], (5, 1))
    normals[[2, 4]] = 0.0
    with pytest.raises(InputError) as exc:
        PointCloud(points, normals, source="scan.ply")
    assert str(exc.value) == (
        "scan.ply: normals: 2 of 5 rows are (0, 0, 0) (first at row 2): a normal needs a "
        "direction; leave the normals out to have them estimated"
    )
    with pytest.raises(InputError, match="first at row 2"):
        PointCloud(points).with_normals(normals)


def test_a_cloud_with_a_negative_sigma_is_refused_naming_the_row():
    """σ is a standard deviation: -0.5 was kept as the point's noise without a word."""
    with pytest.raises(InputError) as exc:
        PointCloud(_plane(4), sigma=[0.001, 0.001, -0.5, 0.0], source="scan.ply")
    assert str(exc.value) == (
        "scan.ply: sigma: 1 of 4 values are negative (first at row 2: -0.5): a noise sigma is "
        "a standard deviation, >= 0"
    )


def test_a_cloud_keeps_dropping_non_finite_normal_and_sigma_rows():
    """As documented: a NaN row of normals or σ is dropped with its point, not refused."""
    normals = np.tile([0.0, 0.0, -1.0], (4, 1))
    normals[1] = np.nan
    cloud = PointCloud(_plane(4), normals, sigma=[0.001, 0.001, np.inf, 0.0])
    assert (len(cloud), cloud.n_dropped) == (2, 2)


# -- kabsch: NaN points, bad weights --------------------------------------------------------------


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ("nan_source", "kabsch: the source points have non-finite entries (NaN or inf)"),
        ("inf_target", "kabsch: the target points have non-finite entries (NaN or inf)"),
        ("nan_weight", "kabsch: the weights have non-finite entries (NaN or inf)"),
        ("zero_weights", "kabsch: the weights of a set of pairs are all zero"),
        ("negative_weights", "kabsch: weights must be >= 0, got -1"),
        ("short_weights", "kabsch needs one weight per point pair (10,), got (3,)"),
    ],
)
def test_kabsch_of_bad_pairs_is_an_input_error(change, message):
    """NaN points, a NaN or all-zero weight ended in numpy's LinAlgError ('SVD did not
    converge'); negative weights gave a wrong transform without a word."""
    rng = np.random.default_rng(3)
    source = rng.normal(size=(10, 3))
    target = source + np.array([0.1, 0.0, 0.0])
    weights = None
    if change == "nan_source":
        source[4, 1] = np.nan
    elif change == "inf_target":
        target[0, 0] = np.inf
    elif change == "nan_weight":
        weights = np.r_[np.nan, np.ones(9)]
    elif change == "zero_weights":
        weights = np.zeros(10)
    elif change == "negative_weights":
        weights = -np.ones(10)
    else:
        weights = np.ones(3)
    with pytest.raises(InputError) as exc:
        kabsch(source, target, weights)
    assert str(exc.value) == message


def test_kabsch_with_good_weights_is_unchanged():
    rng = np.random.default_rng(3)
    source = rng.normal(size=(10, 3))
    T = kabsch(source, source + np.array([0.1, 0.0, 0.0]), np.ones(10, dtype=bool))
    np.testing.assert_allclose(T[:3, 3], [0.1, 0.0, 0.0], atol=1e-12)


# -- one-call functions given a config that is not their model -----------------------------------


def _one_calls():
    """(name, call with a config) of every README one-call function taking a stage config."""
    points = _plane()
    cloud = estimate_normals(points)
    return [
        ("compute_fpfh", "FPFHConfig", lambda c: compute_fpfh(cloud, c)),
        ("extract_planes", "PlaneConfig", lambda c: extract_planes(points, c)),
        ("estimate_normals", "NormalsConfig", lambda c: estimate_normals(points, c)),
        ("mpp_mls", "MLSConfig", lambda c: mpp_mls(points, c)),
        ("icp", "ICPConfig", lambda c: icp(cloud, cloud, np.eye(4), c)),
        ("gicp", "GICPConfig", lambda c: gicp(cloud, cloud, np.eye(4), c)),
        ("find_rectangles", "RectangleConfig", lambda c: find_rectangles(points, config=c)),
    ]


@pytest.mark.parametrize("given", [None, "gicp", 3, ()])
def test_a_config_that_is_no_config_is_a_config_error(given):
    """None, a string, a number or a tuple as the config ended in AttributeError
    ('NoneType' object has no attribute 'radius')."""
    for name, model, call in _one_calls():
        with pytest.raises(ConfigError) as exc:
            call(given)
        assert str(exc.value) == (
            f"config must be a {model} (or a dict of its fields), got {type(given).__name__}"
        ), name


def test_a_config_of_another_stage_is_a_config_error():
    with pytest.raises(ConfigError, match=r"^config must be a FPFHConfig .* got PlaneConfig$"):
        compute_fpfh(estimate_normals(_plane()), PlaneConfig())


def test_a_config_given_as_a_dict_is_validated_as_the_tracker_does():
    """A dict of fields is read as the Tracker reads one: validated into the model (it ended
    in AttributeError: 'dict' object has no attribute 'seed')."""
    points = _plane()
    planes = extract_planes(points, {"seed": 1, "max_planes": 1})
    assert [len(p.inliers) for p in planes] == [len(points)]
    cloud = estimate_normals(points)
    np.testing.assert_array_equal(
        compute_fpfh(cloud, {"radius": 0.05}), compute_fpfh(cloud, FPFHConfig(radius=0.05))
    )
    with pytest.raises(ConfigError) as exc:
        extract_planes(points, {"sead": 1})
    assert str(exc.value) == "invalid plane config: sead: Extra inputs are not permitted"
    with pytest.raises(ConfigError, match=r"^plane_config must be a PlaneConfig"):
        find_rectangles(points, plane_config=None)


def test_global_registration_configs_and_voxel_size_are_checked():
    """A dict override ended in AttributeError (an empty one was taken for None), and a voxel
    size given as text in numpy's TypeError ('ufunc isfinite not supported')."""
    points = _plane()
    with pytest.raises(ConfigError) as exc:
        global_registration(points, points, 0.01, fpfh={"max_nn": 0})
    assert str(exc.value).startswith("invalid FPFH config: max_nn: ")
    with pytest.raises(ConfigError, match=r"^ransac must be a RansacConfig .* got str$"):
        global_registration(points, points, 0.01, ransac="fast")
    with pytest.raises(InputError) as exc:
        global_registration(points, points, "1cm")
    assert str(exc.value) == "voxel_size must be a positive number of metres, got '1cm'"


# -- a run folder with a timestamps.txt -----------------------------------------------------------


@pytest.fixture(scope="module")
def lab_run(tmp_path_factory):
    """A two-frame lab run, written by simulate."""
    run = tmp_path_factory.mktemp("lab") / "run"
    assert main(["simulate", "lab", "--frames", "2", "--seed", "0", "--out", str(run)]) == 0
    return run


@pytest.mark.parametrize("where", ["timestamps.txt", "frames/timestamps.txt", "Timestamps.txt"])
def test_a_timestamps_file_in_a_run_folder_is_warned_about(tmp_path, lab_run, capsys, where):
    """A run's frames are timed by groundtruth.tum: a timestamps.txt put in the run (the frame
    folder format's) was passed over without a word."""
    import shutil

    run = shutil.copytree(lab_run, tmp_path / "run")
    stamps = run / where
    stamps.write_text("0\n0.5\n")
    message = (
        f"{stamps}: not read: a run folder's frames are timed by its groundtruth.tum "
        "(timestamps.txt times a folder of frame files; give frames/ itself to time its frames "
        "by it, or remove it)"
    )
    with pytest.warns(SpaceposeWarning) as caught:
        read_run(run)
    assert [str(w.message) for w in caught] == [message]
    capsys.readouterr()
    assert main(["track", str(run), "--out", str(tmp_path / "est.tum")]) == 0
    assert f"warning: {message}" in capsys.readouterr().err.splitlines()


def test_a_run_folder_without_timestamps_reads_without_a_word(lab_run):
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error", SpaceposeWarning)
        assert len(read_run(lab_run)) == 2


# -- normal_consistency: an array, a bin width of 0 or NaN ---------------------------------------


@pytest.mark.parametrize(
    ("args", "message"),
    [
        ((), "cloud: normal consistency needs a cloud with normals (run estimate_normals first)"),
        ((10, 0.0), "bin_width_deg must divide 180, got 0.0"),
        ((10, float("nan")), "bin_width_deg must divide 180, got nan"),
        ((0,), "cloud: normal consistency needs k >= 1 neighbours, got 0"),
    ],
)
def test_normal_consistency_of_bad_arguments_is_an_input_error(args, message):
    """An (N, 3) array ended in AttributeError ('has_normals'), a bin width of 0 in
    ZeroDivisionError, one of NaN in 'cannot convert float NaN to integer', and k = 0 in a
    NaN share without a word."""
    points = _plane()
    cloud = points if not args else estimate_normals(points)
    with pytest.raises(InputError) as exc:
        normal_consistency(cloud, *args)
    assert str(exc.value) == message


# -- writers: a folder by the file's name, float32 overflow ---------------------------------------


@pytest.mark.parametrize("name", ["cloud.ply", "cloud.npz", "est.tum", "est.kitti"])
def test_writing_onto_a_folder_names_it(tmp_path, name):
    """A folder by the output's name ended in a bare IsADirectoryError."""
    out = tmp_path / name
    out.mkdir()
    with pytest.raises(InputError) as exc:
        if name.startswith("cloud"):
            write_cloud(out, _plane(10))
        else:
            trajectory = Trajectory(np.arange(2.0), np.tile(np.eye(4), (2, 1, 1)))
            (write_tum if name.endswith(".tum") else write_kitti)(out, trajectory)
    assert str(exc.value) == f"{out}: output exists and is not a regular file (a folder?)"


def test_writing_float32_beyond_its_range_is_refused(tmp_path):
    """1e100 m written as float32 was stored as inf (numpy's overflow warning alone), and the
    file read back without those points. Asked for, float32 is refused; by default such a cloud
    is written as float64."""
    out = tmp_path / "far.ply"
    points = _plane(10)
    points[3] = [1e100, 0.0, 1.0]
    with pytest.raises(InputError) as exc:
        write_cloud(out, points, dtype="float32")
    assert str(exc.value) == (
        f"{out}: points reach |coordinate| 1e+100, beyond float32's 3.4e+38: write them with "
        "dtype='float64'"
    )
    assert not out.exists()
    write_cloud(out, points)
    np.testing.assert_array_equal(read_cloud(out).points, points)


# -- se3: a rotation matrix where a transform goes ------------------------------------------------


@pytest.mark.parametrize("apply", [se3.transform_points, se3.rotate_vectors])
def test_a_3x3_matrix_is_no_transform(apply):
    """transform_points(R, p) with R 3x3 added R's third column as a translation without a
    word; points of the wrong width ended in numpy's matmul error."""
    points = _plane(5)
    with pytest.raises(InputError) as exc:
        apply(np.eye(3), points)
    assert str(exc.value) == "T_a_b must be a 4x4 transform, got shape (3, 3)"
    with pytest.raises(InputError) as exc:
        apply(np.eye(4), points[:, :2])
    what = "points" if apply is se3.transform_points else "vectors"
    assert str(exc.value) == f"{what} must have shape (N, 3), got (5, 2)"
    np.testing.assert_array_equal(apply(np.eye(4), points), points)
