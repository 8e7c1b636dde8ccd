"""Round 29 of bad inputs: an ASCII PCD whose rows run together, navigation and fusion settings
whose squares overflow (or hang the filter), an orbit beyond the sensor's range, OBJ, GLB and PLY
meshes trimesh misread, a plane warning without its file and experiments of endless frames."""

from __future__ import annotations

import subprocess
import sys

import numpy as np
import pytest
import trimesh

from spacepose.cli import main
from spacepose.errors import ConfigError, FileFormatError


def _error_line(capsys) -> str:
    """The command's stderr, checked to end in one ``error:`` line and no traceback."""
    err = capsys.readouterr().err.strip()
    assert "Traceback" not in err, err
    last = err.splitlines()[-1]
    assert last.startswith("error: "), err
    return last


_PCD_HEAD = (
    "VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 3\nHEIGHT 1\n"
    "POINTS 3\nDATA ascii\n"
)


def test_an_ascii_pcd_whose_rows_hold_other_counts_is_refused(tmp_path):
    """Counted whole, a row of 2 values and one of 4 were read as points of 3, each holding
    the other's coordinates, without a word (PCL refuses such a file)."""
    from spacepose.tools.cloud_io import read_cloud

    path = tmp_path / "scan.pcd"
    path.write_text(_PCD_HEAD + "0 0 1\n1 0\n1 1 0 1\n")
    with pytest.raises(FileFormatError) as info:
        read_cloud(path)
    assert str(info.value) == (
        f"{path}: ASCII PCD point 1 holds 2 values on its line, where FIELDS and COUNT make 3: "
        "one point a line (a row cut short or run together?)"
    )
    path.write_text(_PCD_HEAD + "0 0 1\n\n1 0 1  \n1 1 0\n")  # blank lines, trailing blanks
    np.testing.assert_array_equal(read_cloud(path).points, [[0, 0, 1], [1, 0, 1], [1, 1, 0]])


def _navigation_config(tmp_path, text: str, measurements: str = "rectangles"):
    from spacepose.tools.navigation_config_io import load_navigation_config

    path = tmp_path / "nav.yaml"
    path.write_text(text)
    return path, lambda: load_navigation_config(path, measurements)


@pytest.mark.parametrize(
    ("key", "setting"),
    [
        ("range_sigma", "range_sigma: {}"),
        ("rectangle.sigma", "rectangle:\n  sigma: {}"),
        ("rectangle.focal_px", "rectangle:\n  focal_px: {}"),
    ],
)
def test_a_navigation_sigma_whose_square_overflows_is_refused(tmp_path, key, setting):
    """1e300 ended navigate in an OverflowError traceback (sigma**2, focal_px**2)."""
    path, load = _navigation_config(tmp_path, setting.format("1e300") + "\n")
    with pytest.raises(ConfigError) as info:
        load()
    assert f"{path}: invalid navigation config: {key}: 1e+300 is too large" in str(info.value)
    path.write_text(setting.format("1e40") + "\n")
    load()  # large, but its square stays finite


@pytest.mark.parametrize("key", ["tilt_scale", "spin_scale", "min_attitude_sigma_deg"])
def test_a_navigation_factor_whose_square_overflows_is_named(tmp_path, key):
    """1e300 ended navigate in "measurement covariance must be finite with shape (3, 3), got
    (3, 3)" after numpy's overflow warnings: neither the key nor the file named."""
    path, load = _navigation_config(tmp_path, f"{key}: 1e300\n")
    with pytest.raises(ConfigError, match=rf"nav\.yaml: invalid navigation config: {key}: 1e\+300"):
        load()
    path.write_text(f"{key}: 1e40\n")
    assert getattr(load()[0], key) == 1e40


def test_a_centroid_sigma_floor_of_no_sense_is_refused(tmp_path, capsys):
    """1e300 ended navigate in an OverflowError traceback; 1e50 in "measurement covariance
    must be positive definite", the faces' in-plane σ lost to rounding."""
    path, load = _navigation_config(tmp_path, "min_centroid_sigma: 1e50\n")
    with pytest.raises(ConfigError) as info:
        load()
    assert str(info.value) == (
        f"{path}: invalid navigation config: min_centroid_sigma: Input should be less than or "
        "equal to 1000"
    )
    path.write_text("min_centroid_sigma: 0.01\n")
    assert load()[0].min_centroid_sigma == 0.01


