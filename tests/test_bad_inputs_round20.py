"""Twentieth hostile round: maps and inputs of other conventions, read without a word."""

from __future__ import annotations

import re

import numpy as np
import pytest
from PIL import Image

from spacepose.core.depth import DepthCamera
from spacepose.errors import InputError
from spacepose.tools.depth_io import read_depth_cloud

_CAMERA = DepthCamera(fx=60.0, fy=60.0, cx=31.5, cy=23.5)


def _box_depth(width: int = 64, height: int = 48) -> np.ndarray:
    """(H, W) depths in metres: a 0.3 m square 1.2 m away whose centre bulges 5 cm nearer,
    no return (0) around it."""
    z = np.zeros((height, width), dtype=np.float32)
    z[12:36, 20:44] = 1.2
    z[20:28, 28:36] = 1.15
    return z


def _z_buffer(z: np.ndarray, near: float = 0.1, far: float = 100.0) -> np.ndarray:
    """``z`` as an OpenGL renderer's normalised depth buffer: 1 where nothing was hit."""
    hit = np.where(z > 0, z, 1.0)
    return np.where(z > 0, (1 / near - 1 / hit) / (1 / near - 1 / far), 1.0).astype(np.float32)


def test_a_normalised_depth_buffer_is_refused(tmp_path):
    """A float TIFF holding a renderer's depth buffer (0.92 where the target is, 1 elsewhere)
    was read as metres: a wall 1 m away with a 2 mm relief, tracked without a word. It is now
    refused naming the file; the same scene in metres reads as before, and a map whose far
    plane at 1 m is declared with max_depth is read."""
    path = tmp_path / "000000.tiff"
    Image.fromarray(_z_buffer(_box_depth())).save(path)
    with pytest.raises(
        InputError,
        match=r"000000\.tiff: every value lies in \(0\.9.*1\] and "
        r"81 % are exactly 1: a renderer's normalised depth buffer",
    ):
        read_depth_cloud(path, _CAMERA)
    metres = tmp_path / "metres.tiff"
    Image.fromarray(_box_depth()).save(metres)
    cloud = read_depth_cloud(metres, _CAMERA)
    assert len(cloud) == 24 * 24
    assert np.isclose(cloud.points[:, 2].max(), 1.2)
    declared = read_depth_cloud(path, _CAMERA.model_copy(update={"max_depth": 0.999}))
    assert len(declared) == 24 * 24


def test_frames_in_feet_against_a_model_in_metres_say_the_units(tmp_path):
    """The lab run's frames in feet against its model in metres lost every frame as "fitness
    0.11 < 0.3", naming no unit. The run's reason now says the first frame is 3–4 times the
    model's size; frames in the model's unit are about its size (the lab's: 1.1-1.2)."""
    from spacepose.core.scale import rms_radius
    from spacepose.core.sim.scenarios import LabConfig, simulate_lab
    from spacepose.core.tracker import TrackerConfig
    from spacepose.tools.cloud_io import read_cloud, write_cloud
    from spacepose.tools.runs import write_run
    from spacepose.tools.tracking_io import track_folder

    run = write_run(tmp_path / "run", simulate_lab(LabConfig(frames=2, seed=0)))
    feet = tmp_path / "feet"
    feet.mkdir()
    for path in sorted((run / "frames").glob("*.ply")):
        write_cloud(feet / path.name, read_cloud(path).points * 3.28084)
    summary = track_folder(feet, tmp_path / "est.tum", TrackerConfig(), run / "model.ply", 1)
    assert summary["lost"] == summary["frames"] == 2
    assert re.search(
        r"the first frame is 3\.\d+ times the model's size .*feet are 3\.28 times metres",
        summary["first_lost"],
    )
    frame, model = read_cloud(run / "frames" / "000000.ply"), read_cloud(run / "model.ply")
    assert 1.0 < rms_radius(frame.points) / rms_radius(model.points) < 1.3


@pytest.mark.parametrize("method", ["icp", "gicp"])
def test_covariance_of_clouds_far_from_their_origin_is_the_near_one_moved(method):
    """Two lab frames registered where they are and 10 km and 100 km along x: the pose and the
    information moved as they must, but ``covariance()``'s pseudo-inverse of the far
    information gave a rotation σ of 1.3e-11 rad at 10 km where 1.4e-6 was right (and 1e-14 at
    7,000 km), without a word. It now inverts about the clouds' centre: the far covariance,
    moved back by the adjoint, is the near one."""
    from spacepose.core import se3
    from spacepose.core.gicp import gicp
    from spacepose.core.icp import ICPConfig, icp
    from spacepose.core.sim.scenarios import LabConfig, simulate_lab

    sim = simulate_lab(LabConfig(frames=4, seed=0))
    rng = np.random.default_rng(0)
    a, b = (sim.frame(k).cloud.points for k in (0, 3))
    a, b = (p[rng.choice(len(p), 3000, replace=False)] for p in (a, b))
    if method == "icp":
        config = ICPConfig(method="point_to_plane", max_correspondence_distance=0.02)
        near = icp(a, b, config=config, workers=1).covariance()
    else:
        near = gicp(a, b, workers=1).covariance(1.0)
    for offset, tolerance in ((1e4, 1e-4), (1e5, 1e-2)):
        shift = se3.make_transform(np.eye(3), [offset, 0.0, 0.0])
        if method == "icp":
            far = icp(a + shift[:3, 3], b + shift[:3, 3], config=config, workers=1).covariance()
        else:
            far = gicp(a + shift[:3, 3], b + shift[:3, 3], workers=1).covariance(1.0)
        back = se3.adjoint(se3.invert(shift))
        moved = back @ far @ back.T
        np.testing.assert_allclose(np.sqrt(np.diag(moved)), np.sqrt(np.diag(near)), rtol=tolerance)


