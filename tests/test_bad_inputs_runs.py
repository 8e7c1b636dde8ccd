"""Bad input to the long runs (fuzzer findings): robustness cells, campaign grids, bench outputs.

Each is refused before any work starts, as one line naming the option or file and the problem;
the expensive functions are replaced by stand-ins that fail the test if they are called.
"""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from spacepose.cli import main
from spacepose.errors import ConfigError, InputError
from spacepose.tools import bench, experiments
from spacepose.tools import campaign as cp
from spacepose.tools.campaign_spec import load_campaign_config
from spacepose.tools.experiments import ExperimentOptions, run_experiment
from spacepose.tools.experiments import robustness as rb
from spacepose.tools.experiments.robustness_cells import select_cells

GRID = {"scenario": ["lab"], "noise_scale": [0.0], "method": ["gicp"], "seed": [0]}


def _not_called(*args: object, **kwargs: object) -> None:
    raise AssertionError("the work started before the inputs were checked")


def _cli_error(capsys: pytest.CaptureFixture[str]) -> str:
    """The CLI's stderr, checked to be one ``error:`` line without a traceback."""
    err = capsys.readouterr().err.strip()
    assert err.count("\n") == 0 and err.startswith("error: "), err
    return err


@pytest.fixture
def no_runs(monkeypatch: pytest.MonkeyPatch) -> None:
    """Make any robustness run (or the warm-up before them) fail the test."""
    monkeypatch.setattr(rb, "run_cells", _not_called)
    monkeypatch.setattr(rb, "warm_up", _not_called)
    monkeypatch.setattr(rb, "simulate", _not_called)


# ------------------------------------------------------------------ experiment robustness


@pytest.mark.parametrize(
    ("cells", "names"),
    [
        ("target=moon", ("unknown target 'moon'", "lab, hubble, panels")),
        ("motion=spin", ("unknown motion 'spin'",)),
        ("motion=tumbling-1000", ("tumbling-1000", "(0, 90]")),
        ("clutter=forest", ("unknown clutter 'forest'",)),
        ("range=-1", ("range -1 ",)),
        ("range=0", ("range 0 ",)),
        ("noise=-1", ("noise -1 ",)),
        ("range=1e9", ("range 1e+09 m", "flash-lidar", "200 m")),
        ("range=0.1", ("range 0.1 m", "tof")),
        ("range=1.2,range=3", ("axis range is named twice",)),
        (",", ("names no cells",)),
    ],
)
def test_bad_cells_fail_before_any_run(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], no_runs: None, cells: str, names: tuple
) -> None:
    with pytest.raises(ConfigError) as info:
        run_experiment("robustness", tmp_path / "a", ExperimentOptions(quick=True, cells=cells))
    message = str(info.value)
    assert message.startswith("--cells") and "\n" not in message
    assert all(name in message for name in names), message
    args = ["experiment", "robustness", "--quick", "--cells", cells, "--out", str(tmp_path / "b")]
    assert main(args) == 1
    err = _cli_error(capsys)
    assert "--cells" in err and names[0] in err
    # Refused before any run: no empty output folders left behind.
    assert not (tmp_path / "a").exists() and not (tmp_path / "b").exists()


def test_bad_values_in_a_cells_file_name_the_file(tmp_path: Path, no_runs: None) -> None:
    cells = tmp_path / "cells.yaml"
    cells.write_text(yaml.safe_dump({"target": ["lab"], "noise": [1.0, -2.0]}))
    with pytest.raises(ConfigError, match=r"cells\.yaml: noise -2 ") as info:
        run_experiment("robustness", tmp_path, ExperimentOptions(cells=str(cells)))
    assert "\n" not in str(info.value)


def test_an_empty_cells_file_is_not_the_whole_grid(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], no_runs: None
) -> None:
    cells = tmp_path / "empty.yaml"
    cells.write_text("")
    with pytest.raises(ConfigError, match=r"empty\.yaml: holds no cells"):
        select_cells(str(cells), quick=True, frames=None)
    args = ["experiment", "robustness", "--cells", str(cells), "--out", str(tmp_path)]
    assert main(args) == 1
    assert "empty.yaml: holds no cells" in _cli_error(capsys)


def test_good_cells_still_pass_the_check() -> None:
    runs, _ = select_cells("range=0.3+6+7+200,motion=tumbling-90", quick=True, frames=None)
    assert {r.range for r in runs} == {0.3, 6.0, 7.0, 200.0}
    assert len(select_cells(None, quick=False, frames=None)[0]) == 1500


