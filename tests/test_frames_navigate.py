"""``spacepose navigate`` on the inputs of tools/frames.py: a lost frame, a depth image folder."""

from __future__ import annotations

import csv
import json

import numpy as np
import pytest
import yaml

from spacepose.cli import main
from spacepose.core.depth import DepthCamera, render_depth
from spacepose.core.sim.scenarios import OrbitConfig, simulate_orbit
from spacepose.tools.depth_io import read_depth_image, write_depth_image
from spacepose.tools.runs import write_run

FRAMES = 6


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    return write_run(
        tmp_path_factory.mktemp("orbit") / "run", simulate_orbit(OrbitConfig(frames=FRAMES))
    )


def _rows(path):
    with path.open() as fh:
        return list(csv.reader(fh))[1:]


def test_unreadable_frame_does_not_abort_navigation(run_dir, tmp_path, capsys):
    """Frame 3 is emptied (zero bytes): navigate predicts through it and writes every row."""
    bad = tmp_path / "run"
    bad.mkdir()
    for p in run_dir.rglob("*"):
        if p.is_file():
            (bad / p.relative_to(run_dir)).parent.mkdir(parents=True, exist_ok=True)
            (bad / p.relative_to(run_dir)).write_bytes(p.read_bytes())
    victim = sorted((bad / "frames").glob("*.ply"))[3]
    victim.write_bytes(b"")
    ref, out = tmp_path / "ref.csv", tmp_path / "nav.csv"
    assert main(["navigate", str(run_dir), "--out", str(ref), "--prior-from-scenario"]) == 0
    code = main(["navigate", str(bad), "--out", str(out), "--prior-from-scenario"])
    assert code == 0, capsys.readouterr().err
    rows, ref_rows = _rows(out), _rows(ref)
    assert len(rows) == FRAMES
    assert rows[3][-1] == "predict" and ref_rows[3][-1] == "update"
    assert rows[:3] == ref_rows[:3]  # the frames before the loss are untouched


def test_depth_folder_navigates_like_its_cloud_folder(run_dir, tmp_path, capsys):
    """The orbit frames as 16-bit PNG depth maps (mm) navigate exactly as the .npy clouds
    back-projected here from the same depths."""
    sensor = OrbitConfig(frames=FRAMES).sensor
    camera = DepthCamera(
        fx=sensor.focal_px, fy=sensor.focal_px, cx=0.5 * (sensor.width - 1),
        cy=0.5 * (sensor.height - 1), depth_scale=0.001,
    )  # fmt: skip
    depth_dir, cloud_dir = tmp_path / "depth", tmp_path / "clouds"
    cloud_dir.mkdir()
    sim = simulate_orbit(OrbitConfig(frames=FRAMES))
    for k in range(FRAMES):
        image = render_depth(sim.frame(k).cloud.points, camera, sensor.height, sensor.width)
        units = read_depth_image(write_depth_image(depth_dir / f"{k:03d}.png", image, 0.001))
        v, u = np.nonzero(units)
        z = units[v, u] * 0.001
        xyz = np.column_stack([(u - camera.cx) / camera.fx * z, (v - camera.cy) / camera.fy * z, z])
        np.save(cloud_dir / f"{k:03d}.npy", xyz)
    stamps = "".join(f"{float(t)!r}\n" for t in sim.timestamps)
    for folder in (depth_dir, cloud_dir):
        (folder / "timestamps.txt").write_text(stamps)
    intrinsics = tmp_path / "camera.json"
    intrinsics.write_text(json.dumps(camera.model_dump(exclude_none=True)))
    scenario = json.loads((run_dir / "scenario.json").read_text())
    keep = ("mean_motion", "R_O_C", "rectangles", "initial_q_I_B")
    (tmp_path / "scenario.yaml").write_text(yaml.safe_dump({k: scenario[k] for k in keep}))
    common = ["--scenario", str(tmp_path / "scenario.yaml"), "--prior-from-scenario"]
    ref, out = tmp_path / "ref.csv", tmp_path / "nav.csv"
    assert main(["navigate", str(cloud_dir), "--out", str(ref), *common]) == 0
    args = ["navigate", str(depth_dir), "--out", str(out), "--intrinsics", str(intrinsics)]
    assert main([*args, *common]) == 0, capsys.readouterr().err
    assert out.read_text() == ref.read_text()
    assert {r[-1] for r in _rows(out)[1:]} == {"update"}
