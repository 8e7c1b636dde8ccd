"""Round 24 of bad inputs (the Python API): registrations far from their origin, covariances
that are no covariances, and values that were taken without a word."""

from __future__ import annotations

import numpy as np
import pytest

from spacepose.core import se3
from spacepose.core.cloud import PointCloud
from spacepose.core.icp import ICPConfig, icp, icp_correspondences
from spacepose.core.registration import RegistrationResult
from spacepose.errors import InputError


def _box_views(rng):
    """Two noisy samplings (N, 3) of a 0.6 x 0.4 x 0.3 m box's surface, the second moved by a
    small known motion; and that motion ``T_target_source``."""
    half = np.array([0.3, 0.2, 0.15])

    def sample(n):
        p = rng.uniform(-half, half, (n, 3))
        axis = rng.integers(0, 3, n)
        p[np.arange(n), axis] = np.where(rng.random(n) < 0.5, -1, 1) * half[axis]
        return p + rng.normal(scale=5e-4, size=p.shape)

    T = se3.exp([0.01, -0.02, 0.015, 0.004, -0.003, 0.002])
    return sample(6000), se3.transform_points(T, sample(6000)), T


@pytest.mark.parametrize("method", ["point_to_plane", "point_to_point"])
@pytest.mark.parametrize("offset", [1e6, 1e7])
def test_icp_far_from_the_origin_is_the_icp_at_home(rng, method, offset):
    # 1,000 km out point-to-plane came out 0.015° off and 3,000 km out "degenerate";
    # point-to-point gave covariances with negative variances.
    source, target, _ = _box_views(rng)
    config = ICPConfig(max_correspondence_distance=0.02, method=method)
    home = icp(source, target, config=config)
    o = offset * np.array([1.0, 0.3, -0.2])
    far = icp(source + o, target + o, config=config)
    S = se3.make_transform(np.eye(3), -o)
    moved = S @ far.T_target_source @ se3.invert(S)
    # The same pose to a few units in the last place of the far coordinates (np.spacing(1e7) is
    # 1.9e-9 m): 1e-9 m, below one such unit there, failed on another install's rounding.
    ulps = np.spacing(np.abs(o).max())
    assert np.linalg.norm(se3.log(moved @ se3.invert(home.T_target_source))) < 8 * ulps
    rotation_far = far.covariance()[:3, :3]
    np.testing.assert_allclose(rotation_far, home.covariance()[:3, :3], rtol=1e-6, atol=1e-18)
    assert np.all(np.diag(far.covariance()) > 0)


def test_far_icp_correspondences_are_given_where_the_clouds_are(rng):
    source, target, _ = _box_views(rng)
    o = np.array([2e6, -1e6, 5e5])
    config = ICPConfig(max_correspondence_distance=0.02)
    _, matches = icp_correspondences(source + o, target + o, config=config)
    _, home = icp_correspondences(source, target, config=config)
    np.testing.assert_allclose(matches.points - o, home.points, atol=1e-6)
    config = ICPConfig(max_correspondence_distance=0.02, method="point_to_plane")
    result, matches = icp_correspondences(source + o, target + o, config=config)
    np.testing.assert_allclose(matches.system[0], result.information)


def test_a_registration_result_refuses_what_no_registration_gives():
    with pytest.raises(InputError, match="T_target_source"):
        RegistrationResult(np.diag([2.0, 2.0, 2.0, 1.0]), 0.9, 0.001, 5, True)
    with pytest.raises(InputError, match="fitness"):
        RegistrationResult(np.eye(4), 5.0, 0.001, 5, True)
    with pytest.raises(InputError, match="inlier_rmse"):
        RegistrationResult(np.eye(4), 0.9, -0.1, 5, True)


@pytest.mark.parametrize(
    ("sigma", "match"),
    [(float("nan"), "finite"), (-1.0, "negative"), ("1", "number")],
)
def test_a_covariance_of_a_bad_sigma_is_refused(sigma, match):
    result = RegistrationResult(np.eye(4), 0.9, 0.001, 5, True, np.eye(6))
    with pytest.raises(InputError, match=match):
        result.covariance(sigma=sigma)


def test_a_covariance_of_a_negative_information_is_refused():
    result = RegistrationResult(np.eye(4), 0.9, 0.001, 5, True, -np.eye(6))
    with pytest.raises(InputError, match="negative eigenvalue"):
        result.covariance()


def test_a_point_cloud_refuses_sigma_of_another_shape(rng):
    points = rng.normal(size=(300, 3))
    with pytest.raises(InputError, match="sigma"):
        PointCloud(points, sigma=np.ones((100, 3)))
    assert PointCloud(points, sigma=np.full(300, 0.002)).sigma.shape == (300,)


