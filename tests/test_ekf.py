"""Tests of spacepose.core.ekf on synthetic measurements generated from dynamics truth."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.linalg import expm
from scipy.spatial.transform import Rotation
from scipy.stats import chi2

from spacepose.core import dynamics, se3
from spacepose.core.ekf import RelativeNavEKF
from spacepose.core.ekf_config import EKFConfig
from spacepose.core.nav_state import NavState, discretise, k_from_params, params_from_k
from spacepose.errors import InputError

N = 1.1068e-3
# Boresight z_C along the flight direction x_O (chaser behind the target), x_C = y_O, y_C = z_O.
R_O_C = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
# Rectangle centres in B' and their outward normals: six faces of a 2.4 x 1.8 x 1.4 m bus.
FACES = {
    "+x": ([1.2, 0, 0], [1, 0, 0]),
    "-x": ([-1.2, 0, 0], [-1, 0, 0]),
    "+y": ([0, 0.9, 0], [0, 1, 0]),
    "-y": ([0, -0.9, 0], [0, -1, 0]),
    "+z": ([0, 0, 0.7], [0, 0, 1]),
    "-z": ([0, 0, -0.7], [0, 0, -1]),
}
COM_TRUE = np.array([0.02, -0.03, 0.05])
SIG_C = 0.003
SIG_ATT = np.deg2rad(0.1)


def make_truth(
    steps: int = 400,
    inertia=(1200.0, 1000.0, 800.0),
    rate_deg=(1.0, -2.0, 1.5),
    seed: int = 0,
):
    """Truth states at 1 Hz from the dynamics, and seeded feature location errors."""
    rng = np.random.default_rng(seed)
    x = np.array([25.0, 0.05, -0.04, 0.0005, -0.0002, 0.0003])
    q = Rotation.from_rotvec([0.3, -0.5, 0.2]).as_quat()
    w = np.deg2rad(rate_deg)
    k = dynamics.inertia_ratios(inertia)
    states = []
    for i in range(steps):
        t = float(i)
        states.append(NavState(t, x[:3].copy(), x[3:].copy(), q.copy(), w.copy(), k, COM_TRUE))
        x = dynamics.cw_closed_form(x, N, 1.0)
        q, w = dynamics.propagate_attitude(q, w, inertia, 1.0, substeps=20)
    deltas = {f: rng.normal(0, EKFConfig().sigma_feature, 3) for f in FACES}
    return states, deltas


def measure(truth: NavState, deltas, rng, phi=np.zeros(3)):
    """Noisy centroids of the faces turned towards the sensor, and a noisy attitude.

    ``phi`` (3,): the error of the chaser attitude the filter will be given, in C (the filter
    turns the sensor's attitude into I with ``R_O_C exp([φ]×)``, so it reads it turned by
    ``R_C_Bᵀ φ`` in B).
    """
    R_O_B = dynamics.R_I_O(N, truth.t).T @ Rotation.from_quat(truth.q_I_B).as_matrix()
    R_C_B = R_O_C.T @ R_O_B
    cents = []
    for fid, (d, nrm) in FACES.items():
        if (R_C_B @ nrm)[2] < -0.2:  # facing the sensor
            c = R_O_C.T @ (truth.rho + R_O_B @ (np.asarray(d, float) + deltas[fid] - truth.com))
            cents.append((fid, d, c + rng.normal(0, SIG_C, 3)))
    q_meas = (
        Rotation.from_quat(truth.q_I_B)
        * Rotation.from_rotvec(R_C_B.T @ phi)
        * Rotation.from_rotvec(rng.normal(0, SIG_ATT, 3))
    )
    return cents, q_meas.as_quat()


def initial_guess(truth: NavState, config: EKFConfig, rng) -> NavState:
    """An initial estimate drawn from the filter's own initial covariance (for consistency)."""
    c = config
    p_true = params_from_k(truth.k)
    # Clipped: |k| < 1 for any physical body.
    p0 = np.clip(p_true + rng.normal(0, c.init_sigma_inertia, 2), -0.95, 0.95)
    att = rng.normal(0, np.deg2rad(c.init_sigma_attitude_deg), 3)
    return NavState(
        truth.t,
        truth.rho + rng.normal(0, c.init_sigma_position, 3),
        truth.v + rng.normal(0, c.init_sigma_velocity, 3),
        (Rotation.from_quat(truth.q_I_B) * Rotation.from_rotvec(att)).as_quat(),
        truth.omega_B + rng.normal(0, np.deg2rad(c.init_sigma_rate_deg_s), 3),
        k_from_params(p0),
        truth.com + rng.normal(0, c.init_sigma_com, 3),
    )


