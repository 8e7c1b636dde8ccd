"""Bad inputs found by an eighth hostile round: each ends in one line naming the file (or the
parameter) and the problem, never a traceback or a silently wrong result."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from spacepose.core import se3
from spacepose.core.clusters import cluster_labels, main_cluster_group
from spacepose.core.crlb import crlb
from spacepose.core.depth import DepthCamera, depth_to_cloud, render_depth
from spacepose.core.principal_axes import principal_axes
from spacepose.core.robust import adaptive_scale, robust_weights
from spacepose.core.scale import derive_scale, point_spacing, range_noise
from spacepose.errors import FileFormatError, InputError, SpaceposeWarning
from spacepose.tools.cloud_io import read_cloud


def _plane(n: int = 400, seed: int = 0) -> np.ndarray:
    """``n`` points on a 0.4 m square plate 1 m in front of the sensor, slightly noisy."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-0.2, 0.2, (n, 2))
    return np.column_stack([xy, 1.0 + 1e-4 * rng.normal(size=n)])


# -- cluster_labels: a link length of 0, < 0, NaN or inf ------------------------------------------


@pytest.mark.parametrize("distance", [0.0, -0.02, float("nan"), float("inf")])
def test_cluster_labels_of_no_link_length_is_an_input_error(distance):
    """0 and NaN left every point its own cluster, -0.02 and inf put all in one: no error."""
    points = _plane(50)
    with pytest.raises(InputError) as exc:
        cluster_labels(points, distance)
    assert str(exc.value) == (
        f"distance must be a positive, finite number of metres, got {distance!r}"
    )
    with pytest.raises(InputError, match=r"^merge_distance must be a positive, finite"):
        main_cluster_group(points, 0.02, distance, 0.1)


def test_cluster_labels_of_bad_points_is_an_input_error():
    """(N, 2) points were clustered in the plane without a word; NaN ended in scipy's
    'data must be finite'."""
    points = _plane(50)
    with pytest.raises(InputError) as exc:
        cluster_labels(points[:, :2], 0.02)
    assert str(exc.value) == "cluster_labels: points must have shape (N, 3), got (50, 2)"
    points[7, 2] = np.nan
    with pytest.raises(InputError) as exc:
        cluster_labels(points, 0.02)
    assert str(exc.value) == "cluster_labels: points have non-finite entries (NaN or inf)"
    assert len(cluster_labels(np.zeros((0, 3)), 0.02)) == 0


# -- se3: mis-shaped transforms, NaN twists ------------------------------------------------------


@pytest.mark.parametrize(
    ("call", "message"),
    [
        (
            lambda: se3.invert(np.eye(3)),
            "invert needs a 4x4 transform (or a stack of them), got shape (3, 3)",
        ),
        (
            lambda: se3.invert(np.eye(4)[:3]),
            "invert needs a 4x4 transform (or a stack of them), got shape (3, 4)",
        ),
        (lambda: se3.adjoint(np.eye(3)), "adjoint needs a 4x4 transform, got shape (3, 3)"),
        (
            lambda: se3.make_transform(np.eye(4), [0, 0, 1]),
            "make_transform: R must be a 3x3 rotation matrix, got shape (4, 4)",
        ),
        (
            lambda: se3.make_transform(np.eye(3), [0, 1]),
            "make_transform: t must be 3 numbers (x, y, z), got shape (2,)",
        ),
        (
            lambda: se3.compose(np.eye(4), np.eye(3)),
            "compose: transform 1 must be 4x4, got shape (3, 3)",
        ),
    ],
)
def test_se3_of_a_mis_shaped_transform_is_an_input_error(call, message):
    """Each ended in numpy's IndexError ('index 3 is out of bounds'), broadcast or matmul
    error, naming neither the function nor the argument."""
    with pytest.raises(InputError) as exc:
        call()
    assert str(exc.value) == message


def test_se3_of_good_shapes_is_unchanged():
    T = se3.make_transform(Rotation.from_rotvec([0.1, 0.2, 0.3]), [1.0, 2.0, 3.0])
    np.testing.assert_allclose(se3.compose(T, se3.invert(T)), np.eye(4), atol=1e-12)
    assert se3.invert(np.tile(T, (2, 1, 1))).shape == (2, 4, 4)
    assert se3.make_transform(np.eye(3), [[1.0], [2.0], [3.0]])[2, 3] == 3.0
    np.testing.assert_allclose(se3.adjoint(T)[:3, :3], T[:3, :3])


