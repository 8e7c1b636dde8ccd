"""Bad input to the public Python API's one-call functions (a fuzzing round of the library, not
the CLI): arrays of complex numbers, booleans or text where real numbers go, text or None where
a number, a config, a camera, a catalogue or a path goes, non-rigid or overflowing transforms
and weights, NaN where a filter takes a vector. Each now raises the package's own error with one
line naming the argument, never numpy's, scipy's or pydantic's exception, and never returns a
silently wrong result."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from spacepose.core import metrics, se3
from spacepose.core.cloud import PointCloud, as_points
from spacepose.core.crlb import crlb
from spacepose.core.depth import DepthCamera, backproject
from spacepose.core.dynamics import inertia_ratios
from spacepose.core.ekf import RelativeNavEKF
from spacepose.core.fused_navigation import fused_navigate
from spacepose.core.gicp import gicp
from spacepose.core.icp import icp
from spacepose.core.jicp import average_three_covariance
from spacepose.core.nav_state import NavState
from spacepose.core.navigation import navigate
from spacepose.core.normals import estimate_normals
from spacepose.core.ransac import global_registration, match_features
from spacepose.core.rectangle_measurement import measure_rectangle
from spacepose.core.rectangles import CatalogueEntry, recognise
from spacepose.core.registration import kabsch
from spacepose.core.track_sequence import track_sequence
from spacepose.core.trajectory import Trajectory
from spacepose.core.voxel import voxel_downsample
from spacepose.errors import ConfigError, InputError
from spacepose.tools.cloud_io import read_cloud, write_cloud
from spacepose.tools.evaluation import compare_trajectory_files
from spacepose.tools.register import register
from spacepose.tools.trajectory_io import read_tum, write_tum

I4 = np.eye(4)


def _box(n: int = 400, seed: int = 0) -> np.ndarray:
    """``n`` points on the faces of a 0.3 x 0.2 x 0.1 m box 1 m in front of the sensor."""
    rng = np.random.default_rng(seed)
    size = np.array([0.3, 0.2, 0.1])
    pts = rng.uniform(-0.5, 0.5, (n, 3)) * size
    face = rng.integers(6, size=n)
    pts[np.arange(n), face // 2] = np.where(face % 2, 0.5, -0.5) * size[face // 2]
    return pts + np.array([0.0, 0.0, 1.0])


BOX = _box()


@pytest.fixture(scope="module")
def orbit():
    """Two orbit frames, their catalogue, mean motion and chaser attitude."""
    from spacepose.core.nav_start import scenario_geometry
    from spacepose.core.sim.scenarios import OrbitConfig, simulate_orbit
    from spacepose.tools.catalogue import parse_catalogue

    sim = simulate_orbit(OrbitConfig(frames=2))
    scenario = sim.scenario()
    n, R_O_C = scenario_geometry(scenario)
    frames = [(sim.frame(k).timestamp, sim.frame(k).cloud) for k in range(2)]
    return frames, parse_catalogue(scenario), n, R_O_C


@pytest.mark.parametrize(
    "values, kind",
    [
        (BOX.astype(complex), "complex numbers"),
        (BOX > 1.0, "booleans"),
        (BOX.astype(str), "text"),
    ],
)
def test_points_of_complex_booleans_or_text_are_refused(values, kind) -> None:
    """A complex (N, 3) array was cast to its real parts with only numpy's ComplexWarning, a
    boolean one (a mask passed by mistake) became coordinates of 0 and 1, and text holding
    numbers was parsed: every stage then ran on them. Now each is an InputError naming the
    points and what they are."""
    for call in (
        lambda: PointCloud(values),
        lambda: as_points(values),
        lambda: voxel_downsample(values, 0.02),
        lambda: icp(values, BOX),
    ):
        with pytest.raises(InputError, match=f"must be real numbers, got an array of {kind}"):
            call()


def test_pointcloud_sigma_as_text_is_an_input_error() -> None:
    """``PointCloud(points, sigma="s")`` ended in numpy's "could not convert string to float"
    ValueError. Now it is an InputError naming sigma."""
    with pytest.raises(InputError, match="sigma are not numeric"):
        PointCloud(BOX, sigma="s")
    with pytest.raises(InputError, match="sigma must be real numbers"):
        PointCloud(BOX, sigma=np.full(len(BOX), 0.01, dtype=complex))


@pytest.mark.parametrize("T", [I4.astype(complex), I4.astype(bool)])
def test_transforms_of_complex_or_booleans_are_refused(T) -> None:
    """An initial transform of complex numbers was cast with a ComplexWarning and one of
    booleans read as the identity; a complex trajectory and a complex twist passed the same
    way. Now each is an InputError naming the argument."""
    with pytest.raises(InputError, match="init_T_target_source must be real numbers"):
        icp(BOX, BOX, T)
    with pytest.raises(InputError, match="poses must be real numbers"):
        Trajectory([0.0], T[None])
    with pytest.raises(InputError, match="a twist must be real numbers"):
        se3.exp(np.zeros(6, dtype=T.dtype))


@pytest.mark.parametrize(
    "call",
    [
        lambda: se3.invert("T"),
        lambda: se3.log("T"),
        lambda: se3.adjoint("T"),
        lambda: se3.compose(I4, "T"),
        lambda: se3.transform_points("T", BOX),
        lambda: se3.transform_points(I4, "points"),
        lambda: se3.make_transform("R", [0, 0, 0]),
        lambda: se3.skew("v"),
        lambda: se3.geodesic_mean("T"),
    ],
)
def test_se3_helpers_given_text_raise_input_errors(call) -> None:
    """Text for a transform, points or a vector ended in numpy's "could not convert string to
    float" ValueError in every se3 helper. Now it is an InputError naming the argument."""
    with pytest.raises(InputError, match="must be numbers"):
        call()