def test_information_centre_of_point_to_point_rows_is_their_centroid(rng):
    """Closed form: point-to-point rows ``[-[p]ₓ, I]`` couple rotation and translation least
    about their centroid."""
    from spacepose.core.icp_systems import point_to_point_information
    from spacepose.core.registration import information_centre

    points = rng.normal([3.0, -2.0, 40.0], 0.5, size=(200, 3))
    centre = information_centre(point_to_point_information(points))
    np.testing.assert_allclose(centre, points.mean(axis=0), atol=1e-9)


@pytest.mark.parametrize("method", ["icp", "gicp"])
def test_millimetre_arrays_against_a_gate_in_metres_are_warned_of(method):
    """Integer millimetres (a driver's output) given to icp or gicp with the default gate of
    0.05 m came out converged at the identity with 1.6 % of the points paired, without a
    word. Now a warning names the spacing and the gate; the same clouds in metres say nothing."""
    import warnings

    from spacepose.core.gicp import gicp
    from spacepose.core.icp import icp
    from spacepose.core.sim.scenarios import LabConfig, simulate_lab
    from spacepose.errors import SpaceposeWarning

    register = icp if method == "icp" else gicp
    sim = simulate_lab(LabConfig(frames=2, seed=0))
    a, b = (sim.frame(k).cloud.points for k in (0, 1))
    with pytest.warns(
        SpaceposeWarning,
        match=r"points lie \d\.\d+ apart .* farther than the gate "
        r"of 0\.05: millimetres given to lengths in metres",
    ):
        register((a * 1000).astype(np.int32), (b * 1000).astype(np.int32), workers=1)
    with warnings.catch_warnings():
        warnings.simplefilter("error", SpaceposeWarning)
        assert register(a, b, workers=1).fitness > 0.9


def test_a_model_in_millimetres_given_to_the_tracker_is_warned_of():
    """``Tracker(model=points_in_mm)`` lost every frame and never named the units: the check
    lived in the command line's loop. The tracker now measures the model's size against the
    first frame's and warns at five times or more; its own model says nothing."""
    import warnings

    from spacepose.core.sim.scenarios import LabConfig, simulate_lab
    from spacepose.core.tracker import Tracker, TrackerConfig
    from spacepose.errors import SpaceposeWarning

    sim = simulate_lab(LabConfig(frames=1, seed=0))
    frame = sim.frame(0).cloud
    tracker = Tracker(TrackerConfig(), sim.model_cloud().points * 1000.0, workers=1)
    with pytest.warns(SpaceposeWarning, match=r"the model is 8\d\d times the size of the first"):
        tracker.track_frame(frame, 0.0)
    assert 800.0 < tracker.model_size_ratio < 900.0
    own = Tracker(TrackerConfig(), sim.model_cloud(), workers=1)
    with warnings.catch_warnings():
        warnings.simplefilter("error", SpaceposeWarning)
        own.track_frame(frame, 0.0)
    assert 0.8 < own.model_size_ratio < 0.9


def test_navigate_registration_on_a_run_without_its_model_goes_model_free(tmp_path, capsys):
    """An orbit run folder whose model.ply was removed stopped at "run folder is missing
    model.ply", where the README says registration without a model runs model-free. It now
    does, and says why four frames navigate nothing: the model-free batch."""
    from spacepose.cli import main

    run = tmp_path / "orbit"
    assert main(["simulate", "orbit", "--frames", "4", "--out", str(run)]) == 0
    (run / "model.ply").unlink()
    capsys.readouterr()
    out = tmp_path / "nav.csv"
    assert main(["navigate", str(run), "--measurements", "registration", "--out", str(out)]) == 1
    err = capsys.readouterr().err
    assert "missing model.ply" not in err
    assert "without a model the filter starts on a batch of 200 ok poses" in err
    assert len(out.read_text().splitlines()) == 5  # a row for every frame, and the header


