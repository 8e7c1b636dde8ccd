"""Bad inputs found by a fifth hostile round: each ends in one line naming the file and the
problem (or a warning naming it), never a traceback, a hang or a silently wrong result."""

from __future__ import annotations

import gc
import json
import warnings
from pathlib import Path

import numpy as np
import pytest

from spacepose.cli import main
from spacepose.core import se3
from spacepose.core.sim.scenarios import TRUTH_COLUMNS
from spacepose.core.trajectory import Trajectory
from spacepose.errors import ConfigError, FileFormatError, InputError, SpaceposeWarning
from spacepose.tools.cloud_io import read_cloud, write_cloud
from spacepose.tools.depth_io import write_depth_image
from spacepose.tools.evaluation import compare_trajectory_files
from spacepose.tools.register import RegisterConfig
from spacepose.tools.register_io import register_files
from spacepose.tools.report import build_report
from spacepose.tools.runs import read_run
from spacepose.tools.trajectory_io import write_kitti, write_tum
from test_bad_inputs_round4 import INTRINSICS, _cli_error, _refused


def _depth_pair(root: Path, intrinsics: str | None = INTRINSICS) -> tuple[Path, Path]:
    """Two 32 x 24 depth maps of a curved surface about 1.2 m away (seeded noise), and an
    intrinsics file beside them."""
    rng = np.random.default_rng(5)
    root.mkdir(parents=True, exist_ok=True)
    yy, xx = np.mgrid[:24, :32]
    surface = 1.2 + 0.01 * xx + 0.005 * yy + 0.0004 * (xx - 16) ** 2 + 0.0006 * (yy - 12) ** 2
    paths = []
    for k in range(2):
        path = root / f"{k:06d}.png"
        write_depth_image(path, surface + 0.002 * k + rng.normal(scale=1e-4, size=surface.shape))
        paths.append(path)
    if intrinsics is not None:
        (root / "intrinsics.yaml").write_text(intrinsics)
    return paths[0], paths[1]


# -- register: --intrinsics beside a depth image's own file ---------------------------------------


def test_register_intrinsics_that_differ_from_the_images_own_are_refused(tmp_path, capsys):
    """--intrinsics given for a depth image with an intrinsics.yaml beside it won without a
    word (the image's own calibration ignored); depth folders refuse it, register now too."""
    source, target = _depth_pair(tmp_path / "depth")
    given = tmp_path / "given.yaml"
    given.write_text(INTRINSICS.replace("fx: 30", "fx: 40"))
    message = (
        f"{source.parent}: --intrinsics {given} and the folder's intrinsics.yaml differ "
        "(fx 40.0 vs 30.0): keep one (move intrinsics.yaml out, or leave out --intrinsics)"
    )
    argv = ["register", str(source), str(target), "--intrinsics", str(given)]
    _refused(
        capsys, InputError, message, lambda: register_files(source, target, intrinsics=given), argv
    )


# The pair's geometry (a shallow bowl seen by 768 pixels) is not the point: its degeneracy
# warning is left out.
@pytest.mark.filterwarnings("ignore::spacepose.errors.SpaceposeWarning")
def test_register_intrinsics_equal_to_the_images_own_are_accepted(tmp_path):
    """The same calibration given twice (here as JSON beside the folder's YAML) is no
    conflict."""
    source, target = _depth_pair(tmp_path / "depth")
    given = tmp_path / "given.json"
    given.write_text('{"fx": 30, "fy": 30, "cx": 15.5, "cy": 11.5}')
    outcome = register_files(source, target, intrinsics=given)
    assert outcome.n_source > 3


# -- report: the run's truth checked as navigate checks it ---------------------------------------


