"""PointCloud validation, the shared Kabsch fit, configs and the CLI error handler."""

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from spacepose.cli import main
from spacepose.core import se3
from spacepose.core.cloud import MAX_ABS_COORDINATE, PointCloud, as_cloud
from spacepose.core.config import StageConfig, dump_config, load_config
from spacepose.core.registration import RegistrationResult, kabsch
from spacepose.errors import ConfigError, DegenerateGeometryError, InputError


def test_pointcloud_drops_and_counts_non_finite_rows() -> None:
    pts = np.array([[0.0, 0, 1], [np.nan, 0, 1], [1, np.inf, 1], [1, 2, 3]])
    normals = np.tile([0.0, 0, 1], (4, 1))
    cloud = PointCloud(pts, normals, source="x.ply")
    assert len(cloud) == 2 and cloud.n_dropped == 2
    np.testing.assert_array_equal(cloud.points, pts[[0, 3]])
    assert cloud.normals is not None and cloud.normals.shape == (2, 3)
    with pytest.raises(ValueError):
        cloud.points[0, 0] = 5.0  # read-only: a stage cannot corrupt its caller's data


@pytest.mark.parametrize(
    "points, match",
    [
        (np.zeros((0, 3)), "empty"),
        (np.full((5, 3), np.nan), "no finite point"),
        (np.zeros((5, 2)), r"shape \(N, 3\)"),
        ([["a", "b", "c"]], "must be real numbers, got an array of text"),
    ],
)
def test_pointcloud_rejects_bad_points_naming_the_source(points, match: str) -> None:
    with pytest.raises(InputError, match=match) as info:
        PointCloud(points, source="scan_07.ply")
    assert "scan_07.ply" in str(info.value)


def test_finite_points_with_no_finite_normal_say_so() -> None:
    # "No finite point" would send the user to coordinates that are fine.
    with pytest.raises(
        InputError,
        match=r"no row with finite points and normals \(the points "
        r"alone are finite on 5 of 5 rows\)",
    ):
        PointCloud(np.ones((5, 3)), normals=np.full((5, 3), np.nan), source="n.npz")


def test_pointcloud_rejects_mismatched_normals_and_sigma() -> None:
    with pytest.raises(InputError, match="2 normals for 3 points"):
        PointCloud(np.zeros((3, 3)), normals=np.zeros((2, 3)))
    with pytest.raises(InputError, match="sigma"):
        PointCloud(np.zeros((3, 3)), sigma=np.ones(4))


def test_pointcloud_transform_and_select() -> None:
    rng = np.random.default_rng(0)
    T = se3.make_transform(Rotation.random(random_state=1), [1.0, 2.0, 3.0])
    n = rng.normal(size=(6, 3))
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    cloud = PointCloud(rng.normal(size=(6, 3)), n, sigma=np.arange(6.0))
    moved = cloud.transformed(T)
    np.testing.assert_allclose(moved.points, cloud.points @ T[:3, :3].T + T[:3, 3])
    np.testing.assert_allclose(moved.normals, n @ T[:3, :3].T)
    sub = cloud.select(np.array([True, False] * 3))
    np.testing.assert_array_equal(sub.sigma, [0.0, 2.0, 4.0])


@pytest.mark.parametrize("seed", range(3))
def test_kabsch_recovers_a_known_transform_and_batches(seed: int) -> None:
    rng = np.random.default_rng(seed)
    T = se3.make_transform(Rotation.random(random_state=seed), rng.normal(size=3))
    src = rng.normal(size=(20, 3))
    np.testing.assert_allclose(kabsch(src, se3.transform_points(T, src)), T, atol=1e-12)
    # A batch of 4 independent problems gives the 4 single answers.
    Ts = [
        se3.make_transform(Rotation.random(random_state=10 + i), rng.normal(size=3))
        for i in range(4)
    ]
    srcs = rng.normal(size=(4, 5, 3))
    dsts = np.stack([se3.transform_points(Ti, s) for Ti, s in zip(Ts, srcs, strict=True)])
    np.testing.assert_allclose(kabsch(srcs, dsts), np.stack(Ts), atol=1e-10)