# The truth has no process noise, hence a small Q; a moderate inertia prior keeps the EKF in its
# linear regime (the wide-prior case is tested for convergence, not consistency).
CONFIG = EKFConfig(
    sigma_centroid=SIG_C,
    sigma_attitude_deg=np.rad2deg(SIG_ATT),
    sigma_accel=1e-7,
    sigma_angular_accel=1e-7,
    init_sigma_inertia=0.1,
)


def run_filter(states, deltas, seed=1, config=CONFIG, use_attitude=True, phi=np.zeros(3)):
    rng = np.random.default_rng(seed)
    R_O_C_given = R_O_C @ Rotation.from_rotvec(phi).as_matrix()
    ekf = RelativeNavEKF(N, R_O_C_given, initial_guess(states[0], config, rng), config)
    nees, errors = [], []
    for truth in states:
        ekf.predict(truth.t)
        cents, q_meas = measure(truth, deltas, rng, phi)
        if use_attitude:
            ekf.update_attitude(q_meas)
        for fid, d, c in cents:
            ekf.update_centroid(fid, d, c)
        nees.append(ekf.nees(truth))
        errors.append(ekf.error_state(truth))
    return ekf, np.array(nees), np.array(errors)


@pytest.fixture(scope="module")
def default_run():
    states, deltas = make_truth()
    return states, deltas, *run_filter(states, deltas)