def _nav_like(truth: Path, nav: Path) -> None:
    """A navigation output equal to ``truth`` (sigmas of 1 mm): scored without an error."""
    head, *rows = truth.read_text().splitlines()
    sigmas = [f"sig_{c}" for c in head.split(",")[1:] if not c.startswith("q")]
    sigmas += ["sig_att_x", "sig_att_y", "sig_att_z"]
    body = "".join(f"{row},{','.join(['0.001'] * len(sigmas))},2,ok\n" for row in rows)
    nav.write_text(f"{head},{','.join(sigmas)},n_rect,status\n{body}")


# A truth row's state after its time: rho, v, q (w last), omega, k, com.
_STATE = "25,0,0,0,0,0,0,0,0,1,0,0,0.01,-0.2,0.4,-0.25,0.02,-0.03,0.05"
_HEAD = ",".join(TRUTH_COLUMNS)


@pytest.mark.parametrize(
    ("body", "problem"),
    [
        # Frame 0 is at t = 0 s (groundtruth.tum): a truth row at 7 s is another frame's state.
        (
            f"7,{_STATE}",
            "row 1 is at t = 7 s, frame 0 at 0 s (groundtruth.tum): the truth "
            "and the frames must share their times",
        ),
        (f"0,nan,{_STATE[3:]}", "row 1: rho_x is nan; the truth must be finite"),
    ],
)
def test_report_checks_the_truth_as_navigate_does(tmp_path, bare_orbit_run, body, problem):
    """The report read truth.csv without read_run's checks: a truth at other times than the
    frames (or with a hole) scored the navigation against the wrong states without a word;
    its section is now left out naming truth.csv and the row, as navigate refuses it."""
    run = bare_orbit_run(tmp_path / "run", truth=f"{_HEAD}\n{body}\n".encode())
    truth = run / "truth.csv"
    _nav_like(truth, run / "nav.csv")
    with pytest.raises(FileFormatError) as exc:
        read_run(run)
    assert str(exc.value) == f"{truth}: {problem}"
    with pytest.warns(SpaceposeWarning) as caught:
        page = build_report(run).read_text()
    messages = [str(w.message) for w in caught]
    assert f"{truth}: left out of the report: {problem}" in messages
    assert "Relative navigation" not in page


def test_report_checks_the_truth_without_ground_truth_too(tmp_path, bare_orbit_run):
    """Without groundtruth.tum there are no frame times to check, but the table still is."""
    run = bare_orbit_run(tmp_path / "run", truth=f"{_HEAD}\n0,inf,{_STATE[3:]}\n".encode())
    (run / "groundtruth.tum").unlink()
    _nav_like(run / "truth.csv", run / "nav.csv")
    with pytest.warns(SpaceposeWarning) as caught:
        build_report(run)
    problem = "left out of the report: row 1: rho_x is inf; the truth must be finite"
    message = f"{run / 'truth.csv'}: {problem}"
    assert message in [str(w.message) for w in caught]


def test_report_scores_a_sound_truth(tmp_path, bare_orbit_run):
    """The check passes a truth at the frames' times: its navigation is scored."""
    run = bare_orbit_run(tmp_path / "run", truth=f"{_HEAD}\n0,{_STATE}\n".encode())
    _nav_like(run / "truth.csv", run / "nav.csv")
    with warnings.catch_warnings():
        warnings.simplefilter("error", SpaceposeWarning)
        assert "Relative navigation" in build_report(run).read_text()


# -- simulate --model FOLDER ----------------------------------------------------------------------


@pytest.mark.parametrize(
    ("name", "holds", "hint"),
    [
        ("mesh.obj", (), "it holds no mesh (.obj, .stl, .ply, .glb, .gltf, .off)"),
        ("meshes", ("b.stl", "a.OBJ", "notes.txt"), "give one of its meshes (a.OBJ, b.stl)"),
    ],
)
def test_simulate_model_that_is_a_folder_says_so(tmp_path, capsys, name, holds, hint):
    """A folder given as --model was 'no such mesh file' (named *.obj) or an 'unknown mesh
    extension' '' though the user sees it there."""
    folder = tmp_path / name
    folder.mkdir()
    for file in holds:
        (folder / file).write_bytes(b"")
    argv = ["simulate", "orbit", "--frames", "2", "--model", str(folder)]
    assert main([*argv, "--out", str(tmp_path / "run")]) == 1
    assert _cli_error(capsys) == f"error: {folder}: --model is a folder, not a mesh file: {hint}"
    assert not (tmp_path / "run").exists()


