"""Bad inputs found by a fourth hostile round: each ends in one line naming the file and the
problem (or a warning naming it), never a traceback, a hang or a silently wrong result."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest

from spacepose.cli import main
from spacepose.core.depth import DepthCamera
from spacepose.errors import ConfigError, FileFormatError, InputError, SpaceposeWarning
from spacepose.tools.cloud_io import read_cloud, write_cloud
from spacepose.tools.depth_folder import read_tum_depth_list
from spacepose.tools.depth_io import read_depth_image, write_depth_image
from spacepose.tools.frames import open_frames, read_timestamps
from spacepose.tools.runs import read_run
from test_bag_io import IMAGE, INFO, PC2, ROS2, _camera_info, _image, _pointcloud2, _write

INTRINSICS = "fx: 30\nfy: 30\ncx: 15.5\ncy: 11.5\n"


def _cli_error(capsys) -> str:
    """The CLI's stderr, checked to be one ``error:`` line without a traceback."""
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "Traceback" not in err, err
    assert err.startswith("error:"), err
    return err


def _refused(capsys, error: type, message: str, read, argv: list[str]) -> None:
    """``read()`` raises ``error`` with ``message``, and the CLI run ``argv`` ends in that one
    line."""
    with pytest.raises(error) as exc:
        read()
    assert str(exc.value) == message
    assert main(argv) == 1
    assert _cli_error(capsys) == f"error: {message}"


def _cloud_folder(root: Path, frames: int = 4, seed: int = 0) -> Path:
    """``frames`` small clouds 1 m in front of the sensor, one .ply each."""
    rng = np.random.default_rng(seed)
    root.mkdir(parents=True, exist_ok=True)
    for k in range(frames):
        write_cloud(root / f"{k:06d}.ply", rng.normal(size=(300, 3)) * 0.1 + [0.0, 0.0, 1.0])
    return root


def _depth_folder(root: Path, frames: int = 2, intrinsics: str | None = INTRINSICS) -> Path:
    """``frames`` 32 x 24 depth maps (a tilted plane about 1.2 m away), and an intrinsics file."""
    root.mkdir(parents=True, exist_ok=True)
    yy, xx = np.mgrid[:24, :32]
    for k in range(frames):
        write_depth_image(root / f"{k:06d}.png", 1.2 + 0.01 * xx + 0.005 * yy + 0.01 * k)
    if intrinsics is not None:
        (root / "intrinsics.yaml").write_text(intrinsics)
    return root


# -- frame times counted in milliseconds --------------------------------------------------------


def test_a_millisecond_clock_from_the_start_is_refused(tmp_path, capsys):
    """A 30 Hz camera's times from the start in milliseconds (0, 33, 67, 100, ...) were read as
    a frame every 33 s without a word: the target's rates came out a thousand times too
    slow, and navigate integrated the orbit half a minute a frame."""
    frames = _cloud_folder(tmp_path / "frames")
    stamps = frames / "timestamps.txt"
    stamps.write_text("".join(f"{round(k * 1000 / 30)}\n" for k in range(4)))
    with pytest.raises(InputError) as exc:
        read_timestamps(stamps, 4)
    message = str(exc.value)
    assert message.startswith(f"{stamps}: whole-number times 33 apart (median)")
    assert "a 30 Hz camera's milliseconds" in message and "times are seconds" in message
    assert main(["track", str(frames), "--out", str(tmp_path / "e.tum")]) == 1
    err = _cli_error(capsys)
    assert str(stamps) in err and "milliseconds" in err
    depth_list = tmp_path / "depth.txt"
    depth_list.write_text("".join(f"{round(k * 1000 / 15)} d/{k}.png\n" for k in range(5)))
    with pytest.raises(InputError, match="a 15 Hz camera's milliseconds"):
        read_tum_depth_list(depth_list)


