"""Bad config-like input (fuzzer findings): undecodable files, non-finite values, negative seeds,
a quaternion prior that is no rotation. Each is one line naming the file, option or field."""

from __future__ import annotations

import importlib
import json
import math
import pkgutil
import re
import types
import typing

import numpy as np
import pytest

import spacepose
from spacepose.cli import main
from spacepose.core.background import BackgroundConfig
from spacepose.core.config import StageConfig, config_name, dump_config, load_config
from spacepose.core.depth import DepthCamera
from spacepose.core.navigation import NavigationConfig
from spacepose.core.planes import PlaneConfig
from spacepose.core.tracker_config import TrackerConfig
from spacepose.errors import ConfigError, FileFormatError, SpaceposeWarning
from spacepose.tools.catalogue import load_catalogue, parse_catalogue
from spacepose.tools.navigation_config_io import prior_quaternion
from spacepose.tools.report import build_report
from spacepose.tools.runs import read_run
from spacepose.tools.tracking_io import tracker_config

# What the fuzzer fed: a UTF-16 byte order mark and bytes that are no UTF-8.
BINARY = b"\xff\xfe\x00\xc0garbage\x81\n"
EYE = np.eye(3).tolist()


def _one_line(exc: pytest.ExceptionInfo, *names: object) -> str:
    """The message, checked to be one line naming every one of ``names``."""
    message = str(exc.value)
    assert "\n" not in message, message
    for name in names:
        assert str(name) in message, message
    return message


def _cli_error(capsys) -> str:
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and "Traceback" not in err, err
    return err


def _entry(**change: object) -> dict:
    return {"name": "front", "center": [0, 0, 0], "R_model_plane": EYE, "a": 0.4, "b": 0.6} | change


# -- 1. files that are not UTF-8 text ---------------------------------------------------------


@pytest.mark.parametrize("model", [TrackerConfig, NavigationConfig, DepthCamera])
def test_binary_config_file_is_a_config_error_naming_it(tmp_path, model):
    path = tmp_path / "bin.yaml"
    path.write_bytes(BINARY)
    with pytest.raises(ConfigError) as exc:
        load_config(model, path)
    _one_line(exc, path, "not UTF-8 text")


def test_binary_catalogue_is_a_config_error_naming_it(tmp_path):
    path = tmp_path / "cat_bin.yaml"
    path.write_bytes(BINARY)
    with pytest.raises(ConfigError) as exc:
        load_catalogue(path)
    _one_line(exc, path, "not UTF-8 text")


def test_binary_scenario_file_is_one_line_from_navigate(tmp_path, capsys):
    frames = tmp_path / "frames"
    frames.mkdir()
    np.savetxt(frames / "000000.xyz", np.random.default_rng(0).uniform(-1, 1, (50, 3)))
    scenario = tmp_path / "garbage.yaml"
    scenario.write_bytes(BINARY)
    args = ["navigate", str(frames), "--out", str(tmp_path / "nav" / "p.csv")]
    assert main([*args, "--scenario", str(scenario)]) == 1
    err = _cli_error(capsys)
    assert str(scenario) in err and "not UTF-8 text" in err


def test_binary_truth_csv_is_a_file_format_error_naming_it(tmp_path, bare_orbit_run):
    run = bare_orbit_run(tmp_path / "run", b"t," + BINARY)
    with pytest.raises(FileFormatError) as exc:
        read_run(run)
    _one_line(exc, run / "truth.csv", "not UTF-8 text")


@pytest.mark.filterwarnings("error")
def test_truth_csv_with_its_header_alone_is_one_clean_error(tmp_path, bare_orbit_run):
    header = (
        "t,rho_x,rho_y,rho_z,v_x,v_y,v_z,qx,qy,qz,qw,w_x,w_y,w_z,k_x,k_y,k_z,com_x,com_y,com_z\n"
    )
    run = bare_orbit_run(tmp_path / "run", header.encode())
    # numpy's "input contained no data" warning is an error here: none may leak.
    with pytest.raises(FileFormatError) as exc:
        read_run(run)
    _one_line(exc, run / "truth.csv", "expected 1 rows", "got none")