@pytest.mark.parametrize(
    "key", ["pose_sigma_scale", "pose_sigma_scale_translation", "model_free_sigma_scale"]
)
def test_a_fusion_sigma_factor_of_no_sense_is_refused(tmp_path, key):
    """pose_sigma_scale 1e300 ended navigate --measurements registration in an OverflowError
    traceback; pose_sigma_scale_translation in "measurement covariance must be finite" (1e50:
    "... positive definite"), naming neither the key nor the file."""
    text = f"measurements: registration\ntracker: {{}}\n{key}: 1e50\n"
    path, load = _navigation_config(tmp_path, text, "registration")
    with pytest.raises(ConfigError) as info:
        load()
    assert str(info.value) == (
        f"{path}: invalid fusion config: {key}: Input should be less than or equal to 1000000"
    )
    path.write_text(text.replace("1e50", "4.0"))
    assert getattr(load()[1], key) == 4.0


def test_inertia_ratios_of_no_rigid_body_name_the_key_and_the_file(tmp_path):
    """Refused when the filter started, as "inertia ratios [5. 5. 5.] are not those of
    positive principal moments", naming neither init_k nor the file."""
    path, load = _navigation_config(tmp_path, "init_k: [5, 5, 5]\n")
    with pytest.raises(ConfigError) as info:
        load()
    assert str(info.value) == (
        f"{path}: invalid navigation config: init_k: inertia ratios [5. 5. 5.] are not those of "
        "positive principal moments"
    )
    path.write_text("init_k: [0.2, -0.1, -0.10204081632653061]\n")
    assert load()[0].init_k[0] == 0.2


def test_ekf_substeps_without_end_are_refused(tmp_path):
    """substeps 10**9 ran navigate for ever (its first prediction unfinished)."""
    path, load = _navigation_config(tmp_path, f"ekf:\n  substeps: {10**9}\n")
    with pytest.raises(ConfigError) as info:
        load()
    assert str(info.value) == (
        f"{path}: invalid navigation config: ekf.substeps: Input should be less than or equal "
        "to 20000"
    )
    path.write_text("ekf:\n  substeps: 20000\n")
    assert load()[0].ekf.substeps == 20000


def test_a_navigation_sigma_that_overflows_is_one_line_from_navigate(tmp_path, capsys):
    run = tmp_path / "orbit"
    assert main(["simulate", "orbit", "--out", str(run), "--frames", "2"]) == 0
    config = tmp_path / "nav.yaml"
    config.write_text("range_sigma: 1e300\n")
    capsys.readouterr()
    assert main(["navigate", str(run), "--out", str(tmp_path / "nav.csv"), "--config", str(config)])
    assert _error_line(capsys).startswith(
        f"error: {config}: invalid navigation config: range_sigma: 1e+300 is too large"
    )


def test_an_orbit_standoff_beyond_the_sensor_is_refused_before_the_truth(tmp_path):
    """--range 1e300 integrated the orbit for ever (1e7 m failed at frame 0 only after it)."""
    out = tmp_path / "run"
    code = (
        "from spacepose.cli import main; raise SystemExit(main(['simulate', 'orbit', '--frames',"
        f" '2', '--range', '1e300', '--out', {str(out)!r}]))"
    )
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    assert done.returncode == 1, done.stderr
    assert done.stderr.strip().splitlines()[-1] == (
        "error: scenario orbit: a standoff of 1e+300 m puts the whole target (reaching 7.47 m "
        "from its centre) beyond the sensor's 200 m range: it would see nothing; stand off nearer"
    )
    assert not (out / "frames").exists()


_OBJ_CORNERS = "v 0 0 0\nv 1 0 0\nv 0 1 0\nv 0 0 1\n"
_OBJ_FACES = "f 1 2 3\nf 1 2 4\nf 1 3 4\nf 2 3 4\n"


