"""The tracker's external prior (``Tracker.track_frame(..., prior=(T, cov))``): a prediction made
outside the tracker, such as the navigation filter's, seeds registration and confirms the pose."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from spacepose.core import se3
from spacepose.core.metrics import pose_errors
from spacepose.core.motion import Prediction
from spacepose.core.sim.scenarios import LabConfig, simulate_lab
from spacepose.core.tracker import Tracker
from spacepose.core.tracker_config import TrackerConfig
from spacepose.errors import InputError

N_FRAMES = 6
JUMP_AT = 3


@pytest.fixture(scope="module")
def jumped():
    """Lab frames whose target turns by 25° about its centre from frame 3 on (no motion model
    can foresee it), with the true poses after the jump."""
    sim = simulate_lab(LabConfig(frames=N_FRAMES))
    frames = [sim.frame(k) for k in range(N_FRAMES)]
    c = frames[0].cloud.points.mean(axis=0)
    turn = se3.make_transform(Rotation.from_euler("y", 25.0, degrees=True), np.zeros(3))
    jump = se3.make_transform(np.eye(3), c) @ turn @ se3.make_transform(np.eye(3), -c)
    clouds, truth = [], []
    for k, f in enumerate(frames):
        J = jump if k >= JUMP_AT else np.eye(4)
        clouds.append(f.cloud.transformed(J))
        truth.append(J @ f.T_sensor_target)
    return sim, clouds, np.array(truth)


def _off(T: np.ndarray, deg: float, metres: float) -> np.ndarray:
    """``T`` moved by a left perturbation of ``deg`` about x and ``metres`` along y."""
    return se3.exp([np.radians(deg), 0.0, 0.0, 0.0, metres, 0.0]) @ T


def test_a_prior_seeds_registration_across_an_unforeseen_jump(jumped):
    sim, clouds, truth = jumped
    model = sim.model_cloud()
    cov = np.diag([np.radians(1.0) ** 2] * 3 + [0.005**2] * 3)
    cfg = TrackerConfig(method="point_to_plane")

    alone = Tracker(cfg, model, workers=2)
    plain = [alone.track_frame(cl, t) for cl, t in zip(clouds, sim.timestamps, strict=True)]
    # The motion model predicts no jump: frame 3 needs coarse registration or is not ok.
    assert plain[JUMP_AT].coarse or plain[JUMP_AT].status != "ok"

    seeded = Tracker(cfg, model, workers=2)
    results = [
        seeded.track_frame(cl, t, prior=(_off(T, 1.0, 0.005), cov))
        for cl, t, T in zip(clouds, sim.timestamps, truth, strict=True)
    ]
    # A prior 1° and 5 mm off the truth: no coarse registration, every frame right. The first
    # is degraded (1° is beyond the prediction bound before any prediction error is measured);
    # from then on the bound follows the prior's measured error and every frame is ok.
    assert not any(r.coarse for r in results)
    assert [r.status for r in results] == ["degraded"] + ["ok"] * (N_FRAMES - 1)
    dt, de = pose_errors(np.array([r.T_sensor_target for r in results]), truth)
    assert np.abs(dt).max() < 2e-3 and np.degrees(np.abs(de)).max() < 0.2


def test_a_prior_far_from_the_data_is_not_confirmed(jumped):
    """The health check judges the registration against the prior as against any prediction:
    a prior 20° off is not where the registration lands, and the frame is not ok."""
    sim, clouds, truth = jumped
    cfg = TrackerConfig(method="point_to_plane")
    tracker = Tracker(cfg, sim.model_cloud(), workers=2)
    cov = np.diag([np.radians(1.0) ** 2] * 3 + [0.005**2] * 3)
    for k in range(JUMP_AT):
        assert tracker.track_frame(clouds[k], sim.timestamps[k]).status in ("ok", "degraded")
    far = _off(truth[JUMP_AT], -20.0, 0.0)
    result = tracker.track_frame(clouds[JUMP_AT], sim.timestamps[JUMP_AT], prior=(far, cov))
    assert result.status != "ok"


def test_given_prediction_is_checked():
    T = se3.exp([0.1, 0.2, -0.3, 1.0, 2.0, 3.0])
    p = Prediction.given(T, np.eye(6) * 1e-4)
    np.testing.assert_allclose(p.T_sensor_target, T, atol=1e-12)
    assert p.velocity_known
    with pytest.raises(InputError):
        Prediction.given(np.eye(4) * 2.0, np.eye(6))
    with pytest.raises(InputError):
        Prediction.given(T, np.eye(5))
    with pytest.raises(InputError):
        Prediction.given(T, np.full((6, 6), np.nan))