def test_frames_slower_than_any_camera_are_warned_about(tmp_path):
    """Milliseconds with their fractions (0, 33.333, 66.667) cannot be told from a frame every
    33 s: read so without a word. Such times are now warned about, naming the file; real
    camera rates read without a word, and a frame a minute still reads (with the warning)."""
    stamps = tmp_path / "timestamps.txt"
    stamps.write_text("".join(f"{k * 1000 / 30:.3f}\n" for k in range(4)))
    with pytest.warns(SpaceposeWarning) as caught:
        read_timestamps(stamps, 4)
    assert str(caught[0].message) == (
        f"{stamps}: the frames are 33.33 s apart (median), slower than a ToF camera or flash "
        "LiDAR frames (1-100 Hz) (times are seconds; milliseconds, microseconds or "
        "nanoseconds given?)"
    )
    stamps.write_text("".join(f"{60 * k}\n" for k in range(4)))  # a simulated slow run
    with pytest.warns(SpaceposeWarning, match="60 s apart"):
        np.testing.assert_array_equal(read_timestamps(stamps, 4), [0, 60, 120, 180])
    for text in ("".join(f"{1.7e9 + k / 30:.6f}\n" for k in range(4)), "0\n1\n2\n3.5\n"):
        stamps.write_text(text)
        with warnings.catch_warnings():
            warnings.simplefilter("error")
            read_timestamps(stamps, 4)


# -- --intrinsics beside a folder's own intrinsics file -------------------------------------------


def test_intrinsics_given_that_differ_from_the_folders_own_are_refused(tmp_path, capsys):
    """--intrinsics won over the folder's own intrinsics.yaml without a word, the calibration
    recorded with the images ignored."""
    folder = _depth_folder(tmp_path / "depth")
    given = tmp_path / "other.yaml"
    given.write_text(INTRINSICS.replace("fx: 30", "fx: 45"))
    with pytest.raises(InputError) as exc:
        open_frames(folder, intrinsics=given)
    assert str(exc.value) == (
        f"{folder}: --intrinsics {given} and the folder's intrinsics.yaml differ (fx 45.0 vs "
        "30.0): keep one (move intrinsics.yaml out, or leave out --intrinsics)"
    )
    out = tmp_path / "e.tum"
    assert main(["track", str(folder), "--out", str(out), "--intrinsics", str(given)]) == 1
    assert "differ (fx 45.0 vs 30.0)" in _cli_error(capsys) and not out.exists()
    # The same camera given again (or the folder's file itself) reads.
    given.write_text(INTRINSICS)
    for intrinsics in (given, folder / "intrinsics.yaml"):
        assert all(f.cloud is not None for f in open_frames(folder, intrinsics=intrinsics))


# -- lens distortion that folds the image ---------------------------------------------------------


@pytest.mark.parametrize(
    ("k1", "fold"),
    [
        (-50.0, "folds back about 2 pixels"),  # a sign or unit slip
        (-0.5, "folds back about 16 pixels"),  # folds only the corners
    ],
)
def test_a_distortion_that_folds_within_the_image_is_refused(tmp_path, capsys, k1, fold):
    """k1 = -2 on a 32 x 24 image of fx 30 folds its corners: their pixels were given the
    direction of the opposite side, or lost, without a word (the camera is refused only when
    more than half of the image folds)."""
    folder = _depth_folder(tmp_path / "depth", intrinsics=INTRINSICS + f"k1: {k1}\n")
    with pytest.raises(ConfigError) as exc:
        open_frames(folder)
    message = str(exc.value)
    assert message.startswith(f"{folder / 'intrinsics.yaml'}: the lens distortion (k1..k6 {k1:g}")
    assert "is not one-to-one over the 32x24 image" in message and fold in message
    assert main(["track", str(folder), "--out", str(tmp_path / "e.tum")]) == 1
    assert "not one-to-one" in _cli_error(capsys)
    # A real lens's barrel (a few pixels at the corners) reads without a word.
    (folder / "intrinsics.yaml").write_text(INTRINSICS + "k1: -0.2\nk2: 0.05\n")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert all(f.cloud is not None for f in open_frames(folder))


