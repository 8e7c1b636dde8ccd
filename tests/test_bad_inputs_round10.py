"""Bad inputs found by a tenth hostile round (about 820 runs of the CLI): each ends in one line
naming the file and the problem, the error last, never a traceback, a hang or a wrong reason."""

from __future__ import annotations

import time

import numpy as np
import pytest

from spacepose.cli import main
from spacepose.core.config import load_config
from spacepose.core.metrics import associate
from spacepose.core.tracker_config import TrackerConfig
from spacepose.errors import ConfigError, FileFormatError, InputError
from spacepose.tools.cloud_io import read_cloud

# -- YAML aliases that stand for a structure without end ------------------------------------------


def _laughs(levels: int) -> str:
    """Aliases of aliases: ``levels`` lines of ten aliases each stand for 10**levels values."""
    text = "a0: &a0 [x, x, x, x, x, x, x, x, x, x]\n"
    for i in range(1, levels + 1):
        text += f"a{i}: &a{i} [" + ", ".join([f"*a{i - 1}"] * 10) + "]\n"
    return text


_WITHOUT_END = "its aliases stand for a structure without end or far larger than the file"


@pytest.mark.parametrize(
    ("text", "problem"),
    [
        ("a: &a [*a]\n", _WITHOUT_END),
        ("a: &a {inner: *a}\n", "line 1:4: found unconstructable recursive node"),
        (_laughs(8), _WITHOUT_END),
    ],
    ids=["list in itself", "mapping in itself", "a billion values"],
)
def test_yaml_aliases_without_end_are_one_config_error(tmp_path, text, problem):
    """A list anchored inside itself ended in a RecursionError traceback (the key check walked
    the cycle; PyYAML refuses a mapping so itself); eight levels of aliases of aliases (430
    bytes) hung the run."""
    path = tmp_path / "config.yaml"
    path.write_text(text)
    tic = time.perf_counter()
    with pytest.raises(ConfigError) as exc:
        load_config(TrackerConfig, path)
    assert time.perf_counter() - tic < 10.0  # a hang before: not a speed goal, a sanity bound
    assert str(exc.value).startswith(f"{path}: not valid YAML: {problem}")


def test_an_alias_that_reuses_a_block_is_read(tmp_path):
    """A config that repeats a value by alias stays legal: only its keys decide."""
    path = tmp_path / "config.yaml"
    path.write_text("gate: &g 0.9\nhealth: {min_points: 150}\ncoarse_voxel: *g\n")
    config = load_config(TrackerConfig, path)
    assert config.gate == config.coarse_voxel == 0.9 and config.health.min_points == 150


def test_a_recursive_intrinsics_file_is_one_line_on_the_command_line(tmp_path, capsys):
    """The depth folder's intrinsics.yaml went through the same walk."""
    from PIL import Image

    folder = tmp_path / "depth"
    folder.mkdir()
    Image.fromarray(np.full((12, 16), 1200, np.uint16)).save(folder / "000000.png")
    (folder / "intrinsics.yaml").write_text("fx: &a [*a]\nfy: 12\ncx: 7.5\ncy: 5.5\n")
    assert main(["track", str(folder), "--out", str(tmp_path / "est.tum")]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"error: {folder / 'intrinsics.yaml'}: not valid")


# -- PLY values beyond their declared type -------------------------------------------------------


@pytest.mark.parametrize(
    ("kind", "value", "problem"),
    [
        ("float", "1e300", "overflow encountered in cast"),
        ("uchar", "300", "Python integer 300 out of bounds for uint8"),
    ],
)
def test_a_ply_value_beyond_its_type_names_the_file_and_the_problem(tmp_path, kind, value, problem):
    """1e300 declared float was cast to inf with numpy's bare warning, and the cloud refused
    for NaN/inf it did not hold; 300 declared uchar ended in plyfile's OverflowError."""
    path = tmp_path / "huge.ply"
    x = value if kind == "float" else "1"
    extra = "property uchar red\n" if kind == "uchar" else ""
    last = f" {value}" if kind == "uchar" else ""
    path.write_text(
        "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
        f"property float z\n{extra}end_header\n{x} 0 1{last}\n0 1 1{last and ' 2'}\n"
        f"1 1 1{last and ' 3'}\n"
    )
    with pytest.raises(FileFormatError) as exc:
        read_cloud(path)
    assert str(exc.value) == f"{path}: a value does not fit its declared PLY type ({problem})"


# -- a timestamp of 1e300 in the error of an unmatched estimate ----------------------------------


def test_an_unmatched_timestamp_is_written_as_a_number_not_three_hundred_digits():
    with pytest.raises(InputError) as exc:
        associate(np.array([0.0, 1e300]), np.array([0.0, 1.0]))
    assert "(first: t = 1e+300, nearest ground truth 1e+300 s away)" in str(exc.value)
    assert len(str(exc.value)) < 200


# -- the error line last ---------------------------------------------------------------------------


def test_the_error_is_the_last_line_after_the_warning_counts(tmp_path, capsys):
    """A folder whose every frame is lost printed its error, then "N more with the same
    warning": the error was not the last line."""
    for i in range(6):
        (tmp_path / f"f{i}.xyz").write_text("garbage\n")
    assert main(["track", str(tmp_path), "--out", str(tmp_path / "est.tum")]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-2].startswith("warning: 3 more with the same warning: not read, frame lost")
    assert err[-1].startswith(f"error: {tmp_path}: every frame was lost")


def test_a_model_free_run_with_nothing_after_its_first_frame_exits_1(tmp_path, capsys):
    """Model-free, the first frame is the identity by definition: a run whose every later frame
    was lost tracked nothing, yet exited 0 with "1 ok"."""
    from spacepose.core.sim import scenario_config, simulate

    frame = simulate(scenario_config("lab", frames=1)).frame(0)
    np.savetxt(tmp_path / "f0.xyz", frame.cloud.points)
    for i in range(1, 4):
        (tmp_path / f"f{i}.xyz").write_text("garbage\n")
    out = tmp_path / "est.tum"
    assert main(["track", str(tmp_path), "--out", str(out)]) == 1
    err = capsys.readouterr().err.strip().splitlines()
    assert err[-1].startswith(f"error: {tmp_path}: every frame after the first was lost (frame 1")
    assert len(out.read_text().splitlines()) == 4  # the rows are written all the same


@pytest.mark.parametrize(
    ("text", "problem"),
    [
        ("1,2,3\n4 5 6\n7,8,9\n", "line 2: fields separated by blanks where the first row's are"),
        ("1 2 3\n4,5,6\n7 8 9\n", "line 2: fields separated by commas where the first row's are"),
    ],
)
def test_a_text_cloud_mixing_separators_names_the_line(tmp_path, text, problem):
    """Said only "cannot parse text point file", with no line."""
    path = tmp_path / "mixed.csv"
    path.write_text(text)
    with pytest.raises(FileFormatError) as exc:
        read_cloud(path)
    assert str(exc.value).startswith(f"{path}: {problem}")
