"""Registration poses in the navigation filter (core/fused_navigation.py) on the orbit run,
against the simulator's truth; the filter's predicted-pose covariance against Monte Carlo."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from spacepose.core import se3
from spacepose.core.ekf import RelativeNavEKF
from spacepose.core.ekf_config import EKFConfig
from spacepose.core.frame_check import HELD
from spacepose.core.fused_navigation import GATE_REASON, FusedNavigator, FusionConfig
from spacepose.core.nav_start import scenario_geometry
from spacepose.core.nav_state import NavState, k_from_params
from spacepose.core.sim.scenarios import OrbitConfig, simulate_orbit
from spacepose.errors import ConfigError
from spacepose.tools.catalogue import parse_catalogue
from spacepose.tools.experiments.fusion import relabelled_truth
from spacepose.tools.experiments.yu_nav import truth_state

FRAMES = 30


@pytest.fixture(scope="module")
def orbit():
    sim = simulate_orbit(OrbitConfig(frames=FRAMES, seed=0))
    scenario = sim.scenario()
    n, R_O_C = scenario_geometry(scenario)
    return sim, n, R_O_C, parse_catalogue(scenario), [sim.frame(k) for k in range(FRAMES)]


def test_pose_covariance_is_that_of_the_predicted_pose():
    """H P Hᵀ against the scatter of ``predict_pose`` over error states drawn from P."""
    initial = NavState(
        100.0,
        np.array([25.0, 0.3, -0.2]),
        np.zeros(3),
        Rotation.from_euler("ZYX", [30, -20, 45], degrees=True).as_quat(),
        np.radians([1.0, -2.0, 1.5]),
        k_from_params([0.1, -0.2]),
        np.array([0.02, -0.03, 0.05]),
    )
    cfg = EKFConfig(init_sigma_position=1e-3, init_sigma_attitude_deg=0.05, init_sigma_com=2e-3)
    ekf = RelativeNavEKF(1.1e-3, Rotation.from_euler("x", 90, degrees=True).as_matrix(),
                         initial, cfg)  # fmt: skip
    T_hat = ekf.predict_pose()
    rng = np.random.default_rng(5)
    draws = rng.multivariate_normal(np.zeros(ekf.dim), ekf.P, size=2000)
    twists = []
    for dx in draws:
        other = RelativeNavEKF(ekf.n, ekf.R_C_O.T, ekf.state(), cfg)
        other._inject(dx)
        twists.append(se3.log(other.predict_pose() @ se3.invert(T_hat)))
    C_mc = np.cov(np.array(twists).T)
    C = ekf.pose_covariance()
    sd = np.sqrt(np.diag(C))
    # Correlation-normalised difference: 2000 draws scatter by about 1/sqrt(2000) = 0.022.
    assert np.abs((C_mc - C) / np.outer(sd, sd)).max() < 0.1
    np.testing.assert_allclose(np.sqrt(np.diag(C_mc)), sd, rtol=0.06)


def _errors(nav: FusedNavigator, sim, k: int) -> np.ndarray:
    return nav.ekf.error_state(truth_state(sim.truth[k]))


def test_registration_navigates_the_orbit_run_without_a_prior(orbit):
    sim, n, R_O_C, _catalogue, frames = orbit
    cfg = FusionConfig(measurements="registration", pose_sigma_scale=4.0, seed_after=5)
    nav = FusedNavigator([], n, R_O_C, cfg, sim.model_cloud())
    rows = [nav.step(f.timestamp, f.cloud) for f in frames]
    statuses = [r.nav.status for r in rows]
    assert statuses[0] in ("waiting", "init") and "init" in statuses
    start = statuses.index("init")
    assert start <= 3 and all(s == "update" for s in statuses[start + 1 :])
    assert sum(r.seeded for r in rows) >= FRAMES - start - 7
    e = _errors(nav, sim, FRAMES - 1)
    # After 30 s: attitude within 0.5°, the body origin's position (ρ − R Δ) within 2 cm.
    assert np.degrees(np.linalg.norm(e[6:9])) < 0.5
    s = nav.ekf.sigmas()
    assert np.all(np.abs(e[6:9]) < 5 * s["att"])


def test_both_fuses_rectangles_and_poses_in_one_filter(orbit):
    sim, n, R_O_C, catalogue, frames = orbit
    cfg = FusionConfig(measurements="both", pose_sigma_scale=4.0)
    nav = FusedNavigator(catalogue, n, R_O_C, cfg, sim.model_cloud())
    rows = [nav.step(f.timestamp, f.cloud) for f in frames]
    used = [r for r in rows if r.pose_used]
    assert len(used) >= FRAMES - 10
    assert any(r.nav.n_rect > 0 for r in used)  # the same frames also used rectangles
    assert np.degrees(np.linalg.norm(_errors(nav, sim, FRAMES - 1)[6:9])) < 0.5


def test_a_pose_the_gate_rejects_is_flagged_in_the_tracker_result(orbit):
    """Frame 20 shifted by 30 cm: the tracker follows the points, the filter's gate rejects
    the pose, and the tracker's result says so."""
    sim, n, R_O_C, _catalogue, frames = orbit
    cfg = FusionConfig(
        measurements="registration",
        pose_sigma_scale=4.0,
        seed_registration=False,
        use_degraded=True,
    )
    nav = FusedNavigator([], n, R_O_C, cfg, sim.model_cloud())
    rows = []
    for k, f in enumerate(frames[:22]):
        shift = se3.make_transform(np.eye(3), [0.3, 0.0, 0.0])
        rows.append(nav.step(f.timestamp, f.cloud.transformed(shift) if k == 20 else f.cloud))
    bad = rows[20]
    assert bad.pose_used is False and bad.pose_nis > 30
    assert bad.track.status == "degraded"
    assert any(r.startswith(GATE_REASON) for r in bad.track.reasons)
    assert rows[21].pose_used


