"""Round 27 of bad inputs (the command line): a cut MCAP bag, tracker factors whose squares
overflow, and numbers written as yes/no or text that foreign layouts took without a word."""

from __future__ import annotations

import contextlib
import json
import os
import struct
import time
from concurrent.futures import ThreadPoolExecutor
from concurrent.futures import TimeoutError as FutureTimeout

import numpy as np
import pytest
from tests.cli_errors import error_line

from spacepose.cli import main
from spacepose.errors import ConfigError, FileFormatError

_MCAP_MAGIC = b"\x89MCAP0\r\n"


@pytest.mark.parametrize(
    "body",
    [
        b"",  # nothing after the magic: ord() of no byte, a TypeError traceback
        b"\x01" + struct.pack("<Q", 2**62),  # a header record of 2**62 bytes: MemoryError
    ],
    ids=["cut-after-magic", "impossible-record-length"],
)
def test_a_cut_mcap_bag_is_one_line_naming_it(tmp_path, capsys, body):
    bag = tmp_path / "run.mcap"
    bag.write_bytes(_MCAP_MAGIC + body)
    assert main(["track", str(bag), "--out", str(tmp_path / "est.tum")]) == 1
    err = error_line(capsys)
    assert f"{bag}: cannot open the bag: truncated or corrupt" in err


@pytest.mark.parametrize(
    "field", ["floor_translation", "floor_rotation", "floor_motion", "range_bias", "crop_margin"]
)
def test_a_tracker_factor_whose_square_overflows_is_refused(tmp_path, field):
    # floor_rotation: 1e300 ended `track` in an OverflowError traceback at frame 1 (range_bias
    # and crop_margin too, and floor_translation from 1e160).
    from spacepose.tools.navigation_config_io import load_navigation_config
    from spacepose.tools.tracking_io import tracker_config

    path = tmp_path / "tracker.yaml"
    path.write_text(f"{field}: 1e160\n")
    with pytest.raises(ConfigError, match=rf"tracker\.yaml: .*{field}: 1e\+160 is too large"):
        tracker_config(path)
    path.write_text(f"{field}: 1e50\n")
    assert getattr(tracker_config(path), field) == 1e50
    fused = tmp_path / "nav.yaml"  # navigate --measurements registration's tracker block
    fused.write_text(f"measurements: registration\ntracker:\n  {field}: 1e200\n")
    with pytest.raises(ConfigError, match=rf"nav\.yaml: .*{field}: 1e\+200 is too large"):
        load_navigation_config(fused, "registration")


def test_a_tracker_floor_whose_square_overflows_is_one_line_from_track(tmp_path, capsys):
    run = tmp_path / "lab"
    assert main(["simulate", "lab", "--out", str(run), "--frames", "2", "--seed", "3"]) == 0
    config = tmp_path / "tracker.yaml"
    config.write_text("floor_rotation: 1e300\n")
    capsys.readouterr()
    args = ["track", str(run), "--out", str(tmp_path / "est.tum"), "--config", str(config)]
    assert main(args) == 1
    err = error_line(capsys)
    assert f"{config}: invalid tracker config: floor_rotation: 1e+300 is too large" in err


def _ros_yaml(data: str, distortion: str = "[0, 0, 0, 0, 0]") -> str:
    return (
        "image_width: 160\nimage_height: 120\n"
        f"camera_matrix:\n  rows: 3\n  cols: 3\n  data: {data}\n"
        "distortion_model: plumb_bob\n"
        f"distortion_coefficients:\n  rows: 1\n  cols: 5\n  data: {distortion}\n"
    )


@pytest.mark.parametrize(
    ("name", "text", "problem"),
    [
        # true read as a focal length of 1 px: every frame lost as "degenerate" instead
        (
            "intrinsics.yaml",
            _ros_yaml("[true, 0, 79.5, 0, 200, 59.5, 0, 0, 1]"),
            "camera_matrix holds a yes/no where numbers go",
        ),
        (
            "intrinsics.yaml",
            _ros_yaml("[200, 0, 79.5, 0, 200, 59.5, 0, 0, 1]", "[true, 0, 0, 0, 0]"),
            "distortion_coefficients holds a yes/no where numbers go",
        ),
        (
            "intrinsics.yaml",
            _ros_yaml('["200", 0, 79.5, 0, 200, 59.5, 0, 0, 1]'),
            "camera_matrix holds text where numbers go",
        ),
        (
            "intrinsics.json",
            json.dumps(
                {
                    "width": 160,
                    "height": 120,
                    "intrinsic_matrix": [200, 0, 0, 0, True, 0, 79.5, 59.5, 1],
                }
            ),
            "intrinsic_matrix holds a yes/no where numbers go",
        ),
        (
            "intrinsics.json",
            json.dumps(
                {
                    "width": 160,
                    "height": 120,
                    "intrinsic_matrix": [200, 0, 0, 0, "200", 0, 79.5, 59.5, 1],
                }
            ),
            "intrinsic_matrix holds text where numbers go",
        ),
    ],
)
def test_a_camera_matrix_of_yes_no_or_quoted_numbers_is_refused(tmp_path, name, text, problem):
    # Our own layout refused "fx: true" and "fx: '200'"; ROS's and Open3D's matrices took both.
    from spacepose.tools.intrinsics_io import read_intrinsics

    path = tmp_path / name
    path.write_text(text)
    with pytest.raises(ConfigError, match=rf"{name}: {problem}"):
        read_intrinsics(path)
    path.write_text(text.replace("true", "200").replace('"200"', "200"))
    assert read_intrinsics(path).fx == 200.0