@pytest.mark.parametrize(
    ("text", "problem"),
    [
        # trimesh: numpy's AxisError traceback
        ("v 0 0\n" + _OBJ_CORNERS[8:] + _OBJ_FACES, "vertex 1 (line 1) has 2 coordinates, not 3"),
        # trimesh dropped the face without a word
        (_OBJ_CORNERS + "f 1 2\n" + _OBJ_FACES[8:], "face 1 (line 5) has 2 corners: a face has 3"),
        # the first vertex lost: "face 2 refers to vertex 4, but the file has 3 vertices"
        (
            "\ufeff" + _OBJ_CORNERS + _OBJ_FACES,
            "line 1 begins with a byte-order mark, which hides its statement ('v 0 0 0')",
        ),
    ],
    ids=["two-coordinates", "two-corners", "byte-order-mark"],
)
def test_an_obj_statement_trimesh_misreads_is_named(tmp_path, text, problem):
    from spacepose.core.sim.mesh_files import load_mesh

    path = tmp_path / "model.obj"
    path.write_text(text, encoding="utf-8")
    with pytest.raises(FileFormatError) as info:
        load_mesh(path)
    assert str(info.value).startswith(f"{path}: {problem}")
    path.write_text("\ufeff# exported\n" + _OBJ_CORNERS + _OBJ_FACES, encoding="utf-8")
    assert len(load_mesh(path).mesh.faces) == 4  # a mark before a comment hides nothing


@pytest.mark.parametrize(
    ("cut", "problem"),
    [
        (0.5, "its header says 928 bytes, the file holds 464: a cut or damaged .glb"),
        (0.0, "the file is empty"),
    ],
)
def test_a_cut_glb_says_so(tmp_path, capsys, cut, problem):
    """trimesh said "Unterminated string starting at: line 1 column 439" of a .glb cut in half,
    "index 0 is out of bounds for axis 0 with size 0" of an empty one."""
    data = trimesh.creation.box().export(file_type="glb")
    assert len(data) == 928
    model = tmp_path / "model.glb"
    model.write_bytes(data[: int(cut * len(data))])
    args = ["simulate", "lab", "--frames", "1", "--model", str(model), "--out", str(tmp_path / "r")]
    assert main(args) == 1
    assert _error_line(capsys) == f"error: {model}: {problem}"
    from spacepose.core.sim.mesh_files import load_mesh

    model.write_bytes(data)
    assert len(load_mesh(model).mesh.faces) == 12


def test_a_ply_face_on_a_fractional_vertex_index_is_refused(tmp_path):
    """A face list of floats: trimesh cut vertex index 3.5 to 3 without a word."""
    from spacepose.core.sim.mesh_files import load_mesh

    head = (
        "ply\nformat ascii 1.0\nelement vertex 4\nproperty float x\nproperty float y\n"
        "property float z\nelement face 2\nproperty list uchar float vertex_indices\nend_header\n"
        "0 0 0\n1 0 0\n0 1 0\n0 0 1\n3 0 1 2\n"
    )
    path = tmp_path / "model.ply"
    path.write_text(head + "3 0 1 3.5\n")
    with pytest.raises(FileFormatError) as info:
        load_mesh(path)
    assert str(info.value) == f"{path}: face 2 lists vertex index 3.5: an index is a whole number"
    path.write_text(head + "3 0 1 3.0\n")  # whole numbers stored as floats: read as before
    assert len(load_mesh(path).mesh.faces) == 2


def test_the_plane_slab_warning_names_the_file(tmp_path, capsys):
    """The warning "the range noise reads 207.0 mm, ..." named no file."""
    rng = np.random.default_rng(0)
    path = tmp_path / "noise.npy"
    np.save(path, rng.normal(size=(500, 3)) * 0.2 + [0.0, 0.0, 1.5])
    main(["planes", str(path)])
    err = capsys.readouterr().err
    assert f"warning: {path}: the range noise reads 207.0 mm, a large share" in err, err


@pytest.mark.parametrize("experiment", ["room", "robustness"])
def test_an_experiment_of_endless_frames_is_refused(tmp_path, capsys, experiment):
    """room --frames 10**12 ended in a MemoryError traceback; robustness --frames 10**9 failed
    every cell on the scenario's bound (the errors in its table) and exited 0."""
    out = tmp_path / "experiments"
    args = ["experiment", experiment, "--quick", "--frames", str(10**12), "--out", str(out)]
    assert main(args) == 1
    assert _error_line(capsys) == (
        f"error: --frames: {10**12} is not a number of frames from 2 to 1,000,000 (a run's "
        "frames are simulated, as simulate's --frames)"
    )
    assert not out.exists()
