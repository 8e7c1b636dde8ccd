"""Bags found wrong by the 21st hostile round: intrinsics given beside a bag's CameraInfo,
an explicit depth_scale, first messages without a header stamp, CameraInfo binning and ROI.
Each was silently wrong (or every frame lost) before."""

from __future__ import annotations

import re
import warnings
from pathlib import Path

import numpy as np
import pytest

from spacepose.cli import main
from spacepose.core.depth import DepthCamera
from spacepose.errors import InputError, SpaceposeWarning
from spacepose.tools.bag_camera import camera_from_info
from spacepose.tools.bag_io import open_bag
from spacepose.tools.frames import open_frames
from spacepose.tools.intrinsics_io import read_intrinsics
from test_bag_io import IMAGE, INFO, PC2, ROS2, _image, _pointcloud2, _restamped, _write

# The bag's camera: a 32 x 24 depth image, fx 30, centred.
CAMERA = DepthCamera(fx=30.0, fy=30.0, cx=15.5, cy=11.5, width=32, height=24)


def _plane(height: int = 24, width: int = 32, k: int = 0) -> np.ndarray:
    """A tilted plane about 1.2 m away (metres, every pixel a return)."""
    yy, xx = np.mgrid[:height, :width]
    return 1.2 + 0.01 * xx + 0.005 * yy + 0.01 * k


def _info(
    camera: DepthCamera,
    binning: tuple[int, int] = (0, 0),
    roi: tuple[int, int, int, int] = (0, 0, 0, 0),
    d: tuple[float, ...] = (0.0,) * 5,
):
    """A ROS 2 CameraInfo of ``camera`` (full-resolution K and size), with its binning and
    ROI (x_offset, y_offset, width, height)."""
    T = ROS2.types
    K = np.array([camera.fx, 0, camera.cx, 0, camera.fy, camera.cy, 0, 0, 1.0])
    header = T["std_msgs/msg/Header"](
        stamp=T["builtin_interfaces/msg/Time"](sec=1_700_000_000, nanosec=0), frame_id="tof"
    )
    x, y, w, h = roi
    return T[INFO](
        header=header, height=camera.height, width=camera.width,
        distortion_model="plumb_bob", d=np.array(d), k=K, r=np.eye(3).ravel(), p=np.zeros(12),
        binning_x=binning[0], binning_y=binning[1],
        roi=T["sensor_msgs/msg/RegionOfInterest"](
            x_offset=x, y_offset=y, height=h, width=w, do_rectify=False
        ),
    )  # fmt: skip


def _depth_bag(path: Path, info, depth_m: np.ndarray, per_metre: float = 1000.0) -> Path:
    """A bag of a CameraInfo (if any) and two 16UC1 images of ``depth_m`` in units of
    1 / ``per_metre``."""
    messages = [] if info is None else [("/cam/camera_info", INFO, info)]
    for k in range(2):
        units = np.rint(depth_m * per_metre).astype(np.uint16)
        messages.append(("/cam/depth", IMAGE, _image(ROS2, k, units)))
    return _write(path, messages)


def _back_projected(camera: DepthCamera, depth_m: np.ndarray) -> np.ndarray:
    """The (H * W, 3) points of a map whose every pixel is a return, row by row."""
    v, u = np.mgrid[: depth_m.shape[0], : depth_m.shape[1]]
    x = (u - camera.cx) / camera.fx * depth_m
    y = (v - camera.cy) / camera.fy * depth_m
    return np.column_stack([x.ravel(), y.ravel(), depth_m.ravel()])


# -- F2: --intrinsics beside the bag's CameraInfo ------------------------------------------------


