"""Bad inputs found by a ninth hostile round: each ends in one line naming the file (or the
parameter) and the problem, never a traceback or a silently wrong result."""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np
import pytest

from spacepose.cli import main
from spacepose.core import se3
from spacepose.core.clusters import main_cluster_group
from spacepose.core.depth import DepthCamera, pixel_rays
from spacepose.core.lens import distort, undistort
from spacepose.core.sim.mesh_files import load_mesh
from spacepose.core.trajectory import Trajectory
from spacepose.errors import FileFormatError, InputError, SpaceposeWarning
from spacepose.tools.navigation_config_io import prior_quaternion
from spacepose.tools.trajectory_io import write_tum

_WIDE = DepthCamera(fx=500.0, fy=500.0, cx=2.0, cy=2.0, k1=0.1)


# -- pixel_rays of an image without pixels ---------------------------------------------------------


@pytest.mark.parametrize("camera", [_WIDE, DepthCamera(fx=500.0, fy=500.0, cx=2.0, cy=2.0)])
@pytest.mark.parametrize(("height", "width", "name"), [(0, 5, "height"), (5, 0, "width")])
def test_pixel_rays_of_no_pixels_is_an_input_error(camera, height, width, name):
    """0 rows or columns gave numpy's 'Mean of empty slice' warnings and an empty array."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(InputError) as exc:
            pixel_rays(camera, height, width)
    assert str(exc.value) == f"pixel_rays: {name} must be a whole number >= 1, got 0"


def test_pixel_rays_of_a_fractional_size_is_an_input_error():
    """A height of 2.5 gave the rays of 3 rows."""
    with pytest.raises(InputError) as exc:
        pixel_rays(_WIDE, 2.5, 5)
    assert str(exc.value) == "pixel_rays: height must be a whole number >= 1, got 2.5"
    assert pixel_rays(_WIDE, 4.0, 5).shape == (4, 5, 2)


# -- distort / undistort of x and y of different lengths ------------------------------------------


@pytest.mark.parametrize("function", [distort, undistort])
def test_distort_of_unequal_coordinates_is_an_input_error(function):
    """x of 3 and y of 2 values ended in numpy's 'operands could not be broadcast together'."""
    name = function.__name__
    x, y = ("x", "y") if name == "distort" else ("xd", "yd")
    with pytest.raises(InputError) as exc:
        function(_WIDE, [0.1, 0.2, 0.3], [0.1, 0.2])
    assert str(exc.value) == f"{name}: {x} and {y} must have the same shape, got (3,) and (2,)"
    xd, yd = distort(_WIDE, [[0.1, 0.2]], [[0.0, 0.1]])
    assert xd.shape == yd.shape == (1, 2)
    np.testing.assert_allclose(undistort(_WIDE, xd, yd)[0], [[0.1, 0.2]], atol=1e-9)


# -- a mesh whose face refers to a vertex the file does not hold ----------------------------------


_TETRA = "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\nf 1 2 3\nf 1 2 4\nf 1 3 4\nf 2 3 4\n"
_PLY = (
    "ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\n"
    "property float z\nelement face 2\nproperty list uchar int vertex_indices\nend_header\n"
    "0 0 0\n1 0 0\n0 1 0\n0 0 1\n3 0 1 2\n3 0 1 {last}\n"
)


def test_an_obj_face_on_a_missing_vertex_names_the_face_and_the_vertex_count(tmp_path, capsys):
    """trimesh's numpy wording came through: 'cannot read mesh: index 8 is out of bounds for
    axis 0 with size 4', naming neither the face nor the vertex it refers to."""
    good = tmp_path / "tetra.obj"
    good.write_text(_TETRA)
    assert len(load_mesh(good).mesh.faces) == 4
    bad = tmp_path / "broken.obj"
    bad.write_text(_TETRA.replace("f 1 2 4", "f 1 2 9"))
    message = (
        f"{bad}: face 2 (line 6) refers to vertex 9, but the file has 4 vertices before it "
        "(OBJ numbers them from 1)"
    )
    with pytest.raises(FileFormatError) as exc:
        load_mesh(bad)
    assert str(exc.value) == message
    argv = ["simulate", "lab", "--frames", "1", "--model", str(bad), "--out", str(tmp_path / "r")]
    assert main(argv) == 1
    assert capsys.readouterr().err.strip() == f"error: {message}"


def test_a_ply_face_on_a_missing_vertex_names_the_face_and_the_vertex_count(tmp_path):
    good = tmp_path / "good.ply"
    good.write_text(_PLY.format(last=3))
    assert len(load_mesh(good).mesh.faces) == 2
    bad = tmp_path / "broken.ply"
    bad.write_text(_PLY.format(last=8))
    with pytest.raises(FileFormatError) as exc:
        load_mesh(bad)
    assert str(exc.value) == (
        f"{bad}: face 2 of 2 refers to vertex index 8, but the file has 4 vertices (indices 0 to 3)"
    )


