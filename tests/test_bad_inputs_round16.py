"""Inputs found by a sixteenth hostile round: each written, read or refused as it should be."""

from __future__ import annotations

import numpy as np
import pytest

from spacepose.cli import main
from spacepose.core import se3
from spacepose.core.planes import PlaneConfig, extract_planes, why_no_planes
from spacepose.core.sim.mesh_files import load_mesh
from spacepose.errors import FileFormatError, InputError
from spacepose.tools.cloud_io import read_cloud, write_cloud


def _box(n: int = 1500, seed: int = 0) -> np.ndarray:
    """Points on three faces of a 0.4 m cube 1.2 m in front of the origin, 1 mm noise."""
    rng = np.random.default_rng(seed)
    faces = []
    for axis in range(3):
        p = rng.uniform(-0.2, 0.2, (n, 3))
        p[:, axis] = -0.2
        faces.append(p)
    return np.vstack(faces) + np.array([0.0, 0.0, 1.2]) + rng.normal(0.0, 0.001, (3 * n, 3))


@pytest.mark.parametrize("suffix", [".ply", ".pcd", ".xyz"])
def test_far_coordinates_are_written_without_flattening_the_cloud(tmp_path, suffix):
    """A cloud 7,000 km out (an Earth-centred frame) was written as float32 by default and
    came back 0.25 m off, every point at one of a few z values: a box read back as a sheet.
    By default such a cloud is written as float64; float32, asked for, is refused."""
    points = _box() + np.array([0.0, 0.0, 7.0e6])
    out = tmp_path / f"far{suffix}"
    write_cloud(out, points)
    np.testing.assert_allclose(read_cloud(out).points, points, rtol=0, atol=1e-9)
    with pytest.raises(InputError, match=r"float32 moves points at \|coordinate\| up to 7e\+06 by"):
        write_cloud(tmp_path / f"f32{suffix}", points, dtype="float32")
    near = tmp_path / "near.ply"
    write_cloud(near, _box())
    assert b"property float x" in near.read_bytes()[:300]  # near the origin float32 serves


@pytest.mark.parametrize("offset", [1e10, 1e11])
def test_planes_far_from_the_origin_are_the_planes_near_it(offset):
    """The lab frame moved 1e11 m out gave 0 planes and numpy's "Mean of empty slice": a
    plane's moments about an origin that far cancel to rounding noise. The same three faces
    are found, their centroids moved by the offset, their normals facing the origin."""
    points = _box()
    near = extract_planes(points)
    far = extract_planes(points + np.array([0.0, 0.0, offset]))
    assert len(near) == len(far) == 3
    for a, b in zip(near, far, strict=True):
        assert len(np.setxor1d(a.inliers, b.inliers)) <= 3
        np.testing.assert_allclose(b.centroid - [0.0, 0.0, offset], a.centroid, atol=1e-4)
        assert b.offset <= 0 and abs(abs(a.normal @ b.normal) - 1) < 1e-6


@pytest.mark.parametrize(
    ("option", "value", "reason"),
    [
        ("--threshold", "1e-12", "the best plane holds 3 points within 1e-12 m, fewer than"),
        ("--min-inliers", "10000000", "4500 points, fewer than min_inliers 10000000"),
        ("--cluster-radius", "1e-9", "(its largest group, links under 1e-09 m), fewer than"),
    ],
)
def test_planes_that_find_nothing_say_why(tmp_path, capsys, option, value, reason):
    """A plane thickness, smallest plane or link too small for the cloud printed an empty
    table (or []) with exit 0 and no word."""
    path = tmp_path / "box.ply"
    write_cloud(path, _box())
    assert main(["planes", str(path), option, value, "--json"]) == 0
    captured = capsys.readouterr()
    assert captured.out.strip() == "[]"
    assert f"{path}: no plane found: " in captured.err and reason in captured.err


def test_why_no_planes_names_a_curved_surface():
    """A sphere's slabs are planes RANSAC finds and extraction drops (no face)."""
    directions = np.random.default_rng(0).normal(size=(6000, 3))
    points = 0.3 * directions / np.linalg.norm(directions, axis=1)[:, None] + [0.0, 0.0, 3.0]
    config = PlaneConfig(distance_threshold=0.005, min_inliers=50)
    assert extract_planes(points, config) == []
    assert why_no_planes(points, config) == (
        "the best plane (122 points within 0.005 m) cuts a curved surface, no face"
    )


