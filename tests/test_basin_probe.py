"""Basin probes on frames no motion model confirms (methods.md §5.5): a registration that stopped
in a shallow minimum a few point spacings along a face is moved to the deeper one."""

from __future__ import annotations

import numpy as np
import pytest

from spacepose.core import fine_stage, frame_registration
from spacepose.core.basin_probe import probe_starts, truncated_cost
from spacepose.core.cloud import PointCloud
from spacepose.core.keyframes import PreparedCloud
from spacepose.errors import InputError
from spacepose.tools.experiments.robustness import run_cell
from spacepose.tools.experiments.robustness_cells import Cell


def _plane(spacing: float = 0.01, half: float = 0.5) -> PreparedCloud:
    """The plane z = 0 sampled on a square grid, normals +z."""
    u = np.arange(-half, half + 1e-9, spacing)
    x, y = np.meshgrid(u, u)
    points = np.c_[x.ravel(), y.ravel(), np.zeros(x.size)]
    return PreparedCloud(PointCloud(points, normals=np.tile([0.0, 0.0, 1.0], (len(points), 1))))


def test_truncated_cost_caps_each_point_at_the_gate() -> None:
    ref, gate, sigma = _plane(), 0.05, 0.01
    points = np.array(
        [
            [0.0, 0.0, 0.02],  # within the gate: (0.02 / 0.01)² = 4
            [0.1, 0.2, -0.03],  # 9
            [0.2, -0.1, 0.08],  # no surface within the gate: capped, (0.05 / 0.01)² = 25
            [3.0, 3.0, 0.0],  # off the plane's extent: capped too
        ]
    )
    assert truncated_cost(ref, points, np.eye(4), gate, sigma, 1) == pytest.approx(63.0)
    # Moved by the transform first: lifting the frame by 1 cm adds to each paired residual.
    T = np.eye(4)
    T[2, 3] = 0.01
    assert truncated_cost(ref, points[:2], T, gate, sigma, 1) == pytest.approx(9.0 + 4.0)


@pytest.mark.parametrize(("gate", "sigma"), [(0.05, 0.0), (0.0, 0.01), (np.nan, 0.01)])
def test_truncated_cost_refuses_a_scale_that_is_not_a_length(gate, sigma) -> None:
    with pytest.raises(InputError, match="positive length"):
        truncated_cost(_plane(), np.zeros((3, 3)), np.eye(4), gate, sigma, 1)


def test_truncated_cost_takes_a_cloud_and_refuses_bad_arrays() -> None:
    plane = _plane()
    points = np.array([[0.0, 0.0, 0.02], [0.1, 0.2, -0.03]])
    # A cloud with normals scores as its prepared form does.
    cost = truncated_cost(plane.cloud, PointCloud(points), np.eye(4), 0.05, 0.01, 1)
    assert cost == pytest.approx(13.0)
    bad = [
        (plane, np.zeros((3, 2)), np.eye(4)),  # not (N, 3)
        (plane, np.full((2, 3), np.nan), np.eye(4)),  # no finite row
        (plane, points, np.eye(3)),  # not 4x4
        (PointCloud(plane.cloud.points), points, np.eye(4)),  # no normals
    ]
    for ref, pts, T in bad:
        with pytest.raises(InputError):
            truncated_cost(ref, pts, T, 0.05, 0.01, 1)


@pytest.mark.parametrize(
    ("cov", "centroid", "step", "directions"),
    [
        (np.eye(5), np.zeros(3), 0.05, 2),
        (np.full((6, 6), np.nan), np.zeros(3), 0.05, 2),
        (np.eye(6), np.zeros(2), 0.05, 2),
        (np.eye(6), np.zeros(3), -0.05, 2),
        (np.eye(6), np.zeros(3), 0.05, 4),
    ],
)
def test_probe_starts_refuse_bad_arrays(cov, centroid, step, directions) -> None:
    with pytest.raises(InputError):
        probe_starts(np.eye(4), cov, centroid, step, directions)