def test_filter_converges_to_truth(default_run) -> None:
    states, _, ekf, _, err = default_run
    late = err[len(err) // 2 :]
    rms = np.sqrt(np.mean(late**2, axis=0))
    assert np.all(rms[0:3] < 2e-3)  # position, m
    assert np.all(rms[3:6] < 1e-4)  # velocity, m/s
    assert np.all(np.rad2deg(rms[6:9]) < 0.05)  # attitude, deg
    assert np.all(np.rad2deg(rms[9:12]) < 0.005)  # rate, deg/s
    truth = states[-1]
    k_err = np.abs(ekf.k - truth.k) / np.abs(truth.k)
    assert np.all(k_err < 0.05), k_err
    assert np.all(np.abs(ekf.com - truth.com) < 0.01)
    # The initial error was far larger than the final one: the filter did the work.
    assert np.linalg.norm(err[0, 0:3]) > 10 * rms[0:3].max()


def test_filter_is_consistent(default_run) -> None:
    *_, nees, _ = default_run
    lo, hi = chi2.ppf([0.025, 0.975], 17)
    inside = np.mean((nees >= lo) & (nees <= hi))
    assert inside >= 0.90, inside


def test_joseph_form_keeps_covariance_spd(default_run) -> None:
    _, _, ekf, *_ = default_run
    np.testing.assert_array_equal(ekf.P, ekf.P.T)
    assert np.linalg.eigvalsh(ekf.P)[0] > 0
    assert ekf.dim == 17 + 3 * len(ekf.features)
    assert ekf.n_rejected == 0


def test_gate_rejects_a_20_sigma_outlier() -> None:
    states, deltas = make_truth(steps=60)
    ekf, *_ = run_filter(states, deltas)
    truth = states[-1]
    fid = next(iter(ekf.features))
    d = np.asarray(FACES[fid][0], float)
    c_true = R_O_C.T @ (
        truth.rho
        + dynamics.R_I_O(N, truth.t).T
        @ Rotation.from_quat(truth.q_I_B).as_matrix()
        @ (d + deltas[fid] - truth.com)
    )
    P_before = ekf.P.copy()
    rho_before = ekf.rho.copy()
    accepted = ekf.update_centroid(fid, d, c_true + np.array([20 * SIG_C, 0, 0]))
    assert not accepted and ekf.n_rejected == 1
    np.testing.assert_array_equal(ekf.P, P_before)
    np.testing.assert_array_equal(ekf.rho, rho_before)
    assert ekf.last_nis > chi2.ppf(0.9999, 3)
    # A good measurement right after passes the gate.
    assert ekf.update_centroid(fid, d, c_true)


def test_other_inertia_rate_and_noise_converge() -> None:
    states, deltas = make_truth(steps=400, inertia=(500.0, 900.0, 700.0), rate_deg=(-2, 1, 3))
    # Wider inertia prior (σ 0.3 on k_x, k_y), double measurement noise in the filter's model.
    config = CONFIG.model_copy(
        update={"init_sigma_inertia": 0.3, "sigma_centroid": 2 * SIG_C, "sigma_accel": 1e-6}
    )
    ekf, _, err = run_filter(states, deltas, seed=7, config=config)
    late = np.sqrt(np.mean(err[200:] ** 2, axis=0))
    assert np.all(late[0:3] < 2e-3)
    assert np.all(np.rad2deg(late[6:9]) < 0.05)
    k_true = states[-1].k
    assert np.all(np.abs(ekf.k - k_true) / np.abs(k_true) < 0.05)


def test_jacobians_match_finite_differences() -> None:
    states, _ = make_truth(steps=3)
    ekf = RelativeNavEKF(N, R_O_C, states[2], EKFConfig())
    ekf.com = np.array([0.03, -0.02, 0.04])
    ekf.add_feature("+x")
    ekf.features["+x"] = np.array([0.001, 0.002, -0.001])
    d = np.array([1.2, 0, 0])

    def z(e: RelativeNavEKF) -> np.ndarray:
        return np.concatenate([e.predict_centroid("+x", d), se3.log(e.predict_pose())])

    import copy

    base = z(ekf)
    T0 = ekf.predict_pose()
    eps = 1e-7
    num = np.zeros((9, ekf.dim))
    for j in range(ekf.dim):
        e = copy.deepcopy(ekf)
        dx = np.zeros(ekf.dim)
        dx[j] = eps
        e._inject(dx)
        zc = e.predict_centroid("+x", d)
        zp = se3.log(e.predict_pose() @ se3.invert(T0))
        num[:, j] = (np.concatenate([zc - base[:3], zp])) / eps
    # Analytic H from the update functions, captured through a zero-gain pass.
    captured = []
    ekf._update = lambda r, H, R: captured.append(H) or True  # type: ignore[method-assign]
    ekf.update_centroid("+x", d, np.zeros(3))
    ekf.update_pose(T0, np.eye(6))
    np.testing.assert_allclose(captured[0], num[:3], atol=1e-5)
    np.testing.assert_allclose(captured[1], num[3:], atol=1e-5)


def test_consider_state_jacobians_match_a_turned_chaser() -> None:
    # φ turns the true sensor frame: R_C_O(true) = exp([φ]×) R_C_O(given). The centroid,
    # attitude and pose the sensor then reports, differentiated numerically in φ.
    states, _ = make_truth(steps=3)
    config = EKFConfig(sigma_chaser_attitude_deg=0.01)
    ekf = RelativeNavEKF(N, R_O_C, states[2], config)
    ekf.com = np.array([0.03, -0.02, 0.04])
    assert ekf.has_consider and ekf.dim == 20
    ekf.add_feature("+x")
    ekf.features["+x"] = np.array([0.001, 0.002, -0.001])
    d = np.array([1.2, 0, 0])
    c0, T0 = ekf.predict_centroid("+x", d), ekf.predict_pose()
    R_I_C = dynamics.R_I_O(N, ekf.t) @ R_O_C
    eps = 1e-7
    num = np.zeros((9, 3))
    for j in range(3):
        turn = Rotation.from_rotvec(eps * np.eye(3)[j]).as_matrix()
        seen = RelativeNavEKF(N, R_O_C @ turn.T, ekf.state(), config)  # the true sensor frame
        seen.features["+x"] = ekf.features["+x"]
        R_I_B_meas = R_I_C @ seen.predict_pose()[:3, :3]  # read through the given R_O_C
        att = (Rotation.from_quat(ekf.q).inv() * Rotation.from_matrix(R_I_B_meas)).as_rotvec()
        num[:3, j] = (seen.predict_centroid("+x", d) - c0) / eps
        num[3:6, j] = att / eps
        num[6:, j] = se3.log(seen.predict_pose() @ se3.invert(T0))[:3] / eps
        np.testing.assert_allclose(se3.log(seen.predict_pose() @ se3.invert(T0))[3:], 0, atol=1e-12)
    captured = []
    ekf._update = lambda r, H, R: captured.append(H) or True  # type: ignore[method-assign]
    ekf.update_centroid("+x", d, np.zeros(3))
    ekf.update_attitude(ekf.q)
    ekf.update_pose(T0, np.eye(6))
    for k, H in enumerate(captured):
        np.testing.assert_allclose(H[:3, 17:20], num[3 * k : 3 * k + 3], atol=1e-5)


def test_schmidt_consider_state_keeps_a_misaligned_chaser_consistent() -> None:
    # The filter is given the chaser attitude 0.05° off per axis (1.3 cm across the line of
    # sight at 25 m, four centroid σ): without the consider state ρ is biased far outside its
    # covariance; with it (σ = the error's size) NEES stays inside its bounds, the consider
    # state keeps its prior and no measurement moves it.
    states, deltas = make_truth(steps=300)
    phi = np.deg2rad(0.05) * np.array([1.0, -1.0, 1.0])
    lo, hi = chi2.ppf([0.025, 0.975], 17)
    _, nees_blind, _ = run_filter(states, deltas, phi=phi)
    config = CONFIG.model_copy(update={"sigma_chaser_attitude_deg": 0.05})
    ekf, nees, err = run_filter(states, deltas, phi=phi, config=config)
    late = slice(len(nees) // 2, None)
    inside = np.mean((nees[late] >= lo) & (nees[late] <= hi))
    inside_blind = np.mean((nees_blind[late] >= lo) & (nees_blind[late] <= hi))
    assert inside >= 0.9 > 0.5 > inside_blind, (inside, inside_blind)
    np.testing.assert_allclose(np.diag(ekf.P)[17:20], np.deg2rad(0.05) ** 2, rtol=1e-12)
    assert ekf.dim == 20 + 3 * len(ekf.features) and ekf.n_rejected == 0
    # ρ's error is the turned line of sight (the bias φ makes), and its σ covers it.
    assert np.all(np.abs(err[late, 0:3]).max(axis=0) < 3 * np.sqrt(np.diag(ekf.P)[0:3]))


def test_propagation_jacobian_matches_finite_differences() -> None:
    states, _ = make_truth(steps=1)
    ekf = RelativeNavEKF(N, R_O_C, states[0], EKFConfig())
    ekf.p = np.array([0.3, -0.2])
    F = ekf._jacobian(ekf.w, ekf.p)
    eps = 1e-7

    def f(w, p):
        kx, ky = p  # moments with Izz = 1, independent of k_from_params
        inertia = np.array([(1 - ky) / (1 + kx * ky), (1 + kx) / (1 + kx * ky), 1.0])
        return dynamics.euler_derivative(w, inertia)

    for j in range(3):
        dw = np.zeros(3)
        dw[j] = eps
        np.testing.assert_allclose(
            F[9:12, 9 + j], (f(ekf.w + dw, ekf.p) - f(ekf.w, ekf.p)) / eps, atol=1e-8
        )
    for j in range(2):
        dp = np.zeros(2)
        dp[j] = eps
        np.testing.assert_allclose(
            F[9:12, 12 + j], (f(ekf.w, ekf.p + dp) - f(ekf.w, ekf.p)) / eps, atol=1e-8
        )


def test_discretisation_matches_van_loan_expm() -> None:
    states, _ = make_truth(steps=1)
    ekf = RelativeNavEKF(N, R_O_C, states[0], EKFConfig())
    ekf.w = np.deg2rad([4.0, -6.0, 5.0])
    F = ekf._jacobian(ekf.w, np.array([0.3, -0.2]))
    Qc = np.diag(np.random.default_rng(0).uniform(0.5, 2.0, 17))
    for dt in (1.0, 7.0):
        m = len(F)
        M = np.block([[-F, Qc], [np.zeros((m, m)), F.T]])
        E = expm(M * dt)
        Phi_ref = E[m:, m:].T
        Phi, Q = discretise(F, Qc, dt)
        np.testing.assert_allclose(Phi, Phi_ref, atol=1e-9)
        np.testing.assert_allclose(Q, Phi_ref @ E[:m, m:], atol=1e-6 * np.abs(Q).max())


def test_pose_fusion_improves_the_estimate() -> None:
    states, deltas = make_truth(steps=30)
    config = CONFIG
    _, _, err_rect = run_filter(states, deltas, config=config)
    rng = np.random.default_rng(3)
    ekf2 = RelativeNavEKF(
        N, R_O_C, initial_guess(states[0], config, np.random.default_rng(1)), config
    )
    cov6 = np.diag([np.deg2rad(0.05) ** 2] * 3 + [0.001**2] * 3)
    L = np.linalg.cholesky(cov6)
    errs = []
    rng_m = np.random.default_rng(1)
    initial_guess(states[0], config, rng_m)  # same measurement noise stream as run_filter
    for truth in states:
        ekf2.predict(truth.t)
        cents, q_meas = measure(truth, deltas, rng_m)
        ekf2.update_attitude(q_meas)
        for fid, d, c in cents:
            ekf2.update_centroid(fid, d, c)
        R_C_B = R_O_C.T @ dynamics.R_I_O(N, truth.t).T @ Rotation.from_quat(truth.q_I_B).as_matrix()
        T_true = se3.make_transform(R_C_B, R_O_C.T @ truth.rho - R_C_B @ truth.com)
        T_meas = se3.exp(L @ rng.normal(size=6)) @ T_true
        assert ekf2.update_pose(T_meas, cov6)
        errs.append(ekf2.error_state(truth))
    errs = np.array(errs)
    rms_rect = np.sqrt(np.mean(err_rect[10:] ** 2, axis=0))
    rms_fused = np.sqrt(np.mean(errs[10:] ** 2, axis=0))
    # Measured: attitude 1.4e-3 -> 0.43e-3 rad, rate 2.8e-4 -> 0.7e-4 rad/s (RMS norms).
    assert np.linalg.norm(rms_fused[6:9]) < 0.5 * np.linalg.norm(rms_rect[6:9])
    assert np.linalg.norm(rms_fused[9:12]) < 0.5 * np.linalg.norm(rms_rect[9:12])


def test_bad_inputs() -> None:
    states, _ = make_truth(steps=2)
    with pytest.raises(InputError, match="R_O_C"):
        RelativeNavEKF(N, np.ones((3, 3)), states[0])
    ekf = RelativeNavEKF(N, R_O_C, states[1])
    with pytest.raises(InputError, match="backwards"):
        ekf.predict(0.0)
    with pytest.raises(InputError, match="centroid"):
        ekf.update_centroid("+x", [1.2, 0, 0], [np.nan, 0, 0])
    with pytest.raises(InputError, match="positive definite"):
        ekf.update_attitude([0, 0, 0, 1], -np.eye(3))
    with pytest.raises(InputError, match="T_sensor_model"):
        ekf.update_pose(np.eye(3), np.eye(6))
    with pytest.raises(InputError, match="positive principal moments"):
        params_from_k([0.5, 0.5, 0.5])
    np.testing.assert_allclose(params_from_k(dynamics.inertia_ratios([3, 2, 4])), [-2 / 3, 0.5])
    np.testing.assert_allclose(k_from_params([-2 / 3, 0.5]), dynamics.inertia_ratios([3, 2, 4]))