@pytest.mark.parametrize("entry", [0, 4])
@pytest.mark.parametrize("value", [np.nan, np.inf])
def test_se3_exp_of_a_non_finite_twist_is_an_input_error(entry, value):
    """exp of a NaN twist returned a transform of NaN (inf in omega: 'math domain error')."""
    xi = np.zeros(6)
    xi[entry] = value
    with pytest.raises(InputError, match=r"^exp: the twist has non-finite entries \(NaN or inf\)"):
        se3.exp(xi)


@pytest.mark.parametrize(("row", "column"), [(0, 0), (2, 1), (1, 3)])
@pytest.mark.parametrize("value", [np.nan, np.inf])
def test_se3_log_of_a_non_finite_transform_is_an_input_error(row, column, value):
    """log of a NaN transform returned a NaN twist; an inf on the diagonal the zero twist."""
    T = np.eye(4)
    T[row, column] = value
    with pytest.raises(InputError) as exc:
        se3.log(T)
    assert str(exc.value) == "log: the transform has non-finite entries (NaN or inf)"


def test_se3_exp_and_log_of_finite_input_are_unchanged():
    xi = np.array([0.1, -0.2, 0.3, 1.0, 2.0, -3.0])
    np.testing.assert_allclose(se3.log(se3.exp(xi)), xi, atol=1e-12)
    assert se3.exp([0, 0, 0, 1e200, 0, 0])[0, 3] == 1e200


# -- adaptive_scale: NaN residuals ----------------------------------------------------------------


def test_adaptive_scale_of_non_finite_residuals_is_an_input_error():
    """NaN gave σ = NaN, and robust weights of NaN; an inf among them a σ without a word."""
    for r in ([0.001, np.nan, 0.002], [0.001, np.inf, 0.002, 0.001]):
        with pytest.raises(InputError) as exc:
            adaptive_scale(r)
        assert (
            str(exc.value) == "adaptive_scale: the residuals have non-finite entries (NaN or inf)"
        )
        with pytest.raises(InputError, match=r"^robust weights: the residuals have non-finite"):
            robust_weights(np.array(r), "huber")


def test_adaptive_scale_of_no_residuals_is_the_documented_zero():
    """No residuals: σ 0, an exact fit, and unit weights downstream (a documented fallback)."""
    assert adaptive_scale([]) == 0.0
    w = robust_weights(np.zeros(0), "cauchy")
    assert (w.scale, len(w.weights)) == (0.0, 0)


# -- read_cloud: a file with NaN normals ----------------------------------------------------------


def _pcd_with_normals(path, normals: np.ndarray) -> None:
    """An ASCII PCD of 200 plate points with the given normals (as PCL writes PointNormal)."""
    points = _plane(len(normals))
    header = (
        "VERSION 0.7\nFIELDS x y z normal_x normal_y normal_z\nSIZE 4 4 4 4 4 4\n"
        f"TYPE F F F F F F\nCOUNT 1 1 1 1 1 1\nWIDTH {len(points)}\nHEIGHT 1\n"
        f"VIEWPOINT 0 0 0 1 0 0 0\nPOINTS {len(points)}\nDATA ascii\n"
    )
    rows = "".join(" ".join(f"{v:.9g}" for v in row) + "\n" for row in np.c_[points, normals])
    path.write_text(header + rows)


@pytest.mark.parametrize("unfilled", [[3], [3, 17, 150], list(range(200))])
def test_nan_normals_in_a_file_are_left_out_not_their_points(tmp_path, unfilled):
    """PCL's normal estimation leaves NaN where a point has too few neighbours: those points
    were dropped without a word, and a file of NaN normals only was refused ('no row with
    finite points and normals'), though every point was good."""
    path = tmp_path / "scan.pcd"
    normals = np.tile([0.0, 0.0, -1.0], (200, 1))
    normals[unfilled] = np.nan
    _pcd_with_normals(path, normals)
    with pytest.warns(SpaceposeWarning) as caught:
        cloud = read_cloud(path)
    assert [str(w.message) for w in caught] == [
        f"{path}: {len(unfilled)} of 200 normals are NaN or inf at finite points (first at "
        f"point {unfilled[0]}), which would drop those points: the file's normals are left out "
        "and estimated"
    ]
    assert (len(cloud), cloud.n_dropped, cloud.has_normals) == (200, 0, False)