# -- main_cluster_group of no points --------------------------------------------------------------


def test_main_cluster_group_of_no_points_is_an_empty_mask():
    """It failed inside argmax ('attempt to get argmax of an empty sequence'); cluster_labels
    of no points gives no labels, so the group of no points is no points."""
    mask = main_cluster_group(np.zeros((0, 3)), 0.02, 0.1, 0.1)
    assert mask.shape == (0,)
    assert mask.dtype == bool


# -- navigate --prior of a norm far from 1 --------------------------------------------------------


def test_a_prior_of_norm_2_is_normalised_with_a_warning(tmp_path, capsys):
    """0,0,0,2 was normalised without a word: a typo or a scaled vector passed for a prior."""
    with pytest.warns(SpaceposeWarning) as record:
        assert prior_quaternion([0, 0, 0, 2], "--prior") == (0.0, 0.0, 0.0, 1.0)
    assert [str(w.message) for w in record] == [
        "--prior: the quaternion has norm 2, not 1; normalised"
    ]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        prior_quaternion([0.7071, 0, 0, 0.7071], "--prior")  # 4 decimals: no warning
    args = ["navigate", str(tmp_path), "--out", str(tmp_path / "nav" / "p.csv")]
    assert main([*args, "--prior", "0,0,0,2"]) == 1  # no frames in the folder
    err = capsys.readouterr().err.splitlines()
    assert err[0] == "warning: --prior: the quaternion has norm 2, not 1; normalised"


# -- report on a run whose health CSV was half written --------------------------------------------


def _lab_run(root: Path, health: str) -> Path:
    """A lab run of 5 frames with one track, ``icp``, and its health table ``health``."""
    (root / "tracks").mkdir(parents=True)
    (root / "scenario.json").write_text(json.dumps({"scenario": "lab", "seed": 0}))
    t = np.arange(5.0)
    poses = np.stack([se3.make_transform(np.eye(3), [0.01 * k, 0.0, 1.2]) for k in t])
    write_tum(root / "groundtruth.tum", Trajectory(t, poses))
    write_tum(root / "tracks" / "icp.tum", Trajectory(t, poses))
    (root / "tracks" / "icp.health.csv").write_text(health)
    return root


_HEALTH = "frame,timestamp,status,fitness\n" + "".join(f"{k},{k}.0,ok,1\n" for k in range(4))


@pytest.mark.parametrize(
    ("last", "problem"),
    [
        ("4,4.0,lo", "line 6 has 3 fields, the header 4: a half-written or hand-edited file?"),
        ("4,4.0", "line 6 has 2 fields, the header 4: a half-written or hand-edited file?"),
        ("4,4.0,LOST,1\n", "row 5 has status 'LOST', not one of ok, degraded, lost"),
    ],
)
def test_report_of_a_half_written_health_csv_leaves_it_out_and_says_why(
    tmp_path, capsys, last, problem
):
    """A last row cut short (a run stopped mid-write) was read with its missing fields as None:
    its status ('lo', or none) was drawn as a black flag of no meaning, without a word."""
    run = _lab_run(tmp_path / "run", _HEALTH + last)
    assert main(["report", str(run)]) == 0
    health = run / "tracks" / "icp.health.csv"
    assert f"warning: {health}: left out of the report: {problem}" in capsys.readouterr().err
    _lab_run(tmp_path / "good", _HEALTH + "4,4.0,lost,nan\n")
    assert main(["report", str(tmp_path / "good")]) == 0
    assert "warning" not in capsys.readouterr().err


def test_a_text_file_named_ply_is_no_ply_mesh(tmp_path, capsys):
    """trimesh's 'list index out of range' came through for a text file named .ply."""
    bad = tmp_path / "notes.ply"
    bad.write_text("hello world\n1 2 3\n")
    argv = ["simulate", "lab", "--frames", "1", "--model", str(bad), "--out", str(tmp_path / "r")]
    assert main(argv) == 1
    err = capsys.readouterr().err.strip()
    assert err == f"error: {bad}: not a PLY file: it begins with b'hell', not the line 'ply'"


def test_an_unreadable_ply_mesh_is_one_error_not_a_traceback(tmp_path, monkeypatch):
    """The .ply check after trimesh failed opened the file again: an unreadable one raised a
    bare PermissionError there. Root reads any file, so the denial is simulated."""
    from pathlib import Path

    mesh = tmp_path / "locked.ply"
    mesh.write_text(_PLY.format(last=3))
    real_open = Path.open

    def denied(self, *args, **kwargs):
        if self == mesh:
            raise PermissionError(13, "Permission denied", str(self))
        return real_open(self, *args, **kwargs)

    def load(*args, **kwargs):
        raise PermissionError("denied")

    monkeypatch.setattr(Path, "open", denied)
    monkeypatch.setattr("trimesh.load", load)
    with pytest.raises(FileFormatError, match=r"locked.ply: cannot read mesh: denied"):
        load_mesh(mesh)
