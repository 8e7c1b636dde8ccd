"""Point cloud files: round trips, peers (Open3D) and every bad-input path."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest

from spacepose.core.cloud import PointCloud, check_scale
from spacepose.errors import FileFormatError, InputError, SpaceposeWarning
from spacepose.tools.cloud_io import read_cloud, write_cloud

EXTENSIONS = [".ply", ".pcd", ".xyz", ".txt", ".csv", ".npy", ".npz"]


@pytest.fixture
def cloud(rng: np.random.Generator) -> PointCloud:
    points = rng.normal(scale=2.0, size=(200, 3))
    normals = rng.normal(size=(200, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    return PointCloud(points, normals)


@pytest.mark.parametrize("ext", EXTENSIONS)
@pytest.mark.parametrize("binary", [True, False])
@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_round_trip_points_and_normals(
    tmp_path: Path, cloud: PointCloud, ext: str, binary: bool, dtype: str
) -> None:
    path = write_cloud(tmp_path / f"c{ext}", cloud, binary=binary, dtype=dtype)
    back = read_cloud(path)
    # Exact at the stored precision: float32 text prints 9 digits, which round-trips float32.
    np.testing.assert_array_equal(back.points.astype(dtype), cloud.points.astype(dtype))
    assert back.normals is not None
    np.testing.assert_array_equal(back.normals.astype(dtype), cloud.normals.astype(dtype))
    assert back.source == str(path)
    if dtype == "float64":
        np.testing.assert_array_equal(back.points, cloud.points)


@pytest.mark.parametrize("ext", EXTENSIONS)
def test_round_trip_points_only_from_array(
    tmp_path: Path, rng: np.random.Generator, ext: str
) -> None:
    points = rng.uniform(-5, 5, size=(31, 3))
    back = read_cloud(write_cloud(tmp_path / f"p{ext}", points, dtype="float64"))
    np.testing.assert_array_equal(back.points, points)
    assert back.normals is None


@pytest.mark.parametrize("ext", [".ply", ".pcd"])
def test_binary_and_ascii_encodings_differ_and_say_so(
    tmp_path: Path, cloud: PointCloud, ext: str
) -> None:
    binary = write_cloud(tmp_path / f"b{ext}", cloud, binary=True).read_bytes()
    ascii_ = write_cloud(tmp_path / f"a{ext}", cloud, binary=False).read_bytes()
    if ext == ".ply":
        assert b"format binary_little_endian 1.0" in binary
        assert b"format ascii 1.0" in ascii_
    else:
        assert b"\nDATA binary\n" in binary
        assert b"\nDATA ascii\n" in ascii_
    ascii_.decode("ascii")  # the ASCII encoding really is text


@pytest.mark.parametrize("ext", EXTENSIONS)
def test_writing_is_deterministic(tmp_path: Path, cloud: PointCloud, ext: str) -> None:
    a = write_cloud(tmp_path / f"a{ext}", cloud).read_bytes()
    b = write_cloud(
        tmp_path / f"b{ext}", PointCloud(cloud.points.copy(), cloud.normals)
    ).read_bytes()
    assert a == b


def test_text_with_header_comments_and_commas(tmp_path: Path) -> None:
    csv = tmp_path / "h.csv"
    csv.write_text("x,y,z\n1,2,3\n4.5, -6, 7e-3\n")
    np.testing.assert_array_equal(read_cloud(csv).points, [[1, 2, 3], [4.5, -6, 7e-3]])
    xyz = tmp_path / "c.xyz"
    xyz.write_text("# scanner output\n\n1 2 3 0 0 1\n4 5 6 1 0 0\n")
    back = read_cloud(xyz)
    np.testing.assert_array_equal(back.points, [[1, 2, 3], [4, 5, 6]])
    np.testing.assert_array_equal(back.normals, [[0, 0, 1], [1, 0, 0]])


def test_nan_rows_are_dropped_and_counted(tmp_path: Path) -> None:
    pts = np.array([[0.0, 0, 1], [np.nan, 0, 1], [1, 2, 3]])
    np.save(tmp_path / "n.npy", pts)
    back = read_cloud(tmp_path / "n.npy")
    np.testing.assert_array_equal(back.points, pts[[0, 2]])
    assert back.n_dropped == 1


def test_pcd_with_extra_fields_and_padding(tmp_path: Path) -> None:
    # Layout as PCL writes it for PointXYZI with a padding field and a 2-wide field.
    path = tmp_path / "extra.pcd"
    rec = np.zeros(
        3,
        dtype=[
            ("x", "<f4"),
            ("y", "<f4"),
            ("z", "<f4"),
            ("_", "u1", (4,)),
            ("intensity", "<f4"),
            ("h", "<f8", (2,)),
        ],
    )
    rec["x"], rec["y"], rec["z"], rec["intensity"] = [1, 2, 3], [4, 5, 6], [7, 8, 9], 0.5
    header = (
        "VERSION 0.7\nFIELDS x y z _ intensity h\nSIZE 4 4 4 1 4 8\nTYPE F F F U F F\n"
        "COUNT 1 1 1 4 1 2\nWIDTH 3\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS 3\nDATA binary\n"
    )
    path.write_bytes(header.encode() + rec.tobytes())
    np.testing.assert_array_equal(read_cloud(path).points, [[1, 4, 7], [2, 5, 8], [3, 6, 9]])


# ---------------------------------------------------------------------------- peers


@pytest.mark.peers
@pytest.mark.parametrize("ext", [".ply", ".pcd"])
@pytest.mark.parametrize("ascii_", [False, True])
def test_reads_open3d_files(tmp_path: Path, cloud: PointCloud, ext: str, ascii_: bool) -> None:
    o3d = pytest.importorskip("open3d")
    pc = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(cloud.points.copy()))
    pc.normals = o3d.utility.Vector3dVector(cloud.normals.copy())
    path = tmp_path / f"o3d{ext}"
    assert o3d.io.write_point_cloud(str(path), pc, write_ascii=ascii_)
    back = read_cloud(path)
    # Open3D stores PLY as float64 (ASCII: 6 decimals) and PCD as float32.
    atol = {(".ply", False): 0.0, (".ply", True): 1e-5, (".pcd", False): 5e-7}.get(
        (ext, ascii_), 1e-6
    )
    np.testing.assert_allclose(back.points, cloud.points, rtol=0, atol=atol)
    np.testing.assert_allclose(back.normals, cloud.normals, rtol=0, atol=atol)


@pytest.mark.peers
@pytest.mark.parametrize("ext", [".ply", ".pcd"])
@pytest.mark.parametrize("dtype", ["float32", "float64"])
def test_open3d_reads_our_binary_files(
    tmp_path: Path, cloud: PointCloud, ext: str, dtype: str
) -> None:
    o3d = pytest.importorskip("open3d")
    path = write_cloud(tmp_path / f"ours{ext}", cloud, binary=True, dtype=dtype)
    # The tensor reader: Open3D 0.20's legacy PCD reader misreads binary 8-byte floats.
    pc = o3d.t.io.read_point_cloud(str(path))
    np.testing.assert_array_equal(pc.point.positions.numpy(), cloud.points.astype(dtype))
    np.testing.assert_array_equal(pc.point.normals.numpy(), cloud.normals.astype(dtype))
    if ext == ".ply" or dtype == "float32":
        legacy = o3d.io.read_point_cloud(str(path))
        np.testing.assert_array_equal(np.asarray(legacy.points), cloud.points.astype(dtype))


# ---------------------------------------------------------------------------- bad input


def _raises_naming(path: Path, match: str, exc: type[Exception] = FileFormatError):
    """Context: the call raises ``exc`` whose message names ``path`` and matches ``match``."""
    return pytest.raises(exc, match=rf"^{_re(str(path))}: .*{match}")


def _re(text: str) -> str:
    import re

    return re.escape(text)


def test_unknown_extension(tmp_path: Path, cloud: PointCloud) -> None:
    path = tmp_path / "cloud.las"
    path.write_text("1 2 3\n")
    with _raises_naming(path, "unknown point cloud extension '.las'"):
        read_cloud(path)
    with _raises_naming(path, "unknown point cloud extension"):
        write_cloud(path, cloud)


@pytest.mark.parametrize("ext", EXTENSIONS)
def test_missing_file(tmp_path: Path, ext: str) -> None:
    path = tmp_path / f"absent{ext}"
    with _raises_naming(path, "no such file"):
        read_cloud(path)


@pytest.mark.parametrize("binary", [True, False])
def test_truncated_ply(tmp_path: Path, cloud: PointCloud, binary: bool) -> None:
    path = write_cloud(tmp_path / "t.ply", cloud, binary=binary)
    data = path.read_bytes()
    # ASCII: drop the last whole line (a number cut short would still parse as a number).
    cut = data[: data.rstrip(b"\n").rfind(b"\n") + 1] if not binary else data[:-20]
    path.write_bytes(cut)
    with _raises_naming(path, "truncated"):
        read_cloud(path)


@pytest.mark.parametrize("binary", [True, False])
def test_truncated_pcd(tmp_path: Path, cloud: PointCloud, binary: bool) -> None:
    path = write_cloud(tmp_path / "t.pcd", cloud, binary=binary)
    data = path.read_bytes()
    # Cut whole ASCII lines so the remaining numbers are still valid.
    cut = data[: data.rstrip(b"\n").rfind(b"\n") + 1] if not binary else data[:-5]
    path.write_bytes(cut)
    with _raises_naming(path, "truncated"):
        read_cloud(path)


def test_truncated_npy_and_npz(tmp_path: Path, cloud: PointCloud) -> None:
    for ext in (".npy", ".npz"):
        path = write_cloud(tmp_path / f"t{ext}", cloud)
        path.write_bytes(path.read_bytes()[:-30])
        with _raises_naming(path, "truncated"):
            read_cloud(path)


def test_pcd_truncated_header(tmp_path: Path) -> None:
    path = tmp_path / "h.pcd"
    path.write_text("VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\n")
    with _raises_naming(path, "no DATA line"):
        read_cloud(path)


def test_wrong_ply_header(tmp_path: Path) -> None:
    path = tmp_path / "w.ply"
    path.write_text("plx\nformat ascii 1.0\nelement vertex 1\nproperty float x\nend_header\n1\n")
    with _raises_naming(path, "expected 'ply'"):
        read_cloud(path)


def test_wrong_pcd_header(tmp_path: Path) -> None:
    path = tmp_path / "w.pcd"
    path.write_text("VERSION 0.7\nSIZE 4 4 4\nTYPE F F F\nPOINTS 1\nDATA ascii\n1 2 3\n")
    with _raises_naming(path, "lacks FIELDS"):
        read_cloud(path)
    path.write_text("FIELDS x y z\nSIZE 4 4 4\nTYPE F F Q\nPOINTS 1\nDATA ascii\n1 2 3\n")
    with _raises_naming(path, "unknown TYPE Q"):
        read_cloud(path)


def test_pcd_binary_compressed_is_refused(tmp_path: Path) -> None:
    path = tmp_path / "c.pcd"
    path.write_bytes(b"FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nPOINTS 1\nDATA binary_compressed\n\0")
    with _raises_naming(path, "binary_compressed .*not supported"):
        read_cloud(path)


def _ascii_ply(path: Path, count: int, names: str) -> Path:
    """An ASCII PLY of one row ``1 2 3`` whose header counts ``count`` vertices of float
    properties ``names`` (space-separated)."""
    properties = "".join(f"property float {n}\n" for n in names.split())
    path.write_text(
        f"ply\nformat ascii 1.0\nelement vertex {count}\n{properties}end_header\n1 2 3\n"
    )
    return path


def test_a_negative_ply_count_is_named(tmp_path: Path) -> None:
    # It read as "bytes of data beyond its header's counts".
    ply = _ascii_ply(tmp_path / "neg.ply", -5, "x y z")
    with _raises_naming(ply, "the header counts -5 'vertex' rows: a count is >= 0"):
        read_cloud(ply)


def test_no_xyz_properties(tmp_path: Path) -> None:
    ply = _ascii_ply(tmp_path / "abc.ply", 1, "a b c")
    with _raises_naming(ply, "no x/y/z properties"):
        read_cloud(ply)
    pcd = tmp_path / "abc.pcd"
    pcd.write_text("FIELDS a b c\nSIZE 4 4 4\nTYPE F F F\nPOINTS 1\nDATA ascii\n1 2 3\n")
    with _raises_naming(pcd, r"no x, y and z fields of COUNT 1 \(FIELDS: a \(COUNT 1\)"):
        read_cloud(pcd)
    # One field of three values is named as such (it read "found []").
    packed = tmp_path / "packed.pcd"
    packed.write_text("FIELDS xyz\nSIZE 4\nTYPE F\nCOUNT 3\nPOINTS 1\nDATA ascii\n1 2 3\n")
    with _raises_naming(packed, r"FIELDS: xyz \(COUNT 3\)"):
        read_cloud(packed)
    npz = tmp_path / "abc.npz"
    np.savez(npz, xyz=np.zeros((2, 3)))
    with _raises_naming(npz, "no 'points' array"):
        read_cloud(npz)


def test_nan_only_cloud(tmp_path: Path) -> None:
    path = tmp_path / "nan.ply"
    path.write_text(
        "ply\nformat ascii 1.0\nelement vertex 2\nproperty float x\nproperty float y\n"
        "property float z\nend_header\nnan nan nan\nnan 1 2\n"
    )
    with _raises_naming(path, "no finite point", InputError):
        read_cloud(path)


def test_bad_text_rows_name_the_line(tmp_path: Path) -> None:
    path = tmp_path / "bad.xyz"
    path.write_text("1 2 3\n4 5 six\n")
    with _raises_naming(path, "line 2: not a number"):
        read_cloud(path)
    path.write_text("1 2 3\n4 5 6 7\n")
    with _raises_naming(path, "line 2: 4 columns where earlier rows have 3"):
        read_cloud(path)
    path.write_text("1 2 3 4\n5 6 7 8\n")
    with _raises_naming(path, "expected 3 .* or 6 .* columns, got 4"):
        read_cloud(path)
    path.write_text("# only a comment\n")
    with _raises_naming(path, "no point rows"):
        read_cloud(path)


@pytest.mark.parametrize(
    ("name", "rows", "hint"),
    [
        ("quoted.csv", ['"0.123","0.4","1.2"', '"-0.19339","0.5","1.0"'], "quoted numbers?"),
        ("hex.xyz", ["0x1.0p-1 0x1.8p+0 0x1.2p+0"] * 2, "hexadecimal floats?"),  # float.hex()
    ],
)
def test_a_first_line_neither_numbers_nor_naming_xyz_is_named_as_line_1(
    tmp_path: Path, name: str, rows: list[str], hint: str
) -> None:
    """Every value quoted, or written by float.hex(): the first line was taken for a header
    naming no x/y/z column and skipped, and the error named line 2."""
    path = tmp_path / name
    path.write_text("\n".join(rows) + "\n")
    with pytest.raises(FileFormatError) as info:
        read_cloud(path)
    head = rows[0].replace(",", " ").split()
    assert str(info.value).startswith(
        f"{path}: line 1: not numbers, and as a header it does not name x, y and z columns: "
        f"{head} ({hint} write them"
    )
    # Headers naming their columns still read.
    for header in ("x y z", "//X,Y,Z", "x,y,z,intensity", '"x","y","z"'):
        sep = "," if "," in header else " "
        path.write_text(f"{header}\n" + sep.join(["1"] * len(header.split(sep))) + "\n")
        np.testing.assert_array_equal(read_cloud(path).points, [[1.0, 1.0, 1.0]])


def test_bad_npy_shape(tmp_path: Path) -> None:
    path = tmp_path / "s.npy"
    np.save(path, np.zeros((5, 4)))
    with _raises_naming(path, r"\(N, 3\) or \(N, 6\)"):
        read_cloud(path)


def test_bad_write_arguments(tmp_path: Path, cloud: PointCloud) -> None:
    path = tmp_path / "x.ply"
    # None is the default: float32 where it holds the points, else float64.
    for bad in ("float16", np.float16, np.dtype("int32"), "f8", object(), ["float32"]):
        with _raises_naming(path, "dtype must be", InputError):
            write_cloud(path, cloud, dtype=bad)
    with _raises_naming(path, r"must be \(N, 3\) or \(N, 6\)", InputError):
        write_cloud(path, np.zeros((3, 4)))
    assert not path.exists()


# --------------------------------------------------------------------------------------------
# Headers that disagree with themselves or with the body, odd encodings, implausible values

_PCD_HEADER = "FIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH {w}\nHEIGHT 1\nPOINTS {p}\n"
_FIVE_ROWS = "".join(f"{i} {i + 1} {i + 2}\n" for i in range(5))


@pytest.mark.parametrize(
    ("width", "points", "match"),
    [
        (5, -5, "POINTS is negative: -5"),
        (-5, 5, "WIDTH is negative"),
        (4, 5, "POINTS 5 disagrees with WIDTH 4 x HEIGHT 1"),
        (3, 3, "inconsistent ASCII PCD: POINTS 3 of 3 values need 9 numbers, the body has 15"),
        (7, 7, "truncated ASCII PCD: POINTS 7 of 3 values need 21 numbers, the body has 15"),
    ],
)
def test_pcd_counts_must_agree_with_each_other_and_the_body(
    tmp_path: Path, width: int, points: int, match: str
) -> None:
    path = tmp_path / "n.pcd"
    path.write_text(_PCD_HEADER.format(w=width, p=points) + "DATA ascii\n" + _FIVE_ROWS)
    with _raises_naming(path, match):
        read_cloud(path)


def test_binary_pcd_with_more_bytes_than_points(tmp_path: Path) -> None:
    path = tmp_path / "b.pcd"
    body = np.arange(15, dtype="<f4").tobytes()  # five points
    path.write_bytes((_PCD_HEADER.format(w=4, p=4) + "DATA binary\n").encode() + body)
    with _raises_naming(path, "POINTS 4 of 12 bytes need 48 bytes of data, file has 60"):
        read_cloud(path)
    path.write_bytes((_PCD_HEADER.format(w=5, p=5) + "DATA binary\n").encode() + body)
    np.testing.assert_array_equal(read_cloud(path).points, np.arange(15.0).reshape(5, 3))


@pytest.mark.parametrize("empty", ["FIELDS", "SIZE", "TYPE", "COUNT"])
def test_pcd_with_an_empty_header_list(tmp_path: Path, empty: str) -> None:
    lines = {"FIELDS": "x y z", "SIZE": "4 4 4", "TYPE": "F F F", "COUNT": "1 1 1"}
    lines[empty] = ""
    header = "".join(f"{k} {v}\n" for k, v in lines.items())
    path = tmp_path / "e.pcd"
    path.write_text(header + "WIDTH 5\nHEIGHT 1\nPOINTS 5\nDATA ascii\n" + _FIVE_ROWS)
    with _raises_naming(path, f"PCD header {empty} is empty"):
        read_cloud(path)


@pytest.mark.parametrize("ext", [".xyz", ".csv"])
def test_text_with_a_utf8_byte_order_mark_keeps_its_first_row(tmp_path: Path, ext: str) -> None:
    path = tmp_path / f"bom{ext}"
    sep = "," if ext == ".csv" else " "
    rows = [[1.5, 2.0, 3.0], [4.0, 5.0, 6.0]]
    path.write_text("\n".join(sep.join(map(str, r)) for r in rows) + "\n", encoding="utf-8-sig")
    assert path.read_bytes()[:3] == b"\xef\xbb\xbf"
    np.testing.assert_array_equal(read_cloud(path).points, rows)
    path.write_text("x,y,z\n1,2,3\n", encoding="utf-8-sig")  # a BOM before a header line
    np.testing.assert_array_equal(read_cloud(path).points, [[1, 2, 3]])


def test_ply_with_list_properties_for_xyz(tmp_path: Path) -> None:
    path = tmp_path / "list.ply"
    path.write_text(
        "ply\nformat ascii 1.0\nelement vertex 2\nproperty list uchar float x\n"
        "property list uchar float y\nproperty list uchar float z\nend_header\n"
        "2 1 1 1 2 1 3\n2 4 4 1 5 1 6\n"
    )
    with _raises_naming(path, "PLY vertex property 'x' is not one number per point"):
        read_cloud(path)


def test_coordinates_whose_squares_overflow_are_refused(tmp_path: Path) -> None:
    path = tmp_path / "huge.npy"
    np.save(path, np.full((10, 3), 1e300) * np.arange(1, 11)[:, None])
    with _raises_naming(path, "reach .coordinate. 1e\\+301.*squares overflow", InputError):
        read_cloud(path)


def test_millimetres_are_warned_about_naming_the_file(tmp_path: Path) -> None:
    from spacepose.core.sim import scenario_config, simulate

    frame_m = simulate(scenario_config("lab", frames=1)).frame(0).cloud
    path = write_cloud(tmp_path / "frame_mm.ply", frame_m.points * 1e3)
    with pytest.warns(
        SpaceposeWarning, match=rf"^{_re(str(path))}: coordinates look like millimetres"
    ):
        cloud = read_cloud(path)
    np.testing.assert_allclose(cloud.points, frame_m.points * 1e3, rtol=1e-6)
    # Read with scale=1e-3 it is the metre frame again (float32 on file), and nothing is said.
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        rescaled = read_cloud(path, scale=1e-3)
        # Its points: write_cloud warns that a simulated frame's per-point sigma is not kept.
        read_cloud(write_cloud(tmp_path / "frame_m.ply", frame_m.points))
    np.testing.assert_allclose(rescaled.points, frame_m.points, atol=1e-6)
    with _raises_naming(path, "scale must be a positive number", InputError):
        read_cloud(path, scale=0.0)


def test_real_outdoor_lidar_in_metres_is_not_taken_for_millimetres() -> None:
    """The small_gicp pair: 73 and 95 m across, 12 mm median spacing, genuinely metres."""
    data = Path(__file__).resolve().parents[1] / "data" / "real" / "small_gicp"
    for name in ("source.ply", "target.ply"):
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            cloud = read_cloud(data / name)
        check = check_scale(cloud.points)
        assert check.extent > 50.0 and check.spacing < 0.02 and not check.millimetres
        mm = check_scale(cloud.points * 1e3)
        assert mm.millimetres and mm.spacing == pytest.approx(1e3 * check.spacing)


def test_normals_of_zero_length_are_left_out_and_others_made_unit(tmp_path: Path) -> None:
    """A file's normals of zero length have no direction (a point type with normal fields no
    step filled): the file's normals are left out, with a warning naming the file, and its
    points read. Normals of another length (5 here) weighed their points' residuals by it;
    they are read as their directions, with a warning. Unit normals are kept bit for bit."""
    p = np.random.default_rng(0).uniform(0, 1, (100, 3))
    zero = tmp_path / "zero.npy"
    normals = np.tile([0.0, 0.0, 1.0], (100, 1))
    normals[7] = 0.0
    np.save(zero, np.c_[p, normals])
    with pytest.warns(SpaceposeWarning, match=r"zero.npy: 1 normals have zero length .*left out"):
        cloud = read_cloud(zero)
    assert cloud.normals is None
    np.testing.assert_array_equal(cloud.points, p)
    long = tmp_path / "long.xyz"
    long.write_text("".join(f"{x:.6f} {y:.6f} {z:.6f} 0 0 5\n" for x, y, z in p))
    with pytest.warns(SpaceposeWarning, match=r"long.xyz: 100 normals are not of unit length"):
        cloud = read_cloud(long)
    np.testing.assert_array_equal(cloud.normals, np.tile([0.0, 0.0, 1.0], (100, 1)))
    # Of 1e300 they are directions too: their squares overflowed (numpy's bare warning, an inf
    # length, and the normals kept 1e300 long).
    huge = tmp_path / "huge.npy"
    np.save(huge, np.c_[p, np.tile([0.0, 3e300, 4e300], (100, 1))])
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        cloud = read_cloud(huge)
    assert [str(w.message) for w in caught] == [
        f"{huge}: 100 normals are not of unit length (point 0: 5e+300); read as their directions"
    ]
    np.testing.assert_allclose(cloud.normals, np.tile([0.0, 0.6, 0.8], (100, 1)), rtol=1e-15)
    n = np.random.default_rng(1).normal(size=(100, 3))
    n /= np.linalg.norm(n, axis=1)[:, None]
    unit = tmp_path / "unit.npy"
    np.save(unit, np.c_[p, n])
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        np.testing.assert_array_equal(read_cloud(unit).normals, n)


def test_an_ascii_ply_is_read_without_leaving_a_file_open(tmp_path: Path) -> None:
    """plyfile read an ASCII body through a text wrapper left open on the file: a
    ResourceWarning each time one was collected."""
    import gc

    path = tmp_path / "a.ply"
    points = np.random.default_rng(0).uniform(size=(50, 3))
    write_cloud(path, points, binary=False)
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        cloud = read_cloud(path)
        gc.collect()
    assert not [w for w in caught if issubclass(w.category, ResourceWarning)], caught
    np.testing.assert_allclose(cloud.points, points, atol=1e-6)


def test_pcd_count_too_large_and_a_field_named_twice(tmp_path: Path) -> None:
    """A COUNT of 10⁹ raised numpy's ValueError (a dtype larger than a C int) out of the
    reader, and stopped a whole `track` run; a second ``x`` was read in place of the first."""
    header = "VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1000000000\n"
    path = tmp_path / "big.pcd"
    path.write_bytes(f"{header}WIDTH 0\nHEIGHT 1\nPOINTS 0\nDATA binary\n".encode())
    with _raises_naming(path, "a point of 4000000008 bytes"):
        read_cloud(path)
    path.write_bytes(f"{header}WIDTH 1\nHEIGHT 1\nPOINTS 1\nDATA binary\n".encode() + bytes(12))
    with _raises_naming(path, "truncated binary PCD"):
        read_cloud(path)
    path = tmp_path / "dup.pcd"
    path.write_text(
        "FIELDS x y z x\nSIZE 4 4 4 4\nTYPE F F F F\nCOUNT 1 1 1 1\nPOINTS 1\nDATA ascii\n1 2 3 9\n"
    )
    with _raises_naming(path, "names field 'x' twice"):
        read_cloud(path)


def test_a_text_file_with_a_header_and_no_rows_is_one_error_and_no_warning(tmp_path: Path):
    """numpy's loadtxt warned "input contained no data" naming its buffer before the error."""
    path = tmp_path / "h.csv"
    path.write_text("x,y,z\n")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with _raises_naming(path, "no point rows"):
            read_cloud(path)


