"""Depth image files (tools/depth_io.py): decoding, intrinsics files, TUM RGB-D's depth.txt."""

from __future__ import annotations

import re
import warnings
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from spacepose.core.depth import DepthCamera
from spacepose.errors import ConfigError, FileFormatError, InputError, SpaceposeWarning
from spacepose.tools.depth_io import (
    depth_files,
    find_intrinsics,
    is_depth_folder,
    read_depth_cloud,
    read_depth_image,
    read_intrinsics,
    read_tum_depth_list,
    write_depth_image,
)

CAMERA = DepthCamera(fx=300.0, fy=300.0, cx=15.5, cy=11.5, depth_scale=0.0002)


def _depth_m(rng) -> np.ndarray:
    depth = rng.uniform(0.5, 4.0, (24, 32))
    depth[rng.random((24, 32)) < 0.2] = 0.0
    return depth


@pytest.mark.parametrize("suffix", [".png", ".tif"])
def test_16_bit_round_trip(tmp_path, suffix):
    depth = _depth_m(np.random.default_rng(1))
    path = write_depth_image(tmp_path / f"d{suffix}", depth, depth_scale=0.0002)
    values = read_depth_image(path)
    assert values.dtype == np.uint16 and values.shape == (24, 32)
    np.testing.assert_array_equal(values, np.rint(depth / 0.0002).astype(np.uint16))
    # Decoded by Pillow independently of our writer: the same 16-bit samples.
    with Image.open(path) as image:
        np.testing.assert_array_equal(np.array(image), values)
    cloud = read_depth_cloud(path, CAMERA)
    assert len(cloud) == int((depth > 0).sum())
    np.testing.assert_allclose(np.sort(cloud.points[:, 2]), np.sort(depth[depth > 0]), atol=1e-4)


def test_float_tiff_in_metres(tmp_path):
    depth = _depth_m(np.random.default_rng(2))
    path = write_depth_image(tmp_path / "d.tiff", depth, depth_scale=1.0)
    values = read_depth_image(path)
    assert values.dtype == np.float32
    cloud = read_depth_cloud(path, CAMERA.model_copy(update={"depth_scale": 1.0}))
    np.testing.assert_allclose(cloud.points[:, 2], depth[depth > 0].astype(np.float32))


@pytest.mark.parametrize(
    ("content", "message"),
    [
        (b"", "not an image"),
        (b"this is a text file, not a PNG\n", "not an image"),
        ("truncated", "cannot decode"),
    ],
)
def test_unreadable_images_are_file_format_errors(tmp_path, content, message):
    path = tmp_path / "bad.png"
    if content == "truncated":
        good = write_depth_image(tmp_path / "good.png", _depth_m(np.random.default_rng(3)))
        content = good.read_bytes()[:-200]
    path.write_bytes(content)
    with pytest.raises(FileFormatError, match=message) as info:
        read_depth_image(path)
    assert "bad.png" in str(info.value) and "\n" not in str(info.value)


def test_colour_and_8_bit_images_are_refused(tmp_path):
    Image.fromarray(np.zeros((4, 4, 3), dtype=np.uint8)).save(tmp_path / "rgb.png")
    Image.fromarray(np.zeros((4, 4), dtype=np.uint8)).save(tmp_path / "grey.png")
    for name in ("rgb.png", "grey.png"):
        with pytest.raises(FileFormatError, match="one channel of 16-bit"):
            read_depth_image(tmp_path / name)
    with pytest.raises(FileFormatError, match="not found"):
        read_depth_image(tmp_path / "missing.png")


def test_write_refuses_out_of_range(tmp_path):
    with pytest.raises(InputError, match="reaches 65535 units"):
        write_depth_image(tmp_path / "far.png", np.full((2, 2), 70.0), depth_scale=0.001)
    # 65535 itself is the no-return code and is refused too; 65534 units are written.
    with pytest.raises(InputError, match="no-return code"):
        write_depth_image(tmp_path / "edge.png", np.full((2, 2), 65.535), depth_scale=0.001)
    path = write_depth_image(tmp_path / "ok.png", np.full((2, 2), 65.534), depth_scale=0.001)
    assert read_depth_image(path).max() == 65534
    with pytest.raises(InputError, match="non-negative"):
        write_depth_image(tmp_path / "neg.png", -np.ones((2, 2)))


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
    assert (camera.width, camera.height, camera.depth_scale) == (640, 480, 0.001)
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
            "needs 9 numbers, got 2",
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


