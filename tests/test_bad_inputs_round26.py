"""Round 26 of bad inputs (navigation runs broken on purpose): a filter whose model does not
fit the data refuses what it sees, and says so."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from spacepose.core.nav_result import NavRow
from spacepose.errors import SpaceposeWarning
from spacepose.tools.navigation_reasons import warn_if_mostly_predicted


def _rows(updated: int, gated: int, idle: int) -> list[NavRow]:
    """A start, then frames that updated, frames whose rectangles the gate refused (a coarse
    pose was measured) and frames with nothing to update with."""
    coarse = np.eye(4)
    rows = [NavRow(0.0, None, None, 0, "init")]
    rows += [NavRow(1.0 + k, None, None, 1, "update") for k in range(updated)]
    rows += [NavRow(500.0 + k, None, None, 0, "predict", coarse) for k in range(gated)]
    rows += [NavRow(900.0 + k, None, None, 0, "predict") for k in range(idle)]
    return rows


@pytest.mark.parametrize(
    ("updated", "gated", "idle", "warned"),
    [
        (100, 78, 17, True),  # a mean motion twice the run's: 95 of 195 frames updated nothing
        (178, 0, 17, False),  # a sound orbit run: faces seen edge-on leave 9 % to prediction
        (120, 0, 73, True),  # a third of the frames without measurements
    ],
)
def test_a_filter_that_updates_on_few_frames_says_so(tmp_path, updated, gated, idle, warned):
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        warn_if_mostly_predicted(_rows(updated, gated, idle), tmp_path / "nav.csv")
    said = [str(w.message) for w in caught if issubclass(w.category, SpaceposeWarning)]
    assert bool(said) is warned
    if warned:
        assert f"{gated + idle} of {updated + gated + idle} frames" in said[0]
        assert f"({gated} of them with rectangles the gate refused, the rest with" in said[0]


def _plate_filling_the_view(rng, sigma=0.01):
    """A ToF view (256 x 256 rays, 28° field) of a plane 1 m out turned 30° about x, every ray
    hitting it, with ``sigma`` m of range noise along the rays; the plane's unit normal."""
    u, v = np.meshgrid(np.linspace(-0.25, 0.25, 256), np.linspace(-0.25, 0.25, 256))
    rays = np.c_[u.ravel(), v.ravel(), np.ones(u.size)]
    rays /= np.linalg.norm(rays, axis=1, keepdims=True)
    normal = np.array([0.0, np.sin(np.radians(30.0)), -np.cos(np.radians(30.0))])
    t = -1.0 * normal[2] / -(rays @ normal)  # the plane n·p = n·(0, 0, 1)
    ranges = t + rng.normal(0.0, sigma, len(t))
    return rays * ranges[:, None], normal


def test_a_close_view_under_heavy_noise_is_one_plane(rng):
    # The 1 cm noise was measured, then set aside as too large a share of the frame's size,
    # and the default 5 mm slab cut the plate into three parallel planes 1.2° off.
    from spacepose.core.planes import PlaneConfig, extract_planes, slab_thickness

    points, normal = _plate_filling_the_view(rng)
    with pytest.warns(SpaceposeWarning, match="large share of the frame's size"):
        slab = slab_thickness(points)
    assert slab == pytest.approx(0.03, rel=0.15)
    planes = extract_planes(points, PlaneConfig(distance_threshold=slab))
    assert len(planes) == 1
    assert np.degrees(np.arccos(abs(planes[0].normal @ normal))) < 0.3


def test_an_orbit_run_of_a_mesh_says_it_has_no_catalogue(tmp_path, capsys):
    # `navigate` with its default measurements then refused the run ("the rectangle catalogue
    # is empty") after `simulate` had said nothing.
    import trimesh

    from spacepose.cli import main

    mesh = tmp_path / "bus.obj"
    trimesh.creation.box(extents=(1.2, 0.8, 0.6)).export(mesh)
    args = ["simulate", "orbit", "--frames", "2", "--seed", "1"]
    assert main([*args, "--model", str(mesh), "--out", str(tmp_path / "mesh_run")]) == 0
    assert "no rectangle catalogue" in capsys.readouterr().err
    assert main([*args, "--out", str(tmp_path / "default_run")]) == 0
    assert "no rectangle catalogue" not in capsys.readouterr().err


@pytest.mark.parametrize(("rectangles", "warned"), [(0, True), (2, False)])
def test_fusing_without_a_rectangle_used_says_so(tmp_path, rectangles, warned):
    # A catalogue 25 % larger than the target navigated 194 frames on the poses alone, as if
    # both had been fused.
    from spacepose.tools.navigation_reasons import warn_if_no_rectangle_used

    rows = [NavRow(float(k), None, None, rectangles if k == 5 else 0, "update") for k in range(9)]
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        warn_if_no_rectangle_used(rows, tmp_path / "nav.csv")
    said = [str(w.message) for w in caught if issubclass(w.category, SpaceposeWarning)]
    assert bool(said) is warned
    assert not said or "registration poses alone" in said[0]