def test_a_camera_matrix_of_yes_no_is_one_line_from_track(tmp_path, capsys):
    from PIL import Image

    rng = np.random.default_rng(27)
    for k in range(2):
        depth = (1500 + rng.integers(-5, 5, (120, 160))).astype(np.uint16)
        Image.fromarray(depth).save(tmp_path / f"{k:06d}.png")
    intrinsics = tmp_path / "intrinsics.yaml"
    intrinsics.write_text(_ros_yaml("[true, 0, 79.5, 0, 200, 59.5, 0, 0, 1]"))
    assert main(["track", str(tmp_path), "--out", str(tmp_path / "out" / "est.tum")]) == 1
    err = error_line(capsys)
    assert f"{intrinsics}: camera_matrix holds a yes/no where numbers go" in err


def test_an_init_transform_of_quoted_numbers_is_refused(tmp_path):
    # numpy read "0.5" as 0.5: a translation written as text was taken without a word.
    from spacepose.tools.register_io import read_transform

    init = tmp_path / "init.json"
    rows = np.eye(4).tolist()
    rows[0][3] = "0.5"
    init.write_text(json.dumps({"T_target_source": rows}))
    with pytest.raises(FileFormatError, match=r"init\.json: expected 16 numbers .*: text where"):
        read_transform(init)
    init.write_text(json.dumps(rows))  # the bare matrix alike
    with pytest.raises(FileFormatError, match=r"write it unquoted"):
        read_transform(init)
    rows[0][3] = 0.5
    init.write_text(json.dumps({"T_target_source": rows}))
    assert read_transform(init)[0, 3] == 0.5


@pytest.mark.parametrize(
    ("key", "value"),
    [("process_noise", 1.25e-6), ("process_noise", "x"), ("config", [0.01])],
)
def test_a_scenario_noise_block_that_is_no_mapping_is_refused(key, value):
    # "process_noise: 1.25e-6" was passed over: the filter kept its default 3e-8.
    from spacepose.core.nav_config import NavigationConfig
    from spacepose.tools.navigation_config_io import with_scenario_noise

    with pytest.raises(ConfigError, match=rf"^s\.json: {key} must be a mapping"):
        with_scenario_noise(NavigationConfig(), {key: value}, "s.json")
    # A one-frame run writes process_noise: null; a mapping is read as before.
    config = with_scenario_noise(NavigationConfig(), {"process_noise": None}, "s.json")
    assert config == NavigationConfig()
    noise = with_scenario_noise(NavigationConfig(), {key: {"sigma_accel": 1e-6}}, "s.json")
    assert noise.ekf.sigma_accel == (
        1e-6 if key == "process_noise" else NavigationConfig().ekf.sigma_accel
    )


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="needs named pipes")
def test_report_leaves_out_named_pipes_without_waiting_for_a_writer(tmp_path, capsys):
    # A pipe named bench.json, an experiment's table or figure, or a track's health table held
    # `report` up for ever (a track, a truth or a scenario named so was already left out).
    from PIL import Image

    run = tmp_path / "run"
    run.mkdir()
    (run / "scenario.json").write_text('{"scenario": "orbit"}')
    poses = "".join(f"{k} 0 0 {1 + 0.01 * k} 0 0 0 1\n" for k in range(3))
    (run / "groundtruth.tum").write_text(poses)
    (run / "est.tum").write_text(poses)
    figures = tmp_path / "experiment"
    figures.mkdir()
    Image.fromarray(np.zeros((4, 4), np.uint8)).save(figures / "a.png")
    pipes = [tmp_path / "bench.json", figures / "table.json", figures / "b.png"]
    pipes.append(run / "est.health.csv")
    for pipe in pipes:
        os.mkfifo(pipe)
    with ThreadPoolExecutor(1) as pool:
        future = pool.submit(main, ["report", str(tmp_path), "--out", str(tmp_path / "r.html")])
        try:
            code = future.result(timeout=60)
        except FutureTimeout:
            code = None
        while not future.done():  # a read blocked in open() is released by a writer's open
            for pipe in pipes:
                with contextlib.suppress(OSError):
                    os.close(os.open(pipe, os.O_WRONLY | os.O_NONBLOCK))
            time.sleep(0.1)
    assert code == 0, "report waited for a writer"
    err = capsys.readouterr().err
    reason = "not a regular file (a pipe or a device?)"
    assert f"warning: {pipes[-1]}: left out of the report: {reason}" in err, err
    page = (tmp_path / "r.html").read_text()
    for pipe in pipes:  # past three, the warnings of one problem are counted; the page lists all
        assert f"<td>{pipe.relative_to(tmp_path)}</td><td>{reason}" in page


