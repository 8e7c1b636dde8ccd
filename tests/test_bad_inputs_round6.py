"""Bad inputs found by a sixth hostile round: each ends in one line naming the file and the
problem, never a traceback, a hang, lost output or a silently wrong result."""

from __future__ import annotations

import pytest
import yaml

from spacepose.cli import main
from spacepose.errors import ConfigError, InputError
from spacepose.tools.campaign_spec import load_campaign_config
from spacepose.tools.tracking_io import check_output
from test_bad_inputs_round4 import _cli_error, _cloud_folder, _refused

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
    assert str(exc.value).startswith(f"{config}: invalid CampaignConfig:")
    assert "frames values must be integers >= 2, got [1]" in str(exc.value)
