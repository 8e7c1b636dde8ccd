"""The poses' σ factor: batch means of whitened errors against closed forms, and the bootstrap."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from spacepose.core import se3
from spacepose.core.pose_noise import (
    batch_ratios,
    gross_failures,
    pose_noise_scale,
    scaled_about_target,
    target_origin_whitened,
    translation_bias,
    whitened_errors,
)
from spacepose.errors import InputError


def _poses(errors: np.ndarray, T_ref: np.ndarray) -> np.ndarray:
    """Poses whose left error ``log(T T_ref⁻¹)`` is ``errors`` (rotation vector, translation)."""
    out = np.empty_like(T_ref)
    for k, e in enumerate(errors):
        D = se3.make_transform(Rotation.from_rotvec(e[:3]).as_matrix(), e[3:])
        out[k] = D @ T_ref[k]
    return out


def test_whitened_errors_are_the_errors_over_their_sigma():
    rng = np.random.default_rng(0)
    n = 20
    T_ref = np.stack(
        [
            se3.make_transform(Rotation.random(random_state=k).as_matrix(), [0, 0, 25.0])
            for k in range(n)
        ]
    )
    sigma = np.array([1e-3, 2e-3, 5e-4, 3e-3, 1e-3, 4e-3])
    errors = rng.normal(0.0, 1.0, (n, 6)) * sigma
    C = np.tile(np.diag(sigma**2), (n, 1, 1))
    C[3] = -C[3]  # not positive definite: no whitened error
    w = whitened_errors(_poses(errors, T_ref), C, T_ref)
    expected = errors / sigma
    expected[3] = np.nan
    np.testing.assert_allclose(w, expected, rtol=1e-6, atol=1e-9)
    with pytest.raises(InputError, match="alike"):
        whitened_errors(T_ref, C[:-1], T_ref)


def test_batch_ratios_match_the_long_run_variance():
    """White unit errors: 1 per axis. AR(1) errors of unit variance and lag-1 correlation ρ:
    the long-run variance (1 + ρ) / (1 − ρ), less its finite-batch shortfall
    2ρ(1 − ρᴮ) / (B(1 − ρ)²). A bias b on white errors: 1 + B b²."""
    rng = np.random.default_rng(1)
    n, batch = 200_000, 50
    # 4,000 batches: each ratio spreads as χ²₄₀₀₀/4000 (σ 0.022; the bias case σ 0.07, the
    # AR(1) case 0.11): the bounds are 4-5 σ.
    white, frames = batch_ratios(rng.normal(size=(n, 6)), batch)
    assert frames == n
    np.testing.assert_allclose(white, 1.0, atol=0.1)

    rho = 0.7
    x = np.empty((n, 6))
    x[0] = rng.normal(size=6)
    innovations = rng.normal(scale=np.sqrt(1 - rho**2), size=(n, 6))
    for k in range(1, n):
        x[k] = rho * x[k - 1] + innovations[k]
    expected = (1 + rho) / (1 - rho) - 2 * rho * (1 - rho**batch) / (batch * (1 - rho) ** 2)
    np.testing.assert_allclose(batch_ratios(x, batch)[0], expected, rtol=0.1)

    b = np.array([0.0, 0.1, 0.2, 0.0, 0.3, 0.0])
    biased = rng.normal(size=(n, 6)) + b
    np.testing.assert_allclose(batch_ratios(biased, batch)[0], 1 + batch * b**2, atol=0.3)


def test_the_scale_is_the_largest_ratio_and_never_below_one():
    rng = np.random.default_rng(2)
    cautious = 0.5 * rng.normal(size=(2_000, 6))
    assert pose_noise_scale(cautious).scale == 1.0
    biased = rng.normal(size=(2_000, 6))
    biased[:, 4] += 0.4  # 1 + 50·0.16 = 9 in variance on one axis
    noise = pose_noise_scale(biased)
    assert noise.scale == pytest.approx(np.sqrt(noise.batch_ratios.max()))
    assert 2.6 < noise.scale < 3.4 and int(np.argmax(noise.batch_ratios)) == 4
    # Lost frames (NaN rows) are left out; too few for 4 batches is refused.
    gaps = biased.copy()
    gaps[::3] = np.nan
    assert pose_noise_scale(gaps).frames == 1300
    with pytest.raises(InputError, match="4 batches need 200"):
        pose_noise_scale(biased[:199])
    with pytest.raises(InputError, match="whole number"):
        batch_ratios(biased, 0)


def test_the_bootstrap_at_the_true_poses_with_the_runs_seed_is_the_run():
    """Rendered at a run's true poses with the run's seed, the bootstrap's frames are the run's
    own, so its factor is the one the run's errors against the truth give."""
    from spacepose.core.pose_bootstrap import bootstrap_pose_noise
    from spacepose.core.sim import OrbitConfig, simulate_orbit
    from spacepose.core.tracker import Tracker, TrackerConfig

    sim = simulate_orbit(OrbitConfig(frames=45, seed=3))
    model = sim.model_cloud()
    tracker = Tracker(TrackerConfig(), model)
    n = len(sim)
    T_est, C = np.full((n, 4, 4), np.nan), np.full((n, 6, 6), np.nan)
    for k, frame in enumerate(sim.frames()):
        result = tracker.track_frame(frame.cloud, frame.timestamp)
        if result.status == "ok":
            T_est[k], C[k] = result.T_sensor_target, result.covariance
    # The run's biases, and the factor of its poses with them taken off.
    w = whitened_errors(T_est, C, sim.T_sensor_target)
    usable = T_est.copy()
    usable[gross_failures(w) | ~np.isfinite(w).all(axis=1)] = np.nan
    bias = translation_bias(usable, sim.T_sensor_target, C, batch=10)
    unbiased = bias.correct(T_est)
    run = pose_noise_scale(whitened_errors(unbiased, C, sim.T_sensor_target), batch=10)
    boot = bootstrap_pose_noise(
        sim.target, sim.sensor, sim.timestamps, sim.T_sensor_target, model, seed=3, batch=10
    )
    assert boot.frames == run.frames == 40
    np.testing.assert_array_equal(boot.batch_ratios, run.batch_ratios)
    assert boot.scale == run.scale >= 1.0
    assert boot.bias.to_dict() == bias.to_dict()
    about = target_origin_whitened(unbiased, C, sim.T_sensor_target)
    about[gross_failures(w)] = np.nan
    np.testing.assert_array_equal(boot.target_ratios, batch_ratios(about, batch=10)[0])
    assert boot.rotation_scale >= 1.0 and boot.translation_scale >= 1.0
    assert np.all(np.abs(bias.body) < 0.01) and np.all(np.abs(bias.sensor) < 0.01)  # at 25 m
    assert np.all(bias.body_sigma > 0) and np.all(bias.sensor_sigma > 0)
    # Another seed: other noise, the same kind of errors.
    other = bootstrap_pose_noise(
        sim.target, sim.sensor, sim.timestamps, sim.T_sensor_target, model, seed=4, batch=10
    )
    assert not np.array_equal(other.batch_ratios, run.batch_ratios)
    assert 1.0 <= other.scale < 4.0


