"""Eighteenth hostile round: a plane slab under a sensor's noise, a NaN row that renumbered
the results, an order-dependent mean of poses, a model given as a path."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from spacepose.cli import main
from spacepose.core import se3
from spacepose.core.sim.scenarios import OrbitConfig, simulate_orbit
from spacepose.errors import InputError, SpaceposeWarning
from spacepose.tools.cloud_io import write_cloud


def test_planes_take_their_slab_from_the_frames_noise(tmp_path, capsys):
    """`planes` on an orbit frame (flash LiDAR at 25 m, 1 cm of range noise) kept its 5 mm slab
    whatever --sigma said, and cut each face in two parallel planes 1 cm apart (5 planes, two
    pairs within 1° of each other), naming none. The slab is now 3σ, σ given or measured
    along the frame's rays: no face is cut in two."""
    sim = simulate_orbit(OrbitConfig(frames=6))
    path = write_cloud(tmp_path / "f5.ply", sim.frame(5).cloud.points)
    for extra in ([], ["--sigma", "0.01"]):
        assert main(["planes", str(path), "--json", *extra]) == 0
        planes = json.loads(capsys.readouterr().out)
        assert len(planes) >= 2
        normals = np.array([p["normal"] for p in planes])
        centroids = np.array([p["centroid"] for p in planes])
        for i in range(len(planes)):
            for j in range(i):
                parallel = abs(normals[i] @ normals[j]) > np.cos(np.radians(3.0))
                apart = abs(normals[i] @ (centroids[i] - centroids[j]))
                assert not (parallel and apart < 0.05), (i, j, apart)


def test_an_array_row_left_out_is_said_with_what_it_does_to_the_numbering():
    """A NaN row in an (N, 3) array was dropped without a word: `icp_correspondences`
    returned indices into the 2,999 rows kept, and the caller's ``src[c.src_idx]`` paired
    points 0.5 m apart. It is now said, with what it means for the indices."""
    from spacepose.core.icp import icp_correspondences

    rng = np.random.default_rng(5)
    target = rng.normal(size=(3000, 3))
    source = target.copy()
    source[0] = np.nan
    with pytest.warns(SpaceposeWarning, match=r"source: 1 of 3000 rows hold NaN .* refer to the"):
        _, pairs = icp_correspondences(source, target)
    kept = source[1:]
    np.testing.assert_allclose(kept[pairs.src_idx], target[pairs.tgt_idx], atol=1e-9)


def _turn(degrees: float) -> np.ndarray:
    return se3.make_transform(Rotation.from_euler("z", degrees, degrees=True), [0.0, 0.0, 0.0])


def test_the_mean_of_poses_does_not_depend_on_their_order():
    """Turns of 0, +170 and −170° about one axis: the mean came back as 0° (summed squared
    distance 57,800 deg², a maximum along the axis) started from the first, and as +120°
    listed 170, 0, −170. Started at the chordal mean it is one of the two minima (±120°,
    21,800 deg²) in any order."""
    means = []
    for order in ([0.0, 170.0, -170.0], [170.0, 0.0, -170.0], [-170.0, 170.0, 0.0]):
        mean = se3.geodesic_mean(np.stack([_turn(d) for d in order]))
        means.append(Rotation.from_matrix(mean[:3, :3]).as_euler("zyx", degrees=True)[0])
    np.testing.assert_allclose(means, means[0], atol=1e-9)
    assert abs(abs(means[0]) - 120.0) < 1e-6


def test_a_model_given_as_a_path_is_said_to_be_one():
    """``Tracker(model="model.ply")`` read the path as numbers: "points are not numeric:
    could not convert string to float". It now says that it is a file name, and how to read
    it."""
    from spacepose.core.tracker import Tracker

    with pytest.raises(InputError, match=r"model is a file name \(model\.ply\): read it with"):
        Tracker(model="model.ply")
