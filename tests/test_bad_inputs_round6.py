"""Bad inputs found by a sixth hostile round: each ends in one line naming the file and the
problem, never a traceback, a hang, lost output or a silently wrong result."""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import numpy as np
import pytest
import yaml
from scipy.spatial.transform import Rotation

from spacepose.cli import main
from spacepose.core.config import dump_config
from spacepose.core.fused_navigation import FusionConfig
from spacepose.core.navigation import NavigationConfig
from spacepose.errors import ConfigError, FileFormatError, InputError, SpaceposeWarning
from spacepose.tools import experiments
from spacepose.tools.campaign_spec import load_campaign_config
from spacepose.tools.cloud_io import read_cloud, write_cloud
from spacepose.tools.evaluation import compare_trajectory_files
from spacepose.tools.intrinsics_io import read_intrinsics
from spacepose.tools.navigation_config_io import load_navigation_config
from spacepose.tools.navigation_io import navigate_run
from spacepose.tools.register_io import read_transform
from spacepose.tools.tracking_io import check_output
from test_bad_inputs_round4 import _cli_error, _cloud_folder, _depth_folder, _refused
from test_bad_inputs_round5 import noisy_pair

# -- simulate: --no-turntable without --background ------------------------------------------------


@pytest.mark.parametrize("scenario", ["lab", "orbit"])
def test_no_turntable_without_background_is_refused(tmp_path, capsys, scenario):
    """The turntable belongs to --background's scene: without it --no-turntable was ignored
    (exit 0, the scene the user meant to change left as it was)."""
    out = tmp_path / "run"
    assert main(["simulate", scenario, "--frames", "2", "--no-turntable", "--out", str(out)]) == 1
    assert _cli_error(capsys) == (
        "error: --no-turntable leaves the turntable out of --background's scene, and "
        "--background is not given: add --background (a wall alone), or leave out --no-turntable"
    )
    assert not out.exists()


# -- track: a trajectory named .kitti -------------------------------------------------------------


@pytest.mark.parametrize("name", ["est.kitti", "EST.KITTI"])
def test_track_out_named_kitti_is_refused(tmp_path, capsys, name):
    """track writes TUM: named .kitti, evaluate then read it as KITTI ('expected 12 values for
    KITTI, got 8'), as evo does; the run's own output could not be scored."""
    frames = _cloud_folder(tmp_path / "frames", frames=2)
    out = tmp_path / name
    message = (
        f"{out}: track writes a TUM trajectory (timestamp tx ty tz qx qy qz qw), and a .kitti "
        "file is read as KITTI (12 numbers a line, no times): name it .tum"
    )
    argv = ["track", str(frames), "--out", str(out)]
    _refused(capsys, InputError, message, lambda: check_output(out), argv)
    assert not list(tmp_path.glob("est.*"))


# -- campaign: a tracking case of one frame --------------------------------------------------------


def test_a_tracking_campaign_of_one_frame_is_refused(tmp_path):
    """A model-free run of one frame scores its start against itself: the campaign wrote
    ATE 0 mm and every axis 0 for it, as if the tracker were perfect."""
    config = tmp_path / "track.yaml"
    grid = {"scenario": ["lab"], "noise_scale": [0.0], "method": ["gicp"], "seed": [0]}
    config.write_text(yaml.safe_dump({"case_kind": "tracking", "grid": grid | {"frames": [1]}}))
    with pytest.raises(ConfigError) as exc:
        load_campaign_config(config)
    assert str(exc.value).startswith(f"{config}: invalid campaign config:")
    assert "frames values must be integers >= 2, got [1]" in str(exc.value)


# -- navigate: NAV.csv among the frames, two priors ----------------------------------------------


def test_navigate_out_among_the_frames_is_refused(tmp_path, capsys):
    """NAV.csv written into the folder of frames it navigates: the next track or navigate over
    the folder read it as one more frame (lost, or 'navigated as empty')."""
    frames = _cloud_folder(tmp_path / "frames", frames=2)
    scenario = tmp_path / "scenario.yaml"
    scenario.write_text("mean_motion: 0.0011\nR_O_C: [[0, 0, 1], [1, 0, 0], [0, 1, 0]]\n")
    out = frames / "nav.csv"
    message = (
        f"{out}: a navigation table named .csv among the frames would be read as a frame by the "
        "next run over the folder: write it elsewhere"
    )
    argv = ["navigate", str(frames), "--scenario", str(scenario), "--out", str(out)]
    _refused(
        capsys, InputError, message, lambda: navigate_run(frames, out, scenario=scenario), argv
    )
    assert sorted(p.name for p in frames.iterdir()) == ["000000.ply", "000001.ply"]