@pytest.mark.parametrize("v", [[0.0, 0.0], None])
def test_skew_of_a_vector_not_of_three_numbers_is_refused(v) -> None:
    """``skew([0, 0])`` and ``skew(None)`` ended in numpy's IndexError. Now an InputError."""
    with pytest.raises(InputError, match=r"skew needs vectors of 3 numbers"):
        se3.skew(v)


def test_geodesic_mean_refuses_non_rigid_transforms_and_overflowing_weights() -> None:
    """A sheared transform was averaged as if it were a turn (a non-rigid "mean" came back);
    weights of 1e308 summed to inf, every normalised weight became 0 and the first transform
    came back as the mean; ``max_iterations="5"`` ended in a TypeError. Now each is an
    InputError."""
    turn = se3.exp([0.0, 0.0, 0.5, 0.1, 0.0, 0.0])
    shear = I4.copy()
    shear[0, 1] = 0.1
    with pytest.raises(InputError, match="transform 1 is not rigid"):
        se3.geodesic_mean(np.stack([I4, shear]))
    with pytest.raises(InputError, match="weights must be finite"):
        se3.geodesic_mean(np.stack([I4, turn]), [1e308, 1e308])
    with pytest.raises(InputError, match="max_iterations must be a whole number >= 1"):
        se3.geodesic_mean(np.stack([I4, turn]), max_iterations="5")


@pytest.mark.parametrize("size", ["0.02", True])
def test_voxel_size_as_text_or_a_boolean_is_refused(size) -> None:
    """``voxel_downsample(cloud, "0.02")`` downsampled at 2 cm and ``voxel_size=True`` at 1 m,
    without a word. Now each is an InputError naming the cell size."""
    with pytest.raises(InputError, match="cell size must be a number of metres"):
        voxel_downsample(BOX, size)


@pytest.mark.parametrize("origin", [(0.0, 0.0), "origin", (0, 0, 0, 0)])
def test_voxel_origin_not_three_numbers_is_refused(origin) -> None:
    """A grid origin of 2 or 4 numbers, or text, ended in numpy's reshape or conversion
    ValueError. Now it is an InputError naming the origin."""
    with pytest.raises(InputError, match="origin must be 3 finite numbers"):
        voxel_downsample(BOX, 0.02, origin=origin)


def test_kabsch_refuses_text_and_weights_whose_sum_overflows() -> None:
    """Text points ended in numpy's ValueError, and weights of 1e308 (their sum inf) in
    numpy's "SVD did not converge" LinAlgError. Now both are InputErrors."""
    with pytest.raises(InputError, match="kabsch: the source points must be numbers"):
        kabsch("points", BOX)
    with pytest.raises(InputError, match="sum past float64's range"):
        kabsch(BOX, BOX, np.full(len(BOX), 1e308))


