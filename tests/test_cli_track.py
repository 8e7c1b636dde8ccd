"""`spacepose track` and the frame folder reader (tools/frames.py)."""

from __future__ import annotations

import csv
import json
import re
from pathlib import Path

import numpy as np
import pytest

from spacepose.cli import main
from spacepose.core.config import load_config
from spacepose.core.frame_check import UNTESTED_MODEL
from spacepose.core.metrics import evaluate
from spacepose.core.sim.scenarios import LabConfig, simulate_lab
from spacepose.core.tracker_config import TrackerConfig
from spacepose.core.trajectory import Trajectory
from spacepose.errors import ConfigError, InputError, Interrupted, SpaceposeWarning
from spacepose.tools.cloud_io import write_cloud
from spacepose.tools.evaluation import compare_trajectory_files
from spacepose.tools.frames import open_frames, read_timestamps
from spacepose.tools.runs import write_run
from spacepose.tools.track_tables import HEALTH_COLUMNS, read_covariance_csv
from spacepose.tools.tracking_io import track_folder, tracker_config
from spacepose.tools.trajectory_io import read_tum, write_tum

N_FRAMES = 4


@pytest.fixture(scope="module")
def lab():
    return simulate_lab(LabConfig(frames=N_FRAMES, seed=3))


@pytest.fixture(scope="module")
def frame_dir(lab, tmp_path_factory) -> Path:
    """A folder of N_FRAMES PLY files (names sorted = time order) and a timestamps.txt."""
    root = tmp_path_factory.mktemp("frames")
    for k in range(N_FRAMES):
        write_cloud(root / f"f{k:03d}.ply", lab.frame(k).cloud)
    (root / "timestamps.txt").write_text("".join(f"{100.0 + 0.5 * k}\n" for k in range(N_FRAMES)))
    return root