def test_navigate_prior_with_the_debug_prior_is_refused(tmp_path, capsys):
    """--debug-prior-from-truth replaced a given --prior without a word."""
    frames = _cloud_folder(tmp_path / "frames", frames=2)
    scenario = tmp_path / "scenario.yaml"
    scenario.write_text("mean_motion: 0.0011\nR_O_C: [[0, 0, 1], [1, 0, 0], [0, 1, 0]]\n")
    out = tmp_path / "nav.csv"
    message = (
        "--prior and --debug-prior-from-truth both give the attitude prior (the second "
        "replaces the first): give one"
    )
    argv = ["navigate", str(frames), "--scenario", str(scenario), "--out", str(out)]
    argv += ["--prior", "0,0,0,1", "--debug-prior-from-truth"]

    def navigate() -> object:
        return navigate_run(
            frames, out, scenario=scenario, prior_q_I_B=(0, 0, 0, 1), debug_prior_from_truth=True
        )

    _refused(capsys, ConfigError, message, navigate, argv)
    assert not out.exists()


# -- a PCD whose VIEWPOINT is not the origin ------------------------------------------------------


def _pcd(path: Path, viewpoint: str) -> Path:
    """A three-point ASCII PCD with the given VIEWPOINT line."""
    path.write_text(
        "VERSION 0.7\nFIELDS x y z\nSIZE 4 4 4\nTYPE F F F\nCOUNT 1 1 1\nWIDTH 3\nHEIGHT 1\n"
        f"VIEWPOINT {viewpoint}\nPOINTS 3\nDATA ascii\n0 0 1\n0 1 1\n1 0 1\n"
    )
    return path


@pytest.mark.parametrize("viewpoint", ["0.5 0 0 1 0 0 0", "0 0 0 0 1 0 0"])
def test_a_pcd_viewpoint_away_from_the_origin_is_warned_about(tmp_path, viewpoint):
    """PCL's VIEWPOINT says where the sensor was in the points' frame; it was ignored, so a
    cloud stored in another frame was tracked as the sensor's without a word."""
    path = _pcd(tmp_path / "cloud.pcd", viewpoint)
    with pytest.warns(SpaceposeWarning) as caught:
        cloud = read_cloud(path)
    assert [str(w.message) for w in caught] == [
        f"{path}: PCD VIEWPOINT {viewpoint} puts the sensor away from the points' origin: the "
        "points are read as stored, in that frame, not the sensor's (move them into the "
        "sensor's frame first)"
    ]
    np.testing.assert_array_equal(cloud.points, [[0, 0, 1], [0, 1, 1], [1, 0, 1]])


@pytest.mark.parametrize("viewpoint", ["0 0 0 1 0 0 0", "0 0 0 0 0 0 0", "0 0 0 -1 0 0 0"])
def test_a_pcd_viewpoint_at_the_origin_reads_without_a_word(tmp_path, viewpoint):
    """The identity (either sign of q, or no rotation written) is the sensor's own frame."""
    with warnings.catch_warnings():
        warnings.simplefilter("error", SpaceposeWarning)
        assert len(read_cloud(_pcd(tmp_path / "cloud.pcd", viewpoint))) == 3


@pytest.mark.parametrize("viewpoint", ["0 0 0 1 0 0", "a b c d e f g", "nan 0 0 1 0 0 0"])
def test_a_pcd_viewpoint_that_is_not_seven_numbers_is_refused(tmp_path, capsys, viewpoint):
    """A VIEWPOINT PCL cannot parse was read past without a word."""
    path = _pcd(tmp_path / "cloud.pcd", viewpoint)
    message = (
        f"{path}: PCD header VIEWPOINT must be 7 numbers (tx ty tz qw qx qy qz), got {viewpoint!r}"
    )
    _refused(capsys, FileFormatError, message, lambda: read_cloud(path), ["planes", str(path)])


# -- register --init: a rotation written to 4 decimals ---------------------------------------------