def test_report_says_a_binary_truth_csv_is_not_text(tmp_path):
    run = tmp_path / "orbit"
    run.mkdir()
    (run / "scenario.json").write_text(json.dumps({"scenario": "orbit"}))
    (run / "nav.csv").write_text("t,rho_x\n0,1\n")
    (run / "truth.csv").write_bytes(BINARY)
    with pytest.warns(SpaceposeWarning) as warned:
        build_report(tmp_path, tmp_path / "report.html")
    reasons = [str(w.message) for w in warned if "truth.csv" in str(w.message)]
    assert len(reasons) == 1 and "not UTF-8 text" in reasons[0], reasons


# -- 2. non-finite values ------------------------------------------------------------------------


def _stage_configs() -> list[type[StageConfig]]:
    """Every StageConfig subclass of the package (each module imported)."""
    for module in pkgutil.walk_packages(spacepose.__path__, "spacepose."):
        importlib.import_module(module.name)
    found, todo = [], [StageConfig]
    while todo:
        for sub in todo.pop().__subclasses__():
            found.append(sub)
            todo.append(sub)
    return found


def _is_float(annotation: object) -> bool:
    if annotation is float:
        return True
    union = typing.get_origin(annotation) in (typing.Union, types.UnionType)
    return union and set(typing.get_args(annotation)) == {float, type(None)}


def test_every_stage_config_rejects_inf_and_nan_in_every_float_field():
    checked = 0
    for model in _stage_configs():
        try:
            defaults = model().model_dump()
        except ConfigError:  # required fields (DepthCamera): tested on their own below
            continue
        for field, info in model.model_fields.items():
            if not _is_float(info.annotation):
                continue
            for value in (math.inf, math.nan):
                if (model, field, value) == (BackgroundConfig, "range_max", math.inf):
                    continue  # "no upper limit", tested below
                with pytest.raises(ConfigError) as exc:
                    model.model_validate(defaults | {field: value})
                _one_line(exc, config_name(model), field)
                checked += 1
    assert checked > 100


def test_every_stage_config_writes_strict_json_that_reads_back(tmp_path):
    for model in _stage_configs():
        try:
            config = model()
        except ConfigError:
            continue
        text = json.dumps(config.model_dump(mode="json"), allow_nan=False)
        assert model.model_validate(json.loads(text)) == config, model.__name__


@pytest.mark.parametrize(
    ("model", "name", "text", "field"),
    [
        (TrackerConfig, "voxinf.yaml", "voxel_size: .inf\n", "voxel_size"),
        (DepthCamera, "intrinsics.yaml", "fx: .inf\nfy: 500\ncx: 320\ncy: 240\n", "fx"),
    ],
)
def test_config_files_with_an_infinite_value_are_refused(tmp_path, model, name, text, field):
    path = tmp_path / name
    path.write_text(text)
    with pytest.raises(ConfigError) as exc:
        load_config(model, path)
    _one_line(exc, path, field, "finite")


def test_background_range_max_is_unbounded_as_none_and_old_inf_reads_as_none():
    assert BackgroundConfig().range_max is None
    # A config written when "no limit" was inf (YAML .inf, JSON Infinity).
    assert BackgroundConfig(range_max=math.inf).range_max is None
    assert BackgroundConfig(range_min=1.0, range_max=2.0).range_max == 2.0
    with pytest.raises(ConfigError) as exc:
        BackgroundConfig(range_min=3.0, range_max=2.0)
    _one_line(exc, "range_min")


def test_track_config_with_a_partial_background_round_trips_as_strict_json(tmp_path):
    # A background section without range_max took the unbounded default: Infinity in JSON.
    path = tmp_path / "bg.json"
    path.write_text(json.dumps({"background": {"seed": 2}}))
    written = dump_config(tracker_config(path, background=True), tmp_path / "est.config.json")
    data = json.loads(written.read_text(), parse_constant=lambda c: pytest.fail(c))
    assert data["background"]["range_max"] is None and data["use_background_removal"]
    assert load_config(TrackerConfig, written) == tracker_config(path, background=True)


@pytest.mark.filterwarnings("error")
@pytest.mark.parametrize(
    ("change", "field"),
    [
        ({"center": [math.inf, 0, 0]}, "center"),
        ({"center": [0, math.nan, 0]}, "center"),
        ({"b": math.inf}, "b"),
    ],
)
def test_catalogue_entry_with_a_non_finite_centre_or_side_is_refused(tmp_path, change, field):
    other = _entry(name="side", center=[1, 0, 0], a=0.3, b=0.9)
    with pytest.raises(ConfigError) as exc:
        parse_catalogue([_entry(**change), other], source=tmp_path / "cat.json")
    _one_line(exc, tmp_path / "cat.json", "entry 0 ('front')", field, "finite")