def test_a_report_not_named_html_is_said_to_be(tmp_path):
    """``report --out afile.txt`` wrote the HTML page into a .txt file without a word."""
    import warnings

    from spacepose.errors import SpaceposeWarning
    from spacepose.tools.report import build_report

    with pytest.warns(SpaceposeWarning, match=r"afile\.txt: not named \.html"):
        with pytest.raises(InputError, match="nothing to report"):
            build_report(tmp_path, tmp_path / "afile.txt")
    with warnings.catch_warnings():
        warnings.simplefilter("error", SpaceposeWarning)
        with pytest.raises(InputError, match="nothing to report"):
            build_report(tmp_path, tmp_path / "page.HTML")


def test_a_negative_max_dt_is_blamed_on_the_option(tmp_path, capsys, random_trajectory):
    """``evaluate EST GT --max-dt -1`` said "error: EST.tum: against gt.tum: tolerance must
    be ... >= 0", blaming the estimate's file for the option's value."""
    from spacepose.cli import main
    from spacepose.tools.trajectory_io import write_tum

    est = write_tum(tmp_path / "est.tum", random_trajectory)
    gt = write_tum(tmp_path / "gt.tum", random_trajectory)
    assert main(["evaluate", str(est), str(gt), "--max-dt", "-1"]) != 0
    err = capsys.readouterr().err
    assert "Invalid value for '--max-dt'" in err and "est.tum" not in err


def test_float_depth_maps_listed_by_depth_txt_stay_metres(tmp_path):
    """A depth.txt timing float TIFFs in metres applied TUM RGB-D's 5000 units per metre to
    them: every frame lost, blamed on "depth_scale in the intrinsics (0.0002 m per stored
    unit)" that the intrinsics did not hold. TUM's unit is its 16-bit images' (they still get
    it); floats stay metres, and an error about 16-bit ones names the layout as the unit's
    origin."""
    from spacepose.tools.frames import open_frames

    root = tmp_path / "tum"
    (root / "depth").mkdir(parents=True)
    lines = []
    for k in range(2):
        Image.fromarray(_box_depth()).save(root / "depth" / f"{k}.tiff")
        lines.append(f"{100 + 0.1 * k:.1f} depth/{k}.tiff")
    (root / "depth.txt").write_text("\n".join(lines) + "\n")
    (root / "intrinsics.yaml").write_text("fx: 60\nfy: 60\ncx: 31.5\ncy: 23.5\n")
    cloud = next(iter(open_frames(root))).cloud
    assert np.allclose(np.sort(cloud.points[:, 2])[[0, -1]], [1.15, 1.2], atol=1e-6)
    for k in range(2):  # 16-bit values a thousandth of what TUM's unit needs: 0.2 mm away
        (root / "depth" / f"{k}.tiff").unlink()
        Image.fromarray(np.full((48, 64), 1, dtype=np.uint16)).save(root / "depth" / f"{k}.png")
    (root / "depth.txt").write_text("\n".join(lines).replace(".tiff", ".png") + "\n")
    frame = next(iter(open_frames(root)))
    assert frame.cloud is None and "by TUM RGB-D's depth.txt layout, 5000 per metre" in frame.error


def test_a_depth_image_left_out_of_depth_txt_is_said(tmp_path):
    """An image in depth/ that depth.txt does not list was skipped without a word (5 frames of
    6 files); it is now named in a warning, and a complete list says nothing."""
    import warnings

    from spacepose.errors import SpaceposeWarning
    from spacepose.tools.frames import open_frames

    root = tmp_path / "tum"
    (root / "depth").mkdir(parents=True)
    for k in range(3):
        Image.fromarray(np.full((48, 64), 6000, dtype=np.uint16)).save(root / "depth" / f"{k}.png")
    (root / "intrinsics.yaml").write_text("fx: 60\nfy: 60\ncx: 31.5\ncy: 23.5\n")
    (root / "depth.txt").write_text("1.0 depth/0.png\n1.1 depth/2.png\n")
    with pytest.warns(
        SpaceposeWarning, match=r"depth\.txt: 1 depth image\(s\) .* \(the first: 1\.png\)"
    ):
        frames = open_frames(root)
    assert len(frames) == 2
    (root / "depth.txt").write_text("1.0 depth/0.png\n1.05 depth/1.png\n1.1 depth/2.png\n")
    with warnings.catch_warnings():
        warnings.simplefilter("error", SpaceposeWarning)
        assert len(open_frames(root)) == 3


def test_a_covariance_of_a_non_finite_information_is_refused():
    """A result whose information holds NaN ended in numpy's "SVD did not converge in Linear
    Least Squares"; it is now the package's InputError."""
    from spacepose.core.registration import RegistrationResult

    result = RegistrationResult(np.eye(4), 1.0, 1e-3, 1, True, np.full((6, 6), np.nan))
    with pytest.raises(InputError, match="information holds NaN or inf"):
        result.covariance()