def test_feature_matching_refuses_text_complex_features_and_a_huge_worker_count() -> None:
    """Text features ended in numpy's ValueError and complex ones were matched on their real
    parts; ``global_registration(workers=10**20)`` ended in scipy's OverflowError (the other
    stages take a count past the cores as all of them). Now text and complex features are
    InputErrors and the huge count registers as -1 does."""
    features = np.random.default_rng(0).uniform(size=(50, 33))
    with pytest.raises(InputError, match="source_features are not numeric"):
        match_features("a", features)
    with pytest.raises(InputError, match="source_features must be real numbers"):
        match_features(features.astype(complex), features)
    big = global_registration(BOX, BOX, 0.02, workers=10**20)
    every = global_registration(BOX, BOX, 0.02, workers=-1)
    np.testing.assert_array_equal(big.T_target_source, every.T_target_source)


@pytest.mark.parametrize("config", [None, "gicp", {"method": "gicp"}])
def test_tools_register_takes_its_config_as_every_stage_does(config) -> None:
    """``register(source, target, config=None)`` (or text, or a dict) ended in an
    AttributeError on ``config.global_registration``. Now a dict is validated into a
    RegisterConfig, as the other one-call functions take one, and anything else is a
    ConfigError."""
    if isinstance(config, dict):
        assert register(BOX, BOX, config=config).result.fitness > 0.99
    else:
        with pytest.raises(ConfigError, match="config must be a RegisterConfig"):
            register(BOX, BOX, config=config)


def test_estimate_normals_refuses_a_tree_that_is_no_search_index() -> None:
    """``estimate_normals(cloud, tree="tree")`` ended in an AttributeError (``'str' object has
    no attribute 'n'``). Now an InputError naming the tree."""
    with pytest.raises(InputError, match="tree must be a cKDTree or VoxelIndex"):
        estimate_normals(BOX, tree="tree")


def test_gicp_covariances_as_text_are_an_input_error() -> None:
    """``gicp(..., source_covariances="c")`` ended in numpy's ValueError. Now an InputError."""
    with pytest.raises(InputError, match="source_covariances must be numbers"):
        gicp(BOX, BOX, source_covariances="c")


def test_metrics_refuse_text_tolerance_non_trajectories_and_overflowing_poses(tmp_path) -> None:
    """A tolerance given as text (or None) ended in a TypeError of the comparison, in
    ``associate`` and in ``compare_trajectory_files``; ``evaluate("a", "b")`` in an
    AttributeError; a pose 1e300 m away gave an error table of inf and NaN after numpy's
    overflow warnings. Now each is an InputError."""
    with pytest.raises(InputError, match="tolerance must be a number of seconds"):
        metrics.associate([0.0, 1.0], [0.0, 1.0], tolerance="1e-6")
    traj = Trajectory([0.0, 1.0], np.stack([I4, I4]))
    est, gt = write_tum(tmp_path / "e.tum", traj), write_tum(tmp_path / "g.tum", traj)
    with pytest.raises(InputError, match="tolerance must be a number of seconds"):
        compare_trajectory_files(est, gt, tolerance=None)
    with pytest.raises(InputError, match="est must be a Trajectory"):
        metrics.evaluate("a", traj)
    far = I4.copy()
    far[0, 3] = 1e300
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(InputError, match="true pose 1 has a translation beyond"):
            metrics.error_table(np.stack([I4, I4]), np.stack([I4, far]))


@pytest.mark.parametrize("camera", ["cam", None])
def test_backproject_refuses_a_camera_that_is_no_depth_camera(camera) -> None:
    """``backproject(depth, "cam")`` ended in an AttributeError on ``camera.width``. Now a
    ConfigError naming the camera (a dict of its fields is read as a DepthCamera)."""
    depth = np.full((24, 32), 1000, dtype=np.uint16)
    with pytest.raises(ConfigError, match="camera must be a DepthCamera"):
        backproject(depth, camera)
    fields = {"fx": 100.0, "fy": 100.0, "cx": 15.5, "cy": 11.5}
    np.testing.assert_array_equal(
        backproject(depth, fields).points, backproject(depth, DepthCamera(**fields)).points
    )


