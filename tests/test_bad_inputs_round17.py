"""Inputs found by a seventeenth hostile round: each written, read or refused as it should be."""

from __future__ import annotations

import json
import math
import warnings

import numpy as np
import pytest
from PIL import Image

from spacepose.core.cloud import PointCloud
from spacepose.core.config import load_config
from spacepose.core.depth import DepthCamera
from spacepose.core.ransac import RansacConfig, iteration_bound
from spacepose.core.tracker import TrackerConfig
from spacepose.errors import ConfigError, InputError, SpaceposeWarning
from spacepose.tools.cloud_io import read_cloud, write_cloud
from spacepose.tools.depth_io import read_depth_cloud
from spacepose.tools.frames import open_frames


def _strict(text: str) -> object:
    """``text`` parsed as strict JSON: a bare NaN or Infinity token raises."""

    def refuse(token: str) -> object:
        raise ValueError(f"non-standard JSON token {token}")

    return json.loads(text, parse_constant=refuse)


def _plane_png(path, width: int = 64, height: int = 48, units: int = 1200) -> None:
    """A 16-bit depth map of a wall ``units`` stored units in front of the camera."""
    Image.fromarray(np.full((height, width), units, dtype=np.uint16)).save(path)


# -- 4. A principal point with cx and cy swapped -------------------------------------------------


def test_swapped_principal_point_of_a_sized_camera_is_warned_of(tmp_path):
    """``cx: 239.5, cy: 319.5, width: 640, height: 480`` was taken without a word (13 % and
    17 % of the image off centre, under the one-fifth check, which intrinsics with a size
    skipped): a model-based track 264 mm off. Now the folder's intrinsics file is named in a
    warning that says "cx and cy swapped?"; the right point gives none. Here at 64 x 48."""
    for k in range(2):
        _plane_png(tmp_path / f"{k:06d}.png")
    intrinsics = tmp_path / "intrinsics.yaml"
    sized = "fx: 50\nfy: 50\n{}\nwidth: 64\nheight: 48\ndepth_scale: 0.001\n"
    intrinsics.write_text(sized.format("cx: 23.5\ncy: 31.5"))
    with pytest.warns(
        SpaceposeWarning,
        match=r"intrinsics\.yaml: the principal point \(23\.5, 31\.5\) is the centre of a 48x64 "
        r"image, not of this 64x48 one: cx and cy swapped\?",
    ):
        open_frames(tmp_path)
    intrinsics.write_text(sized.format("cx: 31.5\ncy: 23.5"))
    with warnings.catch_warnings():
        warnings.simplefilter("error", SpaceposeWarning)
        open_frames(tmp_path)


def test_off_centre_principal_point_is_warned_of_when_a_size_is_given(tmp_path):
    """The one-fifth-of-the-image check ran only for intrinsics without a size: a principal
    point 45 % of the width off centre, with ``width`` and ``height`` given, passed unsaid.
    Now it is warned of at the size given."""
    for k in range(2):
        _plane_png(tmp_path / f"{k:06d}.png")
    (tmp_path / "intrinsics.yaml").write_text(
        "fx: 50\nfy: 50\ncx: 60\ncy: 23.5\nwidth: 64\nheight: 48\ndepth_scale: 0.001\n"
    )
    with pytest.warns(
        SpaceposeWarning,
        match=r"intrinsics\.yaml: the principal point lies far from the image's centre: "
        r"intrinsics of another resolution\? \(\(60, 23\.5\) in a 64x48 image\)",
    ):
        open_frames(tmp_path)


def test_swap_check_spares_a_real_off_centre_lens():
    """The hostile round's 640 x 480 numbers are called swapped; a lens's own offset (an Azure
    Kinect's depth camera, 640 x 576, principal point some 50 px below the centre) and a
    principal point a few pixels off are not."""
    from spacepose.tools.intrinsics_io import principal_point_problem

    swapped = DepthCamera(fx=483.6, fy=483.6, cx=239.5, cy=319.5, width=640, height=480)
    assert "cx and cy swapped?" in (principal_point_problem(swapped, 640, 480) or "")
    kinect = DepthCamera(fx=504.0, fy=504.0, cx=319.3, cy=339.1, width=640, height=576)
    assert principal_point_problem(kinect, 640, 576) is None
    near = DepthCamera(fx=483.6, fy=483.6, cx=325.0, cy=236.0, width=640, height=480)
    assert principal_point_problem(near, 640, 480) is None