def test_an_init_rotation_written_to_four_decimals_is_read_as_its_rotation(tmp_path):
    """cos 30° written 0.8660 leaves RᵀR 4e-5 off the identity: the init was refused as 'not a
    proper rotation', though KITTI files of as few digits are read."""
    init = tmp_path / "init.txt"
    init.write_text("0.8660 -0.5 0 0.01\n0.5 0.8660 0 0\n0 0 1 0\n0 0 0 1\n")
    T = read_transform(init)
    np.testing.assert_allclose(T[:3, :3].T @ T[:3, :3], np.eye(3), atol=1e-12)
    np.testing.assert_allclose(
        T[:3, :3], Rotation.from_euler("z", 30, degrees=True).as_matrix(), atol=1e-4
    )
    np.testing.assert_array_equal(T[:3, 3], [0.01, 0, 0])


@pytest.mark.parametrize(
    ("rows", "problem"),
    [
        ("0.87 -0.5 0 0\n0.5 0.87 0 0", "RᵀR off the identity by 0.0069, det 1.007"),
        ("-1 0 0 0\n0 1 0 0", "RᵀR off the identity by 0, det -1"),
    ],
)
def test_an_init_that_is_no_rotation_says_how_far_off_it_is(tmp_path, capsys, rows, problem):
    """'not a proper rotation' said neither whether it was a reflection, a scale or digits
    cut too short."""
    rng = np.random.default_rng(19)
    points = rng.normal(size=(300, 3)) * 0.1 + [0.0, 0.0, 1.0]
    source = write_cloud(tmp_path / "s.ply", points)
    target = write_cloud(tmp_path / "t.ply", points)
    init = tmp_path / "init.txt"
    init.write_text(f"{rows}\n0 0 1 0\n0 0 0 1\n")
    message = (
        f"{init}: init transform rotation block is not a proper rotation ({problem}; a rotation "
        "has 0 and 1)"
    )
    argv = ["register", str(source), str(target), "--init", str(init)]
    _refused(capsys, InputError, message, lambda: read_transform(init), argv)


# -- ROS camera_info: a matrix shorter than its rows x cols ----------------------------------------

_CAMERA_INFO = (
    "image_width: 32\nimage_height: 24\n"
    "camera_matrix:\n  rows: 3\n  cols: 3\n  data: [30, 0, 15.5, 0, 30, 11.5, 0, 0, 1]\n"
    "distortion_model: plumb_bob\n"
    "distortion_coefficients:\n  rows: 1\n  cols: 5\n  data: {data}\n"
)


def test_camera_info_data_shorter_than_its_size_is_refused(tmp_path, capsys):
    """camera_calibration's YAML says rows x cols: 5 coefficients announced and 1 given (a
    file cut short) were read as k1 alone, the lens's other terms zero, without a word."""
    folder = _depth_folder(tmp_path / "depth", intrinsics=_CAMERA_INFO.format(data="[0.1]"))
    intrinsics = folder / "intrinsics.yaml"
    message = (
        f"{intrinsics}: distortion_coefficients announces rows 1 x cols 5 = 5 numbers, its "
        "data holds 1"
    )
    argv = ["track", str(folder), "--out", str(tmp_path / "est.tum")]
    _refused(capsys, ConfigError, message, lambda: read_intrinsics(intrinsics), argv)
    intrinsics.write_text(_CAMERA_INFO.format(data="[0.01, 0, 0, 0, 0]"))
    assert read_intrinsics(intrinsics).k1 == 0.01


def test_registers_own_out_named_txt_reads_back_as_init(tmp_path):
    """register --out result.txt writes JSON; --init result.txt was then refused as 'expected
    16 numbers (a 4x4 matrix) or JSON with T_target_source', though it held one."""
    result = tmp_path / "result.txt"
    T = np.eye(4)
    T[:3, :3] = Rotation.from_euler("x", 10, degrees=True).as_matrix()
    T[:3, 3] = [0.1, 0.0, 0.02]
    result.write_text(json.dumps({"fitness": 1.0, "T_target_source": T.tolist()}, indent=2))
    np.testing.assert_allclose(read_transform(result), T)
    result.write_text(json.dumps(T.tolist()))  # the bare matrix, as a .json holds it
    np.testing.assert_allclose(read_transform(result), T)


# -- navigate --config: the NAV.config.json a fused run wrote ----------------------------------