@pytest.mark.peers
def test_open3d_intrinsics_json_back_projects_as_open3d_does(tmp_path):
    """Open3D writes the file and back-projects the depth image: the reference."""
    o3d = pytest.importorskip("open3d")
    width, height, fx, fy, cx, cy = 32, 24, 301.5, 297.0, 15.25, 11.75
    intrinsic = o3d.camera.PinholeCameraIntrinsic(width, height, fx, fy, cx, cy)
    o3d.io.write_pinhole_camera_intrinsic(str(tmp_path / "intrinsics.json"), intrinsic)
    camera = read_intrinsics(tmp_path / "intrinsics.json")
    assert (camera.fx, camera.fy, camera.cx, camera.cy) == (fx, fy, cx, cy)
    assert (camera.width, camera.height, camera.distorted) == (width, height, False)
    rng = np.random.default_rng(3)
    depth_mm = np.round(_depth_m(rng) * 1000).astype(np.uint16)
    path = tmp_path / "000000.png"
    Image.fromarray(depth_mm).save(path)
    ours = read_depth_cloud(path, camera).points
    theirs = np.asarray(
        o3d.geometry.PointCloud.create_from_depth_image(
            o3d.geometry.Image(depth_mm), intrinsic, depth_scale=1000.0, depth_trunc=100.0
        ).points
    )
    assert len(ours) == np.count_nonzero(depth_mm) == len(theirs)
    np.testing.assert_allclose(ours, theirs, atol=1e-6)


def test_tum_depth_list(tmp_path):
    (tmp_path / "depth").mkdir()
    (tmp_path / "depth.txt").write_text(
        "# depth maps\n# file: 'rgbd_dataset_freiburg1_xyz.bag'\n# timestamp filename\n"
        "1305031102.160407 depth/1305031102.160407.png\n"
        "1305031102.194330 depth/1305031102.194330.png\n"
    )
    paths, stamps = read_tum_depth_list(tmp_path / "depth.txt")
    assert paths == (
        tmp_path / "depth/1305031102.160407.png",
        tmp_path / "depth/1305031102.194330.png",
    )
    np.testing.assert_array_equal(stamps, [1305031102.160407, 1305031102.194330])
    assert is_depth_folder(tmp_path)
    (tmp_path / "depth.txt").write_text("1.0 a.png\nsoon b.png\n")
    with pytest.raises(InputError, match="line 2"):
        read_tum_depth_list(tmp_path / "depth.txt")
    (tmp_path / "depth.txt").write_text("2.0 a.png\n1.0 b.png\n")
    with pytest.raises(InputError, match=r"must increase: frame 1 goes back to 1\.0"):
        read_tum_depth_list(tmp_path / "depth.txt")


def test_depth_files_sorted(tmp_path):
    for name in ("b.png", "a.tif", "c.TIFF", "notes.txt"):
        (tmp_path / name).write_bytes(b"")
    assert [p.name for p in depth_files(tmp_path)] == ["a.tif", "b.png", "c.TIFF"]
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="no depth images"):
        depth_files(tmp_path / "empty")


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


def test_exr_depth_channels(tmp_path):
    """One channel, or the one named as depth (Blender's multilayer ``ViewLayer.Depth.Z``
    beside its colour), or equal R, G, B (a depth saved grey); a colour image is refused with
    its channels' names, and a corrupt file as such."""
    import OpenEXR

    depth = _depth_m(np.random.default_rng(3)).astype(np.float32)
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}

    def exr(name: str, channels: dict) -> Path:
        with OpenEXR.File(header, channels) as f:
            f.write(str(tmp_path / name))
        return tmp_path / name

    colour = np.random.default_rng(4).random((24, 32)).astype(np.float16)
    for path in (
        write_depth_image(tmp_path / "z.exr", depth, depth_scale=1.0),
        exr(
            "layers.exr",
            {
                "ViewLayer.Combined.R": colour,
                "ViewLayer.Combined.G": colour,
                "ViewLayer.Depth.Z": depth,
            },
        ),
        exr("grey.exr", {"R": depth, "G": depth, "B": depth, "A": np.ones_like(depth)}),
    ):
        values = read_depth_image(path)
        assert values.dtype == np.float32
        np.testing.assert_array_equal(values, depth)
    half = exr("half.exr", {"V": depth.astype(np.float16)})
    np.testing.assert_array_equal(read_depth_image(half), depth.astype(np.float16))
    with pytest.raises(FileFormatError, match=r"colour.exr: channels B, G, R: none is depth"):
        read_depth_image(exr("colour.exr", {"R": colour, "G": depth, "B": depth}))
    (tmp_path / "bad.exr").write_bytes(b"v/1\x01" + bytes(200))
    with pytest.raises(FileFormatError, match=r"bad.exr: cannot decode the image"):
        read_depth_image(tmp_path / "bad.exr")
    with pytest.raises(FileFormatError, match=r"none.exr: file not found"):
        read_depth_image(tmp_path / "none.exr")