def test_kabsch_never_returns_a_reflection() -> None:
    # A mirrored point set: the best proper rotation, not the reflection, must come back.
    src = np.array([[1.0, 0, 0], [0, 1, 0], [0, 0, 1], [1, 1, 1]])
    T = kabsch(src, src * np.array([1.0, 1.0, -1.0]))
    assert np.linalg.det(T[:3, :3]) == pytest.approx(1.0)


def test_kabsch_rejects_degenerate_and_short_input() -> None:
    line = np.c_[np.arange(5.0), np.zeros(5), np.zeros(5)]
    with pytest.raises(DegenerateGeometryError):
        kabsch(line, line + 1.0)
    with pytest.raises(InputError, match="at least 3"):
        kabsch(np.zeros((2, 3)), np.zeros((2, 3)))
    with pytest.raises(InputError):
        kabsch(np.zeros((4, 3)), np.zeros((5, 3)))


def test_registration_result_covariance_is_scaled_inverse_information() -> None:
    info = np.diag([1.0, 2.0, 4.0, 8.0, 16.0, 32.0])
    result = RegistrationResult(np.eye(4), 1.0, 0.002, 5, True, info, 100)
    np.testing.assert_allclose(result.covariance(), 0.002**2 * np.linalg.inv(info))
    assert result.condition_number == pytest.approx(32.0)


class _Demo(StageConfig):
    voxel_size: float = 0.01
    iterations: int = 30


def test_config_round_trip_and_unknown_keys(tmp_path) -> None:
    path = tmp_path / "cfg.yaml"
    path.write_text("voxel_size: 0.02\n")
    assert load_config(_Demo, path) == _Demo(voxel_size=0.02)
    dumped = dump_config(_Demo(), tmp_path / "eff.json")
    assert json.loads(dumped.read_text()) == {"voxel_size": 0.01, "iterations": 30}
    path.write_text("voxel_sise: 0.02\n")
    with pytest.raises(ConfigError, match="voxel_sise") as info:
        load_config(_Demo, path)
    assert str(path) in str(info.value)
    path.write_text("voxel_size: [1, 2\n")
    with pytest.raises(ConfigError, match="not valid"):
        load_config(_Demo, path)
    with pytest.raises(ConfigError, match="cannot read"):
        load_config(_Demo, tmp_path / "missing.yaml")


def test_cli_maps_package_errors_to_one_line_and_exit_1(capsys) -> None:
    assert main(["experiment", "no-such-experiment", "--out", "unused"]) == 1
    err = capsys.readouterr().err
    assert "unknown experiment" in err and "Traceback" not in err


@pytest.mark.parametrize(
    ("argv", "message"),
    [
        (["--definitely-not-an-option"], "spacepose: No such option: --definitely-not-an-option"),
        (["evaluate", "a.tum", "b.tum", "--jsn"], "spacepose evaluate: No such option: --jsn"),
        (["no-such-command"], "spacepose: No such command 'no-such-command'"),
        (["evaluate", "a.tum"], "spacepose evaluate: Missing argument 'gt'"),
        (["planes", "x.ply", "--sigma", "abc"], "spacepose planes: Invalid value for '--sigma'"),
    ],
)
def test_cli_usage_errors_are_one_line_and_exit_1_as_the_readme_says(
    argv: list[str], message: str, capsys
) -> None:
    assert main(argv) == 1
    out, err = capsys.readouterr()
    assert out == ""
    assert len(err.strip().splitlines()) == 1
    assert err.startswith(f"error: {message}") and "--help" in err and "Usage" not in err


def test_pointcloud_leaves_the_callers_array_writable() -> None:
    pts = np.zeros((4, 3))
    PointCloud(pts)
    pts[0, 0] = 1.0  # must not raise: the cloud froze its own copy, not the caller's array
    assert pts[0, 0] == 1.0


def test_cli_error_message_keeps_square_brackets(tmp_path, capsys) -> None:
    # A config file name with brackets must come out verbatim, not eaten as rich markup.
    bad = tmp_path / "cfg[v2].yaml"
    bad.write_text("unknown_option: 1\n")
    assert (
        main(["track", str(tmp_path), "--out", str(tmp_path / "e.tum"), "--config", str(bad)]) == 1
    )
    assert "cfg[v2].yaml" in capsys.readouterr().err