def test_a_fused_runs_own_config_is_taken_back(tmp_path, capsys):
    """navigate --measurements registration|both writes its effective FusionConfig as
    NAV.config.json; given back as --config it was refused with eleven 'Extra inputs are not
    permitted' (NavigationConfig only)."""
    written = FusionConfig(measurements="both", pose_sigma_scale=2.5)
    config = dump_config(written, tmp_path / "nav.config.json")
    navigation, fusion = load_navigation_config(config, "both")
    assert fusion == written and navigation == written.navigation
    # A navigation config is read as before.
    plain = dump_config(NavigationConfig(), tmp_path / "plain.json")
    assert load_navigation_config(plain, "both") == (NavigationConfig(), None)
    # The fusion's measurements and the command line's must agree: one would be dropped.
    frames = _cloud_folder(tmp_path / "frames", frames=2)
    argv = ["navigate", str(frames), "--out", str(tmp_path / "nav.csv"), "--config", str(config)]
    assert main(argv) == 1
    assert _cli_error(capsys) == (
        f"error: {config}: a fusion config for --measurements both, given with --measurements "
        "rectangles: give --measurements both, or a navigation config"
    )


def test_model_scale_with_target_size_is_refused(tmp_path, capsys):
    """--target-size sizes the lab target whatever its scale: --model-scale 2 beside it was
    dropped without a word (the same scene as without it)."""
    mesh = tmp_path / "box.obj"
    corners = "".join(f"v {x} {y} {z}\n" for x in (0, 1) for y in (0, 1) for z in (0, 1))
    mesh.write_text(corners + "f 1 2 4\nf 1 4 3\nf 5 7 8\nf 5 8 6\n")
    out = tmp_path / "run"
    argv = ["simulate", "lab", "--frames", "1", "--model", str(mesh), "--model-scale", "2"]
    assert main([*argv, "--target-size", "0.3", "--out", str(out)]) == 1
    assert _cli_error(capsys) == (
        "error: --model-scale applies to a --model's coordinates, and --target-size sets the "
        "target's size whatever its scale: give one of them"
    )
    assert not out.exists()


def test_campaign_workers_with_a_scheduler_is_refused(tmp_path, capsys):
    """--workers starts local worker processes; with --scheduler the running cluster's
    workers ran the cases and --workers was dropped without a word."""
    config = tmp_path / "campaign.yaml"
    grid = {"scenario": ["lab"], "noise_scale": [0.0], "method": ["gicp"], "seed": [0]}
    config.write_text(yaml.safe_dump({"out": str(tmp_path / "out"), "grid": grid}))
    argv = ["campaign", str(config), "--scheduler", "tcp://127.0.0.1:1", "--workers", "4"]
    assert main(argv) == 1
    assert _cli_error(capsys) == (
        "error: --workers sets the local cluster's worker processes, and --scheduler uses a "
        "running cluster and its workers: give one of them"
    )
    assert not (tmp_path / "out").exists()


# -- experiment: options an experiment would ignore ----------------------------------------------


def _not_run(out_dir: Path, options: experiments.ExperimentOptions) -> dict:
    raise AssertionError("the experiment ran")


@pytest.mark.parametrize(
    ("options", "refused"),
    [
        (["--frames", "5"], "--frames: experiment 'li-l2' does not use it (only fusion, "
         "robustness, room do)"),
        (["--seeds", "3"], "--seeds: experiment 'li-l2' does not use it (only fusion, li-l1, "
         "li-l3, room do)"),
        (["--jobs", "2"], "--jobs: experiment 'li-l2' does not use it (only robustness does)"),
        (["--frames-csv"], "--frames-csv: experiment 'li-l2' does not use it (only robustness "
         "does)"),
    ],
)  # fmt: skip
def test_frames_seeds_and_jobs_an_experiment_ignores_are_refused(
    tmp_path, capsys, monkeypatch, options, refused
):
    """li-l2 --frames 5 (or --seeds, --jobs, --frames-csv) ran the experiment's own sizes and
    said nothing; --cells, --tracker and --targets were already refused so."""
    experiments.available()
    monkeypatch.setitem(experiments._REGISTRY, "li-l2", _not_run)
    argv = ["experiment", "li-l2", "--quick", *options, "--out", str(tmp_path)]
    assert main(argv) == 1
    assert _cli_error(capsys) == f"error: {refused}"
    assert not (tmp_path / "li-l2").exists()