@pytest.mark.parametrize("member", ["points.npy", "normals.npy", "points"])
def test_an_npz_member_that_is_no_npy_array_is_named(tmp_path, capsys, member):
    # numpy hands such a member back as its bytes: `planes` ended in an AttributeError traceback.
    import zipfile

    path = tmp_path / "cloud.npz"
    points = np.random.default_rng(27).normal(size=(50, 3))
    with zipfile.ZipFile(path, "w") as archive:
        if member == "normals.npy":
            with archive.open("points.npy", "w") as fh:
                np.save(fh, points)
        archive.writestr(member, b"not an array")
    assert main(["planes", str(path)]) == 1
    name = member.removesuffix(".npy")
    assert f"{path}: .npz '{name}' is no .npy array (no NumPy header)" in error_line(capsys)


def test_a_cells_file_of_frames_alone_is_not_the_whole_grid(tmp_path):
    # "frames: 5" alone started all 1,500 runs of the grid, as an empty file had.
    from spacepose.tools.experiments.robustness_cells import select_cells

    cells = tmp_path / "frames.yaml"
    cells.write_text("frames: 5\n")
    with pytest.raises(ConfigError, match=r"frames\.yaml: holds no cells; set any of target"):
        select_cells(str(cells), quick=False, frames=None)
    cells.write_text("frames: 5\nseed: [0]\n")
    runs, frames = select_cells(str(cells), quick=True, frames=None)
    assert len(runs) == 1 and frames == 5


def test_an_obj_face_on_vertex_zero_is_named(tmp_path):
    """OBJ counts vertices from 1: trimesh read ``f 0 1 2`` as a face on the last vertex, and
    the file was refused as "all 1 triangles have zero area" (or, beside good faces, rendered
    with a wrong one)."""
    from spacepose.core.sim.mesh_files import load_mesh

    vertices = "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\n"
    for faces in ("f 0 1 2\n", "f 2 3 4\nf 0 1 2\n"):
        path = tmp_path / "model.obj"
        path.write_text(vertices + faces)
        with pytest.raises(FileFormatError, match=r"refers to vertex 0.*OBJ numbers them from 1"):
            load_mesh(path)
    path.write_text(vertices + "f 1 2 3\nf 2 3 4\n")
    assert len(load_mesh(path).mesh.faces) == 2


def test_a_ros_camera_matrix_announced_of_another_size_is_refused(tmp_path):
    """A ``camera_matrix`` announced 2 x 3 with 9 numbers was read as the 3 x 3 they make; the
    same mismatch in ``distortion_coefficients`` was already refused."""
    from spacepose.tools.intrinsics_io import read_intrinsics

    path = tmp_path / "intrinsics.yaml"
    text = _ros_yaml("[200, 0, 79.5, 0, 200, 59.5, 0, 0, 1]")
    path.write_text(text.replace("rows: 3\n  cols: 3", "rows: 2\n  cols: 3", 1))
    with pytest.raises(ConfigError, match=r"intrinsics\.yaml: camera_matrix announces rows 2 x"):
        read_intrinsics(path)
    path.write_text(text)
    assert read_intrinsics(path) is not None


def test_a_health_row_at_no_time_is_not_paired_by_position(tmp_path):
    """A health table row whose time is NaN (a cell another tool blanked to "nan") compared as
    no mismatch, and its lost flag was laid on the pose in its row without a word; the table is
    now another run's, as a row at another time makes it: lost frames scored, and said so."""
    from spacepose.errors import SpaceposeWarning
    from spacepose.tools.evaluation import compare_trajectory_files
    from test_bad_inputs_round5 import noisy_pair

    est_path, gt_path = noisy_pair(tmp_path, 23)
    rows = [f"{k},{'nan' if k == 5 else float(k)},{'lost' if k == 3 else 'ok'}" for k in range(10)]
    (tmp_path / "est.health.csv").write_text("frame,timestamp,status\n" + "\n".join(rows) + "\n")
    with pytest.warns(SpaceposeWarning) as caught:
        result = compare_trajectory_files(est_path, gt_path)
    assert result.table.n == 10
    note = "est.health.csv row 6 is at t = nan s, pose 5 at 5 s: lost frames, if any, are scored"
    assert f"{est_path}: {note}" in [str(w.message) for w in caught]