# -- 5. Experiments write strict JSON ------------------------------------------------------------


def test_robustness_writes_null_for_non_finite_numbers(tmp_path, monkeypatch):
    """``experiment robustness`` wrote ``"crlb_t_mm": NaN`` into robustness.json and
    robustness_runs.jsonl, which strict JSON parsers refuse (campaign wrote null). Now both
    hold null for NaN and inf (NumPy's too); the tracking is replaced by a record of those."""
    from spacepose.tools.experiments import robustness

    record = {
        "cell": {"target": "box", "range": 5.0},
        "crlb_t_mm": math.nan,
        "err_t_mm": np.float64(math.nan),
        "ms": np.float64(math.inf),
        "share": [0.5, math.nan],
        "frames": [{"frame": 0}],
    }
    monkeypatch.setattr(robustness, "warm_up", lambda workers=1: None)
    monkeypatch.setattr(robustness, "run_cell", lambda *args, **kwargs: dict(record))
    log = tmp_path / "robustness_runs.jsonl"
    records = robustness.run_cells([object()], frames=2, jobs=1, workers=1, log=log)
    line = _strict(log.read_text().splitlines()[0])
    assert line["crlb_t_mm"] is None and line["err_t_mm"] is None and line["ms"] is None
    assert line["share"] == [0.5, None]
    # The table, its Markdown and figure are another matter: the JSON's writer alone.
    monkeypatch.setattr(robustness, "cell_table", lambda records: [])
    monkeypatch.setattr(robustness, "markdown_table", lambda table: "")
    monkeypatch.setattr(robustness, "summary_figure", lambda table: None)
    monkeypatch.setattr(robustness.plots, "figure_png", lambda figure: b"")
    robustness.write_outputs(tmp_path, records, frames=2, frames_csv=False)
    text = (tmp_path / "robustness.json").read_text()
    assert "NaN" not in text and "Infinity" not in text
    assert _strict(text)["runs"][0]["crlb_t_mm"] is None


def test_strict_json_keeps_finite_numbers_and_nulls_the_rest():
    """The shared writer (bench, every experiment): finite values as they were, NumPy's as
    Python's, non-finite ones null, and nothing a strict parser refuses."""
    from spacepose.tools.text_io import strict_json

    value = {"a": [1, 2.5, np.int64(3)], "b": (math.nan, -math.inf), "c": np.float32(0.25)}
    assert _strict(strict_json(value)) == {"a": [1, 2.5, 3], "b": [None, None], "c": 0.25}


# -- 6. ransac.max_iterations is bounded ---------------------------------------------------------


def test_ransac_max_iterations_has_an_upper_bound(tmp_path):
    """``ransac: {max_iterations: 1000000000000}`` was accepted, and the first model-based
    frame ran for hours (killed by a 100 s timeout). Now a config past 10⁷ is a ConfigError
    naming the field; 10⁷ still covers the confidence stop at a 1 % inlier ratio."""
    config = tmp_path / "hang.yaml"
    config.write_text("ransac:\n  max_iterations: 1000000000000\n")
    with pytest.raises(
        ConfigError,
        match=r"hang\.yaml: invalid tracker config: ransac\.max_iterations: .*less than or "
        r"equal to 10000000",
    ):
        load_config(TrackerConfig, config)
    most = RansacConfig(max_iterations=10_000_000).max_iterations
    assert iteration_bound(0.01, RansacConfig().confidence) < most
    assert iteration_bound(0.01, 0.9999) < most


# -- 7. A depth_scale no sensor's depths can have --------------------------------------------------


@pytest.mark.parametrize(
    ("scale", "depth", "side"),
    [
        (1e-300, r"1\.2e-297", "nearer"),
        (1e-8, r"1\.2e-05", "nearer"),
        (1000, r"1\.2e\+06", "farther"),
    ],
)
def test_an_absurd_depth_scale_is_refused_naming_it(tmp_path, scale, depth, side):
    """depth_scale 1e-300, 1e-8 and 1000 ended in "all points lie on a line" or "the surface
    is degenerate", naming neither the unit nor the depth (1e-8 behind a warning buried among
    others). Now the frame is refused in one line naming the file, the depth in metres
    and the depth_scale."""
    path = tmp_path / "d.png"
    _plane_png(path, 32, 24)
    camera = DepthCamera(fx=30.0, fy=30.0, cx=15.5, cy=11.5, depth_scale=scale)
    where = "farthest 1 % of the returns lie within" if side == "nearer" else "nearest 1 % of "
    where += "" if side == "nearer" else "the returns lie beyond"
    with pytest.raises(
        InputError,
        match=rf"d\.png: the {where} {depth} m, {side} than any ToF "
        rf"camera or flash LiDAR ranges: the depths are in another unit\? check depth_scale in "
        rf"the intrinsics \({scale:g} m per stored unit\)",
    ):
        read_depth_cloud(path, camera)