def test_a_pincushion_beyond_any_lens_is_warned_about(tmp_path):
    """k1 = 50 is one-to-one, but draws the corners to a fifth of their pinhole directions:
    read without a word."""
    folder = _depth_folder(tmp_path / "depth", intrinsics=INTRINSICS + "k1: 50\n")
    with pytest.warns(SpaceposeWarning) as caught:
        open_frames(folder)
    message = str(caught[0].message)
    assert message.startswith(f"{folder / 'intrinsics.yaml'}: the lens distortion (k1..k6 50")
    assert "narrowing the 32x24 image's view beyond any lens" in message


# -- ROS bags: the same checks as files -----------------------------------------------------------


def test_bag_clouds_in_kilometres_are_warned_about(tmp_path):
    """A folder's cloud files nearer than any sensor ranges were warned about; a bag's
    PointCloud2 frames were not."""
    rng = np.random.default_rng(1)
    grid = (rng.normal(size=(8, 10, 3)) * 0.1 + [0.0, 0.0, 1.2]) * 1e-3  # km
    bag = _write(tmp_path / "km", [("/pc", PC2, _pointcloud2(ROS2, k, grid)) for k in range(2)])
    with pytest.warns(SpaceposeWarning) as caught:
        frames = list(open_frames(bag))
    assert all(f.cloud is not None for f in frames)
    messages = [str(w.message) for w in caught]
    assert any(
        m.startswith(f"{bag}:/pc#1: the returns lie") and "kilometres" in m for m in messages
    ), messages


def test_bag_depth_images_in_other_units_and_folded_lenses_say_so(tmp_path):
    """A bag's depth Image frames had no unit check (a float image in millimetres, metres
    read as smaller units), and a CameraInfo whose distortion folds the image was used."""
    camera = DepthCamera(fx=30, fy=30, cx=15.5, cy=11.5, width=32, height=24)
    yy, xx = np.mgrid[:24, :32]
    near = 5 + (xx + yy) // 10  # 5-10 mm: a driver writing centimetres as millimetres?
    messages = [("/cam/camera_info", INFO, _camera_info(ROS2, camera, ros1=False))]
    messages += [("/cam/depth", IMAGE, _image(ROS2, k, near)) for k in range(2)]
    bag = _write(tmp_path / "near", messages)
    with pytest.warns(SpaceposeWarning) as caught:
        frames = list(open_frames(bag))
    assert all(f.cloud is not None for f in frames)
    assert any(
        str(w.message).startswith(f"{bag}:/cam/depth#0: the returns lie")
        and "16UC1 encoding is 0.001 m per unit" in str(w.message)
        for w in caught
    ), [str(w.message) for w in caught]
    # An intrinsics file whose lens folds the image, for the bag's Image topic.
    folded = tmp_path / "folded.yaml"
    folded.write_text("fx: 30\nfy: 30\ncx: 15.5\ncy: 11.5\nk1: -2\nwidth: 32\nheight: 24\n")
    with pytest.raises(ConfigError) as exc:
        open_frames(bag, intrinsics=folded)
    assert str(exc.value).startswith(f"{folded}: the lens distortion (k1..k6 -2")
    # Without its size, it differs from the bag's CameraInfo (k1 0): refused (round 21).
    folded.write_text("fx: 30\nfy: 30\ncx: 15.5\ncy: 11.5\nk1: -2\n")
    with pytest.raises(InputError, match=r"CameraInfo on /cam/camera_info differ \(k1 -2 vs 0\)"):
        open_frames(bag, intrinsics=folded)