def test_a_boolean_for_a_number_is_refused_in_a_config_and_a_catalogue(tmp_path):
    # Pydantic reads true as 1.0: an ok condition of one would flag every frame, a side of one
    # metre would name no rectangle. Switches still take booleans.
    path = tmp_path / "tracker.yaml"
    path.write_text("health:\n  ok_condition: true\n")
    with pytest.raises(ConfigError) as exc:
        load_config(TrackerConfig, path)
    _one_line(exc, path, "health.ok_condition", "yes/no")
    assert TrackerConfig(use_background_removal=True).use_background_removal
    # The other way round: a number for a switch (pydantic reads 1 as true).
    path.write_text("use_mls: 1\n")
    with pytest.raises(ConfigError) as exc:
        load_config(TrackerConfig, path)
    _one_line(exc, path, "use_mls", "is a number, not a yes/no")
    other = _entry(name="side", center=[1, 0, 0], a=0.3, b=0.9)
    with pytest.raises(ConfigError) as exc:
        parse_catalogue([_entry(a=True), other], source=tmp_path / "cat.json")
    _one_line(exc, tmp_path / "cat.json", "entry 0 ('front')", "a", "yes/no")
    with pytest.raises(ConfigError) as exc:
        parse_catalogue([_entry(center=[True, 0, 0]), other], source=tmp_path / "cat.json")
    _one_line(exc, tmp_path / "cat.json", "entry 0 ('front')", "center", "yes/no")
    # Quoted numbers were read as numbers, where configs refuse them.
    for quoted in ({"a": "0.3"}, {"center": ["0", 0, 0]}):
        with pytest.raises(ConfigError) as exc:
            parse_catalogue([_entry(**quoted), other], source=tmp_path / "cat.json")
        _one_line(exc, tmp_path / "cat.json", "entry 0 ('front')", "holds text", "unquoted")


@pytest.mark.parametrize(
    ("text", "words"),
    [
        (
            "health:\n  ok_fitness: 0.3\n  lost_fitness: 0.9\n",
            ("lost_fitness 0.9", "ok_fitness 0.3"),
        ),
        ("health:\n  ok_rmse: 5\n  lost_rmse: 0.1\n", ("ok_rmse 5", "lost_rmse 0.1")),
        ("health:\n  ok_condition: 1e5\n", ("ok_condition 100000", "lost_condition 10000")),
        (
            "use_mls: true\nmls:\n  min_neighbors: 200\n  max_neighbors: 10\n",
            ("min_neighbors 200", "max_neighbors 10"),
        ),
    ],
)
def test_an_ok_bound_beyond_its_lost_bound_is_refused_at_load(tmp_path, text, words):
    """An ok bound past its lost bound let a run go on with overlapping statuses (1 ok and 3
    lost where the defaults give 3 ok); more MLS neighbours needed than taken lost every frame
    with a reason that did not name the config."""
    path = tmp_path / "tracker.yaml"
    path.write_text(text)
    with pytest.raises(ConfigError) as exc:
        load_config(TrackerConfig, path)
    _one_line(exc, path, *words)


def test_a_number_written_as_text_is_refused_in_a_config(tmp_path):
    """Pydantic reads "0.5" as 0.5: a quoted number (or one with its unit, "5 mm") was taken
    in silence. Refused, naming the field; text fields still take text."""
    path = tmp_path / "tracker.yaml"
    path.write_text('gate: "0.5"\nhealth:\n  ok_rmse: "0.67"\n')
    with pytest.raises(ConfigError) as exc:
        load_config(TrackerConfig, path)
    _one_line(exc, path, "gate: '0.5' is text", "health.ok_rmse", "unquoted")
    with pytest.raises(ConfigError, match="points_per_frame"):
        TrackerConfig.model_validate({"points_per_frame": "3000"})
    assert TrackerConfig.model_validate({"method": "gicp"}).method == "gicp"
    assert BackgroundConfig.model_validate({"range_max": None}).range_max is None
    # PyYAML (YAML 1.1) reads 1e5 and 1.0e5 as text; unquoted they are numbers, as in YAML 1.2.
    path.write_text("health:\n  lost_condition: 1e5\n  ok_condition: 2.5e3\n")
    health = load_config(TrackerConfig, path).health
    assert (health.lost_condition, health.ok_condition) == (1e5, 2500.0)


