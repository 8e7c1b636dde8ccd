"""``spacepose navigate`` on the inputs of tools/frames.py: a lost frame, a depth image folder."""

from __future__ import annotations

import json
import re
import shutil
import warnings

import numpy as np
import pytest
import yaml

from spacepose.core.depth import DepthCamera, render_depth
from spacepose.core.sim.scenarios import OrbitConfig, simulate_orbit
from spacepose.errors import InputError, SpaceposeWarning
from spacepose.tools.depth_io import read_depth_image, write_depth_image
from spacepose.tools.navigation_config_io import SCENARIO_KEYS
from spacepose.tools.navigation_io import navigate_run
from spacepose.tools.runs import write_run

FRAMES = 6


@pytest.fixture(scope="module")
def run_dir(tmp_path_factory):
    return write_run(
        tmp_path_factory.mktemp("orbit") / "run", simulate_orbit(OrbitConfig(frames=FRAMES))
    )


def _prior(run_dir) -> tuple[float, ...]:
    """The simulator's initial attitude as the coarse prior (picks among symmetric poses)."""
    return tuple(json.loads((run_dir / "scenario.json").read_text())["initial_q_I_B"])


def test_unreadable_frame_does_not_abort_navigation(run_dir, tmp_path):
    """Frame 3 is emptied (zero bytes): navigation predicts through it and writes every row."""
    bad = tmp_path / "run"
    bad.mkdir()
    for p in run_dir.rglob("*"):
        if p.is_file():
            (bad / p.relative_to(run_dir)).parent.mkdir(parents=True, exist_ok=True)
            (bad / p.relative_to(run_dir)).write_bytes(p.read_bytes())
    victim = sorted((bad / "frames").glob("*.ply"))[3]
    victim.write_bytes(b"")
    ref = navigate_run(run_dir, tmp_path / "ref.csv", prior_q_I_B=_prior(run_dir))
    # The loss is not silent: a warning names the frame and its file.
    with pytest.warns(SpaceposeWarning, match=rf"frame 3 cannot be read.*{victim.name}"):
        got = navigate_run(bad, tmp_path / "nav.csv", prior_q_I_B=_prior(run_dir))
    assert len(got.rows) == FRAMES
    assert [r.n_rect > 0 for r in got.rows] == [k != 3 for k in range(FRAMES)]
    assert ref.rows[3].n_rect > 0 and got.rows[3].status == "predict"
    ref_lines, got_lines = ((tmp_path / n).read_text().splitlines() for n in ("ref.csv", "nav.csv"))
    assert got_lines[:4] == ref_lines[:4]  # header and frames 0-2 untouched by the loss


@pytest.mark.parametrize(
    ("points", "problem"),
    [
        ([[0.0, 0.0, 10.0], [0.0, 0.1, 10.0]], "2 point(s): a plane needs 3"),
        ([[0.0, 0.0, 10.0], [0.0, 0.1, 10.0], [0.0, 0.2, 10.0]], "all 3 points are collinear"),
        ([[0.0, 0.0, 10.0]] * 50, "all 50 points are at one place"),
    ],
)
@pytest.mark.parametrize("measurements", ["rectangles", "both"])
def test_a_frame_without_a_plane_does_not_abort_navigation(
    run_dir, tmp_path, points, problem, measurements
):
    """Frame 3 holds 2 points, 3 on a line, or 50 at one place: plane extraction refused it
    and that ended the whole run (exit 1, nothing written). Now it is navigated as empty,
    warned about by name, and every row is written."""
    from spacepose.tools.cloud_io import write_cloud

    bad = tmp_path / "run"
    for p in run_dir.rglob("*"):
        if p.is_file():
            (bad / p.relative_to(run_dir)).parent.mkdir(parents=True, exist_ok=True)
            (bad / p.relative_to(run_dir)).write_bytes(p.read_bytes())
    victim = write_cloud(bad / "frames" / "000003.ply", np.array(points))
    with pytest.warns(SpaceposeWarning, match=rf"frame 3 holds no plane, navigated as empty: "
                      rf"{victim}: {re.escape(problem)}"):  # fmt: skip
        got = navigate_run(
            bad, tmp_path / "nav.csv", prior_q_I_B=_prior(run_dir), measurements=measurements
        )
    assert len(got.rows) == FRAMES and got.rows[3].n_rect == 0
    assert got.rows[3].status == "predict" and got.rows[4].state is not None
    if measurements == "both":
        health = (tmp_path / "nav.health.csv").read_text().splitlines()
        assert ",lost," in health[4] and problem in health[4]


