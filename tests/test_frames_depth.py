"""Depth image folders as tracking input (tools/frames.py with tools/depth_folder.py).

A simulated lab run is rendered into 16-bit PNG depth maps (0.1 mm units); the equivalent point
cloud folder holds, as float64 .npy, the points of the same quantised depths back-projected here
by the textbook pinhole formula, ``x = (u - cx) / fx · z``, in the same order of operations: the
quantised depths put points exactly on voxel edges, where a one-ulp difference picks another
voxel. Both must track to the same poses (to 1e-9; measured 4e-17).
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest

from spacepose.cli import main
from spacepose.core.depth import DepthCamera, render_depth
from spacepose.core.metrics import evaluate
from spacepose.core.sim import scenario_config, simulate
from spacepose.core.trajectory import Trajectory
from spacepose.errors import InputError, SpaceposeWarning
from spacepose.tools.depth_io import read_depth_image, write_depth_image
from spacepose.tools.frames import FrameSequence, open_frames
from spacepose.tools.tracking_io import track_folder, tracker_config
from spacepose.tools.trajectory_io import read_tum

N_FRAMES = 6
DEPTH_SCALE = 1e-4  # 0.1 mm units: the lab target at 1.1-1.3 m fits 16 bits easily


@pytest.fixture(scope="module")
def sim():
    return simulate(scenario_config("lab", frames=N_FRAMES))


@pytest.fixture(scope="module")
def camera(sim) -> DepthCamera:
    """The simulator's pinhole (principal point at the image centre, square pixels)."""
    s = sim.config.sensor
    c = (0.5 * (s.width - 1), 0.5 * (s.height - 1))
    return DepthCamera(
        fx=s.focal_px, fy=s.focal_px, cx=c[0], cy=c[1], depth_scale=DEPTH_SCALE,
        width=s.width, height=s.height,
    )  # fmt: skip


@pytest.fixture(scope="module")
def folders(sim, camera, tmp_path_factory) -> dict[str, Path]:
    """The PNG depth folder (with intrinsics.yaml) and its equivalent .npy cloud folder."""
    root = tmp_path_factory.mktemp("depth")
    depth_dir, cloud_dir = root / "depth", root / "clouds"
    stamps = "".join(f"{10.0 + 0.25 * k!r}\n" for k in range(N_FRAMES))
    for k in range(N_FRAMES):
        image = render_depth(sim.frame(k).cloud.points, camera, camera.height, camera.width)
        png = write_depth_image(depth_dir / f"{k:04d}.png", image, DEPTH_SCALE)
        units = read_depth_image(png)
        v, u = np.nonzero(units)  # row-major, as the simulator's pixels
        z = units[v, u] * DEPTH_SCALE
        x = (u - camera.cx) / camera.fx * z
        y = (v - camera.cy) / camera.fy * z
        cloud_dir.mkdir(exist_ok=True)
        np.save(cloud_dir / f"{k:04d}.npy", np.column_stack([x, y, z]))
    (depth_dir / "intrinsics.yaml").write_text(
        "".join(f"{k}: {v!r}\n" for k, v in camera.model_dump().items() if v is not None)
    )
    for folder in (depth_dir, cloud_dir):
        (folder / "timestamps.txt").write_text(stamps)
    return {"depth": depth_dir, "clouds": cloud_dir, "root": root}


def test_depth_frames_equal_the_simulated_clouds(sim, folders):
    frames = open_frames(folders["depth"])
    assert isinstance(frames, FrameSequence) and len(frames) == N_FRAMES
    for k, frame in enumerate(frames):
        truth = sim.frame(k).cloud.points
        assert frame.error is None and len(frame.cloud) == len(truth)
        # Same pixels in the same order; depth rounded to 0.1 mm moves a point along its ray.
        assert np.max(np.linalg.norm(frame.cloud.points - truth, axis=1)) < 0.06e-3
        np.testing.assert_allclose(frame.timestamp, 10.0 + 0.25 * k)


