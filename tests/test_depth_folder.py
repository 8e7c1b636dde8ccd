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
    for name in ("b.png", "a.tif", "c.TIFF", "notes.txt"):
        (tmp_path / name).write_bytes(b"")
    assert [p.name for p in depth_files(tmp_path)] == ["a.tif", "b.png", "c.TIFF"]
    (tmp_path / "empty").mkdir()
    with pytest.raises(InputError, match="no depth images"):
        depth_files(tmp_path / "empty")
