"""The voxel grid's share of a model-free frame's covariance (core.window_registration
.with_grid_spread, docs/methods.md §5.3)."""

from __future__ import annotations

import numpy as np

from spacepose.core import range_bias, se3, window_registration
from spacepose.core.frame_check import UNTESTED_MODEL
from spacepose.core.sim import simulate
from spacepose.core.tracker import Tracker, TrackerConfig
from spacepose.tools.experiments.robustness_cells import Cell, cell_scenario


def _per_axis_nsigma(result, T_true):
    d = se3.log(result.T_sensor_target @ se3.invert(T_true))
    return np.abs(d) / np.sqrt(np.diag(result.covariance))


def test_a_frame_the_grid_biases_carries_the_bias_in_its_sigma(monkeypatch):
    """satellite_panels at 3 m, accelerating: frame 2 onto the first keyframe is 0.38° off
    wherever the seed puts the noise (the grid's cut of the panels' edges). Its σ held 0.02°,
    and the frame passed every check of its own at 7.2σ (degraded only because no frame had
    tested the motion model yet); with the second sampling's spread it is within 3σ. The pose
    itself is the same with and without the term."""
    # The grid's run of 12 frames (its accelerating profile spans the run); 3 are tracked.
    sim = simulate(cell_scenario(Cell("panels", 3.0, 1.0, "accelerating", "none", 0), 12))
    T0_inv = se3.invert(sim.T_sensor_target[0])

    def track(with_spread: bool):
        if not with_spread:
            monkeypatch.setattr(window_registration, "with_grid_spread", lambda r, s, e, *_: e)
        tracker = Tracker(TrackerConfig(), workers=1)
        frames = [sim.frame(k) for k in range(3)]
        out = [tracker.track_frame(f.cloud, f.timestamp) for f in frames][2]
        monkeypatch.undo()
        return out

    plain, spread = track(False), track(True)
    T_true = sim.T_sensor_target[2] @ T0_inv
    np.testing.assert_array_equal(plain.T_sensor_target, spread.T_sensor_target)
    error_deg = np.degrees(np.linalg.norm(se3.log(spread.T_sensor_target @ se3.invert(T_true))[:3]))
    assert 0.3 < error_deg < 0.45  # measured 0.38
    assert plain.reasons == spread.reasons == (UNTESTED_MODEL,)
    assert _per_axis_nsigma(plain, T_true).max() > 6.0  # measured 7.2
    assert _per_axis_nsigma(spread, T_true).max() < 3.0  # measured 1.2
    # The term is d dᵀ / 2: positive semi-definite, of rank one.
    extra = spread.covariance - plain.covariance
    eigenvalues = np.linalg.eigvalsh(0.5 * (extra + extra.T))
    assert eigenvalues[-1] > 0 and np.all(np.abs(eigenvalues[:-1]) < 1e-9 * eigenvalues[-1])


def test_a_model_based_frame_carries_the_grid_spread_too(monkeypatch):
    """The Hubble kit scaled to 2 m, 5 m from the ToF camera, tracked against its model: the
    frame's voxel sampling biases its registration onto the model as onto a keyframe. Over 20
    frames (seed 0) 19 are ok either way, at the same poses; without the term 16 of them lie
    within 3σ on every axis, with it 18 (frame 3: 3.3 → 2.4σ, frame 7: 3.0 → 1.6σ)."""
    from spacepose.core.sim import simulate_orbit
    from test_tracker import hubble_at_close_range

    sim = simulate_orbit(hubble_at_close_range(20))

    def track(with_spread: bool):
        # The measured range terms (range_bias.py) off in both: they widen a frame of the run
        # without the spread term too (18 within 3σ), standing in for what is tested here.
        monkeypatch.setattr(range_bias, "SHIFT_BOUND", np.inf)
        if not with_spread:
            monkeypatch.setattr(window_registration, "with_grid_spread", lambda r, s, e, *_: e)
        tracker = Tracker(TrackerConfig(), sim.model_cloud(), workers=1)
        out = [tracker.track_frame(f.cloud, f.timestamp) for f in sim.frames()]
        monkeypatch.undo()
        return out

    plain, spread = track(False), track(True)
    within = {}
    for name, results in (("plain", plain), ("spread", spread)):
        nsigma = [
            _per_axis_nsigma(r, f.T_sensor_target).max()
            for r, f in zip(results, sim.frames(), strict=True)
            if r.status == "ok"
        ]
        assert len(nsigma) == 19
        within[name] = sum(n <= 3.0 for n in nsigma)
    # Measured 16 and 18; frame 1 sits at 3.0σ without the term, so allow it either side.
    assert within["plain"] <= 17 and within["spread"] >= 18
    for a, b in zip(plain, spread, strict=True):
        assert a.status == b.status
        np.testing.assert_array_equal(a.T_sensor_target, b.T_sensor_target)
        # d dᵀ / 2 only adds: no direction's variance falls.
        assert np.linalg.eigvalsh(b.covariance - a.covariance)[0] > -1e-12 * np.trace(a.covariance)