def test_as_points_is_the_one_array_check() -> None:
    from spacepose.core.cloud import as_points

    np.testing.assert_array_equal(as_points([[1, 2, 3]]), [[1.0, 2.0, 3.0]])
    cloud = PointCloud(np.ones((4, 3)), source="f.ply")
    assert as_points(cloud) is cloud.points
    with pytest.raises(InputError, match=r"f\.ply: q: need at least 5 point"):
        as_points(cloud, "q", min_points=5)
    with pytest.raises(InputError, match="must be real numbers, got an array of text"):
        as_points([["a", "b", "c"]])
    with pytest.raises(InputError, match=r"shape \(N, 3\)"):
        as_points(np.zeros((3, 2)))
    with pytest.raises(InputError, match="non-empty"):
        as_points(np.zeros((0, 3)))
    with pytest.raises(InputError, match="NaN or inf"):
        as_points([[0.0, np.nan, 1.0]], source="scan.pcd")


def test_stage_config_errors_are_config_errors_naming_the_field() -> None:
    from pydantic import Field

    class _Inner(StageConfig):
        k: int = Field(10, ge=1)

    class OuterConfig(StageConfig):
        voxel_size: float = Field(0.01, gt=0)
        inner: _Inner = _Inner()

    with pytest.raises(ConfigError, match=r"^invalid outer config: voxel_size: .*greater than 0$"):
        OuterConfig(voxel_size=-1)
    with pytest.raises(ConfigError, match=r"^invalid outer config: inner\.k: .*greater than or eq"):
        OuterConfig(inner={"k": 0})
    with pytest.raises(ConfigError, match=r"^invalid outer config: bogus: Extra inputs"):
        OuterConfig.model_validate({"bogus": 1})
    assert OuterConfig(inner={"k": 3}).inner.k == 3 and OuterConfig().voxel_size == 0.01


def test_tracker_config_with_a_negative_voxel_is_a_config_error() -> None:
    from spacepose.core.tracker import TrackerConfig

    with pytest.raises(ConfigError, match=r"invalid tracker config: voxel_size: .*greater than 0"):
        TrackerConfig(voxel_size=-1)


@pytest.mark.parametrize(
    ("text", "where"),
    [
        ("voxel_size: [1, 2\niterations: 3\n", r"line 2:11: expected ',' or '\]', but got ':'"),
        ("voxel_size: 1: 2\n", "line 1:14: mapping values are not allowed here"),
        ("voxel_size: 1\n\titerations: 3\n", r"line 2:1: found character '\\t'"),
    ],
)
def test_malformed_yaml_config_is_one_line_with_line_and_column(tmp_path, text, where) -> None:
    path = tmp_path / "cfg.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError) as info:
        load_config(_Demo, path)
    message = str(info.value)
    assert "\n" not in message
    assert message.startswith(f"{path}: not valid YAML: ")
    assert __import__("re").search(where, message), message


def test_malformed_json_config_is_one_line_with_line_and_column(tmp_path) -> None:
    path = tmp_path / "cfg.json"
    path.write_text('{"voxel_size": 0.1,\n "iterations": }\n')
    with pytest.raises(
        ConfigError, match=r"cfg\.json: not valid JSON: line 2:16: Expecting value$"
    ):
        load_config(_Demo, path)


def test_as_cloud_wraps_an_array_and_passes_a_cloud_through() -> None:
    cloud = PointCloud(np.ones((4, 3)), source="f.ply")
    assert as_cloud(cloud) is cloud
    wrapped = as_cloud([[1, 2, 3], [4, 5, np.nan]], "source")
    np.testing.assert_array_equal(wrapped.points, [[1.0, 2.0, 3.0]])
    assert wrapped.source == "source" and wrapped.n_dropped == 1
    with pytest.raises(InputError, match=r"^f\.ply: need at least 5 points, got 4$"):
        as_cloud(cloud, min_points=5)
    with pytest.raises(InputError, match=r"^src: points must have shape \(N, 3\)"):
        as_cloud(np.zeros((3, 2)), "src")


