"""The tracker's motion model (core/motion.py): constant velocity and its observed error."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.stats import chi2

from spacepose.core import se3
from spacepose.core.motion import SETTLED_TESTS, MotionModel


def test_model_error_is_the_rms_of_the_recent_errors_and_drops_old_ones():
    m = MotionModel()
    assert m.model_error() is None
    for e in [(0.003, 0.01), (0.004, 0.02)]:
        m.accept(0.0, np.eye(4), np.zeros((6, 6)), e, restart=False)
    assert m.model_error() == pytest.approx((np.sqrt(12.5e-6), np.sqrt(2.5e-4)))
    for _ in range(30):
        m.accept(0.0, np.eye(4), np.zeros((6, 6)), (0.001, 0.0), restart=False)
    assert m.model_error() == pytest.approx((0.001, 0.0))  # the window forgot the first two


def test_prediction_and_its_covariance():
    m = MotionModel()
    assert m.predict(1.0, 0, (0.01, 0.1)) is None
    D = se3.exp([0.0, 0.02, 0.0, 0.01, 0.0, 0.0])
    m.accept(0.0, np.eye(4), np.zeros((6, 6)), None, restart=True)
    first = m.predict(1.0, 0, (0.01, 0.1))
    assert not first.velocity_known
    np.testing.assert_allclose(first.T_sensor_target, np.eye(4))
    # Without a measured error the fallback (0.01 m, 0.1 rad) spreads over three axes.
    np.testing.assert_allclose(np.diag(first.covariance), [0.1**2 / 3] * 3 + [0.01**2 / 3] * 3)
    m.accept(1.0, D, np.zeros((6, 6)), None, restart=False)
    p = m.predict(2.0, 0, (0.01, 0.1))
    assert p.velocity_known
    np.testing.assert_allclose(p.T_sensor_target, D @ D, atol=1e-12)
    # Two frames missed: the step's uncertainty is counted three times over (in σ).
    late = m.predict(2.0, 2, (0.01, 0.1))
    np.testing.assert_allclose(late.covariance, 9 * p.covariance, rtol=1e-12)
    # A restart forgets the velocity.
    m.accept(3.0, D, np.zeros((6, 6)), None, restart=True)
    assert not m.predict(4.0, 0, (0.01, 0.1)).velocity_known


def test_a_velocity_is_tested_once_it_has_predicted_a_frame_and_again_after_a_restart():
    """The first velocity, and the first after a coarse restart, is one registered step that
    nothing confirmed; the errors kept from before a restart are of another velocity, so they
    do not count (the tracker holds such a frame back from `ok`)."""
    m = MotionModel()
    pose, cov = np.eye(4), np.zeros((6, 6))
    m.accept(0.0, pose, cov, None, restart=True)  # the first frame
    m.accept(1.0, pose, cov, None, restart=False)  # no velocity yet to predict with
    assert not m.tested
    m.accept(2.0, pose, cov, (0.002, 0.01), restart=False)  # predicted and measured
    assert m.tested
    m.accept(3.0, pose, cov, (0.001, 0.01), restart=False)
    m.accept(4.0, pose, cov, None, restart=True)  # a coarse restart
    m.accept(5.0, pose, cov, None, restart=False)
    assert not m.tested and m.model_error() is not None  # the old errors stay, as bounds
    m.accept(6.0, pose, cov, (0.003, 0.02), restart=False)
    assert m.tested


def test_a_velocity_settles_after_six_measured_predictions_and_again_after_a_restart():
    """Six errors bound their RMS within a factor of two at 95 % (χ²₆), five do not."""
    assert np.sqrt(SETTLED_TESTS / chi2.ppf(0.05, SETTLED_TESTS)) <= 2.0
    assert np.sqrt((SETTLED_TESTS - 1) / chi2.ppf(0.05, SETTLED_TESTS - 1)) > 2.0
    m = MotionModel()
    pose, cov = np.eye(4), np.zeros((6, 6))
    m.accept(0.0, pose, cov, None, restart=True)
    for k in range(1, SETTLED_TESTS + 1):
        assert not m.settled
        m.accept(float(k), pose, cov, (0.001, 0.01), restart=False)
    assert m.settled and m.tests == SETTLED_TESTS
    m.accept(10.0, pose, cov, None, restart=False)  # a frame without a prediction keeps it
    assert m.settled
    m.accept(11.0, pose, cov, None, restart=True)
    assert not m.settled and not m.tested and m.tests == 0
