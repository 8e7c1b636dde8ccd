"""Reading and checking rectangle catalogues."""

from __future__ import annotations

import json

import numpy as np
import pytest
import yaml

from spacepose.core.rectangles import RectangleConfig
from spacepose.errors import ConfigError
from spacepose.tools.catalogue import load_catalogue, parse_catalogue, size_classes

EYE = np.eye(3).tolist()
FLIP_Z = np.diag([1.0, -1.0, -1.0]).tolist()  # same face turned over: normal −z


def _e(name, a, b, R=EYE, center=(0.0, 0.0, 0.0)):
    return {"name": name, "center": list(center), "R_model_plane": R, "a": a, "b": b}


GOOD = [_e("top", 1.8, 2.4), _e("bottom", 1.8, 2.4, FLIP_Z), _e("wing", 2.0, 6.0)]


def test_scenario_json_and_yaml_layouts(tmp_path):
    scenario = tmp_path / "scenario.json"
    scenario.write_text(json.dumps({"seed": 1, "target": {"name": "orbit", "rectangles": GOOD}}))
    user = tmp_path / "cat.yaml"
    user.write_text(yaml.safe_dump({"rectangles": GOOD}))
    bare = tmp_path / "list.yml"
    bare.write_text(yaml.safe_dump(GOOD))
    for path in (scenario, user, bare):
        entries = load_catalogue(path)
        assert [e.name for e in entries] == ["top", "bottom", "wing"]
        np.testing.assert_array_equal(entries[1].rotation, np.diag([1.0, -1.0, -1.0]))
        assert entries[2].a == 2.0 and entries[2].b == 6.0


def test_simulator_orbit_catalogue_is_accepted():
    targets = pytest.importorskip("spacepose.core.sim.targets")
    rects = [r.to_dict() for r in targets.orbit_target().rectangles]
    names = [e.name for e in parse_catalogue(rects)]
    assert len(names) == 10 and "wing_front" in names and "antenna_front" in names


def test_equal_faces_are_legal_and_listed_as_size_classes():
    targets = pytest.importorskip("spacepose.core.sim.targets")
    # The lab mock-up's two wings: equal size, parallel normals, 0.39 m apart (refused before).
    lab = parse_catalogue([r.to_dict() for r in targets.lab_target().rectangles])
    assert len(lab) == 10
    assert size_classes(lab) == [
        ["bus+x", "bus-x"],  # 0.16 x 0.16
        ["bus+y", "bus-y", "bus+z", "bus-z"],  # 0.16 x 0.20
        ["wing_right_front", "wing_right_back", "wing_left_front", "wing_left_back"],
    ]
    orbit = parse_catalogue([r.to_dict() for r in targets.orbit_target().rectangles])
    assert size_classes(orbit) == [
        ["bus+x", "bus-x"],
        ["bus+y", "bus-y"],
        ["bus+z", "bus-z"],
        ["wing_front", "wing_back"],
        ["antenna_front", "antenna_back"],
    ]
    # Different sizes: one class each.
    assert size_classes(parse_catalogue(GOOD[2:])) == [["wing"]]


@pytest.mark.parametrize(
    ("entries", "match"),
    [
        ([_e("top", 2.4, 1.8)], r"'top'.*exceeds long side"),
        ([_e("skew", 1.0, 2.0, [[1, 0, 0], [0, 1, 0.1], [0, 0, 1]])], r"'skew'.*proper rotation"),
        ([_e("mirror", 1.0, 2.0, np.diag([1.0, 1.0, -1.0]).tolist())], r"'mirror'.*rotation"),
        ([_e("neg", -1.0, 2.0)], r"'neg'.*greater than 0"),
        # NaN is named as such, not by the bound it fails; a centre whose square overflows is
        # refused (it printed numpy's bare overflow warning and went on).
        ([_e("nan", float("nan"), 2.0)], r"'nan'.*a: Input should be a finite number"),
        ([{**_e("far", 1.0, 2.0), "center": [1e300, 0, 0]}], r"'far'.*center: must be finite"),
        ([{"name": "half", "a": 1.0}], r"'half'.*center.*Field required"),
        ([_e("x", 1.0, 2.0), _e("x", 3.0, 4.0)], "duplicate rectangle names: x"),
        # 1.00 x 2.00 and 1.03 x 2.05 with parallel normals, same centre: one face twice.
        ([_e("p", 1.0, 2.0), _e("q", 1.03, 2.05)], r"'p'.*'q'.*cannot be told apart"),
        ([], "empty"),
    ],
)
def test_bad_entries_raise_config_error_naming_file_and_entry(tmp_path, entries, match):
    path = tmp_path / "bad.json"
    path.write_text(json.dumps({"rectangles": entries}))
    with pytest.raises(ConfigError, match=match) as info:
        load_catalogue(path)
    assert str(path) in str(info.value)


def test_tolerance_decides_what_is_distinguishable():
    entries = [_e("p", 1.0, 2.0), _e("q", 1.03, 2.05)]
    tight = RectangleConfig(side_tolerance_abs=0.005, side_tolerance_rel=0.0)
    assert [e.name for e in parse_catalogue(entries, tight)] == ["p", "q"]
    # Perpendicular normals (a box's sides) are told apart by a prediction, whatever the size.
    side = np.array([[0, 0, 1], [0, 1, 0], [-1, 0, 0]], dtype=float).tolist()
    assert len(parse_catalogue([_e("p", 1.0, 2.0), _e("s", 1.0, 2.0, side)])) == 2


def test_unreadable_files(tmp_path):
    with pytest.raises(ConfigError, match="cannot read"):
        load_catalogue(tmp_path / "missing.yaml")
    broken = tmp_path / "broken.json"
    broken.write_text("{not json")
    with pytest.raises(ConfigError, match="not valid JSON"):
        load_catalogue(broken)
    other = tmp_path / "other.yaml"
    other.write_text(yaml.safe_dump({"seed": 3}))
    with pytest.raises(ConfigError, match="no rectangle catalogue"):
        load_catalogue(other)


def test_malformed_yaml_is_one_line_with_line_and_column(tmp_path):
    path = tmp_path / "cat.yaml"
    path.write_text("rectangles:\n  - name: top\n    a: [1.8, 2.4\n    b: 2.4\n")
    with pytest.raises(ConfigError) as info:
        load_catalogue(path)
    assert str(info.value) == (
        f"{path}: not valid YAML: line 4:6: expected ',' or ']', but got ':' "
        "(while parsing a flow sequence)"
    )