def test_a_cut_multi_part_or_background_exr(tmp_path):
    """A file cut short is a FileFormatError in the library's words, its six lines on stdout and
    stderr held back (it ended in a traceback, "file has 0 parts"); a render's passes as parts
    give their depth part, not the first (its luminance was read as depths); a map of the far
    plane alone is no return, not a cloud 1e10 m out."""
    import OpenEXR

    depth = _depth_m(np.random.default_rng(5)).astype(np.float32)
    whole = write_depth_image(tmp_path / "whole.exr", depth, depth_scale=1.0).read_bytes()
    (tmp_path / "cut.exr").write_bytes(whole[: len(whole) // 2])
    with pytest.raises(FileFormatError, match=r"cut.exr: cannot decode the image"):
        read_depth_image(tmp_path / "cut.exr")

    def header(name: str) -> dict:
        return {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage, "name": name}

    luminance = np.full_like(depth, 0.4)
    parts = [
        OpenEXR.Part(header("beauty"), {"Y": luminance}),
        OpenEXR.Part(header("depth"), {"Z": depth}),
    ]
    OpenEXR.File(parts).write(str(tmp_path / "passes.exr"))
    np.testing.assert_array_equal(read_depth_image(tmp_path / "passes.exr"), depth)
    background = write_depth_image(tmp_path / "bg.exr", np.full((24, 32), 1e10), depth_scale=1.0)
    camera = CAMERA.model_copy(update={"depth_scale": 1.0})
    with pytest.raises(
        InputError, match=r"bg.exr: no return: every pixel lies at 1e\+10 m or more"
    ):
        read_depth_cloud(background, camera)


def test_the_exr_library_says_nothing_of_its_own(tmp_path, capfd):
    depth = _depth_m(np.random.default_rng(6))
    whole = write_depth_image(tmp_path / "d.exr", depth, depth_scale=1.0).read_bytes()
    (tmp_path / "cut.exr").write_bytes(whole[: len(whole) // 2])
    with pytest.raises(FileFormatError):
        read_depth_image(tmp_path / "cut.exr")
    out, err = capfd.readouterr()
    assert out == "" and err == ""


def test_odd_pixels_of_a_map_that_back_projects_are_warned_about(tmp_path):
    """Negative depths among the others were dropped unsaid; intrinsics of half the resolution
    that give no size put every ray off without a word (their principal point sits a quarter
    of the image from its centre)."""
    depth = _depth_m(np.random.default_rng(7)).astype(np.float32)
    depth[:, :4] *= -1.0
    path = write_depth_image(tmp_path / "d.tiff", np.abs(depth), depth_scale=1.0)
    Image.fromarray(depth).save(path)  # the negative columns as the file's own
    camera = CAMERA.model_copy(update={"depth_scale": 1.0})
    negative = int((depth < 0).sum())
    with pytest.warns(SpaceposeWarning, match=rf"d.tiff: pixels of negative depth read as no "
                      rf"return \({negative} of 768\)"):  # fmt: skip
        read_depth_cloud(path, camera)
    half = camera.model_copy(update={"fx": 150.0, "fy": 150.0, "cx": 7.75, "cy": 5.75})
    with pytest.warns(SpaceposeWarning, match=r"principal point lies far from the image's cen"):
        read_depth_cloud(path, half)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        read_depth_cloud(write_depth_image(tmp_path / "e.tiff", np.abs(depth), 1.0), camera)


def test_a_far_plane_is_one_shared_value_not_every_far_depth(tmp_path):
    """A half-float render's background (65504, the largest half) is a far plane; a sensor's map
    whose 2 % of spurious returns lie at a millimetre keeps its real returns 10-25 m out (a
    cut at 10^4 times the nearest depths took every one past 10 m)."""
    camera = CAMERA.model_copy(update={"depth_scale": 1.0})
    rng = np.random.default_rng(8)
    render = rng.uniform(1.0, 1.5, (24, 32))
    render[:, 16:] = 65504.0
    path = write_depth_image(tmp_path / "half.exr", render, depth_scale=1.0)
    with pytest.warns(SpaceposeWarning, match=r"far plane, read as no return \(384 pixels at 6"):
        assert len(read_depth_cloud(path, camera)) == 384
    scene = rng.uniform(10.0, 25.0, (24, 32))
    scene.ravel()[rng.choice(768, 16, replace=False)] = 1e-3
    path = write_depth_image(tmp_path / "scene.tiff", scene, depth_scale=1.0)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert len(read_depth_cloud(path, camera)) == 768
