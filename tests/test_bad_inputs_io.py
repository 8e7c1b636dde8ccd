"""Bad files and outputs found by fuzzing the CLI: each ends in one line naming the file, or is
read as its header says, and no frame of a sequence silently disappears."""

from __future__ import annotations

import csv
import re
import warnings
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from spacepose.cli import main
from spacepose.core.depth import DepthCamera
from spacepose.core.sim.scenarios import LabConfig, simulate_lab
from spacepose.errors import (
    DegenerateGeometryError,
    FileFormatError,
    InputError,
    SpaceposeWarning,
)
from spacepose.tools.cloud_io import read_cloud, write_cloud
from spacepose.tools.depth_io import read_depth_cloud
from spacepose.tools.outputs import check_writable
from spacepose.tools.register_io import register_files
from spacepose.tools.tracking_io import track_folder


@pytest.fixture(scope="module")
def frames(tmp_path_factory) -> Path:
    """Five lab frames f000 … f004.ply."""
    lab = simulate_lab(LabConfig(frames=5, seed=4))
    root = tmp_path_factory.mktemp("five")
    for k in range(5):
        write_cloud(root / f"f{k:03d}.ply", lab.frame(k).cloud)
    return root


def _copy(src: Path, dst: Path) -> Path:
    dst.mkdir()
    for p in src.iterdir():
        (dst / p.name).write_bytes(p.read_bytes())
    return dst