# -- a depth image where a point cloud goes --------------------------------------------------------


@pytest.mark.parametrize("suffix", [".png", ".TIFF"])
def test_a_depth_image_where_a_cloud_goes_says_what_to_do(tmp_path, capsys, suffix):
    """planes (or navigate --model) given a depth image said 'unknown point cloud extension';
    neither takes intrinsics, so the user is told to back-project it first."""
    image = tmp_path / f"depth{suffix}"
    image.write_bytes(b"")
    message = (
        f"{image}: a depth image where a point cloud (.csv, .npy, .npz, .pcd, .ply, .txt, .xyz) "
        "goes: back-project it with its camera's intrinsics first "
        "(spacepose.tools.depth_io.read_depth_cloud, then write_cloud to a .ply)"
    )
    _refused(capsys, FileFormatError, message, lambda: read_cloud(image), ["planes", str(image)])


# -- a corrupt .npz leaves no file open -----------------------------------------------------------


def _refusal(path: Path) -> str:
    """The FileFormatError message of reading ``path``; the error (and the frames its
    traceback holds, with any handle left in them) gone on return."""
    try:
        read_cloud(path)
    except FileFormatError as exc:
        return str(exc)
    raise AssertionError(f"{path} was read")


@pytest.mark.parametrize("cut", [0.5, 0.9])
def test_a_corrupt_npz_is_refused_and_closed(tmp_path, capsys, cut):
    """np.load left its handle on a corrupt archive open: a ResourceWarning (hidden by
    default) for each bad file, and an open file that a long run's folder piles up."""
    rng = np.random.default_rng(7)
    path = tmp_path / "cloud.npz"
    np.savez(path, points=rng.normal(size=(200, 3)))
    data = path.read_bytes()
    path.write_bytes(data[: int(len(data) * cut)])
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        message = _refusal(path)
        gc.collect()  # a handle left open is closed, and warned about, when collected
    assert message.startswith(f"{path}: bad or truncated .npz:") and "\n" not in message
    assert not [w for w in caught if issubclass(w.category, ResourceWarning)]


# -- campaign: a damaged part ---------------------------------------------------------------------


def _campaign(tmp_path: Path, seeds: tuple[int, ...] = (0,)) -> tuple[Path, list[Path]]:
    """A registration campaign config whose every case has a stored part (no case runs):
    the config file and the parts, in case order."""
    from spacepose.tools.campaign import PARTS_DIR, prepare_out_dir, write_part
    from spacepose.tools.campaign_spec import expand_grid, load_campaign_config

    config_path = tmp_path / "campaign.yaml"
    grid = {"scenario": ["lab"], "noise_scale": [0.0], "method": ["gicp"], "seed": list(seeds)}
    config_path.write_text(f"name: c\nout: {tmp_path / 'out'}\ngrid: {grid}\n")
    out = prepare_out_dir(load_campaign_config(config_path))
    parts = []
    for case in expand_grid(load_campaign_config(config_path).grid):
        metrics = {"converged": True, "fitness": 0.9, "iterations": 12}
        record = {"case_id": case.case_id, "params": case.params, "metrics": metrics}
        write_part(out, {**record, "error": None, "time_s": 0.5})
        parts.append(out / PARTS_DIR / f"{case.case_id}.json")
    return config_path, parts