def test_biases_in_the_sensors_and_the_targets_frames_are_told_apart_by_a_tumble():
    """Poses off by b_s in the sensor's frame and b_b in the target's (which turns), on top of
    AR(1) noise: ``t_est − t_ref = b_s + R b_b + noise``. The fit gives both within their
    standard errors, and those errors are the spread of the estimates over 100 runs."""
    rng = np.random.default_rng(4)
    b_s, b_b = np.array([0.0, 0.0, 2e-4]), np.array([-5e-4, 2e-4, 0.0])
    n, rho = 600, 0.8
    # The noise's own covariance (1 mm a frame, the rotation's a lever arm 25 m out).
    C = np.tile(np.diag([1e-14] * 3 + [1e-6] * 3), (n, 1, 1))
    # A turn about an axis that itself turns: about a fixed axis the biases' components
    # along it are one and the same (R a = a).
    angle = np.linspace(0, 6.0, n)
    R = (
        Rotation.from_rotvec(np.outer(angle, [0, 0, 1.0]))
        * Rotation.from_rotvec(np.outer(0.7 * angle, [1.0, 0, 0]))
    ).as_matrix()
    T_ref = np.stack([se3.make_transform(r, [0.1, -0.2, 25.0]) for r in R])
    estimates, sigmas = [], []
    for _ in range(100):
        noise = np.empty((n, 3))
        noise[0] = rng.normal(scale=1e-3, size=3)
        for k in range(1, n):
            noise[k] = rho * noise[k - 1] + rng.normal(scale=1e-3 * np.sqrt(1 - rho**2), size=3)
        T_est = T_ref.copy()
        T_est[:, :3, 3] += b_s + np.einsum("nij,j->ni", R, b_b) + noise
        bias = translation_bias(T_est, T_ref, C, significance=0.0)
        estimates.append(np.r_[bias.sensor, bias.body])
        sigmas.append(np.r_[bias.sensor_sigma, bias.body_sigma])
    estimates, sigmas = np.array(estimates), np.array(sigmas)
    spread = estimates.std(axis=0, ddof=1)
    # 100 runs: their mean within 4 standard errors of the truth; the sandwich from 12
    # batches gives their spread within 40 %.
    assert np.all(np.abs(estimates.mean(axis=0) - np.r_[b_s, b_b]) < 4 * spread / 10)
    np.testing.assert_allclose(sigmas.mean(axis=0), spread, rtol=0.4)
    # Taken off, the poses are the reference's plus the noise less the fit's own error.
    corrected = bias.correct(T_est)
    np.testing.assert_allclose(corrected[:, :3, :3], T_ref[:, :3, :3], atol=1e-15)
    residual = corrected[:, :3, 3] - T_ref[:, :3, 3] - noise
    assert np.abs(residual).max() < 5 * sigmas[-1].max()
    # At three standard errors (the default) only what stands out of the noise is kept: a
    # bias of 1.5 mm along the target's x (about 13 standard errors), the rest left at zero.
    T_one = T_ref.copy()
    T_one[:, :3, 3] += np.einsum("nij,j->ni", R, [1.5e-3, 0.0, 0.0]) + noise
    kept = translation_bias(T_one, T_ref, C)
    np.testing.assert_array_equal(kept.sensor, 0.0)
    np.testing.assert_array_equal(kept.body[1:], 0.0)
    assert kept.body[0] == pytest.approx(1.5e-3, abs=4 * kept.body_sigma[0])
    with pytest.raises(InputError, match="4 batches need 200"):
        translation_bias(T_est[:199], T_ref[:199], C[:199])
    for bad in (-1.0, float("nan")):
        with pytest.raises(InputError, match="standard errors >= 0"):
            translation_bias(T_est, T_ref, C, significance=bad)
    with pytest.raises(InputError, match="min_batches"):
        translation_bias(T_est, T_ref, C, min_batches=2.5)


