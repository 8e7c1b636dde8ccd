"""Small text inputs found wanting by a third fuzzing round (trajectories, timestamps, --init
transforms, depth lists): binary bytes, a byte-order mark, a folder or a pipe in a file's place
each end in one line naming the file, and none blocks the command."""

from __future__ import annotations

import csv
import os
from concurrent.futures import ThreadPoolExecutor
from pathlib import Path

import numpy as np
import pytest

from spacepose.cli import main
from spacepose.errors import FileFormatError, InputError
from spacepose.tools.cloud_io import write_cloud
from spacepose.tools.frames import open_frames, read_timestamps
from spacepose.tools.register_io import read_transform
from spacepose.tools.tracking_io import track_folder
from spacepose.tools.trajectory_io import read_trajectory, read_tum

_TUM = "0 0 0 1 0 0 0 1\n1 0.01 0 1 0 0 0 1\n"


def _one_line(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "Traceback" not in err, err
    return err


def test_binary_init_transform_is_one_line_naming_it(tmp_path, capsys):
    rng = np.random.default_rng(0)
    cloud = tmp_path / "c.xyz"
    write_cloud(cloud, rng.normal(size=(200, 3)) * 0.1 + [0, 0, 1])
    init = tmp_path / "init.txt"
    init.write_bytes(b"\xc8" + rng.bytes(100))
    with pytest.raises(FileFormatError, match=r"init\.txt: cannot read the transform: not UTF-8"):
        read_transform(init)
    assert main(["register", str(cloud), str(cloud), "--init", str(init)]) == 1
    assert "init.txt: cannot read the transform: not UTF-8 text" in _one_line(capsys)


def test_timestamps_that_are_binary_or_a_folder_name_the_file(tmp_path, capsys):
    stamps = tmp_path / "timestamps.txt"
    stamps.write_bytes(b"\xea\x00\x17" * 10)
    with pytest.raises(FileFormatError, match=r"timestamps\.txt: cannot read timestamps: not UTF"):
        read_timestamps(stamps, 3)
    stamps.unlink()
    for k in range(3):
        write_cloud(tmp_path / f"{k:06d}.xyz", np.eye(3) + k)
    # A folder named timestamps.txt is no set of times: refused, not replaced by frame numbers.
    stamps.mkdir()
    with pytest.raises(FileFormatError, match=r"timestamps\.txt: a folder"):
        open_frames(tmp_path)
    assert main(["track", str(tmp_path), "--out", str(tmp_path / "o" / "e.tum")]) == 1
    assert "timestamps.txt: a folder" in _one_line(capsys)


def test_a_byte_order_mark_is_read_past(tmp_path):
    (tmp_path / "timestamps.txt").write_bytes(b"\xef\xbb\xbf0.5\n1.5\n")
    assert read_timestamps(tmp_path / "timestamps.txt", 2).tolist() == [0.5, 1.5]
    for name in ("t.tum", "t.txt"):
        (tmp_path / name).write_bytes(b"\xef\xbb\xbf" + _TUM.encode())
        assert read_trajectory(tmp_path / name).timestamps.tolist() == [0.0, 1.0]


def test_a_trajectory_that_is_not_text_says_so_plainly(tmp_path):
    (tmp_path / "b.tum").write_bytes(b"\xd2\x00" * 40)
    with pytest.raises(FileFormatError, match=r"b\.tum: cannot read TUM file: not UTF-8") as info:
        read_tum(tmp_path / "b.tum")
    assert "codec" not in str(info.value)


def _error_reading_a_pipe(read, pipe: Path) -> BaseException | None:
    """What ``read(pipe)`` raises on a new named pipe, within 20 s (a read that blocks fails
    the test, and is released)."""
    os.mkfifo(pipe)
    with ThreadPoolExecutor(1) as pool:
        future = pool.submit(read, pipe)
        try:
            return future.exception(timeout=20)
        finally:
            # A reader blocked in open() is released by a writer's open (and sees no data).
            if not future.done():
                os.close(os.open(pipe, os.O_WRONLY | os.O_NONBLOCK))


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="needs named pipes")
@pytest.mark.parametrize("name", ["est.tum", "est.txt", "init.txt"])
def test_a_named_pipe_is_refused_without_waiting_for_a_writer(tmp_path, name):
    read = read_transform if name == "init.txt" else read_trajectory
    error = _error_reading_a_pipe(read, tmp_path / name)
    assert isinstance(error, FileFormatError), error
    assert f"{name}: not a regular file" in str(error)


def _config_readers():
    from spacepose.core.config import load_config
    from spacepose.core.tracker_config import TrackerConfig
    from spacepose.tools.catalogue import load_catalogue
    from spacepose.tools.intrinsics_io import read_intrinsics

    return {
        "tracker.yaml": lambda p: load_config(TrackerConfig, p),
        "intrinsics.yaml": read_intrinsics,
        "catalogue.yaml": load_catalogue,
    }


@pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="needs named pipes")
@pytest.mark.parametrize("name", ["tracker.yaml", "intrinsics.yaml", "catalogue.yaml"])
def test_a_named_pipe_as_a_config_file_is_refused_without_waiting(tmp_path, name):
    from spacepose.errors import ConfigError

    error = _error_reading_a_pipe(_config_readers()[name], tmp_path / name)
    assert isinstance(error, ConfigError), error
    assert f"{name}: cannot read" in str(error) and "not a regular file" in str(error)


def test_the_evaluate_command_names_a_folder_given_as_a_trajectory(tmp_path, capsys):
    (tmp_path / "gt.tum").write_text(_TUM)
    (tmp_path / "est").mkdir()
    assert main(["evaluate", str(tmp_path / "est"), str(tmp_path / "gt.tum")]) == 1
    assert _one_line(capsys).endswith("est: a folder, not a file")


def _statuses(health: Path) -> list[tuple[str, str]]:
    with health.open() as fh:
        return [(row["status"], row["reasons"]) for row in csv.DictReader(fh)]


@pytest.mark.skipif(not Path("/proc/self/mem").is_file(), reason="needs Linux's /proc")
@pytest.mark.parametrize("suffix", [".xyz", ".pcd", ".npy", ".npz"])
def test_a_frame_the_system_refuses_to_read_is_lost_and_the_run_goes_on(tmp_path, suffix):
    # /proc/self/mem is a regular file whose first page no read can reach (EIO), even for root,
    # as a file without read permission is for anyone else.
    rng = np.random.default_rng(1)
    cloud = rng.normal(size=(400, 3)) * 0.1 + [0, 0, 1]
    for k in (0, 2):
        write_cloud(tmp_path / f"{k:06d}{suffix}", cloud)
    (tmp_path / f"000001{suffix}").symlink_to("/proc/self/mem")
    summary = track_folder(tmp_path, tmp_path / "o" / "e.tum")
    assert summary["frames"] == 3 and summary["lost"] == 1
    status, reason = _statuses(tmp_path / "o" / "e.health.csv")[1]
    assert status == "lost" and f"000001{suffix}: cannot read: Input/output error" in reason


def test_a_folder_named_as_a_depth_frame_is_lost_in_its_place(tmp_path):
    yy, xx = np.mgrid[:24, :32]
    for k in (0, 2):
        np.save(tmp_path / f"{k:06d}.npy", 1.0 + 0.01 * xx + 0.02 * yy + 0.1 * (xx % 3))
    (tmp_path / "000001.npy").mkdir()
    intrinsics = "fx: 30\nfy: 30\ncx: 15.5\ncy: 11.5\ndepth_scale: 1\n"  # metres, as saved
    (tmp_path / "intrinsics.yaml").write_text(intrinsics)
    summary = track_folder(tmp_path, tmp_path / "o" / "e.tum")
    assert summary["frames"] == 3
    status, reason = _statuses(tmp_path / "o" / "e.health.csv")[1]
    assert status == "lost" and "000001.npy: a folder" in reason


def test_an_init_json_nested_too_deeply_is_one_line(tmp_path):
    """json.loads was called directly: a RecursionError traceback."""
    init = tmp_path / "deep.json"
    init.write_text('{"a":' * 50_000 + "1" + "}" * 50_000)
    with pytest.raises(FileFormatError, match=r"deep\.json: expected 16 numbers"):
        read_transform(init)


def test_a_run_folder_without_its_scenario_is_refused(tmp_path, capsys):
    """Without scenario.json a run folder was read as a folder of clouds: its model.ply was
    tracked as the one frame (exit 0), and frames/ left out."""
    from spacepose.core.sim.scenarios import LabConfig, simulate_lab
    from spacepose.tools.runs import write_run

    run = write_run(tmp_path / "run", simulate_lab(LabConfig(frames=2, seed=0)))
    (run / "scenario.json").unlink()
    with pytest.raises(InputError, match=r"has a frames/ folder but no scenario\.json"):
        open_frames(run)
    assert main(["track", str(run), "--out", str(tmp_path / "e.tum")]) == 1
    assert "no scenario.json" in _one_line(capsys)


def test_one_frame_name_twice_is_refused(tmp_path, capsys):
    """000001.ply and 000001.npy were both tracked, and the later frames timed one too far."""
    rng = np.random.default_rng(0)
    for name in ("000000.ply", "000001.ply", "000001.npy", "000002.ply"):
        write_cloud(tmp_path / name, rng.normal(size=(200, 3)) * 0.1 + [0, 0, 1])
    with pytest.raises(InputError, match=r"000001\.npy and 000001\.ply are one frame name twice"):
        open_frames(tmp_path)
    assert main(["track", str(tmp_path), "--out", str(tmp_path / "o" / "e.tum")]) == 1
    assert "one frame name twice" in _one_line(capsys)