def test_frames_faster_than_any_camera_are_refused(tmp_path):
    """Times a nanosecond apart (seconds converted twice, or hours: 9.3e-6 at 30 Hz) were
    read as a billion frames a second without a word."""
    stamps = tmp_path / "timestamps.txt"
    stamps.write_text("".join(f"{k * 1e-9:.3g}\n" for k in range(4)))
    with pytest.raises(InputError) as exc:
        read_timestamps(stamps, 4)
    assert str(exc.value).startswith(f"{stamps}: the frames are 1e-09 s apart (median), faster")
    assert "hours or days given" in str(exc.value)
    stamps.write_text("".join(f"{k / 1000}\n" for k in range(4)))  # a 1 kHz sensor reads
    np.testing.assert_allclose(read_timestamps(stamps, 4), [0, 0.001, 0.002, 0.003])


# -- a run folder's own times -------------------------------------------------------------------


@pytest.fixture(scope="module")
def orbit_run(tmp_path_factory) -> Path:
    """A three-frame orbit run, written by simulate."""
    run = tmp_path_factory.mktemp("orbit") / "run"
    assert main(["simulate", "orbit", "--frames", "3", "--seed", "0", "--out", str(run)]) == 0
    return run


def _copy_run(run: Path, to: Path) -> Path:
    import shutil

    return Path(shutil.copytree(run, to))


def test_a_run_timed_in_milliseconds_is_warned_about(tmp_path, orbit_run):
    """groundtruth.tum times the run's frames; rewritten in milliseconds (0, 1000, 2000) it was
    navigated a thousand times too slow without a word."""
    run = _copy_run(orbit_run, tmp_path / "run")
    gt = run / "groundtruth.tum"
    rows = [line.split(maxsplit=1) for line in gt.read_text().splitlines()]
    gt.write_text("".join(f"{float(t) * 1000:g} {rest}\n" for t, rest in rows))
    truth = run / "truth.csv"
    head, *body = truth.read_text().splitlines()
    rows = [line.split(",", 1) for line in body]
    truth.write_text(head + "\n" + "".join(f"{float(t) * 1000:g},{r}\n" for t, r in rows))
    with pytest.warns(SpaceposeWarning) as caught:
        read_run(run)
    assert str(caught[0].message).startswith(f"{gt}: the frames are 1000 s apart (median)")


def test_a_truth_at_other_times_than_the_frames_is_refused(tmp_path, capsys, orbit_run):
    """truth.csv is paired with the frames row by row: a row at another time (an edited
    file, another run's truth) was navigated and scored against the wrong frame."""
    run = _copy_run(orbit_run, tmp_path / "run")
    truth = run / "truth.csv"
    lines = truth.read_text().splitlines()
    lines[2] = "7" + lines[2][lines[2].index(",") :]
    truth.write_text("\n".join(lines) + "\n")
    message = (
        f"{truth}: row 2 is at t = 7 s, frame 1 at 1 s (groundtruth.tum): the truth and the "
        "frames must share their times"
    )
    argv = ["navigate", str(run), "--out", str(tmp_path / "nav.csv")]
    _refused(capsys, FileFormatError, message, lambda: read_run(run), argv)


# -- the first lost frame names its file ----------------------------------------------------------


def test_every_frame_lost_by_the_tracker_names_the_file(tmp_path, capsys):
    """A frame the tracker could not use (one point left) ended the run as "every frame was
    lost (frame 0: unusable frame: 1 point(s): ...)", naming no file."""
    folder = tmp_path / "frames"
    folder.mkdir()
    np.save(folder / "000000.npy", np.array([[0.0, 0.0, 1.0]]))
    assert main(["track", str(folder), "--out", str(tmp_path / "e.tum")]) == 1
    err = _cli_error(capsys)
    assert err.startswith(
        f"error: {folder}: every frame was lost (frame 0, {folder / '000000.npy'}:"
    )
    assert "1 point(s)" in err


# -- a depth image registered with a folded lens --------------------------------------------------