@pytest.mark.parametrize("held", [False, True])
def test_a_pose_the_prediction_held_never_enters_the_filter(orbit, monkeypatch, held):
    """With ``use_degraded`` a degraded pose enters the filter, but not one whose weak
    directions the motion model's prediction held (methods.md §5.3): its pose carries that
    prediction, the filter's own when it seeded the registration, and would count twice.
    Frame 12's result is made degraded, with or without the held reason."""
    sim, n, R_O_C, _catalogue, frames = orbit
    cfg = FusionConfig(measurements="registration", pose_sigma_scale=4.0, use_degraded=True)
    nav = FusedNavigator([], n, R_O_C, cfg, sim.model_cloud())
    rows = [nav.step(f.timestamp, f.cloud) for f in frames[:12]]
    assert rows[-1].pose_used
    track_frame = nav.tracker.track_frame

    def degraded(*args):
        result = track_frame(*args)
        reasons = (HELD,) if held else ("off the prediction",)
        return replace(result, status="degraded", reasons=reasons)

    monkeypatch.setattr(nav.tracker, "track_frame", degraded)
    row = nav.step(frames[12].timestamp, frames[12].cloud)
    assert row.track.status == "degraded"
    assert bool(row.pose_used) is (not held)


def _biased(nav: FusedNavigator, S: np.ndarray, B: np.ndarray) -> None:
    """Make ``nav``'s tracker hold the biases ``S`` and ``B`` (4, 4) in the sensor's and the
    target's frames: its poses come out ``S T B``, and a prior given to it is taken so too."""
    track_frame = nav.tracker.track_frame

    def biased(cloud, t, prior=None):
        if prior is not None:
            prior = (se3.invert(S) @ prior[0] @ se3.invert(B), prior[1])
        result = track_frame(cloud, t, prior)
        return replace(result, T_sensor_target=S @ result.T_sensor_target @ B)

    nav.tracker.track_frame = biased


def test_biases_the_tracker_holds_are_taken_off(orbit):
    """A tracker whose poses are 2 cm off in the target's frame and 1 cm along the line of
    sight moves the filter's pose by as much (the centre of mass and the position take them);
    with those biases as ``pose_bias_body`` and ``pose_bias_sensor`` the filter is where it
    is without them, its seeds included."""
    sim, n, R_O_C, _catalogue, frames = orbit
    b_s, b_b = np.array([0.0, 0.0, 0.01]), np.array([0.02, -0.01, 0.015])
    S, B = se3.make_transform(np.eye(3), b_s), se3.make_transform(np.eye(3), b_b)
    cfg = FusionConfig(measurements="registration", pose_sigma_scale=4.0, seed_after=5)
    known = {"pose_bias_sensor": tuple(b_s), "pose_bias_body": tuple(b_b)}
    poses = {}
    for name, biased, config in [
        ("plain", False, cfg),
        ("biased", True, cfg),
        ("taken off", True, cfg.model_copy(update=known)),
    ]:
        nav = FusedNavigator([], n, R_O_C, config, sim.model_cloud())
        if biased:
            _biased(nav, S, B)
        rows = [nav.step(f.timestamp, f.cloud) for f in frames]
        assert sum(r.seeded for r in rows) >= 15
        poses[name] = nav.ekf.predict_pose()
    expected = S @ poses["plain"] @ B
    np.testing.assert_allclose(poses["biased"][:3, 3], expected[:3, 3], atol=2e-3)
    np.testing.assert_allclose(poses["taken off"], poses["plain"], atol=1e-5)


