"""Round 28 of bad inputs (the command line): a noise scale whose noise overflows, seeds without
end, PLY, OFF and STL meshes whose headers miscount their faces, a .gltf that is no JSON, a demo
written into a file, a covariance factor of no sense and a depth_scale that overflows."""

from __future__ import annotations

import struct

import numpy as np
import pytest
from tests.cli_errors import error_line

from spacepose.cli import main
from spacepose.errors import ConfigError, FileFormatError


@pytest.mark.parametrize("scale", ["1e300", "1e40"])
def test_a_noise_scale_whose_noise_overflows_names_the_option(tmp_path, capsys, scale):
    # 1e300 failed at frame 0 on "lab frame 0: points reach |coordinate| 5.4e+297 ...", 1e40 on
    # writing the frame ("write them with dtype='float64'"): neither named --noise-scale.
    out = tmp_path / "run"
    args = ["simulate", "lab", "--out", str(out), "--frames", "1", "--noise-scale", scale]
    assert main(args) == 1
    err = error_line(capsys)
    assert f"error: sensor tof: invalid sensor config: noise_scale {float(scale):g} makes σ" in err
    assert "the noisy points would overflow float32, in which a run's frames are written" in err
    assert not (out / "frames").exists()


def test_a_noise_scale_is_bounded_by_the_sigma_it_makes():
    from spacepose.core.sim.sensors import sensor_config

    assert sensor_config("tof", noise_scale=1e35).noise_scale == 1e35  # σ 5e33 m: computable
    with pytest.raises(ConfigError, match=r"noise_scale 1e\+35 makes σ 5e\+37 m at max_range 10"):
        sensor_config("tof", sigma_quad=5.0, noise_scale=1e35)  # the σ, not the scale alone


def test_seeds_without_end_are_refused_in_one_line(tmp_path, capsys):
    # fusion built the list of 10**12 seeds (a MemoryError traceback); li-l1, li-l3 and room
    # ran for ever (one check serves them all).
    out = tmp_path / "experiments"
    args = ["experiment", "fusion", "--quick", "--seeds", str(10**12), "--out", str(out)]
    assert main(args) == 1
    err = error_line(capsys)
    assert f"error: --seeds: {10**12} is not a number of seeds from 1 to 1000" in err
    assert not out.exists()


def test_a_covariance_scale_of_no_sense_is_refused(tmp_path):
    # 1e300 was taken: every frame "degraded" at σ of 1e146, and navigate --measurements
    # registration ended in "the tracker gave no ok pose", naming neither the field nor the file.
    from spacepose.tools.navigation_config_io import load_navigation_config
    from spacepose.tools.tracking_io import tracker_config

    path = tmp_path / "tracker.yaml"
    path.write_text("covariance_scale: 1e300\n")
    with pytest.raises(ConfigError, match=r"tracker\.yaml: .*covariance_scale: 1e\+300 is too"):
        tracker_config(path)
    fused = tmp_path / "nav.yaml"
    fused.write_text("measurements: registration\ntracker:\n  covariance_scale: 1e300\n")
    with pytest.raises(ConfigError, match=r"nav\.yaml: .*covariance_scale: 1e\+300 is too"):
        load_navigation_config(fused, "registration")
    path.write_text("covariance_scale: 1e20\n")
    assert tracker_config(path).covariance_scale == 1e20


_PLY_HEAD = (
    "ply\nformat {fmt} 1.0\nelement vertex 4\nproperty float x\nproperty float y\n"
    "property float z\nelement face {faces}\nproperty list uchar int vertex_indices\nend_header\n"
)
_CORNERS = "0 0 0\n1 0 0\n0 1 0\n0 0 1\n"


def _binary_ply(faces: int, rows: list[list[int]]) -> bytes:
    body = np.array([[0, 0, 0], [1, 0, 0], [0, 1, 0], [0, 0, 1]], "<f4").tobytes()
    for count, *indices in rows:
        body += struct.pack("<B", count) + np.array(indices, "<i4").tobytes()
    return _PLY_HEAD.format(fmt="binary_little_endian", faces=faces).encode() + body


