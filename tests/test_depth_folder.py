"""Depth image folders (tools/depth_folder.py): their images, sorted, and TUM RGB-D's depth.txt."""

from __future__ import annotations

import numpy as np
import pytest

from spacepose.errors import InputError
from spacepose.tools.depth_folder import depth_files, is_depth_folder, read_tum_depth_list


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
    for name in ("b.tif", "a.tif", "c.TIFF", "notes.txt"):
        (tmp_path / name).write_bytes(b"")
    assert [p.name for p in depth_files(tmp_path)] == ["a.tif", "b.tif", "c.TIFF"]
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="no depth images"):
        depth_files(tmp_path / "empty")


def test_a_folder_of_mixed_depth_formats_is_refused_by_its_counts(tmp_path):
    """One depth_scale reads a folder's every image: a renderer's EXR in metres beside 16-bit
    PNGs in millimetres (depth_scale 0.001) came out a thousand times too near. ``.tif`` and
    ``.tiff`` are one format."""
    from spacepose.tools.depth_io import write_depth_image

    depth = np.full((4, 5), 1.2)
    for name in ("000000.png", "000001.png", "000002.exr"):
        write_depth_image(tmp_path / name, depth)
    with pytest.raises(InputError, match=r"mixes depth formats \(2 \.png, 1 \.exr\)") as err:
        depth_files(tmp_path)
    assert str(tmp_path) in str(err.value)
    tiffs = tmp_path / "tiffs"
    tiffs.mkdir()
    for name in ("000000.tif", "000001.tiff"):
        write_depth_image(tiffs / name, depth)
    assert [p.name for p in depth_files(tiffs)] == ["000000.tif", "000001.tiff"]