def test_a_factor_for_the_rotation_and_one_for_the_translation(orbit, monkeypatch):
    """With ``pose_sigma_scale_translation`` each pose enters the filter with its rotation's σ
    about the target's origin times ``pose_sigma_scale`` and its translation's times that
    factor (:func:`~spacepose.core.pose_noise.scaled_about_target`), up to the factor the
    filter measures on its innovations."""
    from spacepose.core.pose_noise import scaled_about_target

    sim, n, R_O_C, _catalogue, frames = orbit
    cfg = FusionConfig(
        measurements="registration", pose_sigma_scale=2.0, pose_sigma_scale_translation=0.5
    )
    nav = FusedNavigator([], n, R_O_C, cfg, sim.model_cloud())
    given: list[np.ndarray] = []

    def recorded(update):
        def update_pose(T, cov):
            given.append(cov)
            return update(T, cov)

        return update_pose

    watched = None
    for f in frames[:12]:
        row = nav.step(f.timestamp, f.cloud)
        if nav.ekf is not None and watched is None:
            watched = nav.ekf
            monkeypatch.setattr(watched, "update_pose", recorded(watched.update_pose))
        elif given and row.pose_used:
            expected = scaled_about_target(row.track.covariance, row.track.T_sensor_target, 2, 0.5)
            ratio = given[-1] / expected
            np.testing.assert_allclose(ratio, ratio[0, 0], rtol=1e-9)
    assert len(given) >= 5


def test_configuration_errors(orbit):
    sim, n, R_O_C, catalogue, _ = orbit
    with pytest.raises(ConfigError, match="model"):
        FusedNavigator(catalogue, n, R_O_C, FusionConfig(measurements="both"), None)
    with pytest.raises(ConfigError, match="catalogue"):
        FusedNavigator([], n, R_O_C, FusionConfig(measurements="both"), sim.model_cloud())
    with pytest.raises(ConfigError, match=r"pose_bias_sensor: .* beyond 1000 m: metres"):
        FusionConfig(pose_bias_sensor=(1e300, 0.0, 0.0))  # overflowed the filter's pose


def test_model_free_registration_starts_after_its_batch():
    """No model: the ok poses are a batch until its moments are a rigid body's (96 frames of
    the orbit run's tumble); the filter then starts on the body frame it estimated (principal
    axes and CoM in the first view's frame) and takes the ok poses."""
    frames = 104
    sim = simulate_orbit(OrbitConfig(frames=frames, seed=0))
    n, R_O_C = scenario_geometry(sim.scenario())
    cfg = FusionConfig(measurements="registration", model_free_frames=15, seed_after=2)
    nav = FusedNavigator([], n, R_O_C, cfg, None)
    track_frame, seeds = nav.tracker.track_frame, []

    def recorded(cloud, t, prior=None):
        result = track_frame(cloud, t, prior)
        if prior is not None and result.status == "ok":
            seeds.append(se3.invert(prior[0]) @ result.T_sensor_target)
        return result

    nav.tracker.track_frame = recorded
    statuses = [nav.step(f.timestamp, f.cloud).nav.status for f in sim.frames()]
    start = statuses.index("init")
    # The filter's prediction seeds the tracker in the tracker's own frame, the first view's:
    # it was given the filter's body frame, the principal axes tens of degrees away.
    assert seeds
    for D in seeds:
        assert Rotation.from_matrix(D[:3, :3]).magnitude() < np.radians(1.0)
        assert np.linalg.norm(D[:3, 3]) < 0.05
    assert 15 <= start <= 100 and set(statuses[:start]) == {"waiting"}
    assert nav.T_F_B is not None and "update" in statuses[start:]
    truth = relabelled_truth(sim.truth, nav.T_F_B, sim.T_sensor_target[0])
    e = nav.ekf.error_state(truth_state(truth[frames - 1]))
    # From a batch this short the CoM is 0.10 m off and the axes tens of degrees (measured):
    # the default batch is 200 frames, scored in the fusion experiment. Here: the plumbing.
    assert np.linalg.norm(e[0:3]) < 0.15
    np.testing.assert_allclose(nav.T_F_B[:3, :3].T @ nav.T_F_B[:3, :3], np.eye(3), atol=1e-9)


def test_a_model_free_batch_drops_a_first_frame_that_gave_way(orbit):
    """A first frame 1 km off (a glitch) no later frame confirms gives way to frame 1 as the
    target frame (core.spare_anchor): its pose, in the abandoned frame, leaves the model-free
    batch, which then holds frame 1's identity and the ok poses after it."""
    _, n, R_O_C, _, frames = orbit
    glitch = frames[0].cloud.points + np.array([0.0, 0.0, 1000.0])
    clouds = [glitch, *(f.cloud for f in frames[1:8])]
    nav = FusedNavigator([], n, R_O_C, FusionConfig(measurements="registration"), None)
    tracks = [nav.step(f.timestamp, c).track for f, c in zip(frames, clouds, strict=False)]
    assert nav.tracker.first_index == 1 and tracks[0].status == "ok"
    assert any(t.revises for t in tracks)
    times = [t for t, _ in nav._batch]
    assert times[0] == frames[1].timestamp and frames[0].timestamp not in times
    np.testing.assert_array_equal(nav._batch[0][1], np.eye(4))
    ok = [t.timestamp for t in tracks[2:] if t.status == "ok"]
    assert times[1:] == ok and ok