@pytest.mark.parametrize(
    ("data", "problem"),
    [
        # three faces announced, two held
        (
            _PLY_HEAD.format(fmt="ascii", faces=3) + _CORNERS + "3 0 1 2\n3 0 1 3\n",
            "element 'face': row 2: early end-of-file",
        ),
        # a face of 4 indices holding 3
        (
            _PLY_HEAD.format(fmt="ascii", faces=2) + _CORNERS + "3 0 1 2\n4 0 1 3\n",
            "element 'face': row 1: property 'vertex_indices': early end-of-line",
        ),
        # a face of 3 indices holding 4
        (
            _PLY_HEAD.format(fmt="ascii", faces=2) + _CORNERS + "3 0 1 2 3\n3 0 1 3\n",
            "element 'face': row 0: expected end-of-line",
        ),
        # one face announced, two held: the second dropped
        (
            _PLY_HEAD.format(fmt="ascii", faces=1) + _CORNERS + "3 0 1 2\n3 0 1 3\n",
            "the file holds 6 rows but its header counts 5: the rest would be dropped",
        ),
        # binary: the last face of 4 indices holding 3
        (
            _binary_ply(2, [[3, 0, 1, 2], [4, 0, 1, 3]]),
            "element 'face': row 1: property 'vertex_indices': early end-of-file",
        ),
    ],
    ids=["more-faces", "list-short", "list-long", "fewer-faces", "binary-list-short"],
)
def test_a_ply_mesh_whose_faces_the_header_miscounts_is_refused(tmp_path, data, problem):
    """trimesh read each as the two faces it could make out, without a word."""
    from spacepose.core.sim.mesh_files import load_mesh

    path = tmp_path / "model.ply"
    if isinstance(data, str):
        path.write_text(data)
    else:
        path.write_bytes(data)
    with pytest.raises(FileFormatError) as info:
        load_mesh(path)
    assert str(info.value) == f"{path}: bad or truncated PLY: {problem}"
    path.write_text(_PLY_HEAD.format(fmt="ascii", faces=2) + _CORNERS + "3 0 1 2\n3 0 1 3\n")
    assert len(load_mesh(path).mesh.faces) == 2
    path.write_bytes(_binary_ply(2, [[3, 0, 1, 2], [3, 0, 1, 3]]))
    assert len(load_mesh(path).mesh.faces) == 2


def test_a_ply_mesh_cut_short_is_one_line_from_simulate(tmp_path, capsys):
    model = tmp_path / "model.ply"
    model.write_text(_PLY_HEAD.format(fmt="ascii", faces=3) + _CORNERS + "3 0 1 2\n3 0 1 3\n")
    args = ["simulate", "lab", "--frames", "1", "--model", str(model), "--out", str(tmp_path / "r")]
    assert main(args) == 1
    err = error_line(capsys)
    assert err == f"error: {model}: bad or truncated PLY: element 'face': row 2: early end-of-file"


@pytest.mark.parametrize(
    ("data", "problem"),
    [
        (b"not json\n", "not valid glTF JSON: line 1:1: Expecting value"),
        (b'{"asset": ', "not valid glTF JSON: line 1:11: Expecting value"),
        (b"glTF\x02\x00\x00\x00\xff", "not valid glTF JSON: not UTF-8 text (a binary .glb"),
        (b"[1, 2]", "not valid glTF JSON: it holds an array, not glTF's object of 'asset'"),
    ],
    ids=["text", "cut", "binary", "array"],
)
def test_a_gltf_that_is_no_json_says_so(tmp_path, capsys, data, problem):
    # trimesh's message was the file's name alone ("cannot read mesh: model.gltf"), or "'list'
    # object has no attribute 'get'".
    model = tmp_path / "model.gltf"
    model.write_bytes(data)
    args = ["simulate", "lab", "--frames", "1", "--model", str(model), "--out", str(tmp_path / "r")]
    assert main(args) == 1
    assert f"error: {model}: {problem}" in error_line(capsys)
    import trimesh

    from spacepose.core.sim.mesh_files import load_mesh

    trimesh.creation.box().export(model)  # glTF's JSON (and its buffers) loads as before
    assert len(load_mesh(model).mesh.faces) == 12