@pytest.mark.parametrize(
    ("command", "name", "message"),
    [
        ("track", "est.png", "a TUM trajectory is text, and a .png file is read as a depth image"),
        ("track", "est.obj", "a TUM trajectory is text, and a .obj file is read as a mesh"),
        ("register", "r.ply", "a JSON result is text, and a .ply file is read as a point cloud"),
        ("navigate", "nav.npy", "a CSV table is text, and a .npy file is read as a point cloud"),
    ],
)
def test_a_text_output_named_as_data_is_refused(tmp_path, capsys, command, name, message):
    """`track --out e.png` wrote its TUM text as e.png, which the next run over the depth
    folder read as a frame (lost: "not an image Pillow can decode"); register wrote JSON as
    a .ply, navigate CSV as a .png, exit 0."""
    frames = tmp_path / "frames"
    for k in range(2):
        write_cloud(frames / f"{k:06d}.ply", _box(seed=k))
    out = tmp_path / "out" / name
    args = {
        "track": ["track", str(frames), "--out", str(out)],
        "register": ["register", str(frames / "000000.ply"), str(frames / "000001.ply")],
        "navigate": ["navigate", str(frames), "--out", str(out)],
    }[command]
    if command == "register":
        args += ["--out", str(out)]
    assert main(args) == 1
    assert (
        capsys.readouterr().err.strip()
        == f"error: {out}: {message}: name it ."
        + {
            "track": "tum",
            "register": "json",
            "navigate": "csv",
        }[command]
    )
    assert not out.exists()


def test_a_mesh_whose_squares_overflow_is_refused_naming_the_file(tmp_path):
    """Vertices at 1e300 leaked five numpy overflow warnings, then an error about the
    mesh's surface samples that named neither the file nor the cause."""
    path = tmp_path / "huge.obj"
    path.write_text("v 0 0 0\nv 1e300 0 0\nv 0 1e300 0\nf 1 2 3\n")
    with pytest.raises(FileFormatError) as exc:
        load_mesh(path)
    assert str(exc.value) == (
        f"{path}: vertices reach |coordinate| 1e+300, beyond 3.12e+144: their squares overflow "
        "float64 (wrong units or a corrupt file?)"
    )


@pytest.mark.parametrize(
    ("T", "problem"),
    [
        (np.diag([2.0, 2.0, 2.0, 1.0]), "rotation block is not a proper rotation"),
        (np.diag([1.0, 1.0, -1.0, 1.0]), "rotation block is not a proper rotation"),
        (np.r_[np.eye(4)[:3], [[0.1, 0.0, 0.0, 1.0]]], "last row must be (0, 0, 0, 1)"),
        (np.full((4, 4), np.nan), "has non-finite entries"),
    ],
)
def test_the_se3_helpers_refuse_what_is_not_a_rigid_transform(T, problem):
    """invert(diag(2, 2, 2, 1)) gave a matrix whose product with it was 4·I; compose, adjoint,
    transform_points and rotate_vectors used a scaled "rotation"; a NaN matrix inverted to
    NaNs; all without a word. A stack's missing (NaN) poses stay NaN."""
    calls = [
        lambda: se3.invert(T),
        lambda: se3.compose(np.eye(4), T),
        lambda: se3.adjoint(T),
        lambda: se3.transform_points(T, np.zeros((1, 3))),
        lambda: se3.rotate_vectors(T, np.ones((1, 3))),
    ]
    for call in calls:
        with pytest.raises(InputError, match=problem.replace("(", r"\(").replace(")", r"\)")):
            call()
    stack = np.stack([np.eye(4), np.full((4, 4), np.nan)])
    assert np.isnan(se3.invert(stack)[1, :3]).all() and (se3.invert(stack)[0] == np.eye(4)).all()
    if np.isfinite(T).all():
        with pytest.raises(InputError, match="invert: transform 1 of 2 is not rigid"):
            se3.invert(np.stack([np.eye(4), T]))


def test_a_frame_far_from_its_origin_is_said_not_to_be_in_the_sensors_frame():
    """The lab's frames moved 10 km out (a world frame) lost every frame after the first with
    "the pose graph edges leave a free node unconstrained", naming neither the cause nor the
    frame: 2.5 mm apart at 10 km is finer than any range sensor resolves."""
    import warnings

    from spacepose.core.sim.scenarios import LabConfig, simulate_lab
    from spacepose.core.tracker import Tracker, TrackerConfig
    from spacepose.errors import SpaceposeWarning

    frame = simulate_lab(LabConfig(frames=1, seed=0)).frame(0)
    with pytest.warns(SpaceposeWarning, match=r"the points are 1\.2\d*e\+04 m from the origin"):
        Tracker(TrackerConfig(), workers=1).track_frame(
            frame.cloud.points + np.array([0.0, 0.0, 1.2e4]), 0.0
        )
    with warnings.catch_warnings():
        warnings.simplefilter("error", SpaceposeWarning)
        Tracker(TrackerConfig(), workers=1).track_frame(frame.cloud.points, 0.0)
