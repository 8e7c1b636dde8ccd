"""The first pass reaches two voxels at least (methods.md §5.5): on sparse frames whose fine gate
is under the sampling, a registration otherwise stops where a short prediction put it. It
reaches as far as its gate under a monotone kernel first."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from spacepose.core import fine_stage, frame_check, se3
from spacepose.core.cloud import PointCloud
from spacepose.core.frame_check import WIDE_PASS_VOXELS, CheckContext, first_pass_gate
from spacepose.core.motion import Prediction
from spacepose.core.scale import DataScale
from spacepose.core.sim.mesh_files import load_mesh
from spacepose.core.sim.sensors import SENSOR_PRESETS, scan
from spacepose.core.tracker import Tracker
from spacepose.core.tracker_config import TrackerConfig
from spacepose.tools.experiments.robustness import run_cell
from spacepose.tools.experiments.robustness_cells import Cell

MODELS = Path(__file__).resolve().parents[1] / "data" / "models"


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


@pytest.mark.parametrize("noise", [0.0, 1.0])
def test_a_target_receding_half_its_radius_a_frame_is_followed(noise) -> None:
    """satellite_panels at a tenth of its size (1.57 m), receding 0.186 m a frame from 1.5 m
    and turning 2° a frame. The first pass under Geman-McClure alone took its scale from the
    pairs on the faces the recession slides along and weighed out those that show it: frames
    stopped 60-90 mm short (noise-free: from frame 4; the ToF's noise: from frame 1, 65 mm and
    2° off), and another renderer's version had a frame `ok` at 58 σ. Huber's kernel first,
    then the redescending one from there: every frame within 3 mm and 0.05°."""
    mesh = load_mesh(MODELS / "satellite_panels.obj", scale=0.1).mesh
    sensor = SENSOR_PRESETS["tof"].model_copy(update={"noise_scale": noise})
    rng = np.random.default_rng(5)
    start = Rotation.from_euler("xyz", [20.0, -35.0, 10.0], degrees=True)
    axis = np.array([0.3, 1.0, 0.2]) / np.linalg.norm([0.3, 1.0, 0.2])
    tracker = Tracker(TrackerConfig(), None, 1)
    T_first, errors, ok = None, [], 0
    for k in range(8):
        turned = start * Rotation.from_rotvec(axis * np.radians(2.0) * k)
        T_sensor_target = se3.make_transform(turned.as_matrix(), [0.0, 0.02, 1.5 + 0.186 * k])
        T_first = T_sensor_target if T_first is None else T_first
        view = scan(mesh.copy().apply_transform(T_sensor_target), sensor, rng)
        result = tracker.track_frame(PointCloud(view.points), 0.5 * k)
        truth = T_sensor_target @ se3.invert(T_first)
        xi = se3.log(result.T_sensor_target @ se3.invert(truth))
        errors.append((np.degrees(np.abs(xi[:3]).max()), 1e3 * np.abs(xi[3:]).max()))
        ok += result.status == "ok"
        if result.status == "ok":
            assert np.all(np.abs(xi) <= 3.0 * result.sigma + 1e-12), k
    # The errors are scored against frame 0's pose: it must still be the target frame.
    assert tracker.first_index == 0
    # Measured: at most 0.04° and 2.2 mm (noise-free), 0.04° and 1.4 mm (the ToF's noise).
    assert max(e[0] for e in errors) < 0.05 and max(e[1] for e in errors) < 3.0
    assert ok >= 6