@pytest.mark.parametrize(
    ("written", "value"),
    [("010", 10), ("0x1F", 31), ("0o17", 15), ("+7", 7), ("1_000", None), ("1:30", None)],
)
def test_yaml_numbers_are_read_as_yaml_1_2_reads_them(tmp_path, written, value):
    """YAML 1.1 (PyYAML) read max_iterations: 010 as 8 (octal), 1:30 as 90 (base 60) and
    1_000 as 1000: values the user did not write, or did not mean. As YAML 1.2 reads them,
    010 is 10, and 1:30 and 1_000 are text, which a number field refuses in one line."""
    path = tmp_path / "tracker.yaml"
    path.write_text(f"icp:\n  max_iterations: {written}\n")
    if value is not None:
        assert load_config(TrackerConfig, path).icp.max_iterations == value
        return
    with pytest.raises(ConfigError) as exc:
        load_config(TrackerConfig, path)
    _one_line(exc, path, f"icp.max_iterations: '{written}' is text")


def test_points_per_frame_below_the_health_minimum_is_refused():
    assert TrackerConfig().points_per_frame == 3000
    assert TrackerConfig(points_per_frame=100).points_per_frame == 100
    with pytest.raises(ConfigError) as exc:
        TrackerConfig.model_validate({"points_per_frame": 1})
    _one_line(exc, "points_per_frame")


# -- 3. negative seeds ---------------------------------------------------------------------------


def test_negative_seeds_are_config_errors_naming_the_field():
    with pytest.raises(ConfigError) as exc:
        PlaneConfig(seed=-1)
    _one_line(exc, "seed")
    with pytest.raises(ConfigError) as exc:
        TrackerConfig.model_validate({"background": {"seed": -1}})
    _one_line(exc, "background.seed")


def test_planes_with_a_negative_seed_exits_1_naming_it(tmp_path, capsys):
    cloud = tmp_path / "c.xyz"
    np.savetxt(cloud, np.random.default_rng(0).uniform(-1, 1, (100, 3)))
    assert main(["planes", str(cloud), "--seed", "-1"]) == 1
    assert "seed" in _cli_error(capsys)


# -- 4. an attitude prior that is no rotation ----------------------------------------------------


@pytest.mark.parametrize(
    "values", [(0, 0, 0, 0), (math.nan, 0, 0, 1), (math.inf, 0, 0, 1), (0, 0, 1), "abcd"]
)
def test_prior_quaternion_must_be_a_rotation(values):
    with pytest.raises(ConfigError) as exc:
        prior_quaternion(values, "prior_q_I_B")
    _one_line(exc, "prior_q_I_B: the quaternion must be four finite numbers with a non-zero norm")


def test_prior_quaternion_of_any_non_zero_norm_is_normalised():
    # Normalised with a warning of the norm (tests/test_bad_inputs_round9.py).
    with pytest.warns(SpaceposeWarning, match="^q: the quaternion has norm 2, not 1"):
        assert prior_quaternion([0, 0, 0, 2], "q") == (0.0, 0.0, 0.0, 1.0)
    # Norms that underflow or overflow on their own.
    for scale in (1e-200, 1e300):
        norm = re.escape(f"norm {scale * math.sqrt(2):.6g}, not 1")
        with pytest.warns(SpaceposeWarning, match=norm):
            q = np.array(prior_quaternion([scale, 0, 0, scale], "q"))
        np.testing.assert_allclose(q, [math.sqrt(0.5), 0, 0, math.sqrt(0.5)])


@pytest.mark.parametrize("prior", ["0,0,0,0", "nan,0,0,1"])
def test_navigate_prior_that_is_no_rotation_exits_1(tmp_path, capsys, prior):
    args = ["navigate", str(tmp_path), "--out", str(tmp_path / "nav" / "p.csv")]
    assert main([*args, "--prior", prior]) == 1
    err = _cli_error(capsys)
    assert "--prior: the quaternion must be four finite numbers with a non-zero norm" in err