def test_a_depth_image_registered_with_a_folded_lens_is_refused(tmp_path, capsys):
    """register reads a depth image with its intrinsics: a lens folding the image was used
    without a word (the image's size is only known once it is read)."""
    folder = _depth_folder(tmp_path / "depth", intrinsics=INTRINSICS + "k1: -0.5\n")
    source, target = folder / "000000.png", folder / "000001.png"
    assert main(["register", str(source), str(target)]) == 1
    err = _cli_error(capsys)
    assert err.startswith(f"error: {source}: the lens distortion (k1..k6 -0.5")
    assert "not one-to-one over the 32x24 image" in err


def test_report_of_a_missing_folder_says_it_does_not_exist(tmp_path, capsys):
    """It said "not a folder", sending the user to look at what the path is."""
    missing = tmp_path / "rnu"
    assert main(["report", str(missing)]) == 1
    assert _cli_error(capsys) == f"error: {missing}: not a folder: it does not exist"


# -- two lists timing one depth folder ------------------------------------------------------------


def test_a_depth_list_beside_timestamps_is_refused(tmp_path):
    """A depth folder with TUM's depth.txt and a timestamps.txt was timed by the list, the
    other file left without a word."""
    folder = _depth_folder(tmp_path / "depth")
    (folder / "depth.txt").write_text("0 000000.png\n1 000001.png\n")
    (folder / "Timestamps.txt").write_text("5\n6\n")
    with pytest.raises(InputError) as exc:
        open_frames(folder)
    assert str(exc.value) == (
        f"{folder}: holds depth.txt and Timestamps.txt, and each times the frames: keep one"
    )


def test_a_depth_list_naming_one_image_twice_is_refused(tmp_path):
    """depth.txt naming one image on two lines tracked it as two frames, without a word."""
    folder = _depth_folder(tmp_path / "depth")
    listing = folder / "depth.txt"
    listing.write_text("# TUM depth list\n0 000000.png\n0.1 000001.png\n0.2 ./000000.png\n")
    with pytest.raises(InputError) as exc:
        read_tum_depth_list(listing)
    assert str(exc.value) == (
        f"{listing}: line 4: ./000000.png is listed again (line 2): one image is one frame"
    )


def test_every_bag_cloud_is_checked_for_its_unit(tmp_path):
    """Only a bag's first PointCloud2 was checked for millimetres: a later message of
    coordinates in the 1e9 m (a corrupt driver's) was tracked without a word."""
    rng = np.random.default_rng(3)
    grid = rng.normal(size=(8, 10, 3)) * 0.1 + [0.0, 0.0, 1.2]
    clouds = [grid, grid * 1e9, grid]
    bag = _write(
        tmp_path / "bag", [("/pc", PC2, _pointcloud2(ROS2, k, g)) for k, g in enumerate(clouds)]
    )
    with pytest.warns(SpaceposeWarning) as caught:
        frames = list(open_frames(bag))
    assert len(frames) == 3
    messages = [str(w.message) for w in caught]
    assert messages == [
        f"{bag}:/pc#1: coordinates span 9.14e+08 m, beyond any sensor's reach even read as "
        "millimetres: corrupt values, or another unit?"
    ], messages


def test_a_depth_map_of_negative_depths_says_so(tmp_path):
    """A renderer looking down -z (OpenGL's camera) writes negative depths: the frame was lost
    as "no return (every pixel zero or invalid)", the sign not named."""
    yy, xx = np.mgrid[:24, :32]
    np.save(tmp_path / "000000.npy", -(1.2 + 0.01 * xx + 0.005 * yy))
    (tmp_path / "intrinsics.yaml").write_text(INTRINSICS + "depth_scale: 1\n")
    frame = next(iter(open_frames(tmp_path)))
    assert frame.cloud is None
    assert frame.error == (
        f"{tmp_path / '000000.npy'}: every depth is negative (median -1.413 m): depths along -z, "
        "as an OpenGL camera's? they are distances in front of the sensor, positive"
    )


# -- a .npy whose header does not parse -----------------------------------------------------------


