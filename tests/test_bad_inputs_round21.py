"""Twenty-first hostile round: ranges too noisy for the target's size, tracked model-free."""

from __future__ import annotations

import numpy as np
import pytest

from spacepose.core import se3
from spacepose.core.scale import COARSE_NOISE_SHARE
from spacepose.core.sim.scenarios import scenario_config, simulate_lab
from spacepose.core.tracker import Tracker, TrackerConfig


def _track(noise_scale: float, seed: int, frames: int = 6):
    """Statuses, reasons and rotation errors (°) of a model-free track of the lab run."""
    sim = simulate_lab(scenario_config("lab", frames=frames, seed=seed, noise_scale=noise_scale))
    tracker = Tracker(TrackerConfig(), workers=1)
    first = sim.frame(0).T_sensor_target
    rows = []
    for k in range(frames):
        frame = sim.frame(k)
        result = tracker.track_frame(frame.cloud, frame.timestamp)
        truth = frame.T_sensor_target @ se3.invert(first)
        error = se3.log(se3.invert(truth) @ result.T_sensor_target)
        rows.append((result.status, result.reasons, np.degrees(np.linalg.norm(error[:3]))))
    return rows, tracker.scale


def test_ranges_a_tenth_of_the_target_are_not_ok_model_free():
    """The lab run at 20 times its range noise (23 mm on a target of 0.26 m RMS radius) was
    `ok` 0.6-1.3° off at up to 8.6σ with no reason given (x30: 12-16σ, x50: 12σ). Such a
    frame is now `degraded`, naming the noise and the radius; at 10 times (0.047 of the
    radius) the rule says nothing and frames are `ok` as before."""
    rows, scale = _track(20.0, 1)
    assert scale.coarse and scale.noise / scale.radius > 1.4 * COARSE_NOISE_SHARE
    assert [s for s, _, _ in rows[1:]] == ["degraded"] * 5
    assert all(any("too coarse a surface" in r for r in reasons) for _, reasons, _ in rows[1:])
    assert max(error for *_, error in rows[1:]) > 0.3  # what the rule keeps from being ok
    rows, scale = _track(10.0, 1)
    assert scale.noise / scale.radius < COARSE_NOISE_SHARE
    assert "ok" in [s for s, _, _ in rows[1:]]
    assert not any("too coarse" in r for _, reasons, _ in rows for r in reasons)


@pytest.mark.parametrize("target_noise", [(0.5, 3.0), (6.0, 3.0)])
def test_the_grid_ranges_stay_below_the_bound(target_noise):
    """The robustness grid's noisiest cells (lab mock-up, noise x3, at 0.5 and 6 m) read
    0.018 and 0.043 of the radius: the bound leaves every grid frame as it was."""
    from spacepose.core.scale import derive_scale
    from spacepose.tools.experiments.robustness_cells import Cell, cell_scenario

    range_m, noise = target_noise
    sim = simulate_lab(cell_scenario(Cell(range=range_m, noise=noise), 2))
    scale = derive_scale(sim.frame(0).cloud.points, 2000)
    assert not scale.coarse and scale.noise / scale.radius < 0.75 * COARSE_NOISE_SHARE


def test_a_navigate_config_given_to_track_is_named_as_such(tmp_path):
    """``track --config`` with a navigate config of one key said only "ekf: Extra inputs are
    not permitted"; a config that mixes in a tracker key is still refused field by field."""
    from spacepose.errors import ConfigError
    from spacepose.tools.tracking_io import tracker_config

    path = tmp_path / "nav.yaml"
    path.write_text("ekf:\n  q_attitude: 1.0e-8\n")
    with pytest.raises(ConfigError, match=r"nav\.yaml: ekf is a navigate setting, not the "):
        tracker_config(path)
    path.write_text("use_mls: true\nekf: 1\n")
    with pytest.raises(ConfigError, match=r"invalid tracker config: ekf: Extra inputs"):
        tracker_config(path)


def test_an_exr_distance_channel_is_said_to_be_read_as_boresight_depth(tmp_path):
    """A render's EXR whose one channel is named ``distance`` (the distance along each ray, as
    a name) was read as depth along the boresight without a word (frames 0.7-1.1° off). It is
    now warned of unless the intrinsics say which depth it is (``depth_kind``)."""
    import warnings

    import OpenEXR

    from spacepose.core.depth import DepthCamera
    from spacepose.errors import SpaceposeWarning
    from spacepose.tools.depth_io import read_depth_cloud

    path = tmp_path / "0.exr"
    values = np.full((48, 64), 2.0, dtype=np.float32)
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with OpenEXR.File(header, {"distance": values}) as exr:
        exr.write(str(path))
    camera = DepthCamera(fx=60.0, fy=60.0, cx=31.5, cy=23.5)
    with pytest.warns(SpaceposeWarning, match=r"channel 'distance' is read as depth along the"):
        boresight = read_depth_cloud(path, camera)
    assert np.allclose(boresight.points[:, 2], 2.0)
    with warnings.catch_warnings():
        warnings.simplefilter("error", SpaceposeWarning)
        ranged = read_depth_cloud(path, camera.model_copy(update={"depth_kind": "range"}))
    assert np.allclose(np.linalg.norm(ranged.points, axis=1), 2.0)
