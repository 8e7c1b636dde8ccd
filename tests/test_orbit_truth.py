"""Tests of the orbit run's truth (spacepose.core.sim.orbit_truth) against closed forms."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from spacepose.core import dynamics
from spacepose.core.sim.orbit_truth import (
    EARTH_J2,
    EARTH_MU,
    EARTH_RADIUS,
    ForceModel,
    keplerian_state,
    lvlh_basis,
    misaligned,
    perturbed_catalogue,
    propagate_pair,
    relative_truth,
    torque_free_attitude,
)
from spacepose.core.sim.targets import orbit_target
from spacepose.errors import InputError

A_LEO = EARTH_RADIUS + 500e3
TWO_BODY = ForceModel(j2=False)


def _period(a: float) -> float:
    return 2.0 * math.pi * math.sqrt(a**3 / EARTH_MU)


def test_keplerian_state_and_lvlh_frame() -> None:
    a, e, i = 7.0e6, 0.05, np.radians(51.6)
    r, v = keplerian_state(a, e, i, 0.3, 0.7, 0.0)  # at perigee
    assert np.linalg.norm(r) == pytest.approx(a * (1 - e), rel=1e-14)
    h = np.cross(r, v)
    assert np.linalg.norm(h) == pytest.approx(math.sqrt(EARTH_MU * a * (1 - e**2)), rel=1e-14)
    assert math.acos(h[2] / np.linalg.norm(h)) == pytest.approx(i, abs=1e-14)
    assert abs(r @ v) < 1e-6 * np.linalg.norm(r) * np.linalg.norm(v)  # perigee: r ⟂ v
    R = lvlh_basis(r, v)
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-15)
    assert np.linalg.det(R) == pytest.approx(1.0)
    np.testing.assert_allclose(R[:, 2], -r / np.linalg.norm(r), atol=1e-15)  # z to the Earth
    assert R[:, 0] @ v > 0.999 * np.linalg.norm(v)  # x along the flight direction
    with pytest.raises(InputError, match="e < 1"):
        keplerian_state(a, 1.2, i, 0, 0, 0)


def test_two_body_conserves_energy_and_angular_momentum_of_both_spacecraft() -> None:
    a, e = A_LEO / 0.95, 0.05
    r0, v0 = keplerian_state(a, e, np.radians(51.6), 0.0, 0.0, 0.0)
    t = np.linspace(0.0, _period(a), 200)
    y = propagate_pair(r0, v0, [20.0, -5.0, 3.0], [0.01, 0.0, -0.02], t, TWO_BODY)
    for r, v in ((y[:, :3], y[:, 3:6]), (y[:, :3] + y[:, 6:9], y[:, 3:6] + y[:, 9:12])):
        energy = 0.5 * np.sum(v**2, axis=1) - EARTH_MU / np.linalg.norm(r, axis=1)
        h = np.cross(r, v)
        assert np.ptp(energy) / abs(energy[0]) < 1e-9
        assert np.abs(h - h[0]).max() / np.linalg.norm(h[0]) < 1e-9
    # After one period the chaser is back where it started.
    assert np.linalg.norm(y[-1, :3] - r0) / np.linalg.norm(r0) < 1e-9


def test_drag_takes_the_energy_the_closed_form_says() -> None:
    """dE/dt = a_drag · v = −½ ρ B |v|³ per spacecraft; twice the ballistic coefficient, twice."""
    rho_air, b_chaser, b_target = 1e-11, 0.01, 0.02
    force = ForceModel(j2=False, drag_density=rho_air, ballistic_chaser=b_chaser,
                       ballistic_target=b_target)  # fmt: skip
    r0, v0 = keplerian_state(A_LEO, 0.0, np.radians(51.6), 0.0, 0.0, 0.0)
    t = np.array([0.0, 600.0])
    y = propagate_pair(r0, v0, [25.0, 0.0, 0.0], np.zeros(3), t, force)
    speed = np.linalg.norm(v0)
    for r, v, b in ((y[:, :3], y[:, 3:6], b_chaser),
                    (y[:, :3] + y[:, 6:9], y[:, 3:6] + y[:, 9:12], b_target)):  # fmt: skip
        energy = 0.5 * np.sum(v**2, axis=1) - EARTH_MU / np.linalg.norm(r, axis=1)
        expected = -0.5 * rho_air * b * speed**3 * t[1]
        assert (energy[1] - energy[0]) / expected == pytest.approx(1.0, abs=1e-3)
    assert ForceModel().drag_density == 0.0  # off by default


def test_j2_nodal_regression_matches_the_secular_rate() -> None:
    a, e, i = A_LEO, 0.001, np.radians(51.6)
    r0, v0 = keplerian_state(a, e, i, 0.0, 0.0, 0.0)
    # Five periods sampled densely: the short-period terms at twice the orbital rate average
    # out of a straight-line fit.
    t = np.linspace(0.0, 5 * _period(a), 2001)
    y = propagate_pair(r0, v0, np.zeros(3), np.zeros(3), t, ForceModel(j2=True))
    h = np.cross(y[:, :3], y[:, 3:6])
    raan = np.unwrap(np.arctan2(h[:, 0], -h[:, 1]))
    rate = np.polyfit(t, raan, 1)[0]
    n, p = math.sqrt(EARTH_MU / a**3), a * (1 - e**2)
    expected = -1.5 * n * EARTH_J2 * (EARTH_RADIUS / p) ** 2 * math.cos(i)
    assert rate == pytest.approx(expected, rel=0.02, abs=0)
    assert np.degrees(expected) * 86400 == pytest.approx(-4.75, abs=0.01)  # °/day at 500 km


def test_torque_free_attitude_conserves_momentum_energy_and_matches_closed_forms() -> None:
    inertia = np.array([1200.0, 1000.0, 800.0])
    R0 = Rotation.from_euler("ZYX", [30.0, -20.0, 45.0], degrees=True).as_matrix()
    w0 = np.radians([1.0, -2.0, 1.5])
    t = np.arange(0.0, 600.0, 1.0)
    q, w = torque_free_attitude(R0, w0, inertia, t)
    energy = 0.5 * np.einsum("ni,i,ni->n", w, inertia, w)
    h_I = Rotation.from_quat(q).apply(w * inertia)
    assert np.ptp(energy) / energy[0] < 1e-10
    assert np.ptp(np.linalg.norm(h_I, axis=1)) / np.linalg.norm(h_I[0]) < 1e-10
    assert np.abs(h_I - h_I[0]).max() / np.linalg.norm(h_I[0]) < 1e-9
    assert np.all(np.einsum("ni,ni->n", q[1:], q[:-1]) > 0)  # sign kept continuous
    # An independent integrator (the filter's RK4 on quaternions and inertia ratios) agrees.
    q_rk, w_rk = q[0], w[0]
    for _ in range(60):
        q_rk, w_rk = dynamics.propagate_attitude(q_rk, w_rk, inertia, 1.0, 20)
    angle = (Rotation.from_quat(q[60]).inv() * Rotation.from_quat(q_rk)).magnitude()
    assert angle < 1e-9 and np.abs(w_rk - w[60]).max() < 1e-12
    # Spin about a principal axis: a uniform rotation R0 · Rz(ω t).
    qz, wz = torque_free_attitude(R0, [0.0, 0.0, 0.05], inertia, t[:100])
    expected = Rotation.from_matrix(R0) * Rotation.from_rotvec(np.outer(0.05 * t[:100], [0, 0, 1]))
    assert (expected.inv() * Rotation.from_quat(qz)).magnitude().max() < 1e-10
    np.testing.assert_allclose(wz, [[0.0, 0.0, 0.05]] * 100, atol=1e-15)


def _circular_truth(standoff: float, t, force: ForceModel):
    r0, v0 = keplerian_state(A_LEO, 0.0, np.radians(51.6), 0.0, 0.0, 0.0)
    return relative_truth(r0, v0, [standoff, 0.0, 0.0], [0.001, -0.002, 0.0015], t, force)


def test_relative_state_is_in_the_filters_frames() -> None:
    t = np.arange(0.0, 60.0, 0.5)
    rel = _circular_truth(25.0, t, ForceModel())
    assert rel.mean_motion == pytest.approx(math.sqrt(EARTH_MU / A_LEO**3), rel=1e-12, abs=0)
    np.testing.assert_allclose(rel.rho_O[0], [25.0, 0.0, 0.0], atol=1e-12)
    np.testing.assert_allclose(rel.v_O[0], [0.001, -0.002, 0.0015], atol=1e-12)
    # ρ in O is the ECI offset seen from I turned by n t about −y; ρ̇ is its time derivative.
    R_O_I = dynamics.R_I_O(rel.mean_motion, t[40]).T
    np.testing.assert_allclose(rel.rho_O[40], R_O_I @ rel.R_eci_I.T @ rel.eci[40, 6:9], atol=1e-12)
    v_fd = (rel.rho_O[2:] - rel.rho_O[:-2]) / 1.0
    np.testing.assert_allclose(v_fd, rel.v_O[1:-1], atol=1e-8)
    with pytest.raises(InputError, match="t = 0"):
        _circular_truth(25.0, t + 1.0, ForceModel())


def test_near_circular_relative_motion_agrees_with_cw_to_second_order() -> None:
    """Without J2, CW's error is the quadratic term ~ n² ρ² / r: 4× for twice the range."""
    t = np.array([0.0, 100.0])
    gaps = []
    for standoff in (25.0, 50.0):
        rel = _circular_truth(standoff, t, TWO_BODY)
        n = rel.mean_motion
        cw = dynamics.cw_closed_form(np.concatenate([rel.rho_O[0], rel.v_O[0]]), n, t[1])
        gaps.append(np.linalg.norm(rel.rho_O[1] - cw[:3]))
        # The along-track quadratic term 3 n² x² / (2 r)... bounded by 3 n² ρ² t² / r.
        assert gaps[-1] < 3 * n**2 * standoff**2 * t[1] ** 2 / A_LEO
    assert gaps[1] / gaps[0] == pytest.approx(4.0, rel=0.05)
    assert gaps[0] > 1e-9  # the truth is not CW
    # J2's differential pull is what the filter misses most on a circular orbit: far larger.
    rel = _circular_truth(25.0, t, ForceModel())
    cw = dynamics.cw_closed_form(np.concatenate([rel.rho_O[0], rel.v_O[0]]), n, t[1])
    gap_j2 = np.linalg.norm(rel.rho_O[1] - cw[:3])
    gradient = 6 * EARTH_J2 * EARTH_MU * EARTH_RADIUS**2 / A_LEO**5  # ~ ∂a_J2/∂r, 1/s²
    assert 100 * gaps[0] < gap_j2 < gradient * 25.0 * t[1] ** 2


def test_knowledge_errors_have_the_stated_spread() -> None:
    rng = np.random.default_rng(7)
    sigma = np.radians(0.01)
    angles = np.array(
        [Rotation.from_matrix(misaligned(np.eye(3), sigma, rng)).as_rotvec() for _ in range(3000)]
    )
    np.testing.assert_allclose(angles.std(axis=0), sigma, rtol=0.06)
    rects = orbit_target().rectangles
    offsets = []
    for seed in range(200):
        known = perturbed_catalogue(rects, 0.002, np.random.default_rng(seed))
        for k, r in zip(known, rects, strict=True):
            assert k.a <= k.b and k.name == r.name
            offsets.append(np.r_[k.center - r.center, k.a - r.a, k.b - r.b])
    np.testing.assert_allclose(np.std(offsets, axis=0), 0.002, rtol=0.08)