@pytest.mark.parametrize("fov", ["zzz", [-10, 500], [60], [60, 0], {"h": 60}])
def test_a_scenario_field_of_view_that_is_no_pair_of_angles_is_one_line(tmp_path, capsys, fov):
    frames = tmp_path / "frames"
    frames.mkdir()
    np.savetxt(frames / "000000.xyz", np.random.default_rng(0).uniform(-1, 1, (50, 3)))
    scenario = tmp_path / "scenario.yaml"
    description = {"mean_motion": 0.001, "R_O_C": EYE, "rectangles": [_entry()]}
    scenario.write_text(json.dumps(description | {"sensor_fov_deg": fov}))
    args = ["navigate", str(frames), "--out", str(tmp_path / "nav" / "p.csv")]
    assert main([*args, "--scenario", str(scenario)]) == 1
    err = _cli_error(capsys)
    assert f"{scenario}: sensor_fov_deg: invalid lost in space config: fov_deg" in err


# Deeper than either parser's recursion: a RecursionError traceback before.
DEEP = "[" * 100_000 + "]" * 100_000


@pytest.mark.parametrize("name", ["deep.json", "deep.yaml"])
def test_structured_files_nested_too_deeply_are_one_line(tmp_path, capsys, name):
    path = tmp_path / name
    path.write_text(DEEP if name.endswith(".json") else f"a: {DEEP}\n")
    with pytest.raises(ConfigError, match="nested too deeply") as info:
        load_config(TrackerConfig, path)
    _one_line(info, path)
    with pytest.raises(ConfigError, match="nested too deeply"):
        load_catalogue(path)
    frames = tmp_path / "frames"
    frames.mkdir()
    np.savetxt(frames / "000000.xyz", np.random.default_rng(0).uniform(-1, 1, (50, 3)))
    out = ["--out", str(tmp_path / "o" / "n.csv")]
    assert main(["navigate", str(frames), "--scenario", str(path), *out]) == 1
    assert f"{path}: not valid" in _cli_error(capsys)


@pytest.mark.parametrize("name", ["long.json", "long.yaml"])
def test_an_integer_too_long_to_read_is_one_line(tmp_path, name):
    """Python's int() refuses more than 4,300 digits: a ValueError traceback before."""
    path = tmp_path / name
    digits = "9" * 5000
    path.write_text(
        f'{{"points_per_frame": {digits}}}' if name.endswith(".json") else f"a: {digits}\n"
    )
    with pytest.raises(ConfigError, match="more digits than can be read") as info:
        load_config(TrackerConfig, path)
    _one_line(info, path)


def test_a_run_whose_scenario_json_is_nested_too_deeply(tmp_path, capsys, bare_orbit_run):
    run = bare_orbit_run(tmp_path / "run", b"")
    (run / "scenario.json").write_text(DEEP)
    with pytest.raises(FileFormatError, match=r"scenario\.json: not valid JSON: nested too deeply"):
        read_run(run)
    assert main(["report", str(run), "--out", str(tmp_path / "r.html")]) == 0
    assert "scenario.json: left out of the report: not valid JSON" in capsys.readouterr().err


@pytest.mark.parametrize(
    ("name", "text", "where"),
    [
        ("tracker.yaml", "gate: 3\nmethod: gicp\ngate: 4\n", "line 3:1"),
        ("tracker.yaml", "icp:\n  max_iterations: 5\n  max_iterations: 9\n", "line 3:3"),
        ("tracker.json", '{"gate": 3, "method": "gicp", "gate": 4}', "line 1:"),
    ],
)
def test_a_key_given_twice_is_refused_not_taken_last(tmp_path, name, text, where):
    """YAML and JSON parsers keep the last of two equal keys without a word; a config whose
    first value of a knob is silently ignored is wrong, so it is one line naming the key."""
    path = tmp_path / name
    path.write_text(text)
    with pytest.raises(ConfigError) as info:
        load_config(TrackerConfig, path)
    message = _one_line(info, path, where)
    assert "is given twice" in message and ("'gate'" in message or "'max_iterations'" in message)


def test_merge_keys_and_equal_keys_in_separate_mappings_stay_legal(tmp_path):
    path = tmp_path / "tracker.yaml"
    path.write_text("base: &b {max_iterations: 5}\nicp:\n  <<: *b\n  method: point_to_plane\n")
    with pytest.raises(ConfigError, match="base") as info:  # merged; 'base' is no field
        load_config(TrackerConfig, path)
    assert "twice" not in str(info.value)
    path.write_text("icp: {max_iterations: 5}\ngicp: {max_iterations: 5}\n")
    config = load_config(TrackerConfig, path)
    assert config.icp.max_iterations == config.gicp.max_iterations == 5