def _one_line_error(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0, err
    return err


def test_track_writes_tum_health_and_config(frame_dir, lab, tmp_path, capsys):
    out = tmp_path / "est.tum"
    code = main(
        ["track", str(frame_dir), "--out", str(out), "--method", "point_to_plane", "--no-mls"]
    )
    assert code == 0, capsys.readouterr().err
    est = read_tum(out)
    assert len(est) == N_FRAMES
    np.testing.assert_allclose(est.timestamps, 100.0 + 0.5 * np.arange(N_FRAMES))
    np.testing.assert_allclose(est.poses[0], np.eye(4), atol=1e-12)  # model-free: identity
    # Accuracy against the re-based ground truth (timestamps of the files, not the sim's).
    gt = Trajectory(est.timestamps, lab.T_sensor_target)
    table = evaluate(est, gt, rebase_first=True).to_dict()
    assert max(table["mean"][a] for a in ("x_mm", "y_mm", "z_mm")) < 2.0
    assert max(table["mean"][a] for a in ("pitch_deg", "yaw_deg", "roll_deg")) < 0.1

    with (tmp_path / "est.health.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    assert tuple(rows[0]) == HEALTH_COLUMNS
    assert [int(r["frame"]) for r in rows] == list(range(N_FRAMES))
    assert {r["status"] for r in rows} <= {"ok", "degraded"}
    assert all(float(r["sig_tx"]) >= 0 for r in rows)
    # The residual structure each model-free frame was checked on (frame 0 defines the target
    # frame: none); a frame degraded by it quotes the same value.
    structure = [float(r["structure"]) for r in rows]
    assert np.isnan(structure[0]) and np.all(np.isfinite(structure[1:]))
    assert 0.0 < min(structure[1:])
    for r, value in zip(rows, structure, strict=True):
        quoted = re.findall(r"residual structure ([\d.]+) > 5: part", r["reasons"])
        assert quoted == ([f"{value:.1f}"] if value > 5.0 else []), (r, value)

    config = json.loads((tmp_path / "est.config.json").read_text())
    assert config["method"] == "point_to_plane" and config["use_mls"] is False
    assert "jicp" in config and "health" in config  # every value, defaults included
    # The effective config reads back as the config the run had.
    assert load_config(TrackerConfig, tmp_path / "est.config.json") == TrackerConfig(
        method="point_to_plane", use_mls=False
    )
    # The lengths the run derived, each by its rule from the voxel (gate 0.83 v, coarse 2 v).
    scale = json.loads((tmp_path / "est.scale.json").read_text())
    v = scale["voxel_m"]
    assert 0.004 < v < 0.008 and scale["spacing_m"] < v  # the lab at 1.2 m: about 6 mm
    assert scale["gate_m"] == pytest.approx(0.83 * v, rel=1e-12)
    assert scale["coarse_voxel_m"] == pytest.approx(2.0 * v, rel=1e-12)
    assert scale["icp_rmse_tolerance_m"] == pytest.approx(1.6e-4 * v, rel=1e-12)


def test_track_run_folder_model_based(tmp_path, capsys):
    run = write_run(tmp_path / "run", simulate_lab(LabConfig(frames=3, seed=3)))
    out = tmp_path / "model_based.tum"
    code = main(
        [
            "track",
            str(run),
            "--out",
            str(out),
            "--method",
            "gicp",
            "--no-mls",
            "--model",
            str(run / "model.ply"),
        ]
    )
    assert code == 0, capsys.readouterr().err
    est = read_tum(out)
    assert len(est) == 3
    # Model-based: absolute poses, compared without re-basing.
    table = evaluate(est, read_tum(run / "groundtruth.tum")).to_dict()
    assert max(table["mean"][a] for a in ("x_mm", "y_mm", "z_mm")) < 3.0


def test_config_file_is_applied(frame_dir, tmp_path, capsys):
    cfg = tmp_path / "cfg.yaml"
    cfg.write_text("method: gicp\nuse_mls: false\nhealth:\n  min_points: 50\n")
    out = tmp_path / "est.tum"
    (tmp_path / "est.scale.json").write_text('{"voxel_m": 1.0}\n')  # a former run's
    assert main(["track", str(frame_dir), "--out", str(out), "--config", str(cfg)]) == 0
    written = json.loads((tmp_path / "est.config.json").read_text())
    assert written["method"] == "gicp" and written["health"]["min_points"] == 50
    assert json.loads((tmp_path / "est.scale.json").read_text())["voxel_m"] < 0.01


def test_empty_folder_exits_1(tmp_path, capsys):
    (tmp_path / "empty").mkdir()
    code = main(["track", str(tmp_path / "empty"), "--out", str(tmp_path / "e.tum")])
    assert code == 1
    assert "no frame files" in _one_line_error(capsys)


def test_unknown_method_exits_1(frame_dir, tmp_path, capsys):
    code = main(["track", str(frame_dir), "--out", str(tmp_path / "e.tum"), "--method", "ndt"])
    assert code == 1
    assert "method" in _one_line_error(capsys)


@pytest.mark.parametrize(
    "content",
    [
        b"",  # zero bytes
        b"ply\nformat binary_little_endian 1.0\nelement vertex 50\n",  # truncated header
        "truncated body",
        b"I am a text file that someone saved as .ply\n",
    ],
)
def test_unreadable_frame_is_lost_and_the_others_written(frame_dir, tmp_path, capsys, content):
    """Frame 2 of 4 cannot be read: it is reported lost with the reason; frames 0, 1, 3 are
    tracked and every frame has its TUM line and health row."""
    bad = tmp_path / "bad"
    bad.mkdir()
    for p in sorted(frame_dir.glob("*")):
        (bad / p.name).write_bytes(p.read_bytes())
    if content == "truncated body":
        content = (bad / "f002.ply").read_bytes()[:-5000]
    (bad / "f002.ply").write_bytes(content)
    out = tmp_path / "e.tum"
    # "icp" is the deprecated name of point_to_plane: accepted, with one warning line.
    code = main(["track", str(bad), "--out", str(out), "--method", "icp", "--no-mls"])
    assert code == 0, capsys.readouterr().err
    printed = capsys.readouterr()
    # The second frame (f001) has no velocity yet to confirm it, and after the lost f002 no
    # frame has yet tested the motion model that predicts f003: both degraded.
    assert "1 ok, 2 degraded, 1 lost" in " ".join(printed.out.split())
    assert "warning: --method icp is deprecated: use point_to_plane" in printed.err
    # Named on stderr too, not only in the table (it was in the summary's count alone).
    said = [line for line in printed.err.splitlines() if "not read" in line]
    assert len(said) == 1 and said[0].startswith(f"warning: {bad / 'f002.ply'}: not read, frame lo")
    with (tmp_path / "e.health.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    assert [r["status"] for r in rows] == ["ok", "degraded", "lost", "degraded"]
    assert "f002.ply" in rows[2]["reasons"] and "\n" not in rows[2]["reasons"]
    assert rows[1]["reasons"] == "no velocity yet to confirm the pose"
    assert rows[0]["reasons"] == ""
    assert rows[3]["reasons"] == UNTESTED_MODEL
    est = read_tum(out)
    np.testing.assert_allclose(est.timestamps, 100.0 + 0.5 * np.arange(N_FRAMES))


def test_a_garbage_first_frame_is_revised_in_the_files(frame_dir, lab, tmp_path, capsys):
    """Model-free, a first frame of noise no later frame confirms gives way to frame 1 as the
    target frame (core.spare_anchor): the files are written again with frame 0 lost and frame
    1 the identity, and frames 1-3 are scored against the truth re-based on frame 1."""
    bad = tmp_path / "bad"
    bad.mkdir()
    for p in sorted(frame_dir.glob("*")):
        (bad / p.name).write_bytes(p.read_bytes())
    noise = np.random.default_rng(0).uniform(-1.0, 1.0, (5000, 3)) + np.array([0.0, 0.0, 2.0])
    write_cloud(bad / "f000.ply", noise)
    out = tmp_path / "e.tum"
    assert main(["track", str(bad), "--out", str(out), "--no-mls"]) == 0
    printed = " ".join(capsys.readouterr().out.split())
    assert "1 ok, 2 degraded, 1 lost" in printed
    with (tmp_path / "e.health.csv").open() as fh:
        rows = list(csv.DictReader(fh))
    assert [int(r["frame"]) for r in rows] == list(range(N_FRAMES))
    assert [r["status"] for r in rows][:2] == ["lost", "ok"]
    assert "target frame is frame 1's" in rows[0]["reasons"]
    assert all(r["status"] != "lost" for r in rows[1:])
    est = read_tum(out)
    np.testing.assert_allclose(est.timestamps, 100.0 + 0.5 * np.arange(N_FRAMES))
    np.testing.assert_allclose(est.poses[1], np.eye(4), atol=1e-12)
    # The user's path: the lost frame 0 left out by its health row, re-based on frame 1.
    gt = write_tum(tmp_path / "gt.tum", Trajectory(est.timestamps, lab.T_sensor_target))
    with pytest.warns(SpaceposeWarning) as caught:
        table = compare_trajectory_files(out, gt, rebase_first=True).table.to_dict()
    notes = [str(w.message) for w in caught]
    assert any("1 frame(s) lost in e.health.csv left out" in note for note in notes), notes
    # The estimate holds 4 poses as the truth does: "3 poses against 4" counted it less the lost.
    assert not any("poses against" in note for note in notes), notes
    assert max(table["mean"][a] for a in ("x_mm", "y_mm", "z_mm")) < 2.0
    assert max(table["mean"][a] for a in ("pitch_deg", "yaw_deg", "roll_deg")) < 0.1


class _NoTracking:
    """Stands in for the Tracker where tracking must not start."""

    def __init__(self, *args, **kwargs):
        raise AssertionError("tracking started before the output was checked")


def test_out_at_a_folder_fails_before_tracking(frame_dir, tmp_path, capsys, monkeypatch):
    monkeypatch.setattr("spacepose.tools.tracking_io.Tracker", _NoTracking)
    (tmp_path / "est.tum").mkdir()
    code = main(["track", str(frame_dir), "--out", str(tmp_path / "est.tum")])
    assert code == 1
    assert "est.tum: output exists and is not a regular file" in _one_line_error(capsys)
    (tmp_path / "run").mkdir()
    (tmp_path / "run" / "est.health.csv").mkdir()  # a sibling output in the way counts too
    assert main(["track", str(frame_dir), "--out", str(tmp_path / "run" / "est.tum")]) == 1
    assert "est.health.csv" in _one_line_error(capsys)


def test_out_under_a_regular_file_fails_before_tracking(frame_dir, tmp_path, capsys, monkeypatch):
    monkeypatch.setattr("spacepose.tools.tracking_io.Tracker", _NoTracking)
    (tmp_path / "notes.txt").write_text("a file, not a folder")
    out = tmp_path / "notes.txt" / "runs" / "est.tum"
    assert main(["track", str(frame_dir), "--out", str(out)]) == 1
    assert "notes.txt: it is a regular file" in _one_line_error(capsys)


def test_rows_are_written_as_the_run_goes(frame_dir, tmp_path, monkeypatch, capsys):
    """A run interrupted at frame 2 keeps the trajectory, health and covariance rows of frames 0
    and 1, whole, and says so: the CLI's one line names how far it got (it said 'aborted', and
    nothing told a later reader that EST.tum stops short), exit code 130."""
    from spacepose.core.tracker import Tracker

    real = Tracker.track_frame

    def dies_at_frame_2(self, cloud, timestamp, prior=None):
        if timestamp >= 101.0:
            raise KeyboardInterrupt
        return real(self, cloud, timestamp, prior)

    monkeypatch.setattr(Tracker, "track_frame", dies_at_frame_2)
    out = tmp_path / "e.tum"
    with pytest.raises(Interrupted, match=r"e\.tum: interrupted after 2 of 4 frames"):
        track_folder(frame_dir, out, tracker_config(method="point_to_plane"))
    np.testing.assert_array_equal(read_tum(out).timestamps, [100.0, 100.5])
    with (tmp_path / "e.health.csv").open() as fh:
        assert [r["frame"] for r in csv.DictReader(fh)] == ["0", "1"]
    assert read_covariance_csv(tmp_path / "e.cov.csv").shape == (2, 6, 6)
    capsys.readouterr()
    assert main(["track", str(frame_dir), "--out", str(tmp_path / "cli.tum")]) == 130
    assert "interrupted after 2 of 4 frames" in _one_line_error(capsys)
    np.testing.assert_array_equal(read_tum(tmp_path / "cli.tum").timestamps, [100.0, 100.5])


def test_timestamps_count_mismatch(frame_dir, tmp_path):
    bad = tmp_path / "ts"
    bad.mkdir()
    for p in frame_dir.glob("*.ply"):
        (bad / p.name).write_bytes(p.read_bytes())
    (bad / "timestamps.txt").write_text("0\n1\n")
    with pytest.raises(InputError, match="2 timestamps for 4 frame files"):
        open_frames(bad)


def test_timestamps_not_a_number(tmp_path):
    path = tmp_path / "timestamps.txt"
    path.write_text("0.0\nabc\n")
    with pytest.raises(InputError, match="line 2"):
        read_timestamps(path, 2)


def test_frames_sorted_by_name_and_index_timestamps(tmp_path, lab):
    for name in ("b.npy", "a.xyz", "c.pcd"):
        write_cloud(tmp_path / name, lab.frame(0).cloud)
    (tmp_path / "notes.md").write_text("not a frame")
    seq = open_frames(tmp_path)
    assert [p.name for p in seq.paths] == ["a.xyz", "b.npy", "c.pcd"]
    np.testing.assert_array_equal(seq.timestamps, [0.0, 1.0, 2.0])
    assert all(f.cloud is not None and len(f.cloud) > 1000 for f in seq)


def test_frame_without_points_is_yielded_empty(tmp_path, lab):
    write_cloud(tmp_path / "0.xyz", lab.frame(0).cloud)
    (tmp_path / "1.xyz").write_text("nan nan nan\n")
    frames = list(open_frames(tmp_path))
    assert frames[0].cloud is not None and frames[0].error is None
    assert frames[1].cloud is None and "1.xyz" in frames[1].error


def test_not_a_folder(tmp_path):
    with pytest.raises(InputError, match="does not exist"):
        open_frames(tmp_path / "missing")
    (tmp_path / "file.ply").write_text("")
    with pytest.raises(InputError, match="not a folder"):
        open_frames(tmp_path / "file.ply")
    with pytest.raises(InputError, match="applies to a ROS bag"):
        open_frames(tmp_path, topic="/points")
    (tmp_path / "file.ply").unlink()
    (tmp_path / "x.ply").write_text("garbage")
    (frame,) = open_frames(tmp_path)
    assert frame.cloud is None and "x.ply" in frame.error


def test_tracker_config_overrides(tmp_path):
    assert tracker_config().use_mls is False
    cfg = tracker_config(method="gicp", mls=True, background=True)
    assert (cfg.method, cfg.use_mls, cfg.use_background_removal) == ("gicp", True, True)
    path = tmp_path / "c.json"
    path.write_text('{"use_mls": true, "method": "point_to_plane"}')
    assert tracker_config(path).use_mls is True  # no override: the file's value stands
    assert tracker_config(path, mls=False, method="jicp").use_mls is False
    path.write_text('{"use_mls": "maybe"}')
    with pytest.raises(ConfigError, match=r"c\.json"):
        tracker_config(path)


def test_an_unreadable_frame_whose_name_is_not_utf8_is_lost_and_the_run_goes_on(
    frame_dir, tmp_path, capsys
):
    """A frame file named with a byte that is not UTF-8 (Linux allows any bytes) and holding
    garbage: its reason quotes the name, which used to end the run with a UnicodeEncodeError
    when the health row was written, the later frames untracked. The name is written with a
    backslash escape and every frame has its row."""
    bad = tmp_path / "bad"
    bad.mkdir()
    for p in sorted(frame_dir.glob("*.ply")):
        (bad / p.name).write_bytes(p.read_bytes())
    name = b"f001x\xff.ply"
    with open(bytes(bad) + b"/" + name, "wb") as fh:
        fh.write(b"not a point cloud\n")
    out = tmp_path / "e.tum"
    assert main(["track", str(bad), "--out", str(out), "--no-mls"]) == 0, capsys.readouterr().err
    with (tmp_path / "e.health.csv").open(encoding="utf-8") as fh:
        rows = list(csv.DictReader(fh))
    assert len(rows) == N_FRAMES + 1
    assert [r["status"] for r in rows].count("lost") == 1
    lost = next(r for r in rows if r["status"] == "lost")
    assert "f001x\\udcff.ply" in lost["reasons"], lost["reasons"]
    assert len(read_tum(out).timestamps) == N_FRAMES + 1


@pytest.mark.parametrize("name", ["est.txt", "EST.CSV", "est.ply"])
def test_a_trajectory_named_as_a_frame_among_the_frames_is_refused(
    frame_dir, tmp_path, capsys, monkeypatch, name
):
    """``--out FRAMES/est.txt`` made the next run over the folder read the trajectory as a
    fifth frame (lost, exit 0): refused before tracking, as one line; ``.tum`` there is fine."""
    folder = tmp_path / "frames"
    folder.mkdir()
    for p in frame_dir.glob("*.ply"):
        (folder / p.name).write_bytes(p.read_bytes())
    with monkeypatch.context() as patch:
        patch.setattr("spacepose.tools.tracking_io.Tracker", _NoTracking)
        assert main(["track", str(folder), "--out", str(folder / name)]) == 1
    err = _one_line_error(capsys)
    assert name in err and "would be read as a frame" in err and ".tum" in err
    assert not (folder / name).exists()
    assert main(["track", str(folder), "--out", str(folder / "est.tum"), "--no-mls"]) == 0
    assert len(read_tum(folder / "est.tum").timestamps) == N_FRAMES


def test_an_error_leaves_stdout_empty(tmp_path, capsys):
    """Off a terminal the progress line is not drawn: an error used to leave an empty line on
    stdout before its one line on stderr (track and simulate)."""
    assert main(["track", str(tmp_path / "missing"), "--out", str(tmp_path / "e.tum")]) == 1
    printed = capsys.readouterr()
    assert printed.out == "" and printed.err.strip().endswith("does not exist")
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("keep")
    assert main(["simulate", "lab", "--out", str(tmp_path / "mine"), "--frames", "2"]) == 1
    assert capsys.readouterr().out == ""


def test_a_model_on_a_line_is_refused_before_any_frame(frame_dir, tmp_path, capsys):
    """It was found on the first frame and blamed on every frame ("every frame was lost (frame
    0, …: in/collinear.ply: all 500 points lie on a line …)"), the output files written."""
    model = tmp_path / "collinear.npy"
    np.save(model, np.outer(np.linspace(0.0, 1.0, 500), [1.0, 2.0, 3.0]))
    out = tmp_path / "est.tum"
    assert main(["track", str(frame_dir), "--out", str(out), "--model", str(model)]) == 1
    err = _one_line_error(capsys)
    assert err.endswith(
        "collinear.npy: model: all 500 points lie on a line or at one place: no surface to "
        "register onto"
    ), err
    assert not out.exists() and not (tmp_path / "est.health.csv").exists()


def test_unreadable_frames_past_three_are_counted_in_one_line(frame_dir, tmp_path, capsys):
    bad = tmp_path / "bad"
    bad.mkdir()
    for p in sorted(frame_dir.glob("*.ply")):
        (bad / p.name).write_bytes(p.read_bytes())
    for k in range(4, 11):
        (bad / f"f{k:03d}.ply").write_bytes(b"")
    assert main(["track", str(bad), "--out", str(tmp_path / "e.tum"), "--no-mls"]) == 0
    err = capsys.readouterr().err.splitlines()
    named = [line for line in err if line.startswith(f"warning: {bad}") and "not read" in line]
    assert [line.split(": not read")[0][-8:] for line in named] == [
        "f004.ply", "f005.ply", "f006.ply"
    ]  # fmt: skip
    assert err[-1].startswith("warning: 4 more with the same warning: not read, frame"), err


@pytest.mark.parametrize(
    ("name", "hint"),
    [("rec.mkv", "an Azure Kinect recording? extract its depth track to 16-bit PNGs"),
     ("scan.pcap", "a LiDAR packet capture: convert its scans to .pcd or .ply frames"),
     ("frame.ply", None)],
)  # fmt: skip
def test_a_recording_no_reader_decodes_says_how_to_get_frames(tmp_path, capsys, name, hint):
    (tmp_path / name).write_bytes(bytes(range(256)) * 4)
    assert main(["track", str(tmp_path / name), "--out", str(tmp_path / "e.tum")]) == 1
    err = _one_line_error(capsys)
    assert f"{name}: not a folder of frames (or a run folder, or a ROS bag)" in err
    assert (hint in err) if hint else err.endswith("ROS bag)"), err


def test_each_frames_covariance_is_written_to_the_bit(frame_dir, tmp_path, capsys):
    """EST.cov.csv holds what the tracker gives a filter, the whole 6×6 covariance (the health
    table has its diagonal's roots alone): read back, its upper triangle is the in-process
    tracker's to the bit, and it is positive definite, its diagonal the health table's σ²."""
    from spacepose.core.tracker import Tracker
    from spacepose.tools.cloud_io import read_cloud
    from spacepose.tools.track_tables import COVARIANCE_COLUMNS, read_covariance_csv

    out = tmp_path / "est.tum"
    assert main(["track", str(frame_dir), "--out", str(out)]) == 0, capsys.readouterr().err
    covariances = read_covariance_csv(tmp_path / "est.cov.csv")
    with (tmp_path / "est.cov.csv").open() as fh:
        assert tuple(next(csv.reader(fh))) == COVARIANCE_COLUMNS and len(COVARIANCE_COLUMNS) == 23
    tracker = Tracker(tracker_config())
    frames = sorted(frame_dir.glob("*.ply"))
    stamps = 100.0 + 0.5 * np.arange(N_FRAMES)
    expected = np.array(
        [
            tracker.track_frame(read_cloud(p), t).covariance
            for p, t in zip(frames, stamps, strict=True)
        ]
    )
    # The upper triangle to the bit; the lower mirrors it (the tracker's own is symmetric to
    # rounding, 5e-16 of its largest entry).
    upper = np.triu_indices(6)
    np.testing.assert_array_equal(
        covariances[:, upper[0], upper[1]], expected[:, upper[0], upper[1]]
    )
    np.testing.assert_allclose(covariances, expected, rtol=1e-12, atol=0)
    assert np.all(np.linalg.eigvalsh(covariances[1:]) > 0)
    with (tmp_path / "est.health.csv").open() as fh:
        sigma = np.array([[float(r[f"sig_{a}"]) for a in ("rx", "ry", "rz", "tx", "ty", "tz")]
                          for r in csv.DictReader(fh)])  # fmt: skip
    diagonal = np.sqrt(np.diagonal(covariances, axis1=1, axis2=2))
    np.testing.assert_allclose(diagonal, sigma, rtol=1e-5)