def test_a_render_with_the_earth_far_behind_its_target_is_not_refused(tmp_path):
    """A renderer's frame of a target 50 m away before the Earth's limb 200-230 km behind it,
    the Earth in 92 % of the pixels (float metres): its median depth is beyond 100 km, and a
    test of the median took the frame for another unit; its nearest returns are the target's."""
    from spacepose.tools.depth_io import depth_cloud

    values = np.linspace(2.0e5, 2.3e5, 24 * 32).reshape(24, 32)
    values[8:14, 10:20] = 50.0
    camera = DepthCamera(fx=30.0, fy=30.0, cx=15.5, cy=11.5, depth_scale=1.0)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")  # the spread reads as millimetres': said, not refused
        cloud = depth_cloud(values, camera, tmp_path / "f.npy", "check depth_scale")
    assert len(cloud) == 24 * 32 and np.sum(cloud.points[:, 2] < 51.0) == 60


def test_a_depth_scale_near_real_ranges_is_still_only_warned_of(tmp_path):
    """1e-6 (a wall 1.2 mm away, its returns 1.28 mm out in the median) was warned of, and
    tracked; it still is: the refusal starts below a millimetre."""
    path = tmp_path / "d.png"
    _plane_png(path, 32, 24)
    camera = DepthCamera(fx=30.0, fy=30.0, cx=15.5, cy=11.5, depth_scale=1e-6)
    with pytest.warns(SpaceposeWarning, match=r"d\.png: the returns lie 1\.28 mm from the sensor"):
        cloud = read_depth_cloud(path, camera)
    assert len(cloud) == 32 * 24


# -- Minor: write_cloud and per-point sigma -------------------------------------------------------


@pytest.mark.parametrize("suffix", [".ply", ".pcd", ".npz", ".xyz"])
def test_write_cloud_says_that_sigma_is_not_written(tmp_path, suffix):
    """A PointCloud's per-point sigma was dropped by every format without a word. It still is
    not written (no reader reads it back), and write_cloud now says so; the points are."""
    rng = np.random.default_rng(17)
    points = rng.uniform(-0.2, 0.2, (200, 3)) + np.array([0.0, 0.0, 1.2])
    cloud = PointCloud(points, sigma=np.full(200, 0.001))
    out = tmp_path / f"c{suffix}"
    with pytest.warns(SpaceposeWarning, match=rf"c\{suffix}: per-point sigma is not written"):
        write_cloud(out, cloud)
    np.testing.assert_allclose(read_cloud(out).points, points, atol=1e-6)
    with warnings.catch_warnings():
        warnings.simplefilter("error", SpaceposeWarning)
        write_cloud(tmp_path / f"plain{suffix}", points)


def test_plane_ransac_iterations_are_bounded_as_features_are():
    """``PlaneConfig(max_iterations=10**12)`` was taken as the features' RANSAC's was: the
    plane search has the same bound now, and names the field."""
    from spacepose.core.planes import PlaneConfig

    with pytest.raises(
        ConfigError, match=r"invalid plane config: max_iterations: .*less than or equal to 10000000"
    ):
        PlaneConfig(max_iterations=10**12)
    assert PlaneConfig(max_iterations=10**7).max_iterations == 10**7


def test_register_checks_a_single_depth_images_sized_intrinsics(tmp_path, capsys):
    """`register a.png b.png` with sized intrinsics whose cx and cy are swapped said nothing
    (a depth folder's are checked at their size; one image's were not). Now it warns as the
    folder does."""
    from spacepose.cli import main

    for name in ("a.png", "b.png"):
        _plane_png(tmp_path / name)
    (tmp_path / "intrinsics.yaml").write_text(
        "fx: 50\nfy: 50\ncx: 23.5\ncy: 31.5\nwidth: 64\nheight: 48\ndepth_scale: 0.001\n"
    )
    main(["register", str(tmp_path / "a.png"), str(tmp_path / "b.png")])
    assert "intrinsics.yaml: the principal point (23.5, 31.5) is the centre of a 48x64" in (
        capsys.readouterr().err
    )
