"""The fine gate follows the measured residual noise (core.residual_noise)."""

import numpy as np
import pytest

from spacepose.core.cloud import PointCloud
from spacepose.core.keyframes import PreparedCloud
from spacepose.core.residual_noise import (
    GATE_SIGMAS,
    MEMORY,
    ResidualNoise,
    point_to_plane_sigma,
)


def _plane(n: int, rng: np.random.Generator) -> PointCloud:
    xy = rng.uniform(-0.5, 0.5, size=(n, 2))
    pts = np.c_[xy, np.zeros(n)]
    return PointCloud(pts, np.tile([0.0, 0.0, 1.0], (n, 1)))


@pytest.mark.parametrize("sigma", [0.5e-3, 2e-3, 8e-3])
def test_sigma_of_gaussian_offsets_from_a_plane(sigma):
    """Source points N(0, σ) off an exact plane: the robust σ is σ (MAD of 20k normal draws
    is within 2 %), whatever the gate, as long as the window holds the distribution."""
    rng = np.random.default_rng(3)
    target = PreparedCloud(_plane(20000, rng))
    src = _plane(20000, rng).points + np.c_[np.zeros((20000, 2)), rng.normal(0, sigma, 20000)]
    measured = point_to_plane_sigma(np.eye(4), src, target, 6 * sigma, workers=1)
    assert measured == pytest.approx(sigma, rel=0.03)
    # Too few pairs within the window: no measurement.
    far = src + np.array([0.0, 0.0, 1.0])
    assert point_to_plane_sigma(np.eye(4), far, target, 0.01, 1) is None


def test_a_hint_narrows_the_search_but_not_the_answer():
    """The registration's last matches, passed as hints, give the σ of an unhinted search to
    the bit, even when some hints are far off (they only bound the search ball)."""
    rng = np.random.default_rng(5)
    target = PreparedCloud(_plane(5000, rng))
    src = _plane(3000, rng).points + np.c_[np.zeros((3000, 2)), rng.normal(0, 2e-3, 3000)]
    unhinted = point_to_plane_sigma(np.eye(4), src, target, 0.01, workers=1)
    hint = rng.integers(-1, 5000, size=3000)
    hinted = point_to_plane_sigma(np.eye(4), src, target, 0.01, workers=2, hint=hint)
    assert hinted == unhinted and 1.8e-3 < unhinted < 2.2e-3


def test_gate_widens_to_three_sigma_and_forgets_lost_frames():
    noise = ResidualNoise(voxel_gate=0.005)
    assert noise.sigma is None and noise.gate == 0.005 and noise.window == pytest.approx(0.015)
    # Below a third of the gate: the voxel gate stands and nothing needs repeating.
    assert noise.add(0.001) is False
    assert noise.gate == 0.005
    noise.commit()
    # A lost frame's large residuals are dropped.
    assert noise.add(0.05) is True
    noise.discard()
    assert noise.sigma == pytest.approx(0.001) and noise.gate == 0.005
    # An accepted noisy sensor: the median of the recent measurements sets the gate.
    for _ in range(MEMORY):
        noise.add(0.004)
        noise.commit()
    assert noise.sigma == pytest.approx(0.004)
    assert noise.gate == pytest.approx(GATE_SIGMAS * 0.004)
    assert noise.add(None) is False


def test_a_candidates_measurements_are_set_aside_until_it_is_kept():
    """The relocaliser registers several candidate poses of one frame; only the kept one's
    residual noise may widen the gate (wrong candidates' residuals are not the sensor's)."""
    noise = ResidualNoise(voxel_gate=0.005)
    noise.add(0.004)
    kept = noise.take()
    assert kept == [0.004] and noise.sigma is None and noise.gate == 0.005
    noise.add(0.05)  # a wrong candidate
    assert noise.gate == pytest.approx(GATE_SIGMAS * 0.05)
    assert noise.take() == [0.05]
    noise.restore(kept)
    noise.commit()
    assert noise.sigma == pytest.approx(0.004)
    assert noise.gate == pytest.approx(GATE_SIGMAS * 0.004)


def test_the_accepted_factor_follows_the_accepted_frames_alone():
    """The health bounds widen by the accepted frames' noise; the frame being checked does not
    widen its own bounds (a garbage frame's residuals would excuse themselves)."""
    noise = ResidualNoise(voxel_gate=0.005)
    assert noise.accepted_factor == 1.0
    noise.add(0.01)  # pending: this frame's own
    assert noise.gate == pytest.approx(0.03) and noise.accepted_factor == 1.0
    noise.commit()
    assert noise.accepted_factor == pytest.approx(GATE_SIGMAS * 0.01 / 0.005)
    noise.add(0.5)
    assert noise.accepted_factor == pytest.approx(6.0)
    noise.discard()
    # Below the voxel gate's third the voxel sets the scale: never narrower than it.
    quiet = ResidualNoise(voxel_gate=0.005)
    quiet.add(0.0005)
    quiet.commit()
    assert quiet.accepted_factor == 1.0
