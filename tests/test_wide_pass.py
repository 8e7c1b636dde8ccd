"""The first pass reaches two voxels at least (methods.md §5.5): on sparse frames whose fine gate
is under the sampling, a registration otherwise stops where a short prediction put it."""

from __future__ import annotations

import numpy as np
import pytest

from spacepose.core import fine_stage, frame_check
from spacepose.core.frame_check import WIDE_PASS_VOXELS, CheckContext, first_pass_gate
from spacepose.core.motion import Prediction
from spacepose.core.scale import DataScale
from spacepose.core.tracker_config import TrackerConfig
from spacepose.tools.experiments.robustness import run_cell
from spacepose.tools.experiments.robustness_cells import Cell


class _Motion:
    def __init__(self, error):
        self.error = error

    def model_error(self):
        return self.error


@pytest.mark.parametrize(
    ("voxel", "error", "gate"),
    [
        # A voxel that is the sensor's own spacing, the model's error measured and small.
        (0.08, (0.001, 0.0001), WIDE_PASS_VOXELS * 0.08),
        # Not yet measured: the frame carries the first look for a support; no first pass.
        (0.08, None, 0.0),
        # A thinned frame (2.5 samples a voxel edge): the model error's reach, as before.
        (0.2, (0.001, 0.0001), 3.0 * (0.001 + 2.2 * 0.0001)),
    ],
)
def test_the_first_pass_reaches_two_voxels_on_frames_the_grid_hardly_thins(
    voxel, error, gate
) -> None:
    scale = DataScale(spacing=0.08, points=800, voxel=voxel, radius=2.2, noise=0.01)
    context = CheckContext(TrackerConfig(), scale, _Motion(error))
    predicted = Prediction.given(np.eye(4), np.eye(6))
    assert predicted.velocity_known
    assert first_pass_gate(context, predicted) == pytest.approx(gate)


@pytest.mark.parametrize(
    ("error", "reach"),
    [
        ((0.01, 0.002), 3.0 * (0.01 + 2.2 * 0.002)),
        # Wrong by a radius (frames followed onto the wrong surfaces): no further than a frame
        # may move knowing no velocity (max_motion, 0.5 radii), the reach without one.
        ((1.5, 0.1), 0.5 * 2.2),
    ],
)
def test_the_prediction_reaches_no_further_than_without_a_velocity(error, reach) -> None:
    scale = DataScale(spacing=0.02, points=8000, voxel=0.05, radius=2.2, noise=0.01)
    context = CheckContext(TrackerConfig(), scale, _Motion(error))
    assert frame_check.wide_gate(context, Prediction.given(np.eye(4), np.eye(6))) == (
        pytest.approx(reach)
    )
    unknown = Prediction(np.eye(4), np.eye(6), velocity_known=False)
    assert frame_check.wide_gate(context, unknown) == pytest.approx(0.5 * 2.2)


@pytest.fixture(scope="module")
def accelerating_at_25m() -> dict:
    # Generated spacecraft 14 on an accelerating slide at 25 m (flash LiDAR, 82 mm voxels):
    # without the floor frames 3-5 stopped 76, 134 and 209 mm short, all `ok` at 4.7-8.5 σ.
    return run_cell(Cell(target="random:14", range=25.0, motion="accelerating"), 12)


def test_sparse_frames_follow_an_accelerating_slide(accelerating_at_25m) -> None:
    rows = accelerating_at_25m["frames"]
    # Measured with the floor: 16, 42 and 26 mm; no `ok` frame beyond 5 σ.
    assert max(r["err_t_mm"] for r in rows[3:6]) < 60.0
    assert not any(r["false_ok"] for r in rows)
    assert sum(r["status"] == "ok" for r in rows) >= 8


def test_without_the_floor_the_same_run_stops_short(accelerating_at_25m, monkeypatch) -> None:
    # The basin probes of the unconfirmed frames 1-2 (methods.md §5.5) give this run a right
    # first velocity, and frames 3-5 then follow without the floor too; both are taken away.
    monkeypatch.setattr(frame_check, "WIDE_PASS_VOXELS", 0.0)
    monkeypatch.setattr(fine_stage, "PROBE_ROUNDS", 0)
    rows = run_cell(Cell(target="random:14", range=25.0, motion="accelerating"), 12)["frames"]
    assert max(r["err_t_mm"] for r in rows[3:6]) > 100.0