def test_a_nan_normal_with_its_nan_point_is_dropped_as_before(tmp_path):
    import warnings

    path = tmp_path / "scan.npy"
    rows = np.c_[_plane(10), np.tile([0.0, 0.0, -1.0], (10, 1))]
    rows[4] = np.nan
    np.save(path, rows)
    with warnings.catch_warnings():
        warnings.simplefilter("error", SpaceposeWarning)
        cloud = read_cloud(path)
    assert (len(cloud), cloud.n_dropped, cloud.has_normals) == (9, 1, True)


# -- principal_axes: NaN times or attitudes, matrices that are no rotation -------------------------


def _spin(n: int = 30) -> tuple[np.ndarray, np.ndarray]:
    """``n`` times 1 s apart and the attitudes of a body turning about a fixed axis."""
    t = np.arange(float(n))
    return t, Rotation.from_rotvec(np.outer(t, [0.01, 0.02, 0.03])).as_matrix()


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ("nan_time", "principal_axes: the times t must be finite and increasing"),
        ("times_2d", "principal_axes: t must be (N,) times, got shape (30, 3)"),
        ("nan_attitude", "principal_axes: R_I_F[3] is not a rotation (finite, orthonormal, "
         "det +1); 1 of 30 attitudes are not"),
        ("zero_attitude", "principal_axes: R_I_F[3] is not a rotation (finite, orthonormal, "
         "det +1); 1 of 30 attitudes are not"),
        ("scaled", "principal_axes: R_I_F[0] is not a rotation (finite, orthonormal, det +1); "
         "30 of 30 attitudes are not"),
        ("nan_baseline", "principal_axes: baseline must be a whole number of frames, got nan"),
    ],
)  # fmt: skip
def test_principal_axes_of_bad_attitudes_is_an_input_error(change, message):
    """NaN times or attitudes ended in numpy's LinAlgError ('SVD did not converge'), a zero
    matrix in scipy's 'Non-positive determinant', (N, 3) times in a broadcast error and a NaN
    baseline in 'cannot convert float NaN to integer'; attitudes scaled by 2 were read as
    their rotations without a word."""
    t, R = _spin()
    baseline = 5
    if change == "nan_time":
        t[5] = np.nan
    elif change == "times_2d":
        t = np.c_[t, t, t]
    elif change == "nan_attitude":
        R[3] = np.nan
    elif change == "zero_attitude":
        R[3] = 0.0
    elif change == "scaled":
        R = 2.0 * R
    else:
        baseline = float("nan")
    with pytest.raises(InputError) as exc:
        principal_axes(t, R, baseline)
    assert str(exc.value) == message


def test_principal_axes_of_good_attitudes_are_unchanged():
    t, R = _spin()
    R[4] = R[4] @ Rotation.from_rotvec([1e-7, 0.0, 0.0]).as_matrix() * (1.0 + 1e-7)
    assert np.isfinite(principal_axes(t, R).moments).all()


# -- scale: counts of points that are no count ------------------------------------------------


@pytest.mark.parametrize("count", [0, -5, 1.5, float("nan"), "many"])
def test_derive_scale_of_no_target_count_is_an_input_error(count):
    """target_points 0 ended in ZeroDivisionError, -5 in 'math domain error', and NaN gave the
    spacing as the voxel without a word."""
    with pytest.raises(InputError) as exc:
        derive_scale(_plane(), count)
    assert str(exc.value) == f"target_points must be a whole number >= 1, got {count!r}"


@pytest.mark.parametrize("samples", [0, -1, 1.5, float("nan")])
@pytest.mark.parametrize("measure", [point_spacing, range_noise])
def test_spacing_and_noise_of_no_sample_count_are_an_input_error(measure, samples):
    """-1 ended in numpy's 'negative dimensions are not allowed', 1.5 in a TypeError, NaN was
    ignored, and range_noise of 0 samples was 0 m without a word."""
    with pytest.raises(InputError) as exc:
        measure(_plane(3000), samples)
    assert str(exc.value) == f"samples must be a whole number >= 1, got {samples!r}"


def test_scale_takes_whole_counts_given_as_floats():
    points = _plane(3000)
    assert point_spacing(points, 2000.0) == point_spacing(points)
    assert derive_scale(points, 1000.0) == derive_scale(points, 1000)