def test_probes_start_along_the_least_constrained_directions_first() -> None:
    T = np.eye(4)
    T[:3, 3] = [0.3, -0.2, 10.0]
    # Translation σ 1, 3 and 2 cm about the sensor origin; no rotation uncertainty.
    cov = np.diag([0.0, 0.0, 0.0, 1e-4, 9e-4, 4e-4])
    assert len(probe_starts(T, cov, T[:3, 3], 0.05)) == 4  # the two a face leaves free
    starts = probe_starts(T, cov, T[:3, 3], 0.05, directions=3)
    shifts = np.array([s[:3, 3] - T[:3, 3] for s in starts])
    assert len(starts) == 6
    np.testing.assert_allclose(np.abs(shifts), 0.05 * np.abs(np.eye(3)[[1, 1, 2, 2, 0, 0]]))
    np.testing.assert_allclose(shifts[0], -shifts[1])
    for s in starts:  # shifts only: the attitude is the estimate's
        np.testing.assert_allclose(s[:3, :3], T[:3, :3])


def test_probes_see_the_lever_arm_of_a_turn() -> None:
    # A turn about x of σ 0.01 rad moves a centroid 10 m down the boresight by 10 cm along y,
    # more than any translation σ (1 mm): y is probed first.
    cov = np.diag([1e-4, 0.0, 0.0, 1e-6, 1e-6, 1e-6])
    first = probe_starts(np.eye(4), cov, np.array([0.0, 0.0, 10.0]), 0.05)[0]
    np.testing.assert_allclose(np.abs(first[:3, 3]), [0.0, 0.05, 0.0], atol=1e-12)


def test_a_second_frame_slid_along_a_face_is_probed_back(monkeypatch) -> None:
    """A generated box-bus spacecraft at 16 m (flash LiDAR, one point every 51 mm), turning 10°
    a frame: without probes the second frame stopped 95 mm along a face, σ 9 mm there, and
    every later frame inherited the slide, ``ok`` at 9-38 σ (9 false ``ok``). The slide is
    reproduced with the first pass under Geman-McClure alone, as it was then: under Huber's
    kernel first (methods.md §5.5) the unprobed second frame stops 37 mm along the face."""
    cell = Cell("random:23", 16.0, 1.0, "tumbling-10", "none", 0)
    monkeypatch.setattr(fine_stage, "PROBE_ROUNDS", 0)
    monkeypatch.setattr(frame_registration, "_WIDE_PASS_KERNELS", ("geman_mcclure",))
    before = run_cell(cell, 12)["frames"]
    monkeypatch.undo()
    after = run_cell(cell, 12)["frames"]
    assert before[1]["err_t_mm"] > 80.0 and sum(r["false_ok"] for r in before) >= 5
    assert after[1]["err_t_mm"] < 10.0
    assert all(r["status"] in ("ok", "degraded") for r in after)
    ok = [r for r in after if r["status"] == "ok"]
    assert len(ok) >= 8
    assert all(r["nsigma_max"] <= 3.0 for r in ok)


def test_a_frame_the_prediction_led_along_a_face_is_not_ok_beyond_its_sigma(monkeypatch) -> None:
    """A generated spacecraft at 16 m whose motion speeds up frame by frame: the constant-velocity
    prediction falls short along the slide, and the registration stops in the minimum it
    starts in. Without probes on frames a tested prediction confirms, frame 4 was ``ok`` 107 mm
    off at 16 σ; probed, it ended within 15 mm, and no ``ok`` frame is beyond 5 σ. The unprobed
    run is that of the first pass under Geman-McClure alone, as it was then. Under Huber's
    kernel first (methods.md §5.5) frame 4 ends 43 mm off with or without probes, within the
    51 mm between samples and ``ok`` at 1.6 σ (11 mm and ``degraded`` before)."""
    cell = Cell("random:19", 16.0, 1.0, "accelerating", "none", 1)
    monkeypatch.setattr(fine_stage.FineStage, "_probed", lambda self, prediction: False)
    monkeypatch.setattr(frame_registration, "_WIDE_PASS_KERNELS", ("geman_mcclure",))
    unprobed = run_cell(cell, 12)["frames"]
    monkeypatch.undo()
    after = run_cell(cell, 12)["frames"]
    assert unprobed[4]["err_t_mm"] > 90.0 and unprobed[4]["false_ok"]
    assert after[4]["err_t_mm"] < 51.0 and after[4]["nsigma_max"] < 3.0
    assert all(r["status"] in ("ok", "degraded") for r in after)
    assert not any(r["false_ok"] for r in after)
    assert sum(r["status"] == "ok" for r in after) >= 8