@pytest.mark.parametrize("under", [False, True])
def test_a_demo_written_into_a_file_says_so(tmp_path, capsys, under):
    # "error: FILE/lab/tracks/point_to_point.tum: Not a directory": a path the demo derived.
    file = tmp_path / "demo"
    file.write_text("notes\n")
    out = file / "sub" if under else file
    assert main(["demo", "--out", str(out), "--orbit-frames", "20"]) == 1
    err = error_line(capsys)
    where = "is a file, not a folder" if not under else f"lies under {file}, a file"
    assert err == (
        f"error: {out}: --out {where}: the demo writes its runs and report.html into a folder"
    )
    assert file.read_text() == "notes\n"


_OFF_CORNERS = "0 0 0\n1 0 0\n0 1 0\n0 0 1\n"


@pytest.mark.parametrize(
    ("text", "problem"),
    [
        (
            "OFF\n4 3 0\n" + _OFF_CORNERS + "3 0 1 2\n3 0 1 3\n",
            "the header counts 4 vertices and 3 faces, 7 lines, but 6 follow it",
        ),
        (
            "OFF\n4 1 0\n" + _OFF_CORNERS + "3 0 1 2\n3 0 1 3\n",  # the second face dropped
            "the header counts 4 vertices and 1 faces, 5 lines, but 6 follow it",
        ),
        (
            "OFF\n5 2 0\n" + _OFF_CORNERS + "3 0 1 2\n3 0 1 3\n",  # a face read as a vertex
            "the header counts 5 vertices and 2 faces, 7 lines, but 6 follow it",
        ),
        (
            "OFF\n4 2 0\n" + _OFF_CORNERS + "3 0 1 2\n4 0 1 3\n",
            "face 2 counts 4 corners but lists 3",
        ),
    ],
    ids=["more-faces", "fewer-faces", "more-vertices", "face-short"],
)
def test_an_off_mesh_its_counts_miscount_is_refused(tmp_path, text, problem):
    """trimesh read an OFF file by its counts: faces dropped, or a face taken as a vertex."""
    from spacepose.core.sim.mesh_files import load_mesh

    path = tmp_path / "model.off"
    path.write_text(text)
    with pytest.raises(FileFormatError, match=rf"model\.off: {problem}"):
        load_mesh(path)
    # Counts on the OFF line, comments, a face's colour after its corners: read as before.
    path.write_text("OFF 4 2 0 # counts\n" + _OFF_CORNERS + "3 0 1 2 255 0 0\n\n3 0 1 3\n")
    assert len(load_mesh(path).mesh.faces) == 2


@pytest.mark.parametrize("count", [3, 1, 10**9])
def test_a_binary_stl_its_header_miscounts_is_named(tmp_path, capsys, count):
    # It was "the file holds no triangles", of a file holding two.
    triangle = np.array([0, 0, 1, 0, 0, 0, 1, 0, 0, 0, 1, 0], "<f4").tobytes() + b"\0\0"
    model = tmp_path / "model.stl"
    model.write_bytes(b"\0" * 80 + struct.pack("<I", count) + 2 * triangle)
    args = ["simulate", "lab", "--frames", "1", "--model", str(model), "--out", str(tmp_path / "r")]
    assert main(args) == 1
    assert error_line(capsys) == (
        f"error: {model}: its header counts {count:,} triangles ({84 + 50 * count:,} bytes), but "
        "the file holds 184 bytes: a cut or miscounted binary STL"
    )


def test_a_depth_scale_that_overflows_the_points_is_named(tmp_path):
    """depth_scale 1e300 was refused as the frame's fault ("points reach |coordinate|
    1.5e+303 ... a corrupt file?"), where 1e-300 named the depth_scale."""
    from PIL import Image

    from spacepose.core.depth import DepthCamera
    from spacepose.errors import InputError
    from spacepose.tools.depth_io import read_depth_cloud

    path = tmp_path / "d.png"
    Image.fromarray(np.full((24, 32), 1200, dtype=np.uint16)).save(path)
    camera = DepthCamera(fx=30.0, fy=30.0, cx=15.5, cy=11.5, depth_scale=1e300)
    with pytest.raises(
        InputError,
        match=r"d\.png: depths reach 1\.2e\+303 m at a depth_scale of 1e\+300 m per stored unit "
        r"\(given\), beyond 3\.12e\+144 m: a wrong depth_scale\?",
    ):
        read_depth_cloud(path, camera)
