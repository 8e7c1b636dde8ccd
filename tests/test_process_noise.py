"""Tests of the measured process noise (spacepose.core.sim.process_noise)."""

from __future__ import annotations

import math

import numpy as np
import pytest

from spacepose.core import dynamics
from spacepose.core.sim.orbit_truth import torque_free_attitude
from spacepose.core.sim.process_noise import model_defect, spectral_density
from spacepose.errors import InputError

INERTIA = [1200.0, 1000.0, 800.0]


def test_white_defect_gives_its_variance_times_the_step() -> None:
    d = 1e-6 * np.random.default_rng(3).standard_normal(20000)
    density = spectral_density(d, 0.5, sigma_measurement=0.01)
    assert density.q / (np.mean(d**2) * 0.5) == pytest.approx(1.0, abs=0.05)


def test_steady_defect_counts_over_the_filter_memory() -> None:
    dt, sigma, a = 1.0, 0.01, 1e-7
    density = spectral_density(np.full(600, a), dt, sigma)
    # Fixed point: q = a² Δt (1 + 2K) (a bias is correlated at every lag) with K = ⌊T/Δt⌋
    # and the memory T = (σ² Δt / q)^¼.
    T = density.memory_s
    assert T == pytest.approx((sigma**2 * dt / density.q) ** 0.25, rel=1e-12, abs=0)
    lags = (density.q / (a**2 * dt) - 1) / 2
    assert lags == pytest.approx(round(lags), abs=1e-9)  # a whole number of lags,
    assert 0 <= round(lags) - T / dt <= 1  # the lags the memory spans, to the step
    assert 20 < T < 200  # 87 s: q is 175× the white-noise value
    assert spectral_density(np.zeros(5), dt, sigma).q == 0.0


def _free_flight_truth(t: np.ndarray, accel: np.ndarray) -> np.ndarray:
    truth = np.zeros((len(t), 20))
    truth[:, 0] = t
    truth[:, 1:4] = 0.5 * np.outer(t**2, accel) + [25.0, 0.0, 0.0]
    truth[:, 4:7] = np.outer(t, accel)
    q, w = torque_free_attitude(np.eye(3), np.radians([1.0, -2.0, 1.5]), INERTIA, t)
    truth[:, 7:11], truth[:, 11:14] = q, w
    truth[:, 14:17] = dynamics.inertia_ratios(INERTIA)
    return truth


def test_model_defect_recovers_a_known_unmodelled_acceleration() -> None:
    t = np.arange(0.0, 100.0, 2.0)
    accel = np.array([3e-7, -1e-7, 0.0])
    truth = _free_flight_truth(t, accel)
    defect = model_defect(truth, 0.0, sigma_position=0.01, substeps=50)  # n = 0: free flight
    np.testing.assert_allclose(defect.rms_accel, np.abs(accel), rtol=1e-9, atol=1e-15)
    expected = spectral_density(np.full(len(t) - 1, 3e-7), 2.0, 0.01)
    assert defect.sigma_accel == pytest.approx(math.sqrt(expected.q), rel=1e-9, abs=0)
    assert defect.memory_s == pytest.approx(expected.memory_s)
    assert defect.sigma_angular_accel < 1e-12  # the rotation is exactly the filter's model
    assert defect.dt == 2.0 and defect.to_dict()["sigma_accel"] == defect.sigma_accel


def test_cw_truth_has_no_translational_defect_and_bad_input_is_refused() -> None:
    n, t = 1.1e-3, np.arange(0.0, 40.0, 1.0)
    truth = _free_flight_truth(t, np.zeros(3))
    x0 = np.array([25.0, 0.1, -0.2, 0.001, 0.002, -0.001])
    truth[:, 1:7] = [dynamics.cw_closed_form(x0, n, ti) for ti in t]
    assert model_defect(truth, n).sigma_accel < 1e-15
    with pytest.raises(InputError, match="equally spaced"):
        model_defect(truth[[0, 1, 3]], n)
    with pytest.raises(InputError, match="truth must be"):
        model_defect(truth[:1], n)