def test_depth_folder_navigates_like_its_cloud_folder(run_dir, tmp_path, capsys):
    """The orbit frames as 16-bit PNG depth maps (mm) navigate exactly as the .npy clouds
    back-projected here from the same depths; the intrinsics come from --intrinsics."""
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
    keep = ("mean_motion", "R_O_C", "rectangles")
    (tmp_path / "scenario.yaml").write_text(yaml.safe_dump({k: scenario[k] for k in keep}))
    common = {"scenario": tmp_path / "scenario.yaml", "prior_q_I_B": _prior(run_dir)}
    ref, out = tmp_path / "ref.csv", tmp_path / "nav.csv"
    navigate_run(cloud_dir, ref, **common)
    got = navigate_run(depth_dir, out, intrinsics=intrinsics, **common)
    assert out.read_text() == ref.read_text()
    assert all(r.n_rect > 0 for r in got.rows)


def test_an_output_that_cannot_be_written_fails_before_navigating(run_dir, tmp_path, monkeypatch):
    def no_navigation(*args, **kwargs):
        raise AssertionError("navigation started before the output was checked")

    monkeypatch.setattr("spacepose.tools.navigation_io.RelativeNavigator.step", no_navigation)
    (tmp_path / "NAV.csv").mkdir()
    with pytest.raises(InputError, match=r"NAV\.csv: output exists and is not a regular file"):
        navigate_run(run_dir, tmp_path / "NAV.csv")
    (tmp_path / "out.config.json").mkdir()  # a companion in the way counts too
    with pytest.raises(InputError, match=r"out\.config\.json"):
        navigate_run(run_dir, tmp_path / "out.csv")


def test_a_scenario_file_key_no_scenario_holds_is_named(run_dir, tmp_path, monkeypatch):
    """A misspelt optional key (``rectangle`` for ``rectangles``) used to be ignored without a
    word. A simulated run's own scenario.json holds no key the warning calls unknown."""

    class Stop(Exception):
        pass

    def stop(*args, **kwargs):
        raise Stop

    monkeypatch.setattr("spacepose.tools.navigation_io.RelativeNavigator.step", stop)
    scenario = json.loads((run_dir / "scenario.json").read_text())
    assert set(scenario) <= SCENARIO_KEYS
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(Stop):
            navigate_run(run_dir, tmp_path / "a.csv", scenario=run_dir / "scenario.json")
    typo = tmp_path / "typo.json"
    typo.write_text(json.dumps(scenario | {"rectangle": scenario["rectangles"]}))
    with pytest.warns(SpaceposeWarning, match=r"typo\.json: unknown keys \['rectangle'\]"):
        with pytest.raises(Stop):
            navigate_run(run_dir, tmp_path / "b.csv", scenario=typo)
    # The same key in a run folder's own scenario.json (edited by hand) was read silently.
    edited = tmp_path / "edited"
    shutil.copytree(run_dir, edited)
    (edited / "scenario.json").write_text(json.dumps(scenario | {"mean_motoin": 1e-3}))
    with pytest.warns(SpaceposeWarning, match=r"scenario\.json: unknown keys \['mean_motoin'\]"):
        with pytest.raises(Stop):
            navigate_run(edited, tmp_path / "c.csv")
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(Stop):
            navigate_run(run_dir, tmp_path / "d.csv")


def test_a_run_with_no_readable_frame_says_so_alone(run_dir, tmp_path):
    """Every frame unreadable: the error went on to "none of the frames shows a whole
    rectangle of the catalogue (check the catalogue's sizes ...)", sending the user after the
    catalogue, which no frame was there to test."""
    bad = tmp_path / "run"
    shutil.copytree(run_dir, bad)
    for frame in (bad / "frames").iterdir():
        frame.write_text("not a cloud\n")
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", SpaceposeWarning)  # one per frame, as it is read
        with pytest.raises(InputError) as exc:
            navigate_run(bad, tmp_path / "nav.csv", prior_q_I_B=_prior(run_dir))
    message = str(exc.value)
    assert f"no frame navigated: none of the {FRAMES} frames could be read (frame 0: " in message
    assert "catalogue" not in message