def test_a_npy_header_that_does_not_parse_names_the_file(tmp_path, capsys):
    """An unclosed bracket in a .npy's header dict ended in tokenize's TokenError traceback
    (register), and in a depth folder the same from the image size read."""
    header = b"{'descr': '<f4', 'fortran_order': False, 'shape': (100, 3"
    bad = tmp_path / "bad.npy"
    bad.write_bytes(
        b"\x93NUMPY\x01\x00" + len(header).to_bytes(2, "little") + header + b"\x00" * 40
    )
    assert main(["register", str(bad), str(bad)]) == 1
    assert _cli_error(capsys) == f"error: {bad}: bad .npy header: its description does not parse"
    folder = tmp_path / "depth"
    folder.mkdir()
    bad.rename(folder / "000000.npy")
    (folder / "intrinsics.yaml").write_text(INTRINSICS)
    frame = next(iter(open_frames(folder)))
    assert frame.cloud is None and frame.error.endswith(
        "bad .npy header: its description does not parse"
    )


# -- damaged TIFF depth maps ----------------------------------------------------------------------


def _damaged_tiff(path: Path, at: int, new: bytes, replace: int = 0) -> Path:
    """A 32 x 24 depth TIFF with ``new`` written at byte ``at`` over ``replace`` bytes."""
    yy, xx = np.mgrid[:24, :32]
    write_depth_image(path, 1.2 + 0.01 * xx + 0.005 * yy)
    data = path.read_bytes()
    path.write_bytes(data[:at] + new + data[at + replace :])
    return path


def test_a_tiff_that_lost_its_size_is_one_error_naming_the_file(tmp_path, capsys):
    """A byte slipped into a TIFF's tags ended in Pillow's TypeError traceback ("Missing
    dimensions"), after a dozen bare 'UserWarning: Tag data larger than file' lines."""
    folder = _depth_folder(tmp_path / "depth", frames=0)
    bad = _damaged_tiff(folder / "000000.tif", 118, b"*")
    good = _damaged_tiff(folder / "000001.tif", 0, b"")  # undamaged: one format per folder
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no Pillow warning escapes
        frames = list(open_frames(folder))
    assert frames[0].cloud is None and frames[1].cloud is not None
    assert frames[0].error == f"{bad}: cannot decode the image: Missing dimensions"
    assert main(["register", str(bad), str(good)]) == 1
    assert _cli_error(capsys) == f"error: {frames[0].error}"


def test_a_tiff_decoded_despite_damage_says_so_once(tmp_path):
    """A TIFF Pillow decodes while skipping a damaged tag printed Pillow's bare warning, naming
    no file."""
    path = _damaged_tiff(tmp_path / "frame.tif", 50, b"\x00\x07", replace=2)
    with pytest.warns(SpaceposeWarning) as caught:
        read_depth_image(path)
    assert [type(w.message) for w in caught] == [SpaceposeWarning]
    assert str(caught[0].message).startswith(f"{path}: decoded despite Pillow's warnings: ")


# -- signalling NaNs ------------------------------------------------------------------------------


@pytest.mark.parametrize("name", ["cloud.npy", "cloud.pcd"])
def test_signalling_nans_are_dropped_without_numpys_warning(tmp_path, name):
    """A float32 signalling NaN (a corrupt or foreign writer's bits) in a .npy or binary PCD
    printed numpy's bare "RuntimeWarning: invalid value encountered in cast", naming no file;
    a PLY's was already dropped quietly as any NaN row."""
    rng = np.random.default_rng(8)
    points = (rng.normal(size=(200, 3)) * 0.1 + [0.0, 0.0, 1.0]).astype(np.float32)
    points[5] = np.array([0x7FA00000] * 3, dtype=np.uint32).view(np.float32)
    path = tmp_path / name
    if name.endswith(".npy"):
        np.save(path, points)
    else:
        header = (
            "VERSION .7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 200\n"
            "HEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS 200\nDATA binary\n"
        )
        path.write_bytes(header.encode() + points.astype("<f4").tobytes())
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        cloud = read_cloud(path)
    assert len(cloud) == 199


