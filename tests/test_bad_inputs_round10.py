"""Bad inputs found by a tenth hostile round (about 820 runs of the CLI): each ends in one line
naming the file and the problem, the error last, never a traceback, a hang or a wrong reason."""

from __future__ import annotations

import numpy as np
import pytest

from spacepose.cli import main
from spacepose.core.config import load_config
from spacepose.core.metrics import associate
from spacepose.core.tracker_config import TrackerConfig
from spacepose.errors import ConfigError, FileFormatError, InputError
from spacepose.tools.cloud_io import read_cloud

# -- YAML aliases that stand for a structure without end ------------------------------------------


def _laughs(levels: int) -> str:
    """Aliases of aliases: ``levels`` lines of ten aliases each stand for 10**levels values."""
    text = "a0: &a0 [x, x, x, x, x, x, x, x, x, x]\n"
    for i in range(1, levels + 1):
        text += f"a{i}: &a{i} [" + ", ".join([f"*a{i - 1}"] * 10) + "]\n"
    return text


_WITHOUT_END = "its aliases stand for a structure without end or far larger than the file"


@pytest.mark.parametrize(
    ("text", "problem"),
    [
        ("a: &a [*a]\n", _WITHOUT_END),
        ("a: &a {inner: *a}\n", "line 1:4: found unconstructable recursive node"),
        (_laughs(8), _WITHOUT_END),
    ],
    ids=["list in itself", "mapping in itself", "a billion values"],
)
def test_yaml_aliases_without_end_are_one_config_error(tmp_path, text, problem):
    """A list anchored inside itself ended in a RecursionError traceback (the key check walked
    the cycle; PyYAML refuses a mapping so itself); eight levels of aliases of aliases (430
    bytes) hung the run."""
    path = tmp_path / "config.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError) as exc:
        load_config(TrackerConfig, path)
    assert str(exc.value).startswith(f"{path}: not valid YAML: {problem}")


def test_an_alias_that_reuses_a_block_is_read(tmp_path):
    """A config that repeats a value by alias stays legal: only its keys decide."""
    path = tmp_path / "config.yaml"
    path.write_text("gate: &g 0.9\nhealth: {min_points: 150}\ncoarse_voxel: *g\n")
    config = load_config(TrackerConfig, path)
    assert config.gate == config.coarse_voxel == 0.9 and config.health.min_points == 150


def test_a_recursive_intrinsics_file_is_one_line_on_the_command_line(tmp_path, capsys):
    """The depth folder's intrinsics.yaml went through the same walk."""
    from PIL import Image

    folder = tmp_path / "depth"
    folder.mkdir()
    Image.fromarray(np.full((12, 16), 1200, np.uint16)).save(folder / "000000.png")
    (folder / "intrinsics.yaml").write_text("fx: &a [*a]\nfy: 12\ncx: 7.5\ncy: 5.5\n")
    assert main(["track", str(folder), "--out", str(tmp_path / "est.tum")]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"error: {folder / 'intrinsics.yaml'}: not valid")


# -- PLY values beyond their declared type -------------------------------------------------------


@pytest.mark.parametrize(
    ("kind", "value", "problem"),
    [
        ("float", "1e300", "overflow encountered in cast"),
        ("uchar", "300", "Python integer 300 out of bounds for uint8"),
    ],
)
def test_a_ply_value_beyond_its_type_names_the_file_and_the_problem(tmp_path, kind, value, problem):
    """1e300 declared float was cast to inf with numpy's bare warning, and the cloud refused
    for NaN/inf it did not hold; 300 declared uchar ended in plyfile's OverflowError."""
    path = tmp_path / "huge.ply"
    x = value if kind == "float" else "1"
    extra = "property uchar red\n" if kind == "uchar" else ""
    last = f" {value}" if kind == "uchar" else ""
    path.write_text(
        "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
        f"property float z\n{extra}end_header\n{x} 0 1{last}\n0 1 1{last and ' 2'}\n"
        f"1 1 1{last and ' 3'}\n"
    )
    with pytest.raises(FileFormatError) as exc:
        read_cloud(path)
    assert str(exc.value) == f"{path}: a value does not fit its declared PLY type ({problem})"


# -- a timestamp of 1e300 in the error of an unmatched estimate ----------------------------------