def test_errors_about_the_targets_origin_are_whitened_block_by_block():
    """A target 25 m out, each pose turned by r about the target's origin and its origin moved
    by d: the errors are (r, d), each block whitened by its own covariance there (the rotation's
    by its 3×3 block, the translation's likewise), at turns of 0.1 rad, where the first-order
    displacement v + ω × t would be 0.1 m off."""
    rng = np.random.default_rng(6)
    n = 12
    T_ref = np.stack(
        [
            se3.make_transform(Rotation.random(random_state=k).as_matrix(), [0.3, -0.1, 25.0])
            for k in range(n)
        ]
    )
    A = rng.normal(size=(6, 6))
    C = np.tile(1e-6 * (A @ A.T + np.eye(6)), (n, 1, 1))
    r = rng.normal(scale=0.1, size=(n, 3))
    d = rng.normal(scale=1e-3, size=(n, 3))
    T_est = T_ref.copy()
    T_est[:, :3, :3] = Rotation.from_rotvec(r).as_matrix() @ T_ref[:, :3, :3]
    T_est[:, :3, 3] += d
    w = target_origin_whitened(T_est, C, T_ref)
    for k in range(n):
        J = np.eye(6)
        J[3:, :3] = -se3.skew(T_ref[k, :3, 3])
        Ct = J @ C[k] @ J.T
        expected = np.r_[
            np.linalg.solve(np.linalg.cholesky(Ct[:3, :3]), r[k]),
            np.linalg.solve(np.linalg.cholesky(Ct[3:, 3:]), d[k]),
        ]
        np.testing.assert_allclose(w[k], expected, rtol=1e-9)