def test_an_npz_with_other_than_one_normal_a_point_is_refused(tmp_path: Path) -> None:
    """10 normals for 5,000 points went on to a numpy broadcast error and a traceback."""
    p = np.random.default_rng(0).uniform(0, 1, (5000, 3))
    path = tmp_path / "short.npz"
    np.savez(path, points=p, normals=np.tile([0.0, 0.0, 1.0], (10, 1)))
    with pytest.raises(FileFormatError, match=r"short.npz: .npz has 10 normals for 5000 points"):
        read_cloud(path)


def test_a_text_cloud_with_all_normals_zero_warns_once_and_reads_its_points(
    tmp_path: Path,
) -> None:
    """Six columns all zero in the last three: no colours and no directions. The colour test
    took the mean of no direction (numpy's bare "Mean of empty slice" warnings, four lines
    before the file's own)."""
    p = np.random.default_rng(1).uniform(0, 1, (200, 3))
    path = tmp_path / "zero.xyz"
    path.write_text("".join(f"{x:.6f} {y:.6f} {z:.6f} 0 0 0\n" for x, y, z in p))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        cloud = read_cloud(path)
    assert [type(w.message) for w in caught] == [SpaceposeWarning]
    assert "200 normals have zero length" in str(caught[0].message)
    assert cloud.normals is None
    np.testing.assert_allclose(cloud.points, p, atol=1e-6)