def test_png_depth_run_tracks_like_the_cloud_folder(sim, folders, tmp_path):
    config = tracker_config()
    depth = track_folder(folders["depth"], tmp_path / "depth.tum", config)
    clouds = track_folder(folders["clouds"], tmp_path / "clouds.tum", config)
    assert depth["frames"] == clouds["frames"] == N_FRAMES and depth["lost"] == 0
    a, b = read_tum(tmp_path / "depth.tum"), read_tum(tmp_path / "clouds.tum")
    np.testing.assert_array_equal(a.timestamps, b.timestamps)
    assert np.max(np.abs(a.poses - b.poses)) < 1e-9
    # And the poses are right: re-based truth, sub-millimetre.
    table = evaluate(a, Trajectory(a.timestamps, sim.T_sensor_target), rebase_first=True)
    assert max(table.to_dict()["mean"][k] for k in ("x_mm", "y_mm", "z_mm")) < 1.0


def test_tum_layout_with_intrinsics_option(folders, tmp_path, capsys):
    """TUM RGB-D's layout: depth.txt lists 'timestamp path'; intrinsics given on the command
    line (the folder has none)."""
    tum_dir = tmp_path / "rgbd"
    (tum_dir / "depth").mkdir(parents=True)
    lines = ["# timestamp filename"]
    for k, png in enumerate(sorted(folders["depth"].glob("*.png"))):
        stamp = f"{1305031102.0 + 0.033 * k:.6f}"
        (tum_dir / "depth" / f"{stamp}.png").write_bytes(png.read_bytes())
        lines.append(f"{stamp} depth/{stamp}.png")
    (tum_dir / "depth.txt").write_text("\n".join(lines) + "\n")
    out = tmp_path / "tum.tum"
    args = ["track", str(tum_dir), "--out", str(out), "--no-mls"]
    assert main(args) == 1
    assert "give --intrinsics" in capsys.readouterr().err
    intrinsics = str(folders["depth"] / "intrinsics.yaml")
    assert main([*args, "--intrinsics", intrinsics]) == 0, capsys.readouterr().err
    est = read_tum(out)
    np.testing.assert_allclose(est.timestamps, 1305031102.0 + 0.033 * np.arange(N_FRAMES))
    track_folder(folders["depth"], tmp_path / "ref.tum", tracker_config(mls=False))
    assert np.max(np.abs(est.poses - read_tum(tmp_path / "ref.tum").poses)) < 1e-9


def test_a_ros_camera_info_file_tracks_like_our_intrinsics(folders, camera, tmp_path):
    """The same depth folder with ROS's camera_info YAML as its intrinsics (our depth_scale
    beside it: the units are 0.1 mm): the same poses, bit for bit."""
    ros_dir = tmp_path / "ros"
    ros_dir.mkdir()
    for png in sorted(folders["depth"].glob("*.png")):
        (ros_dir / png.name).write_bytes(png.read_bytes())
    K = [camera.fx, 0, camera.cx, 0, camera.fy, camera.cy, 0, 0, 1]
    (ros_dir / "intrinsics.yaml").write_text(
        f"image_width: {camera.width}\nimage_height: {camera.height}\ncamera_name: tof\n"
        f"camera_matrix: {{rows: 3, cols: 3, data: {K!r}}}\ndistortion_model: plumb_bob\n"
        f"distortion_coefficients: {{rows: 1, cols: 5, data: [0, 0, 0, 0, 0]}}\n"
        f"depth_scale: {DEPTH_SCALE!r}\n"
    )
    (ros_dir / "timestamps.txt").write_bytes((folders["depth"] / "timestamps.txt").read_bytes())
    config = tracker_config(mls=False)
    ros = track_folder(ros_dir, tmp_path / "ros.tum", config)
    ours = track_folder(folders["depth"], tmp_path / "ours.tum", config)
    assert ros["frames"] == ours["frames"] == N_FRAMES and ros["lost"] == 0
    np.testing.assert_array_equal(
        read_tum(tmp_path / "ros.tum").poses, read_tum(tmp_path / "ours.tum").poses
    )


def test_hidden_files_are_not_frames(folders, tmp_path):
    """A folder copied from macOS holds ``._NAME`` resource forks beside each frame, and
    ``.DS_Store``: they are not frames, in a depth folder or a cloud folder."""
    for kind in ("depth", "clouds"):
        copy = tmp_path / kind
        copy.mkdir()
        for path in sorted(folders[kind].iterdir()):
            (copy / path.name).write_bytes(path.read_bytes())
            if path.name != "timestamps.txt":
                (copy / f"._{path.name}").write_bytes(b"\x00\x05\x16\x07" + bytes(80))
        (copy / ".DS_Store").write_bytes(bytes(64))
        frames = open_frames(copy)
        assert len(frames) == N_FRAMES
        assert not any(p.name.startswith(".") for p in frames.paths)