def test_a_boolean_for_a_number_is_refused_in_an_init_transform_and_a_scenario(tmp_path):
    """numpy reads true as 1: an init translation of true is a metre, a mean motion of true
    one radian a second. Both are refused, naming the file."""
    from spacepose.core.nav_start import scenario_geometry
    from spacepose.errors import InputError
    from spacepose.tools.register_io import read_transform

    init = tmp_path / "init.json"
    rows = np.eye(4).tolist()
    rows[0][3] = True
    init.write_text(json.dumps({"T_target_source": rows}))
    with pytest.raises(FileFormatError, match=r"init\.json: expected 16 numbers"):
        read_transform(init)
    rows[0][3] = 1.0
    init.write_text(json.dumps({"T_target_source": rows}))
    assert read_transform(init)[0, 3] == 1.0
    with pytest.raises(InputError, match=r"s\.json: mean_motion 1e\+30 rad/s .* no body is dense"):
        scenario_geometry({"mean_motion": 1e30, "R_O_C": np.eye(3).tolist()}, "s.json")
    with pytest.raises(InputError, match=r"s\.json: mean_motion holds a yes/no"):
        scenario_geometry({"mean_motion": True, "R_O_C": np.eye(3).tolist()}, "s.json")
    with pytest.raises(InputError, match=r"s\.json: mean_motion holds text"):
        scenario_geometry({"mean_motion": "0.0011", "R_O_C": np.eye(3).tolist()}, "s.json")
    # JSON's NaN reaches here as text through the YAML reader: named as not finite.
    with pytest.raises(InputError, match=r"s\.json: mean_motion must be finite, got 'NaN'"):
        scenario_geometry({"mean_motion": "NaN", "R_O_C": np.eye(3).tolist()}, "s.json")
    with pytest.raises(InputError, match=r"s\.json: R_O_C holds a yes/no"):
        scenario_geometry(
            {"mean_motion": 0.001, "R_O_C": [[True, 0, 0], [0, 1, 0], [0, 0, 1]]}, "s.json"
        )


@pytest.mark.parametrize(
    ("text", "key", "under"),
    [("yes: 3\n", "True", None), ("health:\n  1: 2\n", "1", "health"), ("null: 0\n", "None", None)],
)
def test_a_config_key_yaml_reads_as_no_name_is_refused(tmp_path, text, key, under) -> None:
    # YAML reads yes / 1 / null as a boolean, a number or None: pydantic's TypeError
    # ("keywords must be strings") escaped as a traceback, for the tracker's and the filter's.
    path = tmp_path / "config.yaml"
    path.write_text(text)
    for model in (TrackerConfig, NavigationConfig):
        with pytest.raises(ConfigError) as exc:
            load_config(model, path)
        message = _one_line(exc, path, config_name(model), f"the key {key}")
        assert (f"under {under}" in message) == (under is not None)


def test_a_list_of_quoted_numbers_is_refused_as_a_quoted_number_is() -> None:
    """``sensor_fov_deg: ["30", "30"]`` was read as the angles without a word, while
    ``mean_motion: "0.0011"`` was refused as text."""
    from spacepose.core.lost_in_space import LostInSpaceConfig, with_sensor_fov

    config = LostInSpaceConfig()
    assert with_sensor_fov(config, [30, 20], "scenario.json").fov_deg == (30.0, 20.0)
    for fov in (["30", "30"], [30.0, "20"]):
        with pytest.raises(ConfigError, match=r"^scenario.json: sensor_fov_deg: .*holds text"):
            with_sensor_fov(config, fov, "scenario.json")


@pytest.mark.parametrize("field", ["sigma_feature", "init_sigma_position", "sigma_accel"])
def test_a_filter_sigma_whose_square_overflows_is_refused(tmp_path, field) -> None:
    """1e160 ended navigate in an OverflowError traceback; 1e300 in numpy's overflow warnings,
    then "zero norm quaternions"."""
    path = tmp_path / "nav.yaml"
    path.write_text(f"ekf:\n  {field}: 1e160\n")
    with pytest.raises(ConfigError, match=rf"ekf.{field}: .*1e\+160 is too large a sigma"):
        load_config(NavigationConfig, path)
    path.write_text(f"ekf:\n  {field}: 1e3\n")
    assert getattr(load_config(NavigationConfig, path).ekf, field) == 1e3