def _one_line(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0, err
    return err


@pytest.mark.parametrize("kind", ["folder", "broken link"])
def test_a_frame_that_is_not_a_file_is_lost_in_its_place(frames, tmp_path, kind):
    seq = _copy(frames, tmp_path / "seq")
    (seq / "f002.ply").unlink()
    if kind == "folder":
        (seq / "f002.ply").mkdir()
    else:
        (seq / "f002.ply").symlink_to(tmp_path / "nowhere.ply")
    summary = track_folder(seq, tmp_path / "e.tum")
    assert summary["frames"] == 5 and summary["lost"] == 1
    with (tmp_path / "e.health.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    # Frame 3 keeps its own timestamp: nothing after the bad frame shifts.
    assert [r["frame"] for r in rows] == ["0", "1", "2", "3", "4"]
    assert rows[2]["status"] == "lost"
    assert "f002.ply" in rows[2]["reasons"]
    assert ("a folder" if kind == "folder" else "a broken link") in rows[2]["reasons"]


def test_every_frame_lost_exits_1_with_the_first_reason(frames, tmp_path, capsys):
    seq = tmp_path / "bad"
    seq.mkdir()
    for k in range(3):
        (seq / f"f{k}.ply").write_bytes(b"")
    assert main(["track", str(seq), "--out", str(tmp_path / "e.tum")]) == 1
    err = capsys.readouterr().err.strip().splitlines()[-1]
    assert "every frame was lost (frame 0:" in err and "f0.ply" in err
    # The rows are still written: nothing is lost.
    assert len((tmp_path / "e.tum").read_text().splitlines()) == 3


def test_text_columns_follow_their_header(tmp_path):
    rng = np.random.default_rng(5)
    xyz = rng.uniform(-1, 1, (50, 3)) + np.array([0.0, 0.0, 3.0])
    normals = rng.normal(size=(50, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    table = np.column_stack([xyz[:, 2], rng.random(50), xyz[:, 1], xyz[:, 0], normals])
    path = tmp_path / "zyx.csv"
    np.savetxt(path, table, delimiter=",", header="z,intensity,y,x,nx,ny,nz", comments="")
    cloud = read_cloud(path)
    np.testing.assert_allclose(cloud.points, xyz, atol=1e-15)
    np.testing.assert_allclose(cloud.normals, normals, atol=1e-12)
    # CloudCompare's "//X,Y,Z" header reads too.
    np.savetxt(path, xyz, delimiter=",", header="//X,Y,Z", comments="")
    np.testing.assert_allclose(read_cloud(path).points, xyz, atol=1e-15)
    np.savetxt(path, xyz, delimiter=",", header="a,b,c", comments="")
    with pytest.raises(FileFormatError, match=r"does not name x, y and z") as info:
        read_cloud(path)
    assert "zyx.csv" in str(info.value)
    np.savetxt(path, xyz, delimiter=",", header="x,y", comments="")
    with pytest.raises(FileFormatError, match=r"names 2 columns .* rows hold 3"):
        read_cloud(path)
    # A first row with a malformed number is a bad row, not a header that fails to name x, y, z.
    for bad in ("0x1", "1.0d0"):
        path.write_text(f"{bad},2,3\n1,2,3\n4,5,6\n")
        with pytest.raises(FileFormatError) as info:
            read_cloud(path)
        assert str(info.value).endswith(f"zyx.csv: line 1: not a number in ['{bad}', '2', '3']")
    # Python's float reads 1_000; the table's parser does not (the error had no line).
    path.write_text("1,2,3\n1_000,2,3\n")
    with pytest.raises(FileFormatError, match=r"zyx\.csv: line 2: not a number in \['1_000'"):
        read_cloud(path)
    # A spreadsheet's trailing comma is an empty field, named with its line.
    path.write_text("1,2,3,\n4,5,6,\n")
    with pytest.raises(FileFormatError, match=r"zyx\.csv: line 1: an empty field between commas"):
        read_cloud(path)
    # Text in another encoding is named as not UTF-8 at its byte (it read "binary content").
    latin = tmp_path / "latin.txt"
    latin.write_bytes("# température\n1 2 3\n".encode("latin-1"))
    with pytest.raises(
        FileFormatError, match=r"latin\.txt: not UTF-8 text \(byte 0xe9 at offset 6\)"
    ):
        read_cloud(latin)


@pytest.mark.parametrize("text", [False, True])
def test_a_ply_header_promising_more_rows_than_its_bytes_is_refused(tmp_path, text):
    fmt = "ascii" if text else "binary_little_endian"
    header = (
        f"ply\nformat {fmt} 1.0\nelement vertex 999999999999\n"
        "property float x\nproperty float y\nproperty float z\nend_header\n"
    )
    path = tmp_path / "huge.ply"
    path.write_bytes(header.encode() + (b"1 2 3\n" if text else np.zeros(30, "<f4").tobytes()))
    with pytest.raises(FileFormatError, match=r"promises 999,999,999,999 'vertex' rows") as info:
        read_cloud(path)
    assert "huge.ply" in str(info.value) and "\n" not in str(info.value)


@pytest.mark.parametrize("binary", [True, False])
def test_a_ply_holding_rows_beyond_its_header_count_is_refused(tmp_path, binary):
    """A header counting 400 of 500 rows would drop the last 100 without a word; a trailing
    newline is no row."""
    path = write_cloud(
        tmp_path / "c.ply", np.random.default_rng(3).normal(size=(500, 3)), binary=binary
    )
    raw = path.read_bytes()
    path.write_bytes(raw + b"\n")
    assert len(read_cloud(path)) == 500
    path.write_bytes(raw.replace(b"element vertex 500", b"element vertex 400"))
    with pytest.raises(FileFormatError, match=r"c\.ply: .*beyond its header|c\.ply: .*counts 400"):
        read_cloud(path)


def test_foreign_bytes_and_folders_are_named_as_such(tmp_path):
    rng = np.random.default_rng(6)
    for name in ("r.npy", "r.npz", "r.ply"):
        (tmp_path / name).write_bytes(b"\xc0" + rng.bytes(200))
    with pytest.raises(FileFormatError, match=r"r\.npy: not a \.npy file"):
        read_cloud(tmp_path / "r.npy")
    with pytest.raises(FileFormatError, match=r"r\.npz: not a \.npz archive"):
        read_cloud(tmp_path / "r.npz")
    with pytest.raises(FileFormatError, match=r"r\.ply: not a PLY file"):
        read_cloud(tmp_path / "r.ply")
    np.save(tmp_path / "obj.npy", np.array([{"a": 1}, None], dtype=object), allow_pickle=True)
    with pytest.raises(FileFormatError, match="holds Python objects") as info:
        read_cloud(tmp_path / "obj.npy")
    assert "allow_pickle" not in str(info.value)
    (tmp_path / "d.ply").mkdir()
    with pytest.raises(FileFormatError, match=r"d\.ply: a folder"):
        read_cloud(tmp_path / "d.ply")
    with pytest.raises(FileFormatError, match="a folder"):
        read_cloud(tmp_path)


def test_headers_promising_more_data_than_a_camera_gives_are_refused_before_allocating(tmp_path):
    """A .npy whose header asks for 10¹¹ rows (terabytes) and a PNG claiming 20000 × 20000
    pixels are one-line file errors, not a numpy allocation failure or Pillow's bomb guard."""
    from spacepose.tools.depth_io import image_size, read_depth_image

    huge = tmp_path / "huge.npy"
    with huge.open("wb") as fh:
        header = {"descr": "<f8", "fortran_order": False, "shape": (99999999999, 3)}
        np.lib.format.write_array_header_1_0(fh, header)
        fh.write(np.zeros(15).tobytes())
    with pytest.raises(
        FileFormatError,
        match=r"huge\.npy: truncated \.npy: its header says float64 \(99999999999, 3\)",
    ) as info:
        read_cloud(huge)
    assert "\n" not in str(info.value)
    good = tmp_path / "good.npy"
    np.save(good, np.zeros((5, 3)))
    raw = good.read_bytes()
    short = tmp_path / "short.npy"
    short.write_bytes(raw[:-8])
    with pytest.raises(FileFormatError, match=r"short\.npy: truncated"):
        read_cloud(short)
    # A PNG header of 20000 x 20000 pixels over a few bytes of data.
    import struct
    import zlib

    def chunk(kind: bytes, data: bytes) -> bytes:
        return (
            struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))
        )

    ihdr = struct.pack(">IIBBBBB", 20000, 20000, 16, 0, 0, 0, 0)
    bomb = tmp_path / "bomb.png"
    bomb.write_bytes(
        b"\x89PNG\r\n\x1a\n"
        + chunk(b"IHDR", ihdr)
        + chunk(b"IDAT", zlib.compress(b"\0" * 64))
        + chunk(b"IEND", b"")
    )
    assert image_size(bomb) is None
    with pytest.raises(FileFormatError, match=r"bomb\.png: refused: .*pixels"):
        read_depth_image(bomb)


def test_depth_images_without_intrinsics_say_so(tmp_path, capsys):
    Image.fromarray(np.full((8, 8), 1000, dtype=np.uint16)).save(tmp_path / "000000.png")
    assert main(["track", str(tmp_path), "--out", str(tmp_path / "out" / "e.tum")]) == 1
    assert "depth images need intrinsics" in _one_line(capsys)


@pytest.mark.skipif(not Path("/proc/version").is_file(), reason="needs Linux's /proc")
def test_outputs_that_cannot_be_written_are_refused_up_front(frames, tmp_path, capsys):
    for out in ("/proc/nope/e.tum", "/proc/version"):
        with pytest.raises(InputError, match="cannot write the output") as info:
            check_writable(out)
        assert "\n" not in str(info.value)
    with pytest.raises(InputError, match="needs a file name"):
        check_writable("")
    # The probe leaves nothing behind: no file, no folder.
    check_writable(tmp_path / "new" / "deeper" / "r.json")
    assert not (tmp_path / "new").exists()
    pair = [str(frames / "f000.ply"), str(frames / "f001.ply")]
    for command in (
        ["register", *pair, "--out", "/proc/nope/r.json"],
        ["track", str(frames), "--out", "/proc/nope/e.tum"],
        ["track", str(frames), "--out", ""],
        ["report", str(frames), "--out", "/proc/nope/r.html"],
    ):
        assert main(command) == 1
        assert re.search(r"error: .*(cannot write|file name)", _one_line(capsys)), command


def test_repeated_timestamps_and_corrupt_translations_are_refused(tmp_path):
    from spacepose.tools.frames import read_timestamps
    from spacepose.tools.trajectory_io import read_tum

    (tmp_path / "timestamps.txt").write_text("0.0\n0.1\n0.1\n0.2\n")
    with pytest.raises(InputError, match=r"must increase: frame 2 repeats 0.1"):
        read_timestamps(tmp_path / "timestamps.txt", 4)
    from spacepose.tools.depth_folder import read_tum_depth_list

    (tmp_path / "depth.txt").write_text("0.0 a.png\n0.1 b.png\n0.1 c.png\n")
    with pytest.raises(InputError, match=r"depth\.txt: timestamps must increase: frame 2 repeats"):
        read_tum_depth_list(tmp_path / "depth.txt")
    (tmp_path / "far.tum").write_text("0 0 0 0 0 0 0 1\n1 1e300 0 0 0 0 0 1\n")
    with pytest.raises(InputError, match=r"far\.tum: line 2: pose 1 has a translation beyond"):
        read_tum(tmp_path / "far.tum")


def test_a_voxel_too_fine_to_number_is_an_error_not_a_crash():
    from spacepose.core.voxel import cell_keys, voxel_downsample

    pts = np.random.default_rng(7).uniform(0, 1, (500, 3))
    # 1e-20 m overflowed the int64 cast and crashed the process; 1e-30 returned one point.
    for voxel in (1e-12, 1e-20, 1e-30, 1e-300):
        with pytest.raises(InputError, match="too many to number"):
            voxel_downsample(pts, voxel)  # an array is a cloud too
        with pytest.raises(InputError, match="too many to number"):
            cell_keys(pts, voxel)
    with pytest.raises(InputError, match="must be a number of metres, got 'x'"):
        voxel_downsample(pts, "x")
    assert len(voxel_downsample(pts, 0.5)) == 8


def test_register_takes_arrays_and_refuses_a_voxel_wider_than_the_cloud():
    from spacepose.tools.register import RegisterConfig, register

    rng = np.random.default_rng(8)
    pts = rng.uniform(0, 1, (2000, 3))
    result = register(pts, pts + np.array([0.002, 0.0, 0.0]))
    np.testing.assert_allclose(result.result.T_target_source[:3, 3], [0.002, 0, 0], atol=5e-4)
    with pytest.raises(InputError, match="voxel 1e\\+06 m is wider than the cloud"):
        register(pts, pts, config=RegisterConfig(voxel_size=1e6))


def test_api_errors_are_package_errors():
    from spacepose.core import se3
    from spacepose.core.metrics import error_table
    from spacepose.core.planes import PlaneConfig, extract_planes
    from spacepose.core.ransac import RansacConfig
    from spacepose.errors import ConfigError

    with pytest.raises(InputError, match="4x4 matrix of numbers"):
        se3.as_transform("eye")
    with pytest.raises(InputError, match="6 numbers"):
        se3.exp([1.0, 2.0, 3.0])
    with pytest.raises(InputError, match="4x4"):
        se3.log(np.eye(3))
    # A scaled "pose" is not a pose: its errors would be silently wrong.
    with pytest.raises(InputError, match="estimated pose 0 is not a rigid transform"):
        error_table(2.0 * np.eye(4), np.eye(4))
    assert error_table(np.eye(4), np.eye(4)).n == 1  # one (4, 4) pose is a stack of one
    with pytest.raises(ConfigError, match="batch_size"):
        RansacConfig(batch_size=10**8)
    # Inliers too rare to bound the iterations: max_iterations decides (was ZeroDivisionError).
    flat = np.random.default_rng(9).uniform(0, 1, (300, 3)) * [1.0, 1.0, 1e-4]
    assert len(extract_planes(flat, PlaneConfig(outlier_ratio=0.999999))) == 1


def test_a_simulation_that_sees_nothing_says_why(tmp_path, capsys):
    out = str(tmp_path / "run")
    assert main(["simulate", "lab", "--frames", "2", "--range", "1e9", "--out", out]) == 1
    assert "a range of 1e+09 m puts the whole target" in _one_line(capsys)
    assert main(["simulate", "lab", "--frames", str(10**20), "--out", out]) == 1
    assert "frames" in _one_line(capsys)


def test_tracker_and_normals_arguments_are_checked():
    from spacepose.core.fpfh import FPFHConfig
    from spacepose.core.normals import estimate_normals
    from spacepose.core.tracker import Tracker
    from spacepose.errors import ConfigError

    pts = np.random.default_rng(10).uniform(0, 1, (200, 3))
    assert Tracker({"points_per_frame": 2000}).config.points_per_frame == 2000
    with pytest.raises(ConfigError, match="config must be a TrackerConfig, got list"):
        Tracker([1])
    for workers in (0, -2, 1.5, True):  # refused when built, before a run writes anything
        with pytest.raises(InputError, match=r"workers must be -1 .* or a positive count"):
            Tracker(workers=workers)
    for viewpoint, message in (((0, 0), "3 numbers"), ((np.nan, 0, 0), "finite")):
        with pytest.raises(InputError, match=f"viewpoint must be {message}"):
            estimate_normals(pts, viewpoint=viewpoint)
    with pytest.raises(ConfigError, match="max_nn"):
        FPFHConfig(max_nn=10**7)
    # A normal over 5,000 neighbours took 16 s a frame, over 10⁸ it never came back.
    from spacepose.core.gicp import GICPConfig
    from spacepose.core.normals import NormalsConfig

    with pytest.raises(ConfigError, match="less than or equal to 1000"):
        NormalsConfig(k=5000)
    with pytest.raises(ConfigError, match="less than or equal to 1000"):
        GICPConfig(k_covariance=10**8)
    tracker = Tracker()
    tracker.track_frame(pts, 0.0)
    with pytest.raises(InputError, match="prior must be a pair"):
        tracker.track_frame(pts, 1.0, prior="x")
    for cov in (-np.eye(6), np.zeros((6, 6))):
        with pytest.raises(InputError, match="positive semi-definite and not zero"):
            tracker.track_frame(pts, 1.0, prior=(np.eye(4), cov))


def test_timestamps_and_weights_that_are_not_numbers_are_refused():
    from spacepose.core import se3
    from spacepose.core.metrics import associate

    with pytest.raises(InputError, match="must be finite"):
        associate([0.0, np.nan], [0.0, 1.0])
    with pytest.raises(
        InputError, match="estimated timestamps must be real numbers, got an array of text"
    ):
        associate(["a"], [0.0])
    with pytest.raises(InputError, match="tolerance"):
        associate([0.0], [0.0], tolerance=np.nan)
    with pytest.raises(InputError, match="weights must be finite"):
        se3.geodesic_mean([np.eye(4), np.eye(4)], weights=[np.nan, 1.0])


def test_an_empty_sensor_name_is_refused(tmp_path, capsys):
    out = str(tmp_path / "run")
    assert main(["simulate", "lab", "--frames", "2", "--sensor", "", "--out", out]) == 1
    assert "unknown sensor ''" in _one_line(capsys)


def test_a_model_that_collapses_at_the_frame_voxel_loses_every_frame_by_name(
    frames, tmp_path, capsys
):
    # 200 points within 20 µm pass the model's count, then fall to 1 point at the voxel the
    # first frame sets: the second frame raised AttributeError on half-built stages.
    model = tmp_path / "one_spot.xyz"
    spot = np.random.default_rng(0).uniform(-1e-5, 1e-5, (200, 3))
    np.savetxt(model, spot + np.array([0.1, 0.2, 1.0]))
    out = tmp_path / "e.tum"
    assert main(["track", str(frames), "--model", str(model), "--out", str(out)]) == 1
    err = _one_line(capsys).splitlines()[-1]
    assert "every frame was lost" in err and "one_spot.xyz: model has 1 points" in err
    with out.with_suffix(".health.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == 5
    assert all(r["status"] == "lost" and "one_spot.xyz: model has 1" in r["reasons"] for r in rows)


def test_a_degenerate_pair_names_both_files(tmp_path, capsys):
    t = np.linspace(0.0, 1.0, 300)[:, None]
    line = tmp_path / "line.xyz"
    np.savetxt(line, np.hstack([t, 2 * t, np.full_like(t, 2.0)]))
    with pytest.raises(DegenerateGeometryError, match="do not constrain all 6") as info:
        register_files(line, line)
    assert str(info.value).startswith(f"{line} onto {line}: ")
    assert main(["register", str(line), str(line)]) == 1
    assert f"{line} onto {line}: the correspondences" in _one_line(capsys)


@pytest.mark.parametrize("header", ["x,x,y,z", "x,y,z,nx,ny,nz,nz"])
def test_a_header_naming_a_coordinate_twice_is_refused(tmp_path, header):
    # Before, the first 'x' was taken without a word, whichever column the writer meant.
    rng = np.random.default_rng(2)
    width = len(header.split(","))
    path = tmp_path / "twice.csv"
    np.savetxt(path, rng.normal(size=(20, width)), delimiter=",", header=header, comments="")
    with pytest.raises(FileFormatError, match=r"twice\.csv: the header .* names (x|nz) twice"):
        read_cloud(path)


def test_a_folder_in_millimetres_warns_three_times_then_counts(frames, tmp_path, capsys):
    # Each file's warning carries its own extent and spacing; they are one problem all the same.
    mm = tmp_path / "mm"
    mm.mkdir()
    for path in sorted(frames.glob("*.ply")):
        write_cloud(mm / path.name, read_cloud(path).points * 1e3)
    capsys.readouterr()
    main(["track", str(mm), "--out", str(tmp_path / "e.tum")])
    warned = [ln for ln in capsys.readouterr().err.splitlines() if ln.startswith("warning:")]
    assert len(warned) == 4, warned
    assert all("coordinates look like millimetres" in ln for ln in warned[:3])
    assert warned[3] == ("warning: 2 more with the same warning: coordinates look like millimetres")


@pytest.mark.parametrize(
    ("name", "wall", "wrong", "right", "message"),
    [
        # A 16-bit map in millimetres (a wall 2 m away) with depth_scale 1: 2 km, as metres.
        ("000000.png", np.uint16(2000), 1.0, 0.001, "look like millimetres"),
        # A float TIFF in metres read with depth_scale 0.001: 2 mm away; it was lost as "4
        # points after preprocessing" with no word of the scale.
        ("000000.tiff", np.float32(2.0), 0.001, 1.0, "nearer than any depth camera"),
    ],
)
def test_a_depth_map_read_with_the_wrong_depth_scale_is_warned_about(
    tmp_path, name, wall, wrong, right, message
):
    yy, xx = np.mgrid[:48, :64]
    path = tmp_path / name
    Image.fromarray((wall + (0.0015 * wall) * (xx + yy)).astype(type(wall))).save(path)
    camera = DepthCamera(fx=60.0, fy=60.0, cx=31.5, cy=23.5, depth_scale=wrong)
    with pytest.warns(SpaceposeWarning, match=message) as caught:
        read_depth_cloud(path, camera)
    assert str(path) in str(caught[0].message) and "depth_scale" in str(caught[0].message)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        cloud = read_depth_cloud(path, camera.model_copy(update={"depth_scale": right}))
    assert 1.9 < np.median(cloud.points[:, 2]) < 2.5


def test_a_voxel_refused_for_points_far_out_says_how_far(tmp_path, capsys):
    # 2^63 in every coordinate: one cell, yet past any key; "[1, 1, 1] cells are too many"
    # was all the message said.
    path = tmp_path / "far.npy"
    np.save(path, np.full((100, 3), 2**63, dtype=np.uint64))
    near = tmp_path / "near.npy"
    np.save(near, np.random.default_rng(3).normal(size=(300, 3)) * 0.1 + [0, 0, 1])
    assert main(["register", str(path), str(near)]) == 1
    err = _one_line(capsys)
    assert "far.npy" in err and "reaching |coordinate| 9.22e+18 m" in err


def test_an_orbit_standoff_inside_the_target_is_refused(tmp_path, capsys):
    # At 1 nm the chaser sat inside the satellite and wrote its faces seen from within.
    out = str(tmp_path / "o")
    assert main(["simulate", "orbit", "--frames", "1", "--range", "1e-9", "--out", out]) == 1
    assert "standoff of 1e-09 m puts the chaser within the target's reach" in _one_line(capsys)
    assert not (tmp_path / "o" / "frames").exists()


def test_an_output_onto_an_input_file_is_refused_before_any_work(frames, tmp_path, capsys):
    """Written onto a frame, the timestamps or a run's truth, the output would destroy the
    input before it is read (or the truth a later evaluate compares with); through a link
    too. A new output inside the input folder is fine."""
    root = _copy(frames, tmp_path / "in")
    (root / "timestamps.txt").write_text("".join(f"{k}\n" for k in range(5)))
    before = {p.name: p.read_bytes() for p in root.iterdir()}
    (tmp_path / "link.tum").symlink_to(root / "timestamps.txt")
    for out in (root / "f003.ply", root / "timestamps.txt", tmp_path / "link.tum"):
        assert main(["track", str(root), "--out", str(out)]) == 1
        assert "would overwrite the input" in _one_line(capsys)
    cmd = ["register", str(root / "f000.ply"), str(root / "f001.ply")]
    assert main([*cmd, "--out", str(root / "f001.ply")]) == 1
    assert re.search(r"f001\.ply: would overwrite the input .*f001\.ply", _one_line(capsys))
    assert {p.name: p.read_bytes() for p in root.iterdir()} == before
    est = root / "out" / "est.tum"
    assert main(["track", str(root), "--out", str(est)]) == 0
    assert main(["track", str(root), "--out", str(est)]) == 0  # its own output, again
    # Beside the frames, its tables are no frames of the next run (5 timestamps, 5 frames).
    assert main(["track", str(root), "--out", str(root / "est.tum")]) == 0
    assert (root / "est.health.csv").is_file()
    assert main(["track", str(root), "--out", str(root / "est.tum")]) == 0
    assert len((root / "est.health.csv").read_text().splitlines()) == 1 + 5


def test_frames_named_without_padding_come_in_the_numbers_order(tmp_path):
    """frame0, frame5, frame10, frame15 sorted as text would track 0, 10, 15, 5: a jump back
    the motion model takes for a turn. Numbers by value; a fraction's digits as text, so that
    TUM-style times keep their order (1.25 before 1.5)."""
    from spacepose.tools.depth_folder import frame_entries

    names = ["frame10.ply", "frame5.ply", "frame15.ply", "frame0.ply", ".frame1.ply", "notes.md"]
    names += ["frame05.ply", "frame5b.ply"]  # equal numbers: by text; a name that goes on
    for name in names:
        (tmp_path / name).write_bytes(b"")
    found = [p.name for p in frame_entries(tmp_path, (".ply",))]
    expected = ["frame0.ply", "frame05.ply", "frame5.ply", "frame5b.ply", "frame10.ply"]
    assert found == [*expected, "frame15.ply"]
    times = tmp_path / "times"
    times.mkdir()
    for name in ("1.5.png", "1.25.png", "0.75.png", "10.0.png", "2.png"):
        (times / name).write_bytes(b"")
    found = [p.name for p in frame_entries(times, (".png",))]
    assert found == ["0.75.png", "1.25.png", "1.5.png", "2.png", "10.0.png"]


def test_a_multi_page_tiff_is_not_read_as_its_first_page(tmp_path):
    """Four depth maps stacked in one TIFF were read as the first, the rest dropped."""
    from spacepose.tools.depth_io import read_depth_image

    pages = [Image.fromarray(np.full((6, 8), 1000 + k, dtype=np.uint16)) for k in range(4)]
    pages[0].save(tmp_path / "stack.tif", save_all=True, append_images=pages[1:])
    with pytest.raises(FileFormatError, match=r"stack\.tif: holds 4 images; a depth map is one"):
        read_depth_image(tmp_path / "stack.tif")
    pages[0].save(tmp_path / "one.tif")
    assert read_depth_image(tmp_path / "one.tif")[0, 0] == 1000


def test_a_ply_of_the_other_byte_order_warns_in_words_only(tmp_path):
    """A little-endian body under a big-endian header reads as garbage, signalling NaNs among
    it: numpy's raw 'invalid value encountered in cast' came out beside our own warning."""
    path = write_cloud(tmp_path / "le.ply", np.random.default_rng(5).normal(1.0, 0.2, (400, 3)))
    raw = path.read_bytes()
    body = raw.index(b"end_header\n")
    path.write_bytes(raw[:body].replace(b"binary_little_endian", b"binary_big_endian") + raw[body:])
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            read_cloud(path)
        except InputError:
            pass  # a frame of garbage may be refused outright; it must not warn raw
    assert not [w for w in caught if issubclass(w.category, RuntimeWarning)], caught