def test_cloud_files_in_a_depth_folder_are_named_not_dropped_silently(folders, tmp_path):
    """A .ply beside the depth images is no frame of a depth folder: said once, by name;
    TUM's text lists beside them are no clouds and say nothing."""
    copy = tmp_path / "depth"
    copy.mkdir()
    for path in folders["depth"].iterdir():
        (copy / path.name).write_bytes(path.read_bytes())
    (copy / "rgb.txt").write_text("# timestamp filename\n")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        assert len(open_frames(copy)) == N_FRAMES
    assert not [w for w in caught if issubclass(w.category, SpaceposeWarning)]
    (copy / "extra.ply").write_bytes(b"ply\n")
    with pytest.warns(
        SpaceposeWarning, match=r"1 point cloud file\(s\) \(extra\.ply\) are not read"
    ):
        assert len(open_frames(copy)) == N_FRAMES


def test_bad_depth_image_is_lost_with_its_reason(folders, tmp_path):
    bad = tmp_path / "bad"
    bad.mkdir()
    for p in folders["depth"].glob("*.png"):
        (bad / p.name).write_bytes(p.read_bytes())
    (bad / "0002.png").write_bytes((bad / "0002.png").read_bytes()[:5000])  # truncated
    (bad / "intrinsics.yaml").write_text((folders["depth"] / "intrinsics.yaml").read_text())
    frames = list(open_frames(bad))
    assert [f.cloud is None for f in frames] == [k == 2 for k in range(N_FRAMES)]
    assert "0002.png" in frames[2].error and "cannot decode" in frames[2].error


def test_numpy_depth_maps_read_as_their_images(folders, camera, tmp_path):
    """Depth maps saved as arrays, as renderers write them: the PNGs' units as uint16 give the
    same points bit for bit; float32 metres with NaN and inf for no return, the same points
    to float32's rounding; the folder's intrinsics make .npy files depth maps (the cloud
    folder, .npy without intrinsics, stays clouds)."""
    units_dir, metres_dir = tmp_path / "units", tmp_path / "metres"
    units_dir.mkdir(), metres_dir.mkdir()
    for png in sorted(folders["depth"].glob("*.png")):
        units = read_depth_image(png)
        np.save(units_dir / f"{png.stem}.npy", units)
        metres = (units * DEPTH_SCALE).astype(np.float32)
        metres[units == 0] = np.nan
        metres[0, 0] = np.inf  # a renderer's miss: no return, whatever the pixel
        np.save(metres_dir / f"{png.stem}.npy", metres)
    intrinsics = (folders["depth"] / "intrinsics.yaml").read_text()
    (units_dir / "intrinsics.yaml").write_text(intrinsics)
    (metres_dir / "intrinsics.yaml").write_text(
        intrinsics.replace(f"depth_scale: {DEPTH_SCALE!r}", "depth_scale: 1.0")
    )
    reference = [f.cloud.points for f in open_frames(folders["depth"])]
    for k, frame in enumerate(open_frames(units_dir)):
        np.testing.assert_array_equal(frame.cloud.points, reference[k])
    for k, frame in enumerate(open_frames(metres_dir)):
        assert frame.error is None and len(frame.cloud) == len(reference[k])
        assert np.max(np.abs(frame.cloud.points - reference[k])) < 1e-6
    # A 3-D array is not a depth map: that frame is lost with its reason, the rest read.
    np.save(units_dir / "0001.npy", np.zeros((2, 3, 4), dtype=np.uint16))
    (units_dir / "0003.npy").write_bytes(b"not numpy at all")
    frames = list(open_frames(units_dir))
    assert [f.cloud is None for f in frames] == [k in (1, 3) for k in range(N_FRAMES)]
    assert "0001.npy" in frames[1].error and "2-D integer or float array" in frames[1].error
    error = frames[3].error
    # Said once: the path, then the problem (".npy" twice: the name and the problem's).
    assert error.endswith("/0003.npy: not a .npy file (no NumPy header)")
    assert error.count(".npy") == 2
    assert all(isinstance(f.cloud.points, np.ndarray) for f in open_frames(folders["clouds"]))