def test_intrinsics_that_differ_from_the_bags_camera_info_are_refused(tmp_path, capsys):
    """A file of fx 45 won over the bag's CameraInfo of fx 30 without a word (frames ok at
    5-6.5 sigma); a depth folder refuses the same conflict."""
    depth = np.rint(_plane() * 1000) / 1000
    bag = _depth_bag(tmp_path / "bag", _info(CAMERA), depth)
    other = tmp_path / "other.yaml"
    other.write_text("fx: 45\nfy: 45\ncx: 15.5\ncy: 11.5\n")
    out = tmp_path / "est.tum"
    assert main(["track", str(bag), "--intrinsics", str(other), "--out", str(out)]) == 1
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "Traceback" not in err, err
    assert "CameraInfo on /cam/camera_info differ (fx 45 vs 30, fy 45 vs 30)" in err
    assert not out.exists()
    with pytest.raises(InputError) as exc:
        open_bag(bag, camera=read_intrinsics(other), intrinsics=other)
    assert str(exc.value) == (
        f"{bag}: --intrinsics {other} and the bag's CameraInfo on /cam/camera_info differ "
        "(fx 45 vs 30, fy 45 vs 30): keep one (leave out --intrinsics to use the bag's)"
    )
    # The distortion and the size are the camera's too.
    for text, said in [
        ("k1: -0.1\n", "(k1 -0.1 vs 0)"),
        ("width: 32\nheight: 25\n", "(height 25 vs 24)"),
    ]:
        other.write_text("fx: 30\nfy: 30\ncx: 15.5\ncy: 11.5\n" + text)
        with pytest.raises(InputError, match=re.escape(f"differ {said}: keep one")):
            open_frames(bag, intrinsics=other)
    # Agreeing, the file is used (sized by the CameraInfo): the bag's own points.
    same = tmp_path / "same.yaml"
    same.write_text("fx: 30.0\nfy: 30.0\ncx: 15.5\ncy: 11.5\n")
    frames = open_frames(bag, intrinsics=same)
    assert (frames.camera.fx, frames.camera.width, frames.camera.height) == (30.0, 32, 24)
    first = next(iter(frames))
    np.testing.assert_allclose(first.cloud.points, _back_projected(CAMERA, depth), atol=1e-9)
    # Without a CameraInfo, the file stands alone.
    alone = _depth_bag(tmp_path / "alone", None, depth)
    other.write_text("fx: 45\nfy: 45\ncx: 15.5\ncy: 11.5\n")
    frames = open_frames(alone, intrinsics=other)
    assert (frames.camera.fx, frames.camera.width) == (45.0, None)
    wide = CAMERA.model_copy(update={"fx": 45.0, "fy": 45.0})
    first = next(iter(frames))
    np.testing.assert_allclose(first.cloud.points, _back_projected(wide, depth), atol=1e-9)


def test_an_explicit_depth_scale_wins_over_the_encodings(tmp_path):
    """A 16UC1 bag in quarter-millimetres with depth_scale 0.00025 in the intrinsics was read
    at the encoding's 0.001 m per unit: the target 4 times too far, ok at 85-91 sigma."""
    depth = np.rint(_plane() * 4000) / 4000
    bag = _depth_bag(tmp_path / "q4", _info(CAMERA), depth, per_metre=4000.0)
    given = tmp_path / "q4.yaml"
    given.write_text("fx: 30\nfy: 30\ncx: 15.5\ncy: 11.5\ndepth_scale: 0.00025\n")
    frames = open_frames(bag, intrinsics=given)
    assert frames.camera.depth_scale == 0.00025
    clouds = [f.cloud for f in frames]
    # Pixel (0, 0): 1.2 m; the far corner (31, 23): 1.2 + 0.31 + 0.115 m.
    assert clouds[0].points[0, 2] == pytest.approx(1.2, abs=1e-12)
    assert clouds[0].points[-1, 2] == pytest.approx(1.625, abs=1e-12)
    np.testing.assert_allclose(clouds[1].points, _back_projected(CAMERA, depth), atol=1e-9)
    # Left out, the encoding's unit (millimetres) is the CameraInfo's: 4 times too far.
    frames = open_frames(bag)
    assert frames.camera.depth_scale is None
    assert next(iter(frames)).cloud.points[0, 2] == pytest.approx(4.8, abs=1e-12)


# -- F4: first messages without a header stamp ---------------------------------------------------


