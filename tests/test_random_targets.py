"""Generated spacecraft (``random:K``): the same seed the same shape, asymmetric, a catalogue that
lies on the mesh, and accepted wherever a mesh file is."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from tests.test_targets import _unmatched_share

from spacepose.core.sim import LabConfig, OrbitConfig, simulate_lab, simulate_orbit
from spacepose.core.sim.random_targets import generated_seed, random_spacecraft
from spacepose.errors import ConfigError
from spacepose.tools.experiments.robustness_cells import Cell, cell_problem


def test_the_same_seed_gives_the_same_spacecraft_and_others_differ() -> None:
    a, b, c = random_spacecraft(5), random_spacecraft(5), random_spacecraft(6)
    assert np.array_equal(a.mesh.vertices, b.mesh.vertices)
    assert a.name == "random:5"
    assert a.mesh.vertices.shape != c.mesh.vertices.shape or not np.allclose(
        a.mesh.vertices, c.mesh.vertices
    )


@pytest.mark.parametrize("seed", range(6))
def test_every_catalogue_rectangle_lies_on_the_surface_with_its_normal_outward(seed) -> None:
    target = random_spacecraft(seed)
    assert len(target.rectangles) >= 6  # the bus's faces at least
    for rect in target.rectangles:
        # The centre and the four corners (each moved 1 mm towards the centre) are on the face:
        # 1 mm behind it is inside a part, 1 mm before the centre is outside every part.
        half = np.array([rect.a, rect.b, 0.0]) / 2 - 1e-3
        offsets = [half * np.array([sx, sy, 0.0]) for sx in (-1, 1) for sy in (-1, 1)]
        on_face = rect.center + np.array([np.zeros(3), *offsets]) @ rect.R_model_plane.T
        normal = rect.R_model_plane[:, 2]
        behind = on_face - 1e-3 * normal
        assert np.any([part.contains(behind) for part in target.parts], axis=0).all(), rect.name
        before = (rect.center + 1e-3 * normal)[None]
        assert not any(part.contains(before)[0] for part in target.parts), rect.name


@pytest.mark.parametrize("seed", [1, 3, 5])
@pytest.mark.parametrize("axis", ["x", "y", "z"])
def test_a_spacecraft_with_wings_is_not_its_own_half_turn(seed, axis) -> None:
    turned, floor = _unmatched_share(
        lambda: random_spacecraft(seed), Rotation.from_euler(axis, 180, degrees=True)
    )
    # A half turn leaves at least 2 % of the surface farther than 3 spacings from the unturned
    # one (measured 0.035-0.48), against the sampling's floor (measured at most 0.003).
    assert floor < 0.005 and turned > 0.02


@pytest.mark.parametrize("name", ["random:", "random:-1", "random:1.5", "random:x", "random:٣"])
def test_a_random_name_without_a_whole_seed_is_refused(name) -> None:
    with pytest.raises(ConfigError, match="random:K"):
        generated_seed(name)
    problem = cell_problem(Cell(target=name))
    assert problem is not None and "random:K" in problem


def test_a_mesh_file_name_is_not_a_generated_one() -> None:
    assert generated_seed("satellite_panels.obj") is None
    assert generated_seed("randomised.obj") is None


def test_the_lab_and_orbit_runs_and_the_grid_take_a_generated_spacecraft() -> None:
    lab = simulate_lab(LabConfig(frames=2, model="random:3", target_size_m=0.4))
    assert lab.target.name == "random:3"
    assert np.isclose(lab.target.mesh.extents.max(), 0.4)
    assert lab.frame(0).on_target.sum() > 1000
    orbit = simulate_orbit(OrbitConfig(frames=2, model="random:3", model_scale=0.5))
    assert np.isclose(
        orbit.target.mesh.extents.max(), 0.5 * random_spacecraft(3).mesh.extents.max()
    )
    assert orbit.frame(0).on_target.sum() > 100
    assert cell_problem(Cell(target="random:3", range=6.0)) is None
