"""Intrinsics files (tools/intrinsics_io.py): our layout, ROS's camera_info YAML, Open3D's JSON."""

from __future__ import annotations

import re

import pytest

from spacepose.errors import ConfigError
from spacepose.tools.depth_folder import is_depth_folder
from spacepose.tools.intrinsics_io import find_intrinsics, read_intrinsics


def test_intrinsics_file(tmp_path):
    (tmp_path / "intrinsics.yaml").write_text(
        "fx: 525\nfy: 525\ncx: 319.5\ncy: 239.5\ndepth_scale: 0.0002\nk1: 0.1\np2: -0.001\n"
    )
    assert find_intrinsics(tmp_path) == tmp_path / "intrinsics.yaml"
    assert is_depth_folder(tmp_path)
    camera = read_intrinsics(tmp_path / "intrinsics.yaml")
    assert (camera.fx, camera.cy, camera.k1, camera.p2) == (525.0, 239.5, 0.1, -0.001)
    assert camera.distorted
    (tmp_path / "bad.json").write_text('{"fx": 525, "fy": 525, "cx": 1, "cy": 1, "k7": 0}')
    with pytest.raises(ConfigError, match=r"bad\.json.*k7"):
        read_intrinsics(tmp_path / "bad.json")
    (tmp_path / "neg.json").write_text('{"fx": -5, "fy": 525, "cx": 1, "cy": 1}')
    with pytest.raises(ConfigError, match="fx"):
        read_intrinsics(tmp_path / "neg.json")
    # Focal lengths no pinhole depth camera has (a unit mistake): 1e300 px put every point at
    # one place, 1e-300 px overflowed the coordinates; both lost every frame, exit 0 or 1.
    for fx, bound in ((1e300, "less than or equal to 1000000"), (1e-300, "greater than or equal")):
        (tmp_path / "odd.json").write_text(f'{{"fx": {fx}, "fy": 525, "cx": 1, "cy": 1}}')
        with pytest.raises(ConfigError, match=rf"odd\.json.*fx: Input should be {bound}"):
            read_intrinsics(tmp_path / "odd.json")


# ROS camera_calibration's camera_info YAML (a 640×480 camera, plumb-bob distortion).
ROS_CAMERA_INFO = """\
image_width: 640
image_height: 480
camera_name: tof
camera_matrix:
  rows: 3
  cols: 3
  data: [505.2, 0, 318.7, 0, 506.9, 241.3, 0, 0, 1]
distortion_model: plumb_bob
distortion_coefficients:
  rows: 1
  cols: 5
  data: [-0.12, 0.031, 0.0004, -0.0007, 0.0]
rectification_matrix:
  rows: 3
  cols: 3
  data: [1, 0, 0, 0, 1, 0, 0, 0, 1]
projection_matrix:
  rows: 3
  cols: 4
  data: [505.2, 0, 318.7, 0, 0, 506.9, 241.3, 0, 0, 0, 1, 0]
"""


def test_a_ros_camera_info_yaml_is_an_intrinsics_file(tmp_path):
    path = tmp_path / "intrinsics.yaml"
    path.write_text(ROS_CAMERA_INFO)
    camera = read_intrinsics(path)
    assert (camera.fx, camera.fy, camera.cx, camera.cy) == (505.2, 506.9, 318.7, 241.3)
    assert (camera.k1, camera.k2, camera.p1, camera.p2, camera.k3) == (
        -0.12, 0.031, 0.0004, -0.0007, 0.0
    )  # fmt: skip
    # No depth_scale: by the image's type, as ROS's 16UC1 (mm) and 32FC1 (m).
    assert (camera.width, camera.height, camera.depth_scale) == (640, 480, None)
    # Our own fields may stand beside it; an unknown key is still an error.
    path.write_text(ROS_CAMERA_INFO + "depth_scale: 0.0002\ndepth_kind: range\n")
    camera = read_intrinsics(path)
    assert (camera.depth_scale, camera.depth_kind, camera.fx) == (0.0002, "range", 505.2)
    path.write_text(ROS_CAMERA_INFO + "baseline: 0.05\n")
    with pytest.raises(ConfigError, match=r"intrinsics\.yaml.*baseline"):
        read_intrinsics(path)