def test_a_quick_fusion_takes_the_seeds_and_frames_given(tmp_path, monkeypatch):
    """fusion --quick --seeds 3 --frames 12 ran 1 seed of 30 frames without a word."""
    from spacepose.tools.experiments import fusion

    class Planned(Exception):
        pass

    def planned(target, kind, seeds, frames, base):
        raise Planned(seeds, frames)

    monkeypatch.setattr(fusion, "over_seeds", planned)
    options = experiments.ExperimentOptions(quick=True, seeds=3, frames=12)
    with pytest.raises(Planned) as exc:
        fusion.fusion(tmp_path, options)
    assert exc.value.args == ([0, 1, 2], 12)
    with pytest.raises(Planned) as exc:
        fusion.fusion(tmp_path, experiments.ExperimentOptions(quick=True))
    assert exc.value.args == ([0], 30)


@pytest.mark.parametrize("name", ["nav.tum", "NAV.KITTI"])
def test_navigate_out_named_as_a_trajectory_is_refused(tmp_path, capsys, name):
    """NAV.csv written as nav.tum: report took it for a track and left it out ('expected 8
    values for TUM'), evaluate refused it."""
    frames = _cloud_folder(tmp_path / "frames", frames=2)
    out = tmp_path / name
    message = (
        f"{out}: navigate writes a CSV table (t, rho_x, ...), and a {out.suffix} file is read as "
        "a trajectory (report, evaluate, evo): name it .csv"
    )
    argv = ["navigate", str(frames), "--out", str(out)]
    _refused(capsys, InputError, message, lambda: navigate_run(frames, out), argv)
    assert not list(tmp_path.glob("nav.*")) and not list(tmp_path.glob("NAV.*"))


# -- evaluate: a health table's statuses in other words --------------------------------------------


def _scored(tmp_path: Path, status: str) -> tuple[Path, object]:
    """Ten noisy poses against their truth, frame 3 of the health table beside the estimate
    marked ``status``; the estimate's path and the comparison."""
    est_path, gt_path = noisy_pair(tmp_path, 23)
    rows = [f"{k},{float(k)},{status if k == 3 else 'ok'}" for k in range(10)]
    (tmp_path / "est.health.csv").write_text("frame,timestamp,status\n" + "\n".join(rows) + "\n")
    return est_path, compare_trajectory_files(est_path, gt_path)


def test_a_lost_status_in_capitals_is_left_out(tmp_path):
    """'LOST' (a table re-saved by another tool) was not 'lost': the frame's predicted pose
    was scored as a measurement without a word."""
    with pytest.warns(SpaceposeWarning) as caught:
        est_path, result = _scored(tmp_path, " LOST")
    assert result.table.n == 9
    left_out = "1 frame(s) lost in est.health.csv left out (their poses are the motion model's "
    assert f"{est_path}: {left_out}predictions)" in [str(w.message) for w in caught]


def test_a_status_in_other_words_says_the_lost_frames_are_scored(tmp_path):
    """A status that is none of ok, degraded, lost (another tool's 'failed') was read as not
    lost without a word."""
    with pytest.warns(SpaceposeWarning) as caught:
        est_path, result = _scored(tmp_path, "failed")
    assert [str(w.message) for w in caught] == [
        f"{est_path}: est.health.csv row 4 has status 'failed', not one of ok, degraded, lost: "
        "lost frames, if any, are scored"
    ]
    assert result.table.n == 10


# -- campaign: a metric no axis can span ----------------------------------------------------------


def test_campaign_plot_of_an_unplottable_noise_scale_warns_instead_of_crashing():
    """A grid with noise_scale 1e308: every case failed (its points overflow) and was recorded,
    then matplotlib could not place ticks up to 1e308 and the campaign ended in a traceback
    after writing its table. The figure is now left out with one warning line."""
    from spacepose.tools.campaign_summary import plot_metrics

    summary = [
        {"method": "keyframe", "noise_scale": 1e308, "metric": "time_s", "mean": 0.7, "std": 0.0},
        {"method": "keyframe", "noise_scale": 1.0, "metric": "ate_mm", "mean": 0.4, "std": 0.1},
    ]
    with pytest.warns(SpaceposeWarning, match=r"^time_s\.png not written: "):
        pngs = plot_metrics(summary, ["method", "noise_scale"])
    assert set(pngs) == {"ate_mm"} and pngs["ate_mm"].startswith(b"\x89PNG")