def test_crlb_refuses_text_and_a_sigma_whose_inverse_square_leaves_float64() -> None:
    """σ = 1e-300 m ended in numpy's "Eigenvalues did not converge" LinAlgError; σ = 1e300 m
    gave a bound of no information after numpy's overflow warning; σ = "0.01" was parsed.
    Now each is an InputError naming sigma."""
    normals = estimate_normals(BOX).normals
    for sigma in (1e-300, 1e300):
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            with pytest.raises(InputError, match="inverse square"):
                crlb(BOX, normals, sigma)
    with pytest.raises(InputError, match="sigma must be numbers"):
        crlb(BOX, normals, "0.01")


@pytest.mark.parametrize("bad", [np.eye(5), "c", np.full((6, 6), np.nan)])
def test_jicp_covariance_refuses_covariances_not_finite_six_by_six(bad) -> None:
    """A 5x5 covariance ended in numpy's broadcast ValueError, text in a UFuncTypeError, and
    a NaN one came back as a NaN covariance. Now each is an InputError naming it."""
    good = 1e-4 * np.eye(6)
    with pytest.raises(InputError, match="cov_kj must"):
        average_three_covariance(I4, I4, bad, good, good)


def _state(**changes) -> NavState:
    fields = {
        "t": 0.0,
        "rho": np.array([0.0, 0.0, 10.0]),
        "v": np.zeros(3),
        "q_I_B": np.array([0.0, 0.0, 0.0, 1.0]),
        "omega_B": np.array([0.01, 0.02, 0.03]),
        "k": inertia_ratios([3.0, 2.0, 4.0]),
        "com": np.zeros(3),
    }
    fields.update(changes)
    return NavState(**fields)


@pytest.mark.parametrize(
    "args, match",
    [
        (("x", np.eye(3), _state()), "mean_motion must be a finite number"),
        ((None, np.eye(3), _state()), "mean_motion must be a finite number"),
        ((1e-3, "R", _state()), "R_O_C must be numbers"),
        ((1e-3, np.diag([1.0, 1.0, -1.0]), _state()), "R_O_C must be a 3x3 rotation"),
        ((1e-3, np.eye(3), None), "initial must be a NavState"),
        ((1e-3, np.eye(3), _state(q_I_B=np.zeros(4))), "non-zero norm"),
        ((1e-3, np.eye(3), _state(com="c")), "initial.com must be numbers"),
        ((1e-3, np.eye(3), _state(v=np.zeros((3, 1)))), "initial.v must be finite"),
    ],
)
def test_ekf_constructor_refuses_bad_arguments(args, match) -> None:
    """A text or None mean motion ended in float()'s ValueError / TypeError, text R_O_C in
    numpy's, a reflection for R_O_C was taken (RᵀR = I) and ended in scipy's "non-positive
    determinant" later, None for the state in an AttributeError, a zero quaternion in scipy's
    "zero norm" ValueError, a text CoM in numpy's ValueError and a (3, 1) velocity in numpy's
    concatenate error at the first prediction. Now each is an InputError naming it."""
    with pytest.raises(InputError, match=match):
        RelativeNavEKF(*args)


def test_ekf_takes_a_config_dict_and_refuses_other_configs() -> None:
    """``config={"sigma_accel": 1.0}`` (or text) ended in an AttributeError. Now a dict is
    validated into an EKFConfig and text is a ConfigError."""
    assert RelativeNavEKF(1e-3, np.eye(3), _state(), {"sigma_accel": 1.0}).config.sigma_accel == 1
    with pytest.raises(ConfigError, match="config must be a EKFConfig"):
        RelativeNavEKF(1e-3, np.eye(3), _state(), "c")


