"""``spacepose navigate --measurements registration|both [--model]`` on simulated orbit runs: a
mesh target without rectangles (registration only) and the default target (both)."""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from spacepose.cli import main
from spacepose.core.sim.scenarios import OrbitConfig, simulate_orbit
from spacepose.tools.runs import write_run

FRAMES = 8
HUBBLE = Path(__file__).resolve().parents[1] / "data" / "models" / "hubble_model_kit.obj"


@pytest.fixture(scope="module")
def hubble_run(tmp_path_factory):
    config = OrbitConfig(frames=FRAMES, model=str(HUBBLE), model_scale=0.1)
    return write_run(tmp_path_factory.mktemp("orbit") / "hubble", simulate_orbit(config))


def _rows(path: Path) -> list[dict[str, str]]:
    with path.open() as fh:
        return list(csv.DictReader(fh))


def test_registration_navigates_a_target_without_rectangles(hubble_run, tmp_path):
    out = tmp_path / "nav.csv"
    args = ["navigate", str(hubble_run), "--out", str(out), "--measurements", "registration"]
    assert main(args) == 0
    rows = _rows(out)
    assert len(rows) == FRAMES
    navigated = [r for r in rows if r["status"] in ("init", "update")]
    assert len(navigated) >= FRAMES - 2 and rows[-1]["status"] == "update"
    health = _rows(out.with_suffix(".health.csv"))
    assert len(health) == FRAMES
    # Against the truth: the attitude after 8 frames is within 1° (the registration's start).
    truth = _rows(hubble_run / "truth.csv")
    q_est = [float(rows[-1][k]) for k in ("qx", "qy", "qz", "qw")]
    q_true = [float(truth[-1][k]) for k in ("qx", "qy", "qz", "qw")]
    angle = (Rotation.from_quat(q_est).inv() * Rotation.from_quat(q_true)).magnitude()
    assert np.degrees(angle) < 1.0


def test_model_option_and_refusals(hubble_run, tmp_path, capsys):
    out = tmp_path / "nav.csv"
    base = ["navigate", str(hubble_run), "--out", str(out)]
    # The run's model.ply given explicitly gives the same rows as the default.
    assert main([*base, "--measurements", "registration", "--model",
                 str(hubble_run / "model.ply")]) == 0  # fmt: skip
    assert len(_rows(out)) == FRAMES
    # No rectangle catalogue: 'both' is refused with one line saying so.
    assert main([*base, "--measurements", "both"]) == 1
    assert "catalogue" in capsys.readouterr().err
    assert main([*base, "--measurements", "planes"]) == 1
    assert "--measurements" in capsys.readouterr().err


def test_a_frame_the_tracker_cannot_use_is_said_on_stderr(hubble_run, tmp_path, capsys):
    """With registration poses a frame of two points was lost in NAV.health.csv alone; the
    rectangles' path says such a frame on stderr."""
    import shutil

    from spacepose.tools.cloud_io import write_cloud

    run = tmp_path / "run"
    shutil.copytree(hubble_run, run)
    write_cloud(run / "frames" / "000003.ply", np.array([[0.0, 0.0, 25.0], [0.1, 0.0, 25.0]]))
    out = tmp_path / "nav.csv"
    args = ["navigate", str(run), "--out", str(out), "--measurements", "registration"]
    assert main(args) == 0
    err = capsys.readouterr().err
    assert f"warning: {out.with_suffix('.health.csv')}: frame 3 navigated as empty: unusable" in err


def test_the_poses_sigma_factor_is_measured_on_the_run(hubble_run, tmp_path, monkeypatch):
    """A run folder holds its mesh and sensor: the navigation measures the poses' σ factor by
    the bootstrap and writes it in the effective config; with another model, or the bootstrap
    off, the configured factor stays. (Batches of 2 frames, 2 needed: the run has 8.)"""
    import json

    from spacepose.core.fused_navigation import FusionConfig
    from spacepose.tools import pose_bootstrap_run
    from spacepose.tools.navigation_io import navigate_run

    monkeypatch.setattr(pose_bootstrap_run, "BATCH_FRAMES", 2)
    monkeypatch.setattr(pose_bootstrap_run, "MIN_BATCHES", 2)

    def scale(out: Path, **options) -> float:
        navigate_run(hubble_run, out, measurements="registration", **options)
        return json.loads(out.with_suffix(".config.json").read_text())["pose_sigma_scale"]

    default = FusionConfig().pose_sigma_scale
    measured = scale(tmp_path / "a" / "nav.csv")
    assert measured >= 1.0 and measured != default
    # Beside it, what was measured: the factor is the largest axis's batch ratio's root.
    noise = json.loads((tmp_path / "a" / "nav.pose_noise.json").read_text())
    assert noise["scale"] == pytest.approx(np.sqrt(max(1.0, max(noise["batch_ratios"]))))
    assert len(noise["batch_ratios"]) == len(noise["axes"]) == 6 and noise["batch"] == 2
    # The rotation's factor and the translation's, about the target's origin, are the two the
    # navigation used.
    about = noise["target_origin_ratios"]
    assert noise["rotation_scale"] == measured
    assert measured == pytest.approx(np.sqrt(max(1.0, max(about[:3]))))
    assert noise["translation_scale"] == pytest.approx(np.sqrt(max(1.0, max(about[3:]))))
    assert noise["frames"] % 2 == 0 and 4 <= noise["frames"] <= 8
    # And the biases it found, taken off the poses: the effective config holds them.
    config = json.loads((tmp_path / "a" / "nav.config.json").read_text())
    assert config["pose_sigma_scale_translation"] == noise["translation_scale"]
    assert config["pose_bias_sensor"] == noise["bias"]["sensor_m"]
    assert config["pose_bias_body"] == noise["bias"]["body_m"]
    assert len(noise["bias"]["sensor_sigma_m"]) == len(noise["bias"]["body_sigma_m"]) == 3
    assert scale(tmp_path / "b" / "nav.csv", model=hubble_run / "model.ply") == default
    off = FusionConfig(bootstrap_poses=False)
    # An earlier run's measurement in the same place is removed, not left to mislead.
    stale = tmp_path / "a" / "nav.pose_noise.json"
    assert scale(tmp_path / "a" / "nav.csv", fusion=off) == default
    assert not stale.exists()
    # A run whose mesh cannot be read navigates with the configured factor, and says why.
    import shutil
    import warnings

    from spacepose.errors import SpaceposeWarning

    broken = shutil.copytree(hubble_run, tmp_path / "broken")
    (broken / "model.obj").write_text("v 0 0 nan\n")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        navigate_run(broken, tmp_path / "d" / "nav.csv", measurements="registration")
    said = [str(w.message) for w in caught if issubclass(w.category, SpaceposeWarning)]
    assert any("model.obj" in m and "not measured" in m for m in said), said
    config = json.loads((tmp_path / "d" / "nav.config.json").read_text())
    assert config["pose_sigma_scale"] == default