@pytest.mark.parametrize(
    ("edit", "problem"),
    [
        (lambda r: r.pop("metrics"), "'metrics' must be a mapping of numbers, got NoneType"),
        (lambda r: r["metrics"].update(fitness="high"), "metric 'fitness' is a str, not a scalar"),
        (lambda r: r["metrics"].update(seed=3), "metric 'seed' clashes with a column name"),
        (lambda r: r.update(time_s=-1), "'time_s' must be a number of seconds >= 0, got -1"),
        (lambda r: r.pop("error"), "'error' must be text, or null for a case that succeeded"),
    ],
)
def test_a_damaged_campaign_part_is_refused_naming_it(tmp_path, capsys, edit, problem):
    """A part whose case_id matches but whose record was edited (no metrics, a metric that is
    text, a time of -1 s) ended the campaign in a KeyError or ArrowInvalid traceback; a metric
    named as an axis overwrote that axis' column without a word."""
    config, (part,) = _campaign(tmp_path)
    record = json.loads(part.read_text())
    edit(record)
    part.write_text(json.dumps(record))
    assert main(["campaign", str(config)]) == 1
    message = f"error: {part}: damaged campaign part: {problem}; delete it to run its case again"
    assert _cli_error(capsys) == message


def test_a_metric_true_false_in_one_part_and_a_number_in_another_is_refused(tmp_path, capsys):
    """pyarrow cannot hold both in one column: its ArrowInvalid escaped as a traceback."""
    config, parts = _campaign(tmp_path, seeds=(0, 1))
    record = json.loads(parts[1].read_text())
    record["metrics"]["converged"] = 0.5
    parts[1].write_text(json.dumps(record))
    assert main(["campaign", str(config)]) == 1
    assert _cli_error(capsys) == (
        f"error: {parts[0].parent}: metric 'converged' is true/false in part "
        f"{parts[0].stem} and 0.5 in part {parts[1].stem}: delete the edited one to run its "
        "case again"
    )


def test_sound_campaign_parts_consolidate(tmp_path):
    """The checks pass what execute_case writes: the table is built without a case run."""
    config, _ = _campaign(tmp_path, seeds=(0, 1))
    assert main(["campaign", str(config)]) == 0
    assert (tmp_path / "out" / "results.parquet").is_file()


def test_a_campaign_integer_beyond_64_bits_is_refused_before_any_case(tmp_path, capsys):
    """The results table stores integers in 64 bits: a seed of 10**23 ran every case, then
    ended in pyarrow's OverflowError traceback (and so did every resume)."""
    config = tmp_path / "campaign.yaml"
    grid = (
        "{scenario: [lab], noise_scale: [0.0], method: [gicp], seed: [0, 100000000000000000000000]}"
    )
    config.write_text(f"out: {tmp_path / 'out'}\ngrid: {grid}\n")
    assert main(["campaign", str(config)]) == 1
    assert _cli_error(capsys) == (
        f"error: {config}: invalid campaign config: grid: axis 'seed' has an "
        "integer beyond 64 bits: [0, 100000000000000000000000]"
    )
    assert not (tmp_path / "out").exists()


# -- evaluate: a health table that cannot say which frames were lost -----------------------------


def noisy_pair(tmp_path: Path, seed: int) -> tuple[Path, Path]:
    """Ten poses 1 mm noisy about their truth (10 mm steps at 1.2 m), written as est.tum and
    gt.tum; their paths."""
    rng = np.random.default_rng(seed)
    t = np.arange(10.0)
    gt = np.stack([se3.make_transform(np.eye(3), [0.01 * k, 0.0, 1.2]) for k in t])
    noisy = gt.copy()
    noisy[:, :3, 3] += rng.normal(scale=1e-3, size=(10, 3))
    est_path = write_tum(tmp_path / "est.tum", Trajectory(t, noisy))
    return est_path, write_tum(tmp_path / "gt.tum", Trajectory(t, gt))