def test_a_covariance_scaled_about_the_targets_origin():
    """Equal factors scale the covariance by their square; unequal ones scale its blocks about
    the target's origin, rotation by f_r², translation by f_t², their coupling by f_r f_t."""
    rng = np.random.default_rng(7)
    A = rng.normal(size=(6, 6))
    C = 1e-6 * (A @ A.T + np.eye(6))
    T = se3.make_transform(Rotation.random(random_state=3).as_matrix(), [0.5, 0.2, 25.0])
    np.testing.assert_allclose(scaled_about_target(C, T, 2.0, 2.0), 4.0 * C, rtol=1e-9)
    J = np.eye(6)
    J[3:, :3] = -se3.skew(T[:3, 3])
    about, scaled = J @ C @ J.T, J @ scaled_about_target(C, T, 1.5, 0.5) @ J.T
    np.testing.assert_allclose(scaled[:3, :3], 2.25 * about[:3, :3], rtol=1e-9)
    np.testing.assert_allclose(scaled[3:, 3:], 0.25 * about[3:, 3:], rtol=1e-6)
    np.testing.assert_allclose(scaled[:3, 3:], 0.75 * about[:3, 3:], rtol=1e-6, atol=1e-18)


def test_gross_failures_are_left_out_not_averaged():
    """A tracker that held a half-turned twin for 30 frames: errors of thousands of σ. They are
    what a filter's gate rejects, not noise: left out, the factor is the healthy frames'."""
    rng = np.random.default_rng(3)
    w = rng.normal(size=(600, 6))
    healthy = pose_noise_scale(w)
    w[100:130] = 3e3
    failed = pose_noise_scale(w)
    assert failed.gross == 30 and healthy.gross == 0
    assert failed.frames == 550 and failed.scale == pytest.approx(healthy.scale, rel=0.25)


def test_bad_inputs_are_the_packages_errors():
    """Text, a flag or a zero where numbers and counts go: one InputError naming the argument,
    not numpy's ValueError (before) or a silent batch count of 1 (``True``)."""
    with pytest.raises(InputError, match="poses are not numbers"):
        whitened_errors("a", np.eye(6)[None], np.eye(4)[None])
    with pytest.raises(InputError, match="whitened errors are not numbers"):
        pose_noise_scale("abc")
    for bad in (True, 0, 1.5):
        with pytest.raises(InputError, match="min_batches must be a whole number"):
            pose_noise_scale(np.ones((300, 6)), 50, bad)
    # The bootstrap's one call, before it renders anything.
    from spacepose.core.pose_bootstrap import bootstrap_pose_noise

    with pytest.raises(InputError, match="timestamps must be real numbers, got an array of text"):
        bootstrap_pose_noise(None, None, ["a"], np.eye(4)[None], None)
    with pytest.raises(InputError, match=r"timestamps of shape \(2,\) for poses of shape"):
        bootstrap_pose_noise(None, None, [0.0, 1.0], np.eye(4)[None], None)
    with pytest.raises(InputError, match="start covariance must be"):
        bootstrap_pose_noise(None, None, [0.0], np.eye(4)[None], None, start_covariance=np.eye(3))