@pytest.mark.parametrize("odd", [0, 3])
def test_an_image_of_another_size_is_lost_when_the_intrinsics_give_none(folders, tmp_path, odd):
    """Intrinsics without width and height: the size most of the sequence's images have is
    the camera's, and a frame of another size (another stream's), first or not, is lost with
    its reason, not back-projected with the wrong principal point."""
    mixed = tmp_path / "mixed"
    mixed.mkdir()
    for p in folders["depth"].glob("*.png"):
        (mixed / p.name).write_bytes(p.read_bytes())
    name = f"{odd:04d}.png"
    half = read_depth_image(mixed / name)[::2, ::2]
    write_depth_image(mixed / name, half * DEPTH_SCALE, DEPTH_SCALE)
    lines = (folders["depth"] / "intrinsics.yaml").read_text().splitlines()
    sizeless = [line for line in lines if not line.startswith(("width", "height"))]
    assert len(sizeless) == len(lines) - 2
    (mixed / "intrinsics.yaml").write_text("\n".join(sizeless) + "\n")
    frames = list(open_frames(mixed))
    assert [f.cloud is None for f in frames] == [k == odd for k in range(N_FRAMES)]
    h, w = half.shape
    assert f"image is {w}x{h}, the intrinsics say {2 * w}x{2 * h}" in frames[odd].error


def test_depth_folder_without_intrinsics(folders, tmp_path):
    with pytest.raises(InputError, match=r"0000\.npy holds points, an \(\d+, 3\) array"):
        open_frames(folders["clouds"], intrinsics=folders["depth"] / "intrinsics.yaml")
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(InputError, match="no depth images"):
        open_frames(empty, intrinsics=folders["depth"] / "intrinsics.yaml")


def test_register_takes_depth_images(sim, camera, tmp_path, capsys):
    """`spacepose register` on two 16-bit PNG depth frames gives what it gives on their clouds,
    and lands within 2 mm / 0.2° of the simulator's relative pose of frames 0 and 3."""
    import json

    from spacepose.core import se3
    from spacepose.tools.depth_io import read_depth_cloud
    from spacepose.tools.register_io import register_files

    paths = []
    for k in (0, 3):
        image = render_depth(sim.frame(k).cloud.points, camera, camera.height, camera.width)
        paths.append(write_depth_image(tmp_path / f"{k}.png", image, DEPTH_SCALE))
    (tmp_path / "intrinsics.yaml").write_text(
        "".join(f"{k}: {v}\n" for k, v in camera.model_dump().items() if v is not None)
    )
    out = tmp_path / "result.json"
    assert main(["register", str(paths[1]), str(paths[0]), "--out", str(out)]) == 0, (
        capsys.readouterr().err
    )
    T = np.array(json.loads(out.read_text())["T_target_source"])
    clouds = [read_depth_cloud(p, camera) for p in paths]
    for k, cloud in enumerate(clouds):
        np.save(tmp_path / f"{k}.npy", cloud.points)
    same = register_files(tmp_path / "1.npy", tmp_path / "0.npy").result.T_target_source
    np.testing.assert_allclose(T, same, atol=1e-12)
    truth = sim.frame(0).T_sensor_target @ se3.invert(sim.frame(3).T_sensor_target)
    D = T @ se3.invert(truth)
    assert np.linalg.norm(D[:3, 3]) < 2e-3
    assert np.degrees(np.arccos(np.clip((np.trace(D[:3, :3]) - 1) / 2, -1, 1))) < 0.2
    # Without intrinsics beside the image or on the command line: one line naming the file.
    (tmp_path / "intrinsics.yaml").unlink()
    assert main(["register", str(paths[1]), str(paths[0])]) == 1
    assert "needs --intrinsics" in capsys.readouterr().err


def test_two_intrinsics_files_in_one_folder_are_refused(folders, tmp_path, capsys):
    """intrinsics.yaml (the right camera) beside an intrinsics.json of another: one was taken
    by a rule the user could not see, and the run went on (exit 0). Refused, naming both."""
    copy = tmp_path / "depth"
    copy.mkdir()
    for path in sorted(folders["depth"].iterdir()):
        (copy / path.name).write_bytes(path.read_bytes())
    (copy / "intrinsics.json").write_text('{"fx": 10, "fy": 10, "cx": 31.5, "cy": 23.5}')
    with pytest.raises(InputError, match=r"2 intrinsics files \(intrinsics.yaml, intrinsics.j"):
        open_frames(copy)
    assert main(["track", str(copy), "--out", str(tmp_path / "e.tum")]) == 1
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "keep one" in err and str(copy) in err, err