def test_an_unmatched_timestamp_is_written_as_a_number_not_three_hundred_digits():
    with pytest.raises(InputError) as exc:
        associate(np.array([0.0, 1e300]), np.array([0.0, 1.0]))
    assert "(first: t = 1e+300, nearest ground truth 1e+300 s away)" in str(exc.value)
    assert len(str(exc.value)) < 200


# -- the error line last ---------------------------------------------------------------------------


def test_the_error_is_the_last_line_after_the_warning_counts(tmp_path, capsys):
    """A folder whose every frame is lost printed its error, then "N more with the same
    warning": the error was not the last line."""
    for i in range(6):
        (tmp_path / f"f{i}.xyz").write_text("garbage\n")
    assert main(["track", str(tmp_path), "--out", str(tmp_path / "est.tum")]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-2].startswith("warning: 3 more with the same warning: not read, frame lost")
    assert err[-1].startswith(f"error: {tmp_path}: every frame was lost")


def test_a_model_free_run_with_nothing_after_its_first_frame_exits_1(tmp_path, capsys):
    """Model-free, the first frame is the identity by definition: a run whose every later frame
    was lost tracked nothing, yet exited 0 with "1 ok"."""
    from spacepose.core.sim import scenario_config, simulate

    frame = simulate(scenario_config("lab", frames=1)).frame(0)
    np.savetxt(tmp_path / "f0.xyz", frame.cloud.points)
    for i in range(1, 4):
        (tmp_path / f"f{i}.xyz").write_text("garbage\n")
    out = tmp_path / "est.tum"
    assert main(["track", str(tmp_path), "--out", str(out)]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith(
        f"error: {tmp_path}: every frame but the one that sets the target frame was lost (frame 1"
    )
    assert len(out.read_text().splitlines()) == 4  # the rows are written all the same


@pytest.mark.parametrize(
    ("text", "problem"),
    [
        ("1,2,3\n4 5 6\n7,8,9\n", "line 2: fields separated by blanks where the first row's are"),
        ("1 2 3\n4,5,6\n7 8 9\n", "line 2: fields separated by commas where the first row's are"),
    ],
)
def test_a_text_cloud_mixing_separators_names_the_line(tmp_path, text, problem):
    """Said only "cannot parse text point file", with no line."""
    path = tmp_path / "mixed.csv"
    path.write_text(text)
    with pytest.raises(FileFormatError) as exc:
        read_cloud(path)
    assert str(exc.value).startswith(f"{path}: {problem}")


# -- found on the Python API ----------------------------------------------------------------------


def _box_surface(n: int, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    p = rng.uniform(-0.5, 0.5, (n, 3))
    axis = rng.integers(0, 3, n)
    p[np.arange(n), axis] = np.sign(rng.uniform(-1, 1, n)) * 0.5
    return p


def test_one_far_stray_does_not_make_a_surface_collinear():
    """A box and one return 10⁶ m off: its spread along that direction alone made the cloud
    "collinear" for normals and planes (at 10⁵ m both worked). A line with the stray stays
    a line."""
    from spacepose.core.normals import estimate_normals
    from spacepose.core.planes import extract_planes
    from spacepose.errors import DegenerateGeometryError

    stray = np.array([[1e6, 1e6, 1e6]])
    box = np.r_[_box_surface(2000), stray]
    normals = estimate_normals(box).normals
    # The box's own normals are its faces': unit vectors along an axis (6 faces, ±).
    assert np.median(np.abs(normals[:-1]).max(axis=1)) > 0.99
    assert len(extract_planes(box)) >= 5
    line = np.r_[np.c_[np.linspace(0, 1, 100), np.zeros((100, 2))], stray]
    with pytest.raises(DegenerateGeometryError):
        estimate_normals(line)
    with pytest.raises(DegenerateGeometryError):
        extract_planes(line)


def test_normals_not_of_unit_length_are_refused():
    """A PointCloud took them as given: ICP's pose moved by 1.2 mm and its information by a
    factor of 34 when the normals' lengths ran from 0.1 to 10."""
    from spacepose.core.cloud import PointCloud

    points = _box_surface(100)
    normals = np.zeros_like(points)
    normals[:, 2] = 1.0
    assert PointCloud(points, normals * (1 + 5e-4)).normals is not None  # float rounding
    normals[7] *= 10.0
    with pytest.raises(InputError) as exc:
        PointCloud(points, normals)
    assert str(exc.value) == (
        "normals: 1 of 100 rows are not of unit length (row 7: 10); divide them by their "
        "lengths, or leave them out"
    )


@pytest.mark.parametrize("register", ["icp", "gicp"])
def test_a_registration_of_one_repeated_point_is_degenerate_at_once(register):
    """Every search scanned all the points in one grid cell: 40,000 copies took 2.2 s, two
    million did not finish."""
    from spacepose.core.gicp import gicp
    from spacepose.core.icp import icp
    from spacepose.errors import DegenerateGeometryError

    function = {"icp": icp, "gicp": gicp}[register]
    with pytest.raises(DegenerateGeometryError) as exc:
        function(np.ones((2_000_000, 3)), _box_surface(500), workers=1)
    assert str(exc.value) == ("all 2000000 points of the source cloud at one place: no rigid fit")


def test_a_cloud_whose_first_rows_repeat_is_still_registered():
    """The one-place test reads the first rows first: twenty copies of one point ahead of a
    surface must not be taken for a cloud at one place."""
    from spacepose.core import se3
    from spacepose.core.icp import ICPConfig, icp

    surface = _box_surface(500)
    T_target_source = se3.exp(np.array([0.0, 0.0, 0.02, 0.003, -0.002, 0.001]))
    source = se3.transform_points(se3.invert(T_target_source), surface)
    source = np.vstack([np.repeat(source[:1], 20, axis=0), source])
    config = ICPConfig(max_correspondence_distance=0.05, max_iterations=60)
    result = icp(source, surface, config=config, workers=1)
    assert np.abs(result.T_target_source - T_target_source).max() < 1e-4


@pytest.mark.parametrize(
    ("T", "problem"),
    [
        (np.diag([2.0, 2.0, 2.0, 1.0]), "RᵀR off the identity by 3, det 8"),
        (np.diag([-1.0, 1.0, 1.0, 1.0]), "RᵀR off the identity by 0, det -1"),
        (
            np.array([[1, 1e-5, 0, 0], [0, 1, 0, 0], [0, 0, 1, 0], [0, 0, 0, 1.0]]),
            "RᵀR off the identity by 1e-05, det 1",
        ),
    ],
    ids=["scale", "reflection", "shear"],
)
def test_the_log_of_a_transform_that_is_not_rigid_is_refused(T, problem):
    """A scale or a reflection gave the zero twist, as if no motion."""
    from spacepose.core import se3

    with pytest.raises(InputError) as exc:
        se3.log(T)
    assert str(exc.value).startswith("log: T's rotation block is not a proper rotation")
    assert problem in str(exc.value)
    with pytest.raises(InputError, match="make_transform: R is not a proper rotation"):
        se3.make_transform(T[:3, :3], np.zeros(3))
    bad_row = np.eye(4)
    bad_row[3, 0] = 1.0
    with pytest.raises(InputError, match=r"last row must be \(0, 0, 0, 1\)"):
        se3.log(bad_row)
    twist = np.array([0.1, -0.2, 0.3, 1.0, 2.0, -3.0])
    np.testing.assert_allclose(se3.log(se3.exp(twist)), twist, atol=1e-12)


@pytest.mark.parametrize("timestamp", ["2.0", True])
def test_a_frame_timestamp_given_as_text_or_yes_no_is_refused(timestamp):
    """track_frame read "2.0" and True as numbers, while track_sequence refused them."""
    from spacepose.core.tracker import Tracker

    with pytest.raises(InputError) as exc:
        Tracker().track_frame(_box_surface(500), timestamp)
    assert str(exc.value) == f"frame timestamp (s) must be a number, got {timestamp!r}"


@pytest.mark.parametrize(
    ("values", "kind"),
    [
        ([["1", "2", "3"]] * 3, "text"),
        ([[True, False, True]] * 3, "booleans"),
        (np.zeros((3, 3), "M8[s]"), "dates"),
        (np.zeros((3, 3), "m8[s]"), "time spans"),
        (np.array([[1, "2", 3]] * 3, dtype=object), "text"),
    ],
)
def test_coordinates_that_are_not_real_numbers_are_refused(values, kind):
    """Lists of text or yes/no, dates and objects holding text were read as coordinates."""
    from spacepose import PointCloud

    with pytest.raises(InputError) as exc:
        PointCloud(values)
    assert str(exc.value) == f"points must be real numbers, got an array of {kind}"
    with pytest.raises(InputError, match=f"estimated timestamps must be real numbers.*{kind}"):
        associate(values[0], np.arange(3.0))


def test_a_selection_out_of_range_is_an_input_error():
    """numpy's IndexError before."""
    from spacepose import PointCloud

    cloud = PointCloud(_box_surface(10))
    with pytest.raises(InputError) as exc:
        cloud.select([11])
    assert (
        str(exc.value) == "select of 10 points: index 11 is out of bounds for axis 0 with size 10"
    )
    with pytest.raises(InputError, match="select of 10 points: boolean index did not match"):
        cloud.select(np.ones(3, bool))


def test_pose_noise_of_overflowing_or_complex_errors_is_refused():
    """Errors of 1e200σ gave a factor of inf, complex ones were cut to their real parts."""
    from spacepose.core.pose_noise import pose_noise_scale, whitened_errors

    w = np.random.default_rng(0).normal(size=(300, 6))
    with pytest.raises(
        InputError, match=r"^whitened errors up to .*e\+200σ: their squares overflow"
    ):
        pose_noise_scale(w * 1e200)
    with pytest.raises(
        InputError, match="whitened errors must be real numbers, got an array of complex"
    ):
        pose_noise_scale(w.astype(complex))
    with pytest.raises(InputError, match=r"^poses must be \(N, 4, 4\) .* got \(\), "):
        whitened_errors(5.0, np.eye(6)[None], np.eye(4)[None])
    # White errors their σ describes: each axis's ratio near 1, the factor the root of the
    # largest (or 1).
    fine = pose_noise_scale(w)
    assert np.all((fine.batch_ratios > 0.2) & (fine.batch_ratios < 3.5))
    assert fine.scale == np.sqrt(max(1.0, fine.batch_ratios.max()))


def test_a_pose_graph_of_bad_arguments_is_an_input_error():
    """Text poses, a tuple for an edge, no fixed set, a text iteration count and text node
    numbers ended in numpy's or Python's errors; 0 iterations, a fractional fixed node and an
    asymmetric information were taken."""
    from spacepose.core.posegraph import PoseGraphEdge, optimize_pose_graph

    T = np.eye(4)
    T[0, 3] = 1.0
    poses, info = np.stack([np.eye(4)] * 2), np.eye(6)
    edge = PoseGraphEdge(0, 1, T, info)
    cases = [
        ({"poses": "abc", "edges": []}, "pose graph poses must be numbers"),
        ({"edges": None}, "pose graph edges must be a list of PoseGraphEdge, got NoneType"),
        ({"edges": [(0, 1, T, info)]}, "pose graph edges must be PoseGraphEdge, got tuple"),
        ({"edges": [edge], "fixed": None}, "pose graph fixed nodes must be whole numbers"),
        ({"edges": [edge], "fixed": [0.5]}, "pose graph fixed node must be a whole number >= 0"),
        ({"edges": [edge], "max_iterations": 0}, "max_iterations must be a whole number >= 1"),
        ({"edges": [PoseGraphEdge("0", 1, T, info)]}, "edge node i must be a whole number >= 0"),
        ({"edges": [PoseGraphEdge(0, 1, T, np.triu(np.ones((6, 6))) + info)]}, "symmetric"),
    ]
    for kwargs, problem in cases:
        with pytest.raises(InputError, match=problem):
            optimize_pose_graph(**({"poses": poses} | kwargs))
    # The same graph, well given: node 1 one metre along x.
    assert optimize_pose_graph(poses, [edge]).poses[1][0, 3] == pytest.approx(1.0)


def test_navigation_errors_of_bad_tables_are_input_errors():
    """A missing time, quaternion or σ column ended in KeyError, lists of text in numpy's
    errors, a quaternion of zeros in scipy's ValueError and a table that is not one in a
    TypeError."""
    from spacepose.core.metrics import NAV_GROUPS, navigation_errors

    state = [c for _, cols, _, _ in NAV_GROUPS for c in cols]
    truth = {c: np.zeros(3) for c in ["t", "qx", "qy", "qz", *state]} | {"qw": np.ones(3)}
    nav = truth | {f"sig_{c}": np.ones(3) for c in state}
    nav |= {f"sig_att_{a}": np.ones(3) for a in "xyz"}
    assert np.allclose(navigation_errors(nav, truth).groups["attitude"][2], 0.0)
    without = {k: v for k, v in nav.items() if k != "sig_att_x"}
    with pytest.raises(InputError, match=r"navigation table lacks columns \['sig_att_x'\]"):
        navigation_errors(without, truth)
    with pytest.raises(InputError, match="navigation column qx must be real numbers"):
        navigation_errors(nav | {"qx": ["a", "b", "c"]}, truth)
    with pytest.raises(InputError, match="row 1: a quaternion of zeros"):
        navigation_errors(nav | {"qw": np.array([1.0, 0.0, 1.0])}, truth)
    with pytest.raises(InputError, match="needs two tables of columns"):
        navigation_errors(None, truth)


@pytest.mark.parametrize(
    ("settings", "problem"),
    [
        ({"max_iterations": 0}, "max_iterations must be a whole number >= 1, got 0"),
        ({"max_iterations": -1}, "max_iterations must be a whole number >= 1, got -1"),
        ({"tolerance": float("nan")}, "tolerance must be finite, got nan"),
        ({"tolerance": -1.0}, "tolerance must be positive, got -1.0"),
        ({"tolerance": True}, "tolerance must be a number, got True"),
    ],
)
def test_a_geodesic_mean_of_bad_settings_is_refused(settings, problem):
    """0 or -1 iterations returned the first transform as the mean; a NaN or negative
    tolerance ran every iteration."""
    from spacepose.core import se3

    with pytest.raises(InputError) as exc:
        se3.geodesic_mean([np.eye(4), np.eye(4)], **settings)
    assert str(exc.value) == f"geodesic_mean: {problem}"


def test_the_dynamics_helpers_refuse_text_nan_and_a_zero_quaternion():
    """Text ended in Python's TypeError, NaN came back as a NaN state, a zero quaternion as a
    NaN attitude, a negative mean motion was taken."""
    from spacepose.core.dynamics import cw_stm, propagate_attitude

    q, w, inertia = np.array([0.0, 0.0, 0.0, 1.0]), np.array([0.01, 0.02, 0.03]), [3.0, 2.0, 1.0]
    with pytest.raises(InputError, match="dt must be a number, got 'a'"):
        propagate_attitude(q, w, inertia, "a")
    with pytest.raises(InputError, match="dt must be finite, got nan"):
        propagate_attitude(q, w, inertia, np.nan)
    with pytest.raises(InputError, match=r"substeps must be a whole number >= 1, got 1\.5"):
        propagate_attitude(q, w, inertia, 1.0, 1.5)
    with pytest.raises(InputError, match="a quaternion of zeros"):
        propagate_attitude(np.zeros(4), w, inertia, 1.0)
    with pytest.raises(InputError, match=r"n \(mean motion\) must be >= 0 rad/s, got -1.0"):
        cw_stm(-1.0, 1.0)
    with pytest.raises(InputError, match="t must be finite, got inf"):
        cw_stm(1e-3, np.inf)
    np.testing.assert_array_equal(cw_stm(1e-3, 0.0), np.eye(6))


def test_the_cramer_rao_bound_refuses_a_bad_rtol_and_a_negative_sigma():
    """A NaN rtol gave a zero covariance of rank 0, text a TypeError; a negative range σ came
    back as a negative σ along the normal."""
    from spacepose.core.crlb import crlb, range_sigma_along_normal

    points = _box_surface(300)
    normals = np.zeros_like(points)
    face = np.argmax(np.abs(points), axis=1)
    normals[np.arange(len(points)), face] = np.sign(points[np.arange(len(points)), face])
    for rtol in (float("nan"), -1.0, "a"):
        with pytest.raises(InputError, match=r"crlb: rtol must be a number in \[0, 1\)"):
            crlb(points, normals, 0.001, rtol=rtol)
    assert crlb(points, normals, 0.001).rank == 6
    with pytest.raises(InputError, match="sigma_r must be finite and >= 0"):
        range_sigma_along_normal(-1.0, points, normals)
    along = range_sigma_along_normal(0.01, points, normals)
    assert np.all((along >= 0) & (along <= 0.01))
