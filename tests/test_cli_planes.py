"""``spacepose planes``: JSON keys and values on a two-face scene, table output, errors."""

from __future__ import annotations

import json

import numpy as np
import pytest
import yaml

from spacepose.cli import main

KEYS = {"centroid", "normal", "eigenvalues", "a", "b", "n_inliers", "rectangle", "candidates"}


@pytest.fixture
def scene(tmp_path):
    """Two rectangles on a regular grid (m): 0.4 x 0.6 at z = 2 and 0.3 x 0.9 at x = 1."""
    u = (np.arange(40) + 0.5) / 40
    v = (np.arange(60) + 0.5) / 60
    U, V = (g.ravel() for g in np.meshgrid(u, v, indexing="ij"))
    front = np.column_stack([-0.2 + 0.4 * U, -0.3 + 0.6 * V, np.full(U.size, 2.0)])
    side = np.column_stack([np.full(U.size, 1.0), -0.45 + 0.9 * V, 2.5 + 0.3 * U])
    path = tmp_path / "scene.npy"
    np.save(path, np.vstack([front, side]))
    catalogue = tmp_path / "cat.yaml"
    eye = np.eye(3).tolist()
    catalogue.write_text(
        yaml.safe_dump(
            {
                "rectangles": [
                    {
                        "name": "front",
                        "center": [0, 0, 0],
                        "R_model_plane": eye,
                        "a": 0.4,
                        "b": 0.6,
                    },
                    {"name": "side", "center": [0, 0, 0], "R_model_plane": eye, "a": 0.3, "b": 0.9},
                ]
            }
        )
    )
    return path, catalogue


def test_json_output_has_exactly_the_keys_and_true_values(scene, capsys):
    path, catalogue = scene
    assert main(["planes", str(path), "--catalogue", str(catalogue), "--json"]) == 0
    rows = json.loads(capsys.readouterr().out)
    assert len(rows) == 2
    for row in rows:
        assert set(row) == KEYS
        assert row["n_inliers"] == 2400
    by_name = {row["rectangle"]: row for row in rows}
    assert set(by_name) == {"front", "side"}
    assert [row["candidates"] for row in rows] == [[row["rectangle"]] for row in rows]
    front, side = by_name["front"], by_name["side"]
    np.testing.assert_allclose(front["centroid"], [0, 0, 2.0], atol=1e-12)
    np.testing.assert_allclose(front["normal"], [0, 0, -1.0], atol=1e-9)  # towards the sensor
    # Grid of 40 x 60 cell centres: variance (s²/12)(1 − 1/n²).
    np.testing.assert_allclose(
        front["eigenvalues"],
        [0, 0.4**2 / 12 * (1 - 1 / 40**2), 0.6**2 / 12 * (1 - 1 / 60**2)],
        atol=1e-12,
    )
    assert front["a"] == pytest.approx(0.4, rel=1e-3) and front["b"] == pytest.approx(0.6, rel=1e-3)
    np.testing.assert_allclose(side["centroid"], [1.0, 0.0, 2.65], atol=1e-12)
    np.testing.assert_allclose(side["normal"], [-1.0, 0, 0], atol=1e-9)


def test_faces_of_equal_size_are_reported_ambiguous(scene, tmp_path, capsys):
    # A legal catalogue with two 0.4 x 0.6 faces (a panel's two sides): the sides name "side"
    # but leave the 0.4 x 0.6 plane between "front" and "back".
    path, catalogue = scene
    entries = yaml.safe_load(catalogue.read_text())["rectangles"]
    back = dict(entries[0], name="back", R_model_plane=np.diag([1.0, -1.0, -1.0]).tolist())
    twins = tmp_path / "twins.yaml"
    twins.write_text(yaml.safe_dump({"rectangles": [*entries, back]}))
    assert main(["planes", str(path), "--catalogue", str(twins), "--json"]) == 0
    rows = json.loads(capsys.readouterr().out)
    by_centroid = {round(row["centroid"][2], 2): row for row in rows}
    assert by_centroid[2.0]["rectangle"] is None
    assert by_centroid[2.0]["candidates"] == ["front", "back"]
    assert by_centroid[2.65]["rectangle"] == "side" and by_centroid[2.65]["candidates"] == ["side"]
    assert main(["planes", str(path), "--catalogue", str(twins)]) == 0
    out = capsys.readouterr().out  # the table wraps the cell: check its words
    assert "ambiguous:" in out and "back" in out and "side" in out


def test_fill_check_with_the_camera_focal_length(scene, capsys):
    path, catalogue = scene
    # The front face is a 1 cm grid at 2 m: what a 200 px camera gives (fill 1). A 400 px
    # camera would see 4 times as many points on a whole face: 2400 means most is hidden.
    args = ["planes", str(path), "--catalogue", str(catalogue), "--json", "--focal-px"]
    assert main([*args, "200"]) == 0
    names = {row["rectangle"] for row in json.loads(capsys.readouterr().out)}
    assert "front" in names
    assert main([*args, "400"]) == 0
    names = {row["rectangle"] for row in json.loads(capsys.readouterr().out)}
    assert "front" not in names


def test_without_catalogue_rectangle_is_null_and_table_prints(scene, capsys):
    path, _ = scene
    assert main(["planes", str(path), "--json"]) == 0
    rows = json.loads(capsys.readouterr().out)
    assert [row["rectangle"] for row in rows] == [None, None]
    assert main(["planes", str(path)]) == 0
    out = capsys.readouterr().out
    assert "2 planes" in out and "0.400 x 0.600" in out


def test_errors_are_one_line_and_exit_code_1(scene, tmp_path, capsys):
    path, _ = scene
    assert main(["planes", str(tmp_path / "missing.ply")]) == 1
    assert "missing.ply" in capsys.readouterr().err
    bad = tmp_path / "bad.yaml"
    bad.write_text(yaml.safe_dump([{"name": "x", "center": [0, 0, 0], "a": 2.0, "b": 1.0}]))
    assert main(["planes", str(path), "--catalogue", str(bad)]) == 1
    err = capsys.readouterr().err
    assert "bad.yaml" in err and "'x'" in err
    line = tmp_path / "line.npy"
    np.save(line, np.outer(np.linspace(0, 1, 100), [1.0, 2.0, 3.0]))
    assert main(["planes", str(line)]) == 1
    assert "line.npy: all 100 points are collinear: no plane to fit" in capsys.readouterr().err
    # One repeated point: it used to be told its noise was as large as the cloud.
    np.save(line, np.ones((100, 3)))
    assert main(["planes", str(line)]) == 1
    assert "line.npy: all 100 points are at one place: no plane to fit" in capsys.readouterr().err
    assert main(["planes", str(path), "--threshold", "-1"]) == 1
    assert "distance_threshold" in capsys.readouterr().err
    # A noise as large as the cloud (a wrong unit) printed every side as 0.000.
    assert main(["planes", str(path), "--sigma", "10"]) == 1
    err = capsys.readouterr().err.strip()
    assert "noise sigma 10 m is as large as the cloud itself" in err and "\n" not in err
    # A plane threshold as large: one "plane" of every face, its normal between theirs.
    assert main(["planes", str(path), "--threshold", "100"]) == 1
    err = capsys.readouterr().err.strip()
    assert "plane threshold 100 m is as large as the cloud itself" in err and "\n" not in err
