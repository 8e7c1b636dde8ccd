"""Tests of run folders: write_run / read_run round trip, determinism, bad folders."""

from __future__ import annotations

import json
import shutil

import numpy as np
import pytest
import trimesh

import spacepose
from spacepose.core.sim import LabConfig, OrbitConfig, sensor_config, simulate_lab, simulate_orbit
from spacepose.errors import FileFormatError, InputError
from spacepose.tools.runs import read_run, write_run

SMALL_TOF = sensor_config("tof", width=160, height=120, focal_px=120.9)


@pytest.fixture(scope="module")
def lab_sim():
    return simulate_lab(LabConfig(frames=4, sensor=SMALL_TOF, seed=3, model_points=2000))


@pytest.fixture(scope="module")
def orbit_sim():
    return simulate_orbit(OrbitConfig(frames=5, model_points=2000))


def _files(root):
    return {p.relative_to(root): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def test_lab_round_trip(tmp_path, lab_sim) -> None:
    calls = []
    write_run(tmp_path / "run", lab_sim, progress=calls.append)
    assert calls == [0, 1, 2, 3]
    run = read_run(tmp_path / "run")
    assert len(run) == 4 and run.truth is None
    assert np.array_equal(run.timestamps, [0.0, 1.0, 2.0, 3.0])
    assert np.allclose(run.groundtruth.poses, lab_sim.T_sensor_target, atol=1e-12)
    frame = lab_sim.frame(2)
    # Frames are stored as float32: exact to float32 rounding.
    assert np.array_equal(run.frame(2).points, frame.cloud.points.astype(np.float32))
    assert [len(c) for c in run.frames()] == [len(lab_sim.frame(k).cloud) for k in range(4)]
    model = lab_sim.model_cloud()
    assert run.model.has_normals and len(run.model) == len(model)
    assert np.allclose(run.model.points, model.points, atol=1e-6)
    mesh = trimesh.load(run.mesh_path, force="mesh", process=False)
    assert len(mesh.faces) == len(lab_sim.target.mesh.faces)
    assert np.allclose(mesh.bounds, lab_sim.target.mesh.bounds, atol=1e-8)
    s = run.scenario
    assert s["scenario"] == "lab" and s["seed"] == 3 and s["frames"] == 4
    assert s["spacepose_version"] == spacepose.__version__
    assert s["config"]["sensor"]["width"] == 160 and s["config"]["step_m"] == 0.01
    names = [r.name for r in run.rectangles]
    assert names == [r.name for r in lab_sim.target.rectangles]
    assert np.allclose(run.rectangles[0].R_model_plane, lab_sim.target.rectangles[0].R_model_plane)


def test_same_seed_same_bytes_other_seed_other_frames(tmp_path, lab_sim) -> None:
    write_run(tmp_path / "a", lab_sim)
    write_run(tmp_path / "b", simulate_lab(lab_sim.config))
    a, b = _files(tmp_path / "a"), _files(tmp_path / "b")
    assert a == b and len(a) == 4 + 4
    other = simulate_lab(lab_sim.config.model_copy(update={"seed": 4}))
    write_run(tmp_path / "c", other)
    c = _files(tmp_path / "c")
    frame = next(iter(k for k in a if k.parts[0] == "frames"))
    assert a[frame] != c[frame]


def test_rewriting_a_shorter_run_removes_stale_frames(tmp_path, lab_sim) -> None:
    write_run(tmp_path, lab_sim)
    write_run(tmp_path, simulate_lab(lab_sim.config.model_copy(update={"frames": 2})))
    assert len(read_run(tmp_path)) == 2


def test_orbit_run_has_truth_csv(tmp_path, orbit_sim) -> None:
    write_run(tmp_path, orbit_sim)
    header = (tmp_path / "truth.csv").read_text().splitlines()[0]
    assert header == (
        "t,rho_x,rho_y,rho_z,v_x,v_y,v_z,qx,qy,qz,qw,w_x,w_y,w_z,k_x,k_y,k_z,com_x,com_y,com_z"
    )
    run = read_run(tmp_path)
    assert np.array_equal(run.truth, orbit_sim.truth)  # %.17g round-trips float64 exactly
    s = run.scenario
    assert s["mean_motion"] == pytest.approx(1.1068e-3, rel=1e-4)
    assert np.allclose(s["R_O_C_true"], [[0, 0, 1], [1, 0, 0], [0, 1, 0]])
    # The filter's R_O_C carries the simulated star-tracker error (0.01° 1σ per axis).
    assert np.allclose(s["R_O_C"], s["R_O_C_true"], atol=np.radians(0.1))
    assert s["R_O_C"] != s["R_O_C_true"]
    assert s["inertia"] == [1200.0, 1000.0, 800.0] and s["com_offset"] == [0.02, -0.03, 0.05]
    assert len(run.rectangles) == 10  # the default orbit target: bus, wing and antenna panel


@pytest.mark.parametrize("missing", ["scenario.json", "groundtruth.tum", "frames"])
def test_missing_file_is_named(tmp_path, lab_sim, missing) -> None:
    write_run(tmp_path, lab_sim)
    target = tmp_path / missing
    shutil.rmtree(target) if target.is_dir() else target.unlink()
    with pytest.raises(InputError, match=f"{tmp_path}: run folder is missing {missing}"):
        read_run(tmp_path)


@pytest.mark.parametrize("missing", ["model.ply", "model.obj"])
def test_a_run_without_its_model_is_read_model_free(tmp_path, lab_sim, missing) -> None:
    """A run folder whose model was removed is tracked and navigated model-free: it was
    refused as "missing model.ply" (navigate --measurements registration promised it)."""
    write_run(tmp_path, lab_sim)
    (tmp_path / missing).unlink()
    run = read_run(tmp_path)
    assert (run.model is None) == (missing == "model.ply")
    assert len(run.frame_paths) == len(run.groundtruth)


def test_bad_run_folders(tmp_path, lab_sim, orbit_sim) -> None:
    with pytest.raises(InputError, match="run folder does not exist"):
        read_run(tmp_path / "nowhere")
    write_run(tmp_path / "lab", lab_sim)
    gt = tmp_path / "lab" / "groundtruth.tum"
    rows = gt.read_text().splitlines()
    stamp = rows[1].split()[0]
    gt.write_text(
        "\n".join([rows[0], rows[1], stamp + rows[2][len(rows[2].split()[0]) :], *rows[3:]])
    )
    with pytest.raises(
        InputError, match=r"groundtruth\.tum: timestamps must increase: frame 2 rep"
    ):
        read_run(tmp_path / "lab")
    write_run(tmp_path / "lab", lab_sim)
    (tmp_path / "lab" / "frames" / "000003.ply").unlink()
    with pytest.raises(InputError, match="3 frame files in frames/ but 4 poses"):
        read_run(tmp_path / "lab")
    (tmp_path / "lab" / "scenario.json").write_text("{not json")
    with pytest.raises(FileFormatError, match=r"scenario\.json: not valid JSON"):
        read_run(tmp_path / "lab")
    (tmp_path / "lab" / "scenario.json").write_text("[1, 2]")
    with pytest.raises(FileFormatError, match=r"scenario\.json: must hold a JSON object"):
        read_run(tmp_path / "lab")
    orbit = tmp_path / "orbit"
    write_run(orbit, orbit_sim)
    truth = (orbit / "truth.csv").read_text()
    (orbit / "truth.csv").write_text(truth.replace("rho_x", "rx"))
    with pytest.raises(FileFormatError, match=r"truth\.csv: header must be"):
        read_run(orbit)
    (orbit / "truth.csv").write_text("\n".join(truth.splitlines()[:-1]) + "\n")
    with pytest.raises(FileFormatError, match="expected 5 rows"):
        read_run(orbit)
    rows = truth.splitlines()
    cells = rows[2].split(",")
    cells[3] = "nan"
    (orbit / "truth.csv").write_text("\n".join([*rows[:2], ",".join(cells), *rows[3:]]) + "\n")
    with pytest.raises(FileFormatError, match=r"truth\.csv: row 2: .* is nan; the truth must be"):
        read_run(orbit)
    (orbit / "truth.csv").write_text(truth.replace("\n0,", "\nzero,", 1))
    with pytest.raises(FileFormatError, match=r"truth\.csv: bad row"):
        read_run(orbit)
    # Cut mid-row: numpy's "use `usecols` to select a subset" was no advice a user can take.
    (orbit / "truth.csv").write_text(truth[: len(truth) // 2])
    with pytest.raises(FileFormatError, match=r"truth\.csv: line \d+ has \d+ values, the header"):
        read_run(orbit)
    (orbit / "truth.csv").unlink()
    with pytest.raises(InputError, match=r"missing truth\.csv"):
        read_run(orbit)
    json.loads((orbit / "scenario.json").read_text())  # the rest of the folder is intact


def test_frames_are_paired_with_poses_by_number(tmp_path, lab_sim) -> None:
    """Frames were sorted as text and never checked against their numbers: a run of 12
    frames renamed 0.ply ... 11.ply was tracked as 0, 1, 10, 11, 2, ... (each scored against
    another frame's pose), and one renamed past a gap was taken for the frame before it."""
    root = tmp_path / "lab"
    write_run(root, lab_sim)
    frames = root / "frames"
    for k in range(4):
        (frames / f"{k:06d}.ply").rename(frames / f"{k}.ply")
    (frames / "3.ply").rename(frames / "10.ply")
    with pytest.raises(
        InputError, match=r"lab: frames/10\.ply is numbered 10 where frame 3 belongs"
    ):
        read_run(root)
    (frames / "10.ply").rename(frames / "3.ply")
    run = read_run(root)  # any zero padding, in the numbers' order
    assert [p.name for p in run.frame_paths] == ["0.ply", "1.ply", "2.ply", "3.ply"]
    shutil.copy(frames / "2.ply", frames / "002.ply")
    with pytest.raises(InputError, match=r"frames/2\.ply repeats where frame 3 belongs"):
        read_run(root)
    (frames / "002.ply").rename(frames / "2 copy.ply")
    with pytest.raises(InputError, match=r"frames/2 copy\.ply is not a frame name"):
        read_run(root)


def test_a_frame_of_a_run_in_another_format_is_named_at_the_gap(tmp_path, lab_sim) -> None:
    """Frame 2 written as .npy among .ply frames: the error named the gap at 000003.ply and not
    the file that was there, unread."""
    root = tmp_path / "lab"
    write_run(root, lab_sim)
    frames = root / "frames"
    (frames / "000002.ply").rename(frames / "000002.npy")
    with pytest.raises(
        InputError,
        match=r"frames/000003\.ply is numbered 3 where frame 2 belongs \(000002\.npy not "
        r"read: a run's frames are \.ply\)",
    ):
        read_run(root)


def test_a_run_of_frames_too_sparse_to_track_is_warned_about(tmp_path) -> None:
    """An orbit 200 m out wrote frames of 11 points without a word; every one is lost."""
    from spacepose.core.sim import OrbitConfig, simulate_orbit
    from spacepose.errors import SpaceposeWarning

    with pytest.warns(SpaceposeWarning, match=r"frames: 2 of 2 frames hold fewer than 100 points"):
        write_run(tmp_path / "far", simulate_orbit(OrbitConfig(frames=2, standoff_m=200.0)))