@pytest.mark.parametrize(
    ("option", "value", "user"),
    [
        ("--cells", "foo=1", "robustness"),
        ("--tracker", "bad.yaml", "robustness"),
        ("--targets", "random:3", "fusion"),
    ],
)
def test_options_an_experiment_ignores_are_refused(
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
    option: str,
    value: str,
    user: str,
) -> None:
    experiments.available()
    monkeypatch.setitem(experiments._REGISTRY, "li-l1", _not_called)
    args = ["experiment", "li-l1", "--quick", option, value, "--out", str(tmp_path)]
    assert main(args) == 1
    err = _cli_error(capsys)
    assert f"{option}: experiment 'li-l1' does not use it (only {user} does)" in err
    # Not even the experiment's folder is made.
    assert not (tmp_path / "li-l1").exists()


# ------------------------------------------------------------------ campaign


@pytest.mark.parametrize(
    ("axes", "names"),
    [
        ({"seed": [0, -1]}, ("seeds must be integers >= 0", "-1")),
        ({"max_correspondence_mm": [0.0]}, ("max_correspondence_mm", "> 0")),
        ({"perturbation_deg": [2.0, -5.0]}, ("perturbation_deg", ">= 0", "-5.0")),
        ({"perturbation_mm": ["far"]}, ("perturbation_mm", "numbers")),
    ],
)
def test_campaign_grid_values_fail_at_load(
    tmp_path: Path,
    capsys: pytest.CaptureFixture[str],
    monkeypatch: pytest.MonkeyPatch,
    axes: dict,
    names: tuple,
) -> None:
    config = tmp_path / "grid.yaml"
    config.write_text(yaml.safe_dump({"out": str(tmp_path / "out"), "grid": GRID | axes}))
    with pytest.raises(ConfigError) as info:
        load_campaign_config(config)
    message = str(info.value)
    assert "\n" not in message and "grid.yaml" in message
    assert all(name in message for name in names), message
    monkeypatch.setattr(cp, "run_campaign", _not_called)
    assert main(["campaign", str(config)]) == 1
    err = _cli_error(capsys)
    assert "grid.yaml" in err and names[0] in err


def test_tracking_campaign_frames_fail_at_load(tmp_path: Path) -> None:
    config = tmp_path / "track.yaml"
    grid = GRID | {"frames": [0, 3]}
    config.write_text(yaml.safe_dump({"case_kind": "tracking", "grid": grid}))
    with pytest.raises(ConfigError, match=r"track\.yaml: .*frames values must be integers >= 2"):
        load_campaign_config(config)


# ------------------------------------------------------------------ bench


def _under_a_file(tmp_path: Path) -> tuple[Path, str]:
    (tmp_path / "file").write_text("")
    return tmp_path / "file" / "b.json", "it is a regular file"


def _a_folder(tmp_path: Path) -> tuple[Path, str]:
    return tmp_path, "not a regular file"


def _in_proc(tmp_path: Path) -> tuple[Path, str]:
    return Path("/proc/1/b.json"), "/proc/1"


@pytest.mark.parametrize("where", [_under_a_file, _a_folder, _in_proc])
def test_bench_out_is_checked_before_the_benchmark(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch, where
) -> None:
    out, problem = where(tmp_path)
    monkeypatch.setattr(bench, "run_benchmark", _not_called)
    assert main(["bench", "--quick", "--repeats", "1", "--out", str(out)]) == 1
    err = _cli_error(capsys)
    assert str(out) in err and problem in err and "File exists" not in err


def test_write_bench_under_a_file_says_so(tmp_path: Path) -> None:
    out, problem = _under_a_file(tmp_path)
    with pytest.raises(InputError, match=problem):
        bench.write_bench({}, out)


def test_bench_out_must_be_named_json(tmp_path: Path, capsys, monkeypatch) -> None:
    """``--out run/truth.csv`` wrote the benchmark's JSON over a run's truth, without a word."""
    truth = tmp_path / "truth.csv"
    truth.write_text("t,rho_x\n0,1\n")
    monkeypatch.setattr(bench, "run_benchmark", _not_called)
    assert main(["bench", "--quick", "--repeats", "1", "--out", str(truth)]) == 1
    assert "the benchmark writes JSON: name its file .json, not truth.csv" in _cli_error(capsys)
    assert truth.read_text() == "t,rho_x\n0,1\n"