def test_ekf_updates_refuse_bad_vectors_before_they_corrupt_the_state() -> None:
    """A NaN catalogue centre passed the χ² gate (NaN > bound is false) and turned the whole
    state into NaN, the next call ending in scipy's "zero norm" ValueError; a centre of 2
    numbers ended in a broadcast error, a text covariance in numpy's ValueError, a zero or
    overflowing attitude quaternion in scipy's, a list as feature id in "unhashable type",
    ``predict(None)`` in a TypeError. Now each is an InputError and the state is untouched."""
    ekf = RelativeNavEKF(1.1e-3, np.eye(3), _state())
    before = ekf.state()
    calls = [
        (lambda: ekf.update_centroid("f", [np.nan, 0, 0], [0, 0, 10]), "catalogue centre"),
        (lambda: ekf.update_centroid("f", [0, 0], [0, 0, 10]), "catalogue centre"),
        (lambda: ekf.update_centroid("f", [0, 0, 0], [0, 0, 10], "c"), "covariance must be"),
        (lambda: ekf.update_centroid(["f"], [0, 0, 0], [0, 0, 10]), "feature_id must be"),
        (lambda: ekf.update_attitude(np.zeros(4)), "non-zero norm"),
        (lambda: ekf.update_attitude([0, 0, 0, 1e300]), "non-zero norm"),
        (lambda: ekf.predict(None), "t must be a finite number"),
        (lambda: ekf.predict(np.array([1.0, 2.0])), "t must be a finite number"),
    ]
    for call, match in calls:
        with pytest.raises(InputError, match=match):
            call()
    after = ekf.state()
    np.testing.assert_array_equal(after.rho, before.rho)
    np.testing.assert_array_equal(after.q_I_B, before.q_I_B)
    assert ekf.n_accepted == 0 and np.isfinite(ekf.P).all()


def test_track_sequence_refuses_text_timestamps_and_no_clouds() -> None:
    """Text timestamps ended in numpy's ValueError and ``clouds=None`` in "'NoneType' object
    is not iterable"; one (N, 3) array for ``clouds`` was tracked as N frames of one row each.
    Now each is an InputError."""
    with pytest.raises(InputError, match="timestamps must be numbers"):
        track_sequence([BOX, BOX, BOX], "abc")
    with pytest.raises(InputError, match="clouds must be a list of clouds"):
        track_sequence(None, [0.0])
    with pytest.raises(InputError, match="clouds must be a list of clouds"):
        track_sequence(BOX[:3], [0.0, 1.0, 2.0])


@pytest.mark.parametrize("run", [navigate, fused_navigate])
def test_navigation_refuses_bad_orbit_catalogue_config_and_frames(run, orbit) -> None:
    """Neither navigator checked its arguments: a NaN mean motion ended in numpy's "SVD did
    not converge", text in float()'s ValueError, a reflected R_O_C in scipy's, a (2, 2) one in
    a matmul error, a negative mean motion navigated without a word; a catalogue of text,
    None or dicts ended in an AttributeError or TypeError, a config dict in an
    AttributeError, ``frames=None`` or bare clouds in a TypeError, a NaN frame time in "SVD
    did not converge". Now each is the package's error naming the argument."""
    frames, catalogue, n, R_O_C = orbit
    bad = [
        ({"mean_motion": np.nan}, InputError, "mean_motion must be positive"),
        ({"mean_motion": -1e-3}, InputError, "mean_motion must be positive"),
        ({"mean_motion": "x"}, InputError, "mean_motion holds text"),
        (
            {"R_O_C": np.diag([1.0, 1.0, -1.0])},
            InputError,
            "R_O_C is not a proper rotation: .* det -1",
        ),
        ({"R_O_C": np.eye(2)}, InputError, "R_O_C must be a finite 3x3 rotation"),
        ({"catalogue": "cat"}, InputError, "catalogue must be a list of CatalogueEntry"),
        ({"catalogue": None}, InputError, "catalogue must be a list of CatalogueEntry"),
        ({"catalogue": [{"name": "a"}]}, InputError, "got a dict"),
        ({"config": {"x": 1}}, ConfigError, "x: Extra inputs are not permitted"),
        ({"frames": None}, InputError, "frames must be"),
        ({"frames": [frames[0][1]]}, InputError, "frame 0 must be a"),
        ({"frames": [(np.nan, frames[0][1])]}, InputError, "frame time t must be a finite"),
    ]
    for change, error, match in bad:
        args = {"frames": frames, "catalogue": catalogue, "mean_motion": n, "R_O_C": R_O_C}
        args["config"] = None
        args.update(change)
        with pytest.raises(error, match=match):
            run(**args)