# -- depth: a stride or an image size that is no whole number ----------------------------------


_CAMERA = DepthCamera(fx=60, fy=60, cx=40, cy=30, depth_scale=0.001)


@pytest.mark.parametrize("stride", [0, 1.5, float("nan")])
def test_depth_to_cloud_of_no_whole_stride_is_an_input_error(stride):
    """A stride of 1.5 or NaN ended in a TypeError ('slice indices must be integers')."""
    with pytest.raises(InputError) as exc:
        depth_to_cloud(np.full((60, 80), 1000, np.uint16), _CAMERA, stride, source="d.png")
    assert str(exc.value) == f"d.png: stride must be a whole number >= 1, got {stride!r}"


@pytest.mark.parametrize(("height", "width"), [(-1, 80), (60.5, 80), (60, 0)])
def test_render_depth_of_no_image_size_is_an_input_error(height, width):
    """-1 ended in numpy's 'negative dimensions', 60.5 in a TypeError, 0 gave an empty image."""
    name, value = ("height", height) if height != 60 else ("width", width)
    with pytest.raises(InputError) as exc:
        render_depth(_plane(), _CAMERA, height, width)
    assert str(exc.value) == f"{name} must be a whole number >= 1, got {value!r}"


def test_depth_takes_whole_sizes_given_as_floats():
    image = render_depth(_plane(), _CAMERA, 60.0, 80)
    assert image.shape == (60, 80) and image.max() > 0
    assert len(depth_to_cloud(np.full((60, 80), 1000, np.uint16), _CAMERA, 2.0)) == 30 * 40


# -- crlb: normals that are not unit vectors -----------------------------------------------------


@pytest.mark.parametrize(("length", "shown"), [(2.0, "2"), (0.0, "0"), (0.5, "0.5")])
def test_crlb_of_non_unit_normals_is_an_input_error(length, shown):
    """A normal of length 2 counted its point four times in the Fisher information, one of
    length 0 not at all: the bound came out wrong without a word."""
    normals = np.tile([0.0, 0.0, -1.0], (400, 1))
    normals[[7, 9]] *= length
    with pytest.raises(InputError) as exc:
        crlb(_plane(), normals, 0.001)
    assert str(exc.value) == (
        f"normals must be unit vectors: 2 of 400 are not (first at row 7, length {shown})"
    )


def test_crlb_of_unit_normals_is_unchanged():
    normals = np.tile([0.0, 0.0, -1.0], (400, 1)) * (1.0 + 1e-6)
    bound = crlb(_plane(), normals, 0.001)
    assert bound.rank == 3 and bound.degenerate


# -- simulate --model: a mesh with a NaN vertex --------------------------------------------------


_BOX = (
    "".join(f"v {x} {y} {z}\n" for x in (-0.5, 0.5) for y in (-0.5, 0.5) for z in (-0.5, 0.5))
    + "f 1 2 4\nf 1 4 3\nf 5 7 8\nf 5 8 6\nf 1 5 6\nf 1 6 2\nf 3 4 8\nf 3 8 7\nf 1 3 7\n"
    + ("f 1 7 5\nf 2 6 8\nf 2 8 4\n")
)


def test_a_mesh_with_a_nan_vertex_is_refused(tmp_path, capsys):
    """trimesh's processing dropped the triangles on a NaN vertex without a word: a box with
    one such corner was simulated with a hole (6 of its 12 triangles left), and a one-triangle
    model was refused as 'the file holds no triangles'."""
    from spacepose.cli import main
    from spacepose.core.sim.mesh_files import load_mesh

    good = tmp_path / "box.obj"
    good.write_text(_BOX)
    assert len(load_mesh(good).mesh.faces) == 12
    bad = tmp_path / "corrupt.obj"
    bad.write_text(_BOX.replace("v -0.5 -0.5 -0.5", "v nan -0.5 -0.5"))
    message = (
        f"{bad}: 6 of 12 triangles have a corner of NaN or inf coordinates, and would be left out"
    )
    with pytest.raises(FileFormatError) as exc:
        load_mesh(bad)
    assert str(exc.value) == message
    out = tmp_path / "run"
    argv = ["simulate", "lab", "--frames", "1", "--model", str(bad), "--out", str(out)]
    assert main(argv) == 1
    assert capsys.readouterr().err.strip() == f"error: {message}"
