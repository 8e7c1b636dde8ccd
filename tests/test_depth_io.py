"""Depth image files (tools/depth_io.py): decoding, intrinsics files, TUM RGB-D's depth.txt."""

from __future__ import annotations

import numpy as np
import pytest
from PIL import Image

from spacepose.core.depth import DepthCamera
from spacepose.errors import ConfigError, FileFormatError, InputError
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
    with pytest.raises(InputError, match="decrease"):
        read_tum_depth_list(tmp_path / "depth.txt")


def test_depth_files_sorted(tmp_path):
    for name in ("b.png", "a.tif", "c.TIFF", "notes.txt"):
        (tmp_path / name).write_bytes(b"")
    assert [p.name for p in depth_files(tmp_path)] == ["a.tif", "b.png", "c.TIFF"]
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="no depth images"):
        depth_files(tmp_path / "empty")