def test_coordinates_beyond_the_float64_square_range_are_refused() -> None:
    # sqrt(max float64) / 2**32: squared and summed over 2**32 points it is still finite.
    assert MAX_ABS_COORDINATE**2 * 2.0**32 * 3 < np.finfo(np.float64).max
    ok = np.full((3, 3), MAX_ABS_COORDINATE)
    assert np.all(np.isfinite(PointCloud(ok).points ** 2))
    with pytest.raises(InputError, match=r"^scan\.ply: points reach \|coordinate\| 1e\+300"):
        PointCloud(np.full((5, 3), -1e300), source="scan.ply")
    from spacepose.core.cloud import as_points

    with pytest.raises(InputError, match=r"squares overflow"):
        as_points(np.full((5, 3), 1e200))


def test_planes_on_a_cloud_at_1e300_is_one_line_naming_the_file(tmp_path, capsys) -> None:
    path = tmp_path / "far.npy"
    rng = np.random.default_rng(0)
    np.save(path, rng.normal(size=(500, 3)) * 1e300)
    assert main(["planes", str(path)]) == 1
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1
    assert err.startswith(f"error: {path}: points reach |coordinate|")


@pytest.mark.parametrize(
    "command",
    [
        ["planes", "{cloud}", "--catalogue", "{bad}"],
        ["track", "{frames}", "--out", "{out}/e.tum", "--config", "{bad}"],
        ["navigate", "{frames}", "--out", "{out}/n.csv", "--scenario", "{bad}"],
        ["navigate", "{frames}", "--out", "{out}/n.csv", "--config", "{bad}"],
        ["campaign", "{bad}"],
    ],
    ids=["planes-catalogue", "track-config", "navigate-scenario", "navigate-config", "campaign"],
)
def test_malformed_yaml_on_the_command_line_is_exactly_one_line(tmp_path, capsys, command):
    bad = tmp_path / "bad.yaml"
    bad.write_text("name: x\nvalues: [1, 2\nother: 3\n")
    frames = tmp_path / "frames"
    frames.mkdir()
    cloud = frames / "000000.npy"
    np.save(cloud, np.random.default_rng(0).uniform(-0.1, 0.1, (300, 3)) + np.array([0, 0, 1]))
    names = {"bad": bad, "frames": frames, "cloud": cloud, "out": tmp_path / "out"}
    assert main([arg.format(**names) for arg in command]) == 1
    err = capsys.readouterr().err
    assert len(err.strip().splitlines()) == 1, err
    assert err.startswith(f"error: {bad}: not valid YAML")
    assert "line 3:6: expected ',' or ']', but got ':'" in err


def test_a_cloud_in_millimetres_gets_one_warning_line_naming_the_file(tmp_path, capsys) -> None:
    from spacepose.tools.cloud_io import write_cloud

    # A 20 cm square plate at 1 m, sampled every 5 mm, written in millimetres.
    u, v = np.meshgrid(np.arange(40) * 5.0, np.arange(40) * 5.0)
    path = write_cloud(tmp_path / "plate_mm.ply", np.c_[u.ravel(), v.ravel(), np.full(1600, 1e3)])
    assert main(["planes", str(path), "--json"]) == 0
    err = capsys.readouterr().err
    assert err.splitlines() == [
        f"warning: {path}: coordinates look like millimetres (276 m across, median point "
        "spacing 5.00 m); spacepose works in metres: write its coordinates times 0.001 "
        "(in Python: read_cloud(..., scale=1e-3))"
    ]