def test_record_times_for_unstamped_first_messages_are_said(tmp_path):
    """Three messages stamped 0, then three stamped: every frame, the stamped ones too, was
    timed by its record time without a word."""
    rng = np.random.default_rng(21)
    grid = (rng.normal(size=(6, 8, 3)) * 0.05 + [0.0, 0.0, 1.2]).astype(np.float32)
    messages = [("/pts", PC2, _pointcloud2(ROS2, k, grid)) for k in range(6)]
    for k in range(3):
        _restamped(messages[k][2], 0, 0)
    bag = _write(tmp_path / "z3", messages)
    said = (
        f"{bag}: the first messages on /pts have no header stamp (0): every frame is timed by "
        "its record time (when the bag wrote it, after the driver's and transport's latency), "
        "any stamped later ones too"
    )
    with pytest.warns(SpaceposeWarning) as caught:
        frames = open_bag(bag)
    assert [str(w.message) for w in caught] == [said]
    # _write's record times, 1 s on, 0.1 s apart; the stamps of 3-5 (1.7e9 s) not used.
    times = [f.timestamp for f in frames]
    np.testing.assert_allclose(times, [1.0, 1.1, 1.2, 1.3, 1.4, 1.5], atol=1e-12)
    stamped = [("/pts", PC2, _pointcloud2(ROS2, k, grid)) for k in range(4)]
    with warnings.catch_warnings():
        warnings.simplefilter("error", SpaceposeWarning)
        open_bag(_write(tmp_path / "stamped", stamped))


# -- F5: CameraInfo binning and ROI --------------------------------------------------------------


def test_camera_info_binning_and_roi_give_the_images_camera(tmp_path, capsys):
    """K and the size of a CameraInfo are the full sensor's, the image its ROI binned: a
    2 x 2 binned bag lost every frame ("image is 32x24, the intrinsics say 64x48")."""
    sensor = DepthCamera(fx=60.0, fy=64.0, cx=31.5, cy=23.5, width=64, height=48)
    # The binned bag's frames: every one read, at the binned camera's points.
    depth = np.rint(_plane() * 1000) / 1000
    bag = _depth_bag(tmp_path / "bin2", _info(sensor, binning=(2, 2)), depth)
    frames = list(open_bag(bag))
    assert [f.error for f in frames] == [None, None]
    binned = camera_from_info(_info(sensor, binning=(2, 2)))
    assert (binned.fx, binned.fy, binned.cx, binned.cy) == (30.0, 32.0, 15.75, 11.75)
    assert (binned.width, binned.height, binned.depth_scale) == (32, 24, None)
    np.testing.assert_allclose(frames[0].cloud.points, _back_projected(binned, depth), atol=1e-9)
    # A ROI: the offsets shift the principal point, then the binning scales it.
    cut = camera_from_info(_info(sensor, roi=(8, 4, 32, 24)))
    assert (cut.fx, cut.fy, cut.cx, cut.cy, cut.width, cut.height) == (
        60.0, 64.0, 23.5, 19.5, 32, 24
    )  # fmt: skip
    both = camera_from_info(_info(sensor, binning=(2, 4), roi=(8, 8, 48, 32)))
    assert (both.fx, both.fy, both.cx, both.cy, both.width, both.height) == (
        30.0, 16.0, 11.75, 3.875, 24, 8
    )  # fmt: skip
    # Intrinsics of the full sensor given for it: refused, the binning named.
    full = tmp_path / "full.yaml"
    full.write_text("fx: 60\nfy: 64\ncx: 31.5\ncy: 23.5\n")
    out = str(tmp_path / "e.tum")
    assert main(["track", str(bag), "--intrinsics", str(full), "--out", out]) == 1
    err = capsys.readouterr().err.strip()
    assert (
        "CameraInfo on /cam/camera_info (binning 2x2 applied) differ (fx 60 vs 30, fy 64 vs "
        "32, cx 31.5 vs 15.75, ...): keep one" in err
    ), err
    # A ROI reaching past the sensor is the CameraInfo's fault, said once.
    bad = _depth_bag(tmp_path / "bad", _info(sensor, roi=(40, 0, 32, 24)), depth)
    with pytest.raises(InputError) as exc:
        open_bag(bad)
    assert str(exc.value) == (
        f"{bad}: CameraInfo on /cam/camera_info: roi 32x24 at (40, 0) reaches past the 64x48 sensor"
    )
