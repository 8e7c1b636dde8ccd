"""Twenty-first hostile round: a navigate config given to track, an EXR channel of distances."""

from __future__ import annotations

import numpy as np
import pytest


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