def test_a_cloud_narrower_than_any_sensor_resolves_is_warned_about(tmp_path: Path) -> None:
    """70,000 points within 1e-29 m went to `planes` as one plane of 0 x 0 m, without a word;
    a cloud of a few millimetres (a small part seen close) is read silently."""
    p = np.random.default_rng(2).uniform(0, 1, (500, 3))
    tiny = tmp_path / "tiny.npy"
    np.save(tiny, 1e-29 * p)
    with pytest.warns(SpaceposeWarning, match=r"tiny.npy: coordinates span 1.\d+e-29 m, closer"):
        read_cloud(tiny)
    small = tmp_path / "small.npy"
    np.save(small, 3e-3 * p)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert len(read_cloud(small)) == 500


def test_rows_with_an_infinite_coordinate_are_dropped_with_a_warning(tmp_path) -> None:
    """NaN rows are a sensor's "no return" and go unsaid; inf (or 1e400, past float64) is a
    corrupt value, and was dropped unsaid too."""
    path = tmp_path / "scan.xyz"
    path.write_text("0 0 1\n1 0 1\ninf 0 1\n0 1 1\n1e400 1 1\nnan 0 0\n1 1 1.1\n")
    with pytest.warns(SpaceposeWarning, match=r"scan.xyz: 2 of 7 rows with an infinite coordina"):
        cloud = read_cloud(path)
    assert len(cloud) == 4
    path.write_text("0 0 1\n1 0 1\nnan 0 1\n0 1 1\n")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert len(read_cloud(path)) == 3


@pytest.mark.parametrize("dtype", [np.float32, np.dtype("float64"), np.float64])
def test_numpys_own_dtypes_name_the_same_precision(tmp_path: Path, cloud: PointCloud, dtype):
    """``np.float32`` or ``np.dtype("float64")`` were refused ("dtype must be 'float32' or
    'float64', got dtype('float64')"); they write the same bytes as the names."""
    ours = write_cloud(tmp_path / "ours.ply", cloud, dtype=dtype)
    named = write_cloud(tmp_path / "named.ply", cloud, dtype=np.dtype(dtype).name)
    assert ours.read_bytes() == named.read_bytes()
