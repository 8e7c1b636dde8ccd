"""Twenty-second hostile round: meshes, planes and registrations off the simulator's path."""

from __future__ import annotations

import trimesh

from spacepose.cli import main


def test_simulate_says_its_target_frame_is_not_the_mesh_files(tmp_path, capsys):
    """``simulate --model MESH`` centres the mesh on its bounding box, and the run's model.ply
    is in that frame; tracked against the file itself, an asymmetric mesh's track was 566 mm
    off (a mesh 10 m from its origin: metres), every frame `ok`, without a word. The shift is
    now said; a mesh centred already says nothing."""
    box = trimesh.creation.box(extents=(0.4, 0.3, 0.2))
    centred = tmp_path / "centred.obj"
    box.export(centred)
    moved = tmp_path / "moved.obj"
    box.copy().apply_translation((10.0, 0.0, 0.5)).export(moved)
    capsys.readouterr()

    def simulate(mesh, out):
        return main(["simulate", "lab", "--frames", "1", "--model", str(mesh), "--out", str(out)])

    assert simulate(moved, tmp_path / "a") == 0
    err = capsys.readouterr().err
    assert f"{moved}: the run's target frame is the mesh moved by (-10, 0, -0.5) m" in err
    assert simulate(centred, tmp_path / "b") == 0
    assert "target frame" not in capsys.readouterr().err
    # A generated spacecraft has no file: the check first refused it as a mesh without a suffix.
    assert (
        main(
            [
                "simulate",
                "orbit",
                "--frames",
                "2",
                "--model",
                "random:3",
                "--out",
                str(tmp_path / "c"),
            ]
        )
        == 0
    )
    assert "target frame" not in capsys.readouterr().err


def test_register_says_when_a_quarter_turn_fits_as_well(rng):
    """Points filling a volume (here: 90 % uniform outliers, all of it) fit any pose: `register
    --global` gave a pose 109° off at a fitness of 1.0 and a σ of 0.013°, without a word. A
    warning now says the fit tells no pose from another; a box's two views say nothing."""
    import warnings

    import numpy as np
    import pytest

    from spacepose.errors import SpaceposeWarning
    from spacepose.tools.register import register

    centre = np.array([0.0, 0.0, 3.0])
    volume = rng.uniform(-0.5, 0.5, (4000, 3)) + centre
    other = rng.uniform(-0.5, 0.5, (4000, 3)) + centre
    with pytest.warns(SpaceposeWarning, match=r"a quarter turn fits the target as well"):
        register(volume, other, workers=1)
    box = trimesh.creation.box(extents=(0.6, 0.4, 0.3))
    points, _ = trimesh.sample.sample_surface(box, 4000, seed=1)
    shifted = points + np.array([0.01, -0.005, 0.002])
    with warnings.catch_warnings():
        warnings.simplefilter("error", SpaceposeWarning)
        result = register(shifted, points, workers=1)
    np.testing.assert_allclose(
        result.result.T_target_source[:3, 3], [-0.01, 0.005, -0.002], atol=2e-3
    )


def test_a_plate_sampled_finer_than_its_noise_is_a_plane(rng, tmp_path):
    """A 1.0 x 0.6 m plate of 1 M points under 1 mm of noise was "no plane found: the best
    plane ... cuts a curved surface": each inlier's ten nearest points lay within 1.5 mm,
    their normals mostly noise. Here a 0.2 x 0.12 m plate of 100,000 points (spacing 0.5 mm):
    its normals now reach five noise σ, and the plate is one plane of the right size."""
    import numpy as np

    from spacepose.core.planes import extract_planes

    n = 100_000
    plate = np.c_[rng.uniform(-0.1, 0.1, n), rng.uniform(-0.06, 0.06, n), rng.normal(3, 1e-3, n)]
    planes = extract_planes(plate)
    assert len(planes) >= 1
    largest = max(planes, key=lambda p: len(p.inliers))
    assert len(largest.inliers) > 0.95 * n
    np.testing.assert_allclose(np.abs(largest.normal), [0.0, 0.0, 1.0], atol=1e-3)
