"""The pipelines of ``li-global`` (tools/experiments/li_global_pipelines.py): ours is the same on
any thread count, and bad configs of the experiment are refused."""

from __future__ import annotations

import numpy as np
import pytest

from spacepose.core import se3
from spacepose.core.cloud import PointCloud
from spacepose.core.config import validate_config
from spacepose.core.sim import scenario_config, simulate
from spacepose.errors import ConfigError
from spacepose.tools.experiments.li_global import pose_error, random_poses
from spacepose.tools.experiments.li_global_pipelines import GlobalExperimentConfig, ours_global


def test_ours_is_the_same_on_any_workers():
    sim = simulate(scenario_config("lab", seed=0, frames=1))
    T_source_model = random_poses(1, 0.3, seed=3)[0]
    source = PointCloud(se3.transform_points(T_source_model, sim.model_cloud().points))
    frame = sim.frame(0)
    a = ours_global(source, frame.cloud, workers=1)
    b = ours_global(source, frame.cloud, workers=2)
    np.testing.assert_array_equal(a.T_target_source, b.T_target_source)
    true_T = frame.T_sensor_target @ se3.invert(T_source_model)
    angle, shift = pose_error(a.T_target_source, true_T, T_source_model)
    assert angle < 1.0 and shift < 0.01, (angle, shift)


@pytest.mark.parametrize(
    ("data", "message"),
    [
        ({"poses": 0}, "poses"),
        ({"max_translation": -0.1}, "max_translation"),
        ({"max_rotation_deg": 0}, "max_rotation_deg"),
        ({"seeds": 3}, "seeds"),
    ],
)
def test_bad_config_raises(data, message):
    with pytest.raises(ConfigError, match=message):
        validate_config(GlobalExperimentConfig, data)