@pytest.mark.parametrize(
    ("key", "shown"),
    [
        ("1", "1 is not a field name: YAML reads it as a number"),
        ("yes", "True is not a field name: YAML reads it as a yes/no"),
        ("~", "None is not a field name: YAML reads it as null"),
    ],
)
def test_an_intrinsics_key_that_is_no_name_is_refused(tmp_path, capsys, key, shown):
    """YAML reads "1: 0.1" (k1 that lost its letter) as a number key: pydantic's TypeError
    "keywords must be strings" escaped as a traceback."""
    folder = _depth_folder(tmp_path / "depth", intrinsics=INTRINSICS + f"{key}: 0.1\n")
    message = f"{folder / 'intrinsics.yaml'}: key {shown}"
    argv = ["track", str(folder), "--out", str(tmp_path / "e.tum")]
    _refused(capsys, ConfigError, message, lambda: open_frames(folder), argv)


def test_a_bag_stamp_of_a_second_or_more_of_nanoseconds_is_refused(tmp_path):
    """A header stamp whose nanosec holds a second or more (no ROS time: a driver writing the
    time in nanoseconds there) moved the frame up to 4 s on without a word."""
    rng = np.random.default_rng(9)
    grid = rng.normal(size=(8, 10, 3)) * 0.1 + [0.0, 0.0, 1.2]
    messages = [_pointcloud2(ROS2, k, grid) for k in range(3)]
    messages[1].header.stamp.nanosec = 1_500_000_000
    bag = _write(tmp_path / "bag", [("/pc", PC2, m) for m in messages])
    frames = list(open_frames(bag))
    assert [f.cloud is None for f in frames] == [False, True, False]
    assert frames[1].source == f"{bag}:/pc#1"
    assert frames[1].error == (
        "header stamp nanosec 1500000000 is a second or more: not a ROS time (nanosec counts "
        "within the second)"
    )


def test_intrinsics_of_another_resolution_name_the_intrinsics_file(tmp_path, capsys):
    """A principal point outside the images (intrinsics of the full-resolution stream) lost
    every frame, each naming its image, never the intrinsics file at fault."""
    folder = _depth_folder(tmp_path / "depth", intrinsics="fx: 60\nfy: 60\ncx: 63.5\ncy: 47.5\n")
    message = (
        f"{folder / 'intrinsics.yaml'}: the principal point (63.5, 47.5) lies outside the "
        "32x24 image: intrinsics of another resolution?"
    )
    argv = ["track", str(folder), "--out", str(tmp_path / "e.tum")]
    _refused(capsys, ConfigError, message, lambda: open_frames(folder), argv)


def test_slow_whole_second_runs_with_a_missed_frame_still_read(tmp_path):
    """A frame every 10 s with a frame missed (0, 10, 20, 40, 50) varies its steps too, but by
    a whole frame, not the unit or two of a clock's rounding: read, with the slow warning."""
    stamps = tmp_path / "timestamps.txt"
    stamps.write_text("0\n10\n20\n40\n50\n")
    with pytest.warns(SpaceposeWarning, match="10 s apart"):
        np.testing.assert_array_equal(read_timestamps(stamps, 5), [0, 10, 20, 40, 50])


def test_intrinsics_given_beside_an_unreadable_own_file_say_why_they_are_refused(tmp_path):
    """--intrinsics beside a folder's broken intrinsics.yaml ended in the broken file's error
    alone, as if the intrinsics given had not been read."""
    folder = _depth_folder(tmp_path / "depth", intrinsics="fx: [\n")
    given = tmp_path / "given.yaml"
    given.write_text(INTRINSICS)
    with pytest.raises(InputError) as exc:
        open_frames(folder, intrinsics=given)
    message = str(exc.value)
    assert message.startswith(
        f"{folder}: --intrinsics {given} is given beside the folder's intrinsics.yaml, which "
        f"cannot be read ({folder / 'intrinsics.yaml'}: not valid YAML"
    )
    assert message.endswith("): keep one")