def test_intrinsics_for_point_clouds_are_refused_not_ignored(sim, folders, tmp_path, capsys):
    """--intrinsics with a run folder (track, navigate) or with two cloud files (register) was
    ignored without a word: the user believed the clouds were read through them."""
    from spacepose.tools.runs import write_run

    intrinsics = str(folders["depth"] / "intrinsics.yaml")
    run = write_run(tmp_path / "run", simulate(scenario_config("lab", frames=2)))
    with pytest.raises(InputError, match="run: intrinsics apply to depth images, and this is a"):
        open_frames(run, intrinsics=intrinsics)
    # Refused before the file is read: a cloud given as intrinsics was "not UTF-8" first.
    with pytest.raises(InputError, match="run: intrinsics apply to depth images, and this is a"):
        open_frames(run, intrinsics=run / "frames" / "000000.ply")
    assert (
        main(["track", str(run), "--out", str(tmp_path / "e.tum"), "--intrinsics", intrinsics]) == 1
    )
    assert "leave out --intrinsics" in capsys.readouterr().err
    assert not (tmp_path / "e.tum").exists()
    frames = [str(run / "frames" / f"00000{k}.ply") for k in (0, 1)]
    assert main(["register", *frames, "--intrinsics", intrinsics]) == 1
    err = capsys.readouterr().err.strip()
    assert err.endswith(
        "intrinsics.yaml: intrinsics apply to depth images (.png, .tif, .tiff, .exr), and neither "
        "000000.ply nor 000001.ply is one: leave out --intrinsics"
    ), err


def test_exr_depth_maps_with_a_far_plane_read_as_their_images(folders, tmp_path):
    """A renderer's float EXR depth (Blender's depth pass: metres, 1e10 where nothing is hit)
    gives the PNGs' points to float32's rounding, and tracks as the same maps with 0 for no
    return, to the bit. Its background used to be read as points 1e10 m out: the cloud spread
    over 1e10 m and the poses moved by 0.2 mm."""
    intrinsics = (folders["depth"] / "intrinsics.yaml").read_text()
    stamps = (folders["depth"] / "timestamps.txt").read_text()
    for background in ("far", "zero"):
        (tmp_path / background).mkdir()
        for png in sorted(folders["depth"].glob("*.png")):
            metres = (read_depth_image(png) * DEPTH_SCALE).astype(np.float32)
            metres[metres == 0] = 1e10 if background == "far" else 0.0
            write_depth_image(tmp_path / background / f"{png.stem}.exr", metres, depth_scale=1.0)
        (tmp_path / background / "intrinsics.yaml").write_text(
            intrinsics.replace(f"depth_scale: {DEPTH_SCALE!r}", "depth_scale: 1.0")
        )
        (tmp_path / background / "timestamps.txt").write_text(stamps)
    reference = [f.cloud.points for f in open_frames(folders["depth"])]
    with pytest.warns(SpaceposeWarning, match=r"0000.exr: a renderer's far plane, read as no re"):
        frames = list(open_frames(tmp_path / "far"))
    for k, frame in enumerate(frames):
        assert frame.error is None and len(frame.cloud) == len(reference[k])
        assert np.max(np.abs(frame.cloud.points - reference[k])) < 1e-6
    config = tracker_config()
    with pytest.warns(SpaceposeWarning, match="far plane"):
        track_folder(tmp_path / "far", tmp_path / "far.tum", config)
    with warnings.catch_warnings():
        warnings.simplefilter("error", SpaceposeWarning)
        track_folder(tmp_path / "zero", tmp_path / "zero.tum", config)
    track_folder(folders["depth"], tmp_path / "png.tum", config)
    far, zero = read_tum(tmp_path / "far.tum"), read_tum(tmp_path / "zero.tum")
    np.testing.assert_array_equal(far.poses, zero.poses)
    # float32 metres put points on other sides of voxel edges than 0.1 mm units: 0.03 mm.
    assert np.max(np.abs(far.poses - read_tum(tmp_path / "png.tum").poses)) < 1e-4