@pytest.mark.parametrize(
    ("change", "problem"),
    [
        (("data: [505.2, 0, 318.7", "data: [505.2, 3.0, 318.7"), "must be"),  # skew
        (
            ("data: [505.2, 0, 318.7, 0, 506.9, 241.3, 0, 0, 1]", "data: [505.2, 0]"),
            "announces rows 3 x cols 3 = 9 numbers, its data holds 2",
        ),
        (("data: [505.2, 0, 318.7", "data: [0, 0, 318.7"), "no focal length"),
        (("plumb_bob", "equidistant"), "equidistant"),
        (("data: [-0.12,", "data: [x,"), "numbers"),
        # A YAML null (NaN) is named as such: it read "at most 8 ..., got 5".
        (("data: [-0.12,", "data: [null,"), r"non-finite numbers: \[nan,"),
    ],
)
def test_a_camera_matrix_that_is_not_a_pinhole_is_refused_by_name(tmp_path, change, problem):
    path = tmp_path / "camera_info.yaml"
    path.write_text(ROS_CAMERA_INFO.replace(*change, 1))
    with pytest.raises(ConfigError, match=rf"camera_info\.yaml: .*{problem}"):
        read_intrinsics(path)


@pytest.mark.parametrize(
    ("extra", "problem"),
    [
        ("fx: 400\n", "fx given twice, by the ROS camera_info layout"),
        ("k1: 0\n", "k1 given twice"),
        ("width: 320\n", "width given twice"),
        ("intrinsic_matrix: [400, 0, 0, 0, 400, 0, 320, 240, 1]\n", "holds both camera_matrix"),
    ],
)
def test_a_field_given_twice_by_a_layout_and_a_key_is_refused(tmp_path, extra, problem):
    """The key beside the ROS matrix (or the Open3D matrix beside it) used to win, or lose,
    without a word: a focal length of another camera taken for this one's."""
    path = tmp_path / "intrinsics.yaml"
    path.write_text(ROS_CAMERA_INFO + extra)
    with pytest.raises(ConfigError, match=rf"intrinsics\.yaml: {problem}"):
        read_intrinsics(path)
    (tmp_path / "o3d.json").write_text('{"intrinsic_matrix": [400,0,0,0,400,0,20,10,1], "cx": 5}')
    with pytest.raises(ConfigError, match=r"o3d\.json: cx given twice, by intrinsic_matrix"):
        read_intrinsics(tmp_path / "o3d.json")


@pytest.mark.parametrize("value", ["0.1", "null", "{data: 0.1}"])
def test_a_ros_matrix_that_is_not_a_list_is_refused(tmp_path, value):
    """``distortion_coefficients: 0.1`` was read as k1 = 0.1 (numpy takes a lone number for a
    list of one)."""
    text = ROS_CAMERA_INFO.split("distortion_coefficients:")[0] + "distortion_coefficients: "
    path = tmp_path / "camera_info.yaml"
    path.write_text(text + value + "\n")
    if value == "null":  # no coefficients at all: no distortion, as before
        assert not read_intrinsics(path).distorted
        path.write_text("camera_matrix: null\n")
        match = "camera_matrix must be a list of numbers"
    else:
        match = "distortion_coefficients must be a list of numbers or {rows, cols, data}, got 0.1"
    with pytest.raises(ConfigError, match=rf"camera_info\.yaml: {match}"):
        read_intrinsics(path)


def test_our_layout_may_name_its_distortion_model(tmp_path):
    """ROS's ``distortion_model`` beside our fields: the model our coefficients are is read,
    another refused by name (before: pydantic's 'Extra inputs are not permitted')."""
    flat = "fx: 525\nfy: 525\ncx: 319.5\ncy: 239.5\n"
    path = tmp_path / "intrinsics.yaml"
    path.write_text(flat + "k1: 0.1\ndistortion_model: plumb_bob\n")
    assert read_intrinsics(path).k1 == 0.1
    path.write_text(flat + "distortion_model: equidistant\n")  # no coefficient: no distortion
    assert read_intrinsics(path).k1 == 0.0
    path.write_text(flat + "k1: 0.1\ndistortion_model: equidistant\n")
    message = "distortion model 'equidistant' is not supported (plumb_bob, rational_polynomial)"
    with pytest.raises(ConfigError, match=re.escape(f"intrinsics.yaml: {message}")):
        read_intrinsics(path)