def test_navigate_takes_frames_as_arrays(orbit) -> None:
    """Frames given as (N, 3) arrays ended in an AttributeError (``'numpy.ndarray' object has
    no attribute 'points'``). Now they are taken as clouds, as every other stage takes them,
    and navigate as the PointClouds do."""
    frames, catalogue, n, R_O_C = orbit
    as_arrays = [(t, cloud.points) for t, cloud in frames]
    rows = navigate(as_arrays, catalogue, n, R_O_C)
    same = navigate(frames, catalogue, n, R_O_C)
    assert [r.status for r in rows] == [r.status for r in same]


def test_catalogue_entry_built_in_code_raises_a_config_error() -> None:
    """``CatalogueEntry(a=2, b=1, ...)`` raised pydantic's multi-line ValidationError. Now a
    one-line ConfigError naming the field, as a StageConfig does."""
    fields = {"name": "x", "center": [0, 0, 0], "R_model_plane": np.eye(3).tolist()}
    with pytest.raises(ConfigError, match=r"short side a = 2\.0 exceeds long side b = 1\.0"):
        CatalogueEntry(**fields, a=2.0, b=1.0)
    with pytest.raises(ConfigError, match="center"):
        CatalogueEntry(**{**fields, "center": [np.nan, 0, 0]}, a=0.5, b=1.0)


def test_recognise_refuses_what_is_no_measurement_or_catalogue() -> None:
    """``recognise("m", catalogue)`` ended in an AttributeError, and a catalogue of text or
    None gave None ("not recognised") without a word; a (2, 2) predicted attitude would end in
    a matmul error. Now each is an InputError."""
    plate = np.column_stack(
        [np.random.default_rng(2).uniform([-0.1, -0.2], [0.1, 0.2], (400, 2)), np.ones(400)]
    )
    m = measure_rectangle(plate)
    entry = CatalogueEntry(
        name="x", center=(0, 0, 0), R_model_plane=np.eye(3).tolist(), a=0.2, b=0.4
    )
    with pytest.raises(InputError, match="measurement must be a RectangleMeasurement"):
        recognise("m", [entry])
    for catalogue in ("cat", None):
        with pytest.raises(InputError, match="catalogue must be a list of CatalogueEntry"):
            recognise(m, catalogue)
    with pytest.raises(InputError, match="predicted_R_sensor_model must be a finite 3x3"):
        recognise(m, [entry], predicted_R_sensor_model=np.eye(2))


def test_measure_rectangle_of_text_is_an_input_error() -> None:
    """``measure_rectangle("points")`` ended in numpy's ValueError. Now an InputError."""
    with pytest.raises(InputError, match="points must be numbers"):
        measure_rectangle("points")


def test_cloud_io_refuses_bad_paths_scales_clouds_and_switches(tmp_path) -> None:
    """``read_cloud(None)`` and ``write_cloud(None, ...)`` ended in pathlib's TypeError, a
    scale of text or None in numpy's "ufunc 'isfinite' not supported", ``scale=True`` read
    the file at a scale of 1, a cloud of text in numpy's ValueError and ``binary="no"`` wrote
    binary. Now each is an InputError."""
    path = write_cloud(tmp_path / "a.ply", BOX)
    with pytest.raises(InputError, match="path must be a file name"):
        read_cloud(None)
    with pytest.raises(InputError, match="path must be a file name"):
        write_cloud(None, BOX)
    for scale in ("1e-3", None, True):
        with pytest.raises(InputError, match="scale must be a positive number"):
            read_cloud(path, scale=scale)
    with pytest.raises(InputError, match="cloud is not numeric"):
        write_cloud(tmp_path / "b.ply", "cloud")
    with pytest.raises(InputError, match="binary must be True or False"):
        write_cloud(tmp_path / "c.ply", BOX, binary="no")


def test_trajectory_io_refuses_non_trajectories_and_bad_paths(tmp_path) -> None:
    """``write_tum(path, poses_array)`` ended in an AttributeError (``no attribute 'poses'``),
    ``read_tum(None)`` and ``compare_trajectory_files(None, None)`` in pathlib's TypeError.
    Now each is an InputError."""
    with pytest.raises(InputError, match="traj must be a Trajectory"):
        write_tum(tmp_path / "a.tum", np.stack([I4, I4]))
    with pytest.raises(InputError, match="path must be a file name"):
        read_tum(None)
    with pytest.raises(InputError, match="est_path must be a file name"):
        compare_trajectory_files(None, None)
