"""Tests of ``spacepose simulate``."""

from __future__ import annotations

import json
import time
from pathlib import Path

import numpy as np

from spacepose.cli import main
from spacepose.tools.runs import read_run

# The NASA mesh shipped in the repository (data/README.md).
HUBBLE = str(Path(__file__).resolve().parents[1] / "data" / "models" / "hubble_model_kit.obj")


def _files(root):
    return {p.relative_to(root): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def test_simulate_lab_default_run_is_complete(tmp_path, capsys) -> None:
    start = time.perf_counter()
    assert main(["simulate", "lab", "--out", str(tmp_path / "a")]) == 0
    elapsed = time.perf_counter() - start
    assert "wrote 58 lab frames" in capsys.readouterr().out
    print(f"simulate lab: {elapsed:.1f} s")  # reported, not asserted (speed lives in bench)
    root = tmp_path / "a"
    assert len(list((root / "frames").glob("*.ply"))) == 58
    lines = (root / "groundtruth.tum").read_text().splitlines()
    assert len(lines) == 58
    assert (root / "model.ply").is_file() and (root / "model.obj").is_file()
    scenario = json.loads((root / "scenario.json").read_text())
    assert scenario["seed"] == 0 and scenario["config"]["sensor"]["model"] == "tof"
    run = read_run(root)
    motion = run.groundtruth.poses[-1, :3, 3] - run.groundtruth.poses[0, :3, 3]
    assert np.allclose(motion, (0.57, 0.0, 0.0), atol=1e-12)


def test_simulate_seed_sensor_noise_and_background_options(tmp_path, capsys) -> None:
    out = tmp_path / "c"
    args = ["simulate", "lab", "--out", str(out), "--frames", "2", "--seed", "1"]
    assert main([*args, "--sensor", "gaussian", "--noise-scale", "0", "--background"]) == 0
    run = read_run(out)
    assert len(run) == 2
    cfg = run.scenario["config"]
    assert cfg["seed"] == 1 and cfg["background"] is True
    assert cfg["sensor"]["model"] == "gaussian" and cfg["sensor"]["noise_scale"] == 0.0
    assert np.isclose(run.frame(0).points[:, 2], 2.0, atol=1e-6).sum() > 1000  # the wall
    # Another seed, otherwise identical: other noise in the frames.
    base = ["simulate", "lab", "--frames", "2", "--out"]
    assert main([*base, str(tmp_path / "d")]) == 0
    assert main([*base, str(tmp_path / "e"), "--seed", "1"]) == 0
    assert main([*base, str(tmp_path / "d2")]) == 0
    assert _files(tmp_path / "d") == _files(tmp_path / "d2")  # same seed: same bytes
    d = (tmp_path / "d" / "frames" / "000001.ply").read_bytes()
    assert d != (tmp_path / "e" / "frames" / "000001.ply").read_bytes()


def test_simulate_orbit_and_a_mesh_model(tmp_path, capsys) -> None:
    out = tmp_path / "orbit"
    assert main(["simulate", "orbit", "--out", str(out), "--frames", "3"]) == 0
    run = read_run(out)
    assert run.truth.shape == (3, 20) and len(run) == 3
    assert 600 < len(run.frame(0)) < 2500
    # --range is the orbit's standoff: at 12.5 m instead of 25 m the target fills about four
    # times the pixels.
    near = tmp_path / "near"
    assert main(["simulate", "orbit", "--out", str(near), "--frames", "1", "--range", "12.5"]) == 0
    assert read_run(near).scenario["config"]["standoff_m"] == 12.5
    assert len(read_run(near).frame(0)) > 3 * len(run.frame(0))
    out = tmp_path / "hubble"
    args = ["simulate", "lab", "--out", str(out), "--frames", "1", "--model", HUBBLE]
    assert main([*args, "--model-scale", "0.004"]) == 0
    run = read_run(out)
    assert run.scenario["target"] == "hubble_model_kit" and run.rectangles == []
    assert run.scenario["config"]["model_scale"] == 0.004
    assert len(run.frame(0)) > 1000


def test_simulate_errors_are_one_line(tmp_path, capsys) -> None:
    out = str(tmp_path / "x")
    assert main(["simulate", "moon", "--out", out]) == 1
    assert "unknown scenario 'moon'; choose one of: lab, orbit" in capsys.readouterr().err
    assert main(["simulate", "lab", "--out", out, "--sensor", "sonar"]) == 1
    assert "unknown sensor 'sonar'" in capsys.readouterr().err
    assert main(["simulate", "orbit", "--out", out, "--background"]) == 1
    assert "--background applies to the lab scenario only" in capsys.readouterr().err
    assert main(["simulate", "orbit", "--out", out, "--motion", "tumbling-3"]) == 1
    assert "--motion applies to the lab scenario only" in capsys.readouterr().err
    # A scale with nothing to scale was taken without a word (nan included).
    assert main(["simulate", "orbit", "--out", out, "--model-scale", "nan"]) == 1
    assert "--model-scale applies to a --model's coordinates, and no --model" in (
        capsys.readouterr().err
    )
    assert main(["simulate", "orbit", "--out", out, "--target-size", "0"]) == 1
    assert "--target-size applies to the lab scenario only" in capsys.readouterr().err
    assert main(["simulate", "lab", "--out", out, "--model", str(tmp_path / "none.obj")]) == 1
    assert "none.obj: cannot read the mesh: no such file" in capsys.readouterr().err
    assert main(["simulate", "lab", "--out", out, "--noise-scale", "-1"]) == 1
    assert "noise_scale" in capsys.readouterr().err
    assert not (tmp_path / "x").exists()


def test_simulate_motion_range_and_grid_options(tmp_path, capsys) -> None:
    out = tmp_path / "g"
    args = ["simulate", "lab", "--out", str(out), "--frames", "3", "--grid", "--range", "3"]
    assert main([*args, "--motion", "tumbling-5", "--background", "--sensor", "tof-paper"]) == 0
    cfg = read_run(out).scenario["config"]
    assert (cfg["motion"], cfg["tumble_deg"], cfg["range_m"]) == ("tumbling", 5.0, 3.0)
    assert cfg["wall_distance_m"] == 5.0 and cfg["target_size_m"] == 2.225
    assert cfg["sensor"]["amplitude_exponent"] == 0.5 and cfg["background"] is True
    assert cfg["turntable"] is True
    alone = tmp_path / "w"
    args = ["simulate", "lab", "--out", str(alone), "--frames", "2", "--background"]
    assert main([*args, "--no-turntable"]) == 0
    cfg = read_run(alone).scenario["config"]
    assert cfg["background"] is True and cfg["turntable"] is False
    plain = tmp_path / "p"
    args = ["simulate", "lab", "--out", str(plain), "--frames", "2", "--motion", "accelerating"]
    assert main([*args, "--range", "1.5", "--target-size", "0.5"]) == 0
    cfg = read_run(plain).scenario["config"]
    assert (cfg["motion"], cfg["range_m"], cfg["target_size_m"]) == ("accelerating", 1.5, 0.5)
    assert cfg["wall_distance_m"] == 2.0  # without --grid only the named fields change
    assert main(["simulate", "orbit", "--out", str(out), "--grid"]) == 1
    assert "--grid builds lab scenes only" in capsys.readouterr().err
    assert main(["simulate", "lab", "--out", str(out), "--motion", "wobble"]) == 1
    assert "unknown motion 'wobble'" in capsys.readouterr().err


def test_simulate_refuses_a_folder_that_holds_something_else(tmp_path, capsys) -> None:
    """Into a folder of the user's own files, a run overwrote its groundtruth.tum and mixed
    its frames with theirs (exit 0): refused before the scene is built, nothing touched. An
    earlier run is still rewritten in place, and a folder without files taken."""
    victim = tmp_path / "mine"
    (victim / "frames").mkdir(parents=True)
    (victim / "frames" / "mydata.ply").write_text("keep")
    (victim / "groundtruth.tum").write_text("0 0 0 0 0 0 0 1\n")
    assert main(["simulate", "lab", "--out", str(victim), "--frames", "2"]) == 1
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "not a spacepose run" in err and str(victim) in err, err
    assert sorted(p.name for p in victim.rglob("*")) == ["frames", "groundtruth.tum", "mydata.ply"]
    assert (victim / "groundtruth.tum").read_text() == "0 0 0 0 0 0 0 1\n"
    run = tmp_path / "run"
    assert main(["simulate", "lab", "--out", str(run), "--frames", "3"]) == 0
    assert main(["simulate", "lab", "--out", str(run), "--frames", "2"]) == 0
    assert len(read_run(run).frame_paths) == 2
    (tmp_path / "empty").mkdir()
    assert main(["simulate", "lab", "--out", str(tmp_path / "empty"), "--frames", "2"]) == 0
    # What a run that failed on its first frame leaves: an empty frames folder, no file.
    (tmp_path / "failed" / "frames").mkdir(parents=True)
    assert main(["simulate", "lab", "--out", str(tmp_path / "failed"), "--frames", "2"]) == 0