@pytest.mark.parametrize(
    ("header", "shift", "problem"),
    [
        # Semicolons: one column named 'frame;timestamp;status', every frame read as not lost.
        ("frame;timestamp;status", 0, "has no status column"),
        ("frame,timestamp,Status", 0, "has no status column"),
        # Another run's table, of as many rows: its lost flags fell on other frames.
        ("frame,timestamp,status", 10, "row 1 is at t = 10 s, pose 0 at 0 s"),
    ],
)
def test_a_health_table_that_cannot_mark_the_lost_frames_says_so(tmp_path, header, shift, problem):
    """evaluate leaves out the frames EST.health.csv marks lost; a table without a status
    column, or at other times than the poses, left none out (or other frames) without a
    word. Now the lost frames are scored, with a warning naming the table and why."""
    est_path, gt_path = noisy_pair(tmp_path, 11)
    sep = ";" if ";" in header else ","
    rows = [sep.join((str(k), repr(k + shift), "lost" if k == 3 else "ok")) for k in range(10)]
    health = tmp_path / "est.health.csv"
    health.write_text(header + "\n" + "\n".join(rows) + "\n")
    with pytest.warns(SpaceposeWarning) as caught:
        result = compare_trajectory_files(est_path, gt_path)
    message = f"{est_path}: est.health.csv {problem}: lost frames, if any, are scored"
    assert [str(w.message) for w in caught] == [message]
    assert result.table.n == 10


# -- register: --init with --global ---------------------------------------------------------------


def test_register_init_with_global_is_refused(tmp_path, capsys):
    """The global stage starts from no pose: a given --init was replaced without a word (a
    0.5 m start gave the same answer as none)."""
    rng = np.random.default_rng(13)
    points = rng.normal(size=(500, 3)) * 0.2 + [0.0, 0.0, 1.5]
    source = write_cloud(tmp_path / "s.ply", points)
    target = write_cloud(tmp_path / "t.ply", points + np.array([0.01, 0.0, 0.0]))
    init = tmp_path / "init.txt"
    init.write_text("1 0 0 0.5\n0 1 0 0\n0 0 1 0\n0 0 0 1\n")
    message = (
        "an initial transform (--init) is given with global registration (--global), which "
        "starts from no pose and would replace it: give one of them"
    )
    argv = ["register", str(source), str(target), "--global", "--init", str(init)]
    config = RegisterConfig(global_registration=True)
    _refused(
        capsys, ConfigError, message, lambda: register_files(source, target, init, config), argv
    )


# -- evaluate: KITTI (no times) against a clock ---------------------------------------------------


def test_kitti_against_times_that_are_not_frame_numbers_is_refused(tmp_path, capsys):
    """KITTI poses are timed 0, 1, 2, ...: against a 2 Hz TUM truth (0, 0.5, 1, ...) pose k
    met the truth of frame 2k and was scored against it, with only a length warning."""
    rng = np.random.default_rng(17)
    t = np.arange(20) * 0.5
    gt = np.stack([se3.make_transform(np.eye(3), [0.01 * k, 0.0, 1.2]) for k in range(20)])
    gt_path = write_tum(tmp_path / "gt.tum", Trajectory(t, gt))
    noisy = gt[:10].copy()
    noisy[:, :3, 3] += rng.normal(scale=1e-3, size=(10, 3))
    est_path = write_kitti(tmp_path / "est.kitti", Trajectory(np.arange(10.0), noisy))
    message = (
        f"{gt_path}: its times are not frame numbers (t = 0.5 s), and est.kitti is KITTI, timed "
        "by frame number (0, 1, 2, ...) as it holds no times: give both as KITTI, or both as "
        "TUM with their times"
    )
    argv = ["evaluate", str(est_path), str(gt_path)]
    _refused(capsys, InputError, message, lambda: compare_trajectory_files(est_path, gt_path), argv)
    # Timed by frame number, the truth pairs as before.
    write_tum(gt_path, Trajectory(np.arange(20.0), gt))
    with pytest.warns(SpaceposeWarning, match="10 poses against 20"):
        assert compare_trajectory_files(est_path, gt_path).table.n == 10
