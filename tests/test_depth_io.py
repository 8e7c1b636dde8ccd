"""Depth image files (tools/depth_io.py): decoding, writing, back-projection, EXR maps."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from spacepose.core.depth import DepthCamera
from spacepose.errors import FileFormatError, InputError, SpaceposeWarning
from spacepose.tools.depth_io import read_depth_cloud, read_depth_image, write_depth_image
from spacepose.tools.intrinsics_io import read_intrinsics

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