def _still_filter(mean_motion=0.0):
    from spacepose.core.ekf import RelativeNavEKF
    from spacepose.core.nav_state import NavState

    state = NavState(
        t=0.0,
        rho=np.array([0.0, -10.0, 0.0]),
        v=np.array([0.001, 0.0, 0.0]),
        q_I_B=np.array([0.0, 0.0, 0.0, 1.0]),
        omega_B=np.zeros(3),
        k=np.array([0.3, -0.2, -0.1 / 0.94]),
        com=np.zeros(3),
    )
    return RelativeNavEKF(mean_motion, np.eye(3), state)


def test_a_long_gap_is_discretised_as_van_loan_does():
    # Composed step by step, a 1e5 s gap of a target that does not turn took 12 s (2e6 steps);
    # doubled, it takes its logarithm, and is the same transition and noise.
    from scipy.linalg import expm

    from spacepose.core.nav_state import discretise

    ekf = _still_filter()
    F = ekf._jacobian(ekf.w, ekf.p)
    Qc = np.diag(np.random.default_rng(2).uniform(0.5, 2.0, len(F))) * 1e-12
    dt = 3000.0
    m = len(F)
    E = expm(np.block([[-F, Qc], [np.zeros((m, m)), F.T]]) * dt)
    Phi_ref = E[m:, m:].T
    Phi, Q = discretise(F, Qc, dt)
    np.testing.assert_allclose(Phi, Phi_ref, atol=1e-9 * np.abs(Phi_ref).max())
    np.testing.assert_allclose(Q, Phi_ref @ E[:m, m:], rtol=1e-6, atol=1e-9 * np.abs(Q).max())


def test_a_gap_the_covariance_cannot_cross_is_refused_and_leaves_the_filter():
    from spacepose.errors import PredictionGapError

    ekf = _still_filter()
    before = (ekf.t, ekf.rho.copy(), ekf.P.copy())
    with pytest.raises(PredictionGapError, match="overflows"):
        ekf.predict(1e300)
    assert ekf.t == before[0]
    np.testing.assert_array_equal(ekf.rho, before[1])
    np.testing.assert_array_equal(ekf.P, before[2])


def test_a_mean_motion_no_orbit_has_is_refused():
    # 1e300 rad/s ended in Python's OverflowError; 0.063 is the LEO rate in degrees a second.
    for n in (1e300, 0.063):
        with pytest.raises(InputError, match="mean_motion"):
            _still_filter(n)


@pytest.mark.parametrize(
    ("covariance", "match"),
    [(-1e-4 * np.eye(6), "semi-definite"), (np.eye(6) + 5.0 * np.eye(6, k=1), "symmetric")],
)
def test_j_icp_averages_only_covariances(covariance, match):
    from spacepose.core.jicp import average_three_covariance

    good = 1e-4 * np.eye(6)
    with pytest.raises(InputError, match=f"cov_ji must be.*{match}"):
        average_three_covariance(np.eye(4), np.eye(4), good, good, covariance)
    np.testing.assert_allclose(
        average_three_covariance(np.eye(4), np.eye(4), good, good, good), 0.75 * good
    )


def test_a_predicted_centroid_of_a_non_finite_centre_is_refused():
    # It came out [nan, nan, nan], where update_centroid refuses the same centre.
    ekf = _still_filter()
    with pytest.raises(InputError, match="d_Bp"):
        ekf.predict_centroid("a", [np.nan, 0.0, 0.0])
    np.testing.assert_allclose(ekf.predict_centroid("a", [0.0, 0.0, 0.0]), ekf.rho)


@pytest.mark.parametrize(("fitness", "rmse"), [("0.9", 0.001), (0.9, None)])
def test_a_registration_result_of_fields_that_are_no_numbers_is_refused(fitness, rmse):
    with pytest.raises(InputError, match=r"fitness|inlier_rmse"):
        RegistrationResult(np.eye(4), fitness, rmse, 5, True)
    assert np.isnan(RegistrationResult(np.eye(4), float("nan"), float("nan"), 0, False).fitness)


def test_a_frame_of_text_is_lost_with_the_frames_own_reason():
    # The repeat check converted it first, and numpy's "could not convert string to float"
    # ended the run.
    from spacepose.core.tracker import Tracker

    result = Tracker(workers=1).track_frame(np.array([["a", "b", "c"]] * 200), 0.0)
    assert result.status == "lost"
    assert any("text" in reason for reason in result.reasons)