def test_the_same_warning_for_many_files_is_printed_three_times_then_counted(monkeypatch) -> None:
    import importlib
    import io
    import warnings

    from rich.console import Console

    # spacepose.cli.app the module, not the Typer object spacepose.cli re-exports as "app".
    cli_app = importlib.import_module("spacepose.cli.app")
    from spacepose.errors import SpaceposeWarning

    screen = io.StringIO()
    monkeypatch.setattr(cli_app, "err_console", Console(file=screen, width=200))
    with warnings.catch_warnings(), cli_app._OneLineWarnings() as shown:
        warnings.simplefilter("always")
        warnings.showwarning = shown.show
        for k in range(7):
            warnings.warn(
                SpaceposeWarning("coordinates look like mm (a lot)", f"f{k}.ply"), stacklevel=1
            )
        warnings.warn(SpaceposeWarning("another problem", "g.ply"), stacklevel=1)
        # The same message again (one run folder opened twice by a command): not said again.
        warnings.warn(SpaceposeWarning("another problem", "g.ply"), stacklevel=1)
        warnings.warn(SpaceposeWarning("coordinates look like mm (a lot)", "f0.ply"), stacklevel=1)
    assert screen.getvalue().splitlines() == [
        "warning: f0.ply: coordinates look like mm (a lot)",
        "warning: f1.ply: coordinates look like mm (a lot)",
        "warning: f2.ply: coordinates look like mm (a lot)",
        "warning: g.ply: another problem",
        "warning: 4 more with the same warning: coordinates look like mm",
    ]


def test_pointcloud_drops_exactly_the_rows_numpy_finds_non_finite() -> None:
    rng = np.random.default_rng(3)
    pts, normals, sigma = rng.normal(size=(500, 3)), rng.normal(size=(500, 3)), rng.random(500)
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    pts[rng.choice(500, 40), rng.integers(0, 3, 40)] = np.nan
    normals[rng.choice(500, 20), rng.integers(0, 3, 20)] = -np.inf
    sigma[rng.choice(500, 10)] = np.inf
    keep = np.isfinite(pts).all(axis=1) & np.isfinite(normals).all(axis=1) & np.isfinite(sigma)
    cloud = PointCloud(pts, normals, sigma)
    assert cloud.n_dropped == 500 - keep.sum()
    np.testing.assert_array_equal(cloud.points, pts[keep])
    np.testing.assert_array_equal(cloud.normals, normals[keep])
    np.testing.assert_array_equal(cloud.sigma, sigma[keep])
    # Out of range among the kept rows is refused; a dropped row's value does not count.
    pts[~keep] = np.nan
    pts[np.flatnonzero(keep)[0], 1] = -1e200
    with pytest.raises(InputError, match=r"^points reach \|coordinate\| 1e\+200"):
        PointCloud(pts)


def test_pointcloud_copies_what_the_caller_could_still_write() -> None:
    buffer = np.zeros((4, 3))
    view = buffer.view()
    view.setflags(write=False)  # read-only, but its buffer is not
    single = np.zeros((4, 3), dtype=np.float32)
    clouds = [PointCloud(view), PointCloud(single), PointCloud(buffer.T.copy().T)]
    buffer[0, 0], single[0, 0] = 1.0, 1.0
    for cloud in clouds:
        assert cloud.points[0, 0] == 0.0 and cloud.points.flags.c_contiguous
        assert cloud.points.dtype == np.float64 and not cloud.points.flags.writeable
    # A cloud's own arrays are read-only: the next cloud shares them rather than copying.
    cloud = PointCloud(np.ones((4, 3)), sigma=np.arange(4.0))
    assert cloud.with_normals(np.tile([0.0, 0.0, 1.0], (4, 1))).points is cloud.points
    assert np.shares_memory(cloud.transformed(np.eye(4)).sigma, cloud.sigma)


def test_pointcloud_select_by_mask_index_and_negative_index() -> None:
    rng = np.random.default_rng(4)
    normals = rng.normal(size=(7, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    cloud = PointCloud(rng.normal(size=(7, 3)), normals, rng.random(7))
    mask = np.array([1, 0, 1, 1, 0, 0, 1], dtype=bool)
    for index, rows in ((mask, [0, 2, 3, 6]), ([6, -7, 2], [6, 0, 2])):
        sub = cloud.select(index)
        np.testing.assert_array_equal(sub.points, cloud.points[rows])
        np.testing.assert_array_equal(sub.normals, cloud.normals[rows])
        np.testing.assert_array_equal(sub.sigma, cloud.sigma[rows])
    with pytest.raises(InputError, match="select of 7 points: boolean index did not match"):
        cloud.select(mask[:5])
    with pytest.raises(InputError, match="select of 7 points: index 7 is out of bounds"):
        cloud.select([7])
