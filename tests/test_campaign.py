"""Monte Carlo campaigns on Dask: grid, atomic parts, kill/resume, summary, CLI, bad configs."""

from __future__ import annotations

import json
import logging
import os
import signal
import subprocess
import sys
import time
import uuid
from collections import Counter
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
import pytest
import yaml
from scipy.spatial.transform import Rotation

import spacepose
from spacepose.cli import main
from spacepose.errors import ConfigError, FileFormatError, RegistrationError
from spacepose.tools import campaign as cp
from spacepose.tools import campaign_cases as cc
from spacepose.tools import campaign_spec as cs

TESTS_DIR = Path(__file__).resolve().parent
MARKERS_ENV = "SPACEPOSE_TEST_CAMPAIGN_MARKERS"
DELAY_ENV = "SPACEPOSE_TEST_CAMPAIGN_DELAY"

# 2 scenarios x 3 noise levels x 2 methods x 2 seeds = 24 cases.
GRID_24 = {
    "scenario": ["s1", "s2"],
    "noise_scale": [0.0, 0.5, 1.0],
    "method": ["a", "b"],
    "seed": [0, 1],
}


@cc.case_runner("cheap", choices={"method": ("a", "b", "fail", "bad")}, extra_axes=("frames",))
def cheap_runner(params: dict) -> dict:
    """Closed-form metrics of the parameters; leaves one marker file per computation."""
    if params["method"] == "fail":
        raise RegistrationError("no correspondence within max distance")
    if params["method"] == "bad":
        return {"vector": [1.0, 2.0]}
    time.sleep(float(os.environ.get(DELAY_ENV, "0")))
    draw = np.random.default_rng(params["seed"]).normal()
    metrics = {
        "seed_value": float(params["seed"]),
        "scaled": params["noise_scale"]
        * (1 + params["seed"])
        * (2 if params["method"] == "b" else 1),
        "draw": draw,
        "iterations": 10 + params["seed"],
        "converged": params["seed"] % 2 == 0,
    }
    markers = os.environ.get(MARKERS_ENV)
    if markers:
        Path(markers, f"{cs.case_id(params)}.{uuid.uuid4().hex}").touch()
    return metrics


@pytest.fixture(scope="module")
def markers(tmp_path_factory) -> Path:
    """Folder where the cheap runner leaves one file per computation in the shared cluster."""
    return tmp_path_factory.mktemp("markers")


@pytest.fixture(scope="module")
def scheduler(markers):
    """One shared 2-process cluster, reached through --scheduler (saves cluster start-ups)."""
    from dask.distributed import LocalCluster

    with pytest.MonkeyPatch.context() as mp:
        mp.setenv(MARKERS_ENV, str(markers))  # inherited by the workers spawned now only
        cluster = LocalCluster(
            n_workers=2,
            threads_per_worker=1,
            processes=True,
            dashboard_address=":0",
            scheduler_kwargs={"dashboard": False},
            silence_logs=logging.ERROR,
        )
    with cluster:
        yield cluster.scheduler_address


def _write_config(path: Path, **fields) -> Path:
    data = {"name": "test", "case_kind": "cheap", "grid": GRID_24, "out": "unused"}
    data.update(fields)
    path.write_text(yaml.safe_dump(data))
    return path


def _rows_without_timing(path: Path) -> list[dict]:
    return pq.read_table(path).drop(["time_s"]).to_pylist()


# ------------------------------------------------------------------------------------------------
# grid and case ids
# ------------------------------------------------------------------------------------------------


def test_case_ids_do_not_depend_on_grid_order():
    cases = cs.expand_grid(GRID_24)
    assert len(cases) == 24
    assert len({c.case_id for c in cases}) == 24
    assert [c.case_id for c in cases] == sorted(c.case_id for c in cases)
    shuffled = {k: list(reversed(v)) for k, v in reversed(GRID_24.items())}
    assert {(c.case_id, tuple(sorted(c.params.items()))) for c in cs.expand_grid(shuffled)} == {
        (c.case_id, tuple(sorted(c.params.items()))) for c in cases
    }
    params = {"seed": 3, "method": "a", "noise_scale": 0.5, "scenario": "s1"}
    assert cs.case_id(params) == cs.case_id(dict(reversed(params.items())))
    assert cs.case_id(params) != cs.case_id({**params, "seed": 4})
    assert len(cs.case_id(params)) == 12


def test_mixed_int_float_axis_becomes_float():
    config = cs.CampaignConfig(
        case_kind="cheap", grid={**GRID_24, "noise_scale": [0, 0.5, 2]}, out="x"
    )
    assert config.grid["noise_scale"] == [0.0, 0.5, 2.0]
    assert all(isinstance(v, float) for v in config.grid["noise_scale"])
    ints = cs.CampaignConfig(case_kind="cheap", grid={**GRID_24, "noise_scale": [0, 1]}, out="x")
    assert [type(v) for v in ints.grid["noise_scale"]] == [float, float]
    assert ints.grid["seed"] == [0, 1] and all(type(v) is int for v in ints.grid["seed"])


# ------------------------------------------------------------------------------------------------
# kill and resume
# ------------------------------------------------------------------------------------------------


def test_killed_campaign_resumes_without_loss_or_duplicates(tmp_path, capsys, markers, scheduler):
    config = _write_config(tmp_path / "c.yaml")
    out_a, out_b = tmp_path / "a", tmp_path / "b"
    all_ids = {c.case_id for c in cs.expand_grid(GRID_24)}
    assert not any(m.name.split(".")[0] in all_ids for m in markers.iterdir())
    args = ["campaign", str(config), "--out", str(out_a), "--workers", "2"]
    script = (
        f"import sys; sys.path.insert(0, {str(TESTS_DIR)!r}); import test_campaign; "
        f"from spacepose.cli import main; sys.exit(main({args!r}))"
    )
    env = {**os.environ, MARKERS_ENV: str(markers), DELAY_ENV: "0.25"}
    with open(tmp_path / "stderr.txt", "wb") as err:
        proc = subprocess.Popen(
            [sys.executable, "-c", script],
            env=env,
            start_new_session=True,  # its own process group: the kill takes the workers too
            stdout=subprocess.DEVNULL,
            stderr=err,
        )
        deadline = time.monotonic() + 60
        parts = out_a / "parts"
        while time.monotonic() < deadline and proc.poll() is None:
            if parts.is_dir() and len(list(parts.glob("*.json"))) >= 4:
                break
            time.sleep(0.05)
        assert proc.poll() is None, (tmp_path / "stderr.txt").read_text()
        os.killpg(proc.pid, signal.SIGKILL)
        proc.wait()
    time.sleep(0.5)  # let any orphan finish writing, which would show up as an extra marker
    finished = {p.stem for p in parts.glob("*.json")}
    before = {m.name for m in markers.iterdir()}
    assert 4 <= len(finished) < 24
    assert not (out_a / "results.parquet").exists()
    first_run = Counter(name.split(".")[0] for name in before)
    assert all(first_run[cid] == 1 for cid in finished)

    # Started again (on the shared cluster, whose workers leave markers in the same folder).
    assert main([*args[:-2], "--scheduler", scheduler]) == 0  # its workers, not --workers
    resumed = Counter(m.name.split(".")[0] for m in markers.iterdir() if m.name not in before)
    assert set(resumed) == all_ids - finished
    assert set(resumed.values()) == {1}
    assert len(list(parts.glob("*.json"))) == 24
    assert not list(parts.glob(".*"))
    output = capsys.readouterr().out
    assert f"24 cases ({24 - len(finished)} computed, {len(finished)} already done)" in output

    assert main(["campaign", str(config), "--out", str(out_b), "--scheduler", scheduler]) == 0
    rows_a = _rows_without_timing(out_a / "results.parquet")
    rows_b = _rows_without_timing(out_b / "results.parquet")
    assert len(rows_a) == 24
    assert rows_a == rows_b
    assert [r["case_id"] for r in rows_a] == sorted(all_ids)
    for row in rows_a:
        params = {k: row[k] for k in GRID_24}
        assert row["case_id"] == cs.case_id(params)
        assert row["seed_value"] == row["seed"]
        assert row["draw"] == np.random.default_rng(row["seed"]).normal()


# ------------------------------------------------------------------------------------------------
# results, summary, plots, resume with a changed grid
# ------------------------------------------------------------------------------------------------


def test_results_summary_and_grid_extension(tmp_path, scheduler):
    grid = {
        "scenario": ["s"],
        "noise_scale": [0.0, 1.0],
        "method": ["a", "fail"],
        "seed": [0, 1, 2, 3],
    }
    config = cs.CampaignConfig(name="stats", case_kind="cheap", grid=grid, out=tmp_path / "run")
    result = cp.run_campaign(config, scheduler=scheduler, progress=False)
    assert (result.n_computed, result.n_skipped) == (16, 0)

    table = pq.read_table(tmp_path / "run" / "results.parquet")
    assert table.num_rows == 16
    assert table.column_names[:4] == ["scenario", "noise_scale", "method", "seed"]
    assert table.column_names[-3:] == ["error", "time_s", "case_id"]
    assert str(table.schema.field("iterations").type) == "int64"
    assert str(table.schema.field("converged").type) == "bool"
    meta = table.schema.metadata
    assert json.loads(meta[b"spacepose.campaign"])["grid"] == grid
    assert meta[b"spacepose.version"].decode() == spacepose.__version__
    record = json.loads((tmp_path / "run" / "campaign.json").read_text())
    assert record["config"]["name"] == "stats"
    assert record["spacepose_version"] == spacepose.__version__
    for row in table.to_pylist():
        if row["method"] == "fail":
            assert row["error"] == "RegistrationError: no correspondence within max distance"
            assert row["seed_value"] is None
        else:
            assert row["error"] is None
            assert row["iterations"] == 10 + row["seed"]

    summary = json.loads((tmp_path / "run" / "summary.json").read_text())
    assert summary == result.summary
    cell = {(s["noise_scale"], s["method"], s["metric"]): s for s in summary}
    seeds = np.arange(4.0)
    s = cell[(1.0, "a", "seed_value")]
    assert (s["n"], s["n_failed"]) == (4, 0)
    assert s["mean"] == pytest.approx(1.5)
    assert s["std"] == pytest.approx(np.sqrt(5 / 3))
    assert s["median"] == pytest.approx(1.5)
    assert s["p95"] == pytest.approx(2.85)  # 3 - 0.05 * (3 - 2), linear interpolation
    scaled = cell[(1.0, "a", "scaled")]
    assert scaled["mean"] == pytest.approx(np.mean(1 + seeds))
    assert cell[(0.0, "a", "scaled")]["std"] == 0.0
    assert cell[(1.0, "a", "converged")]["mean"] == pytest.approx(0.5)
    failed = cell[(1.0, "fail", "seed_value")]
    assert (failed["n"], failed["n_failed"], failed["mean"], failed["std"]) == (0, 4, None, None)
    for metric in ("seed_value", "scaled", "draw", "iterations", "converged", "time_s"):
        assert (tmp_path / "run" / f"{metric}.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"

    # Same cases in another order: nothing recomputed, same table.
    shuffled = {k: list(reversed(v)) for k, v in reversed(grid.items())}
    again = cp.run_campaign(config.model_copy(update={"grid": shuffled}), progress=False)
    assert (again.n_computed, again.n_skipped) == (0, 16)
    assert again.table.drop(["time_s"]).to_pylist() == table.drop(["time_s"]).to_pylist()

    # One more seed: only its 4 cases are computed, nothing is lost.
    extended = config.model_copy(update={"grid": {**grid, "seed": [0, 1, 2, 3, 4]}})
    more = cp.run_campaign(extended, scheduler=scheduler, progress=False)
    assert (more.n_computed, more.n_skipped) == (4, 16)
    assert more.table.num_rows == 20
    old_rows = {r["case_id"]: r for r in table.drop(["time_s"]).to_pylist()}
    new_rows = {r["case_id"]: r for r in more.table.drop(["time_s"]).to_pylist()}
    assert all(new_rows[cid] == row for cid, row in old_rows.items())


def test_same_seed_same_metrics_other_seed_different():
    params = {"scenario": "s", "noise_scale": 0.5, "method": "a", "seed": 7}
    first = cp.execute_case(cheap_runner, params)
    second = cp.execute_case(cheap_runner, dict(reversed(params.items())))
    other = cp.execute_case(cheap_runner, {**params, "seed": 8})
    assert first["metrics"] == second["metrics"]
    assert first["case_id"] == second["case_id"] != other["case_id"]
    assert first["metrics"]["draw"] != other["metrics"]["draw"]


def test_a_case_no_scenario_allows_is_recorded_not_fatal():
    """A grid crossing the orbit scenario with the ToF camera raised ConfigError ("the sensor
    sees nothing") in its worker, which ended the whole campaign with a Dask traceback and no
    results table, on every resume too. It is now that case's error, as any other failure."""

    def impossible(params: dict) -> dict:
        raise ConfigError("the sensor sees nothing: target 25 m away, sensor ranges 0.3-10 m")

    params = {"scenario": "orbit", "noise_scale": 1.0, "method": "a", "seed": 0}
    record = cp.execute_case(impossible, params)
    assert record["error"] == (
        "ConfigError: the sensor sees nothing: target 25 m away, sensor ranges 0.3-10 m"
    )
    assert record["metrics"] == {} and record["case_id"] == cs.case_id(params)


# ------------------------------------------------------------------------------------------------
# bad input
# ------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("fields", "expected"),
    [
        ({"colour": "red"}, "colour"),
        ({"grid": {**GRID_24, "seed": []}}, "axis 'seed' is empty"),
        ({"grid": {k: v for k, v in GRID_24.items() if k != "method"}}, "missing axis method"),
        ({"case_kind": "nope"}, "unknown case_kind 'nope'"),
        ({"grid": {**GRID_24, "method": ["a", "zzz"]}}, "unknown method 'zzz'"),
        ({"grid": {**GRID_24, "seed": [0, 0]}}, "duplicate"),
        ({"grid": {**GRID_24, "seed": [0.5]}}, "seeds must be integers"),
        ({"grid": {**GRID_24, "noise_scale": [-1.0]}}, "noise_scale values must be numbers >= 0"),
        ({"grid": {**GRID_24, "method": ["a", 1]}}, "mixes value types"),
        ({"grid": {**GRID_24, "speed": [1, 2]}}, "axis 'speed' is not used by case_kind"),
        ({"grid": {**GRID_24, "case_id": [1]}}, "axis name 'case_id'"),
        ({"workers": 0}, "workers"),
        (
            {
                "case_kind": "registration",
                "grid": {**GRID_24, "scenario": ["lab"], "method": ["gicp"], "sensor": ["sonar"]},
            },
            "unknown sensor 'sonar'",
        ),
        (
            {
                "case_kind": "registration",
                "grid": {
                    **GRID_24,
                    "scenario": ["lab"],
                    "method": ["gicp"],
                    "perturbation_deg": [1000],
                },
            },
            "perturbation_deg values must be numbers >= 0 and <= 180, got [1000]",
        ),
    ],
)
def test_bad_config_is_a_config_error_naming_the_file(tmp_path, capsys, fields, expected):
    path = _write_config(tmp_path / "bad.yaml", **fields)
    with pytest.raises(ConfigError, match=r"bad\.yaml") as info:
        cs.load_campaign_config(path)
    assert expected in str(info.value)
    assert main(["campaign", str(path), "--out", str(tmp_path / "out")]) == 1
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1
    assert "bad.yaml" in err and expected in err
    assert not (tmp_path / "out").exists()


def test_cli_workers_option_must_be_positive(tmp_path, capsys):
    path = _write_config(tmp_path / "c.yaml")
    assert main(["campaign", str(path), "--workers", "0", "--out", str(tmp_path / "o")]) == 1
    assert "workers must be >= 1" in capsys.readouterr().err


def test_incompatible_or_foreign_folder_is_refused(tmp_path):
    config = cs.CampaignConfig(name="one", case_kind="cheap", grid=GRID_24, out=tmp_path / "run")
    cp.prepare_out_dir(config)
    # Worker count and grid values may change on resume; name, case_kind and axes may not.
    cp.prepare_out_dir(config.model_copy(update={"workers": 1}))
    for update, what in (
        ({"name": "two"}, "name='one'"),
        ({"grid": {**GRID_24, "frames": [3]}}, "axes"),
    ):
        with pytest.raises(ConfigError, match=r"campaign\.json") as info:
            cp.prepare_out_dir(config.model_copy(update=update))
        assert what in str(info.value)
    foreign = tmp_path / "foreign"
    foreign.mkdir()
    (foreign / "notes.txt").write_text("mine")
    with pytest.raises(ConfigError, match="not a campaign folder"):
        cp.prepare_out_dir(config.model_copy(update={"out": foreign}))
    with pytest.raises(ConfigError, match="must be a folder"):
        cp.prepare_out_dir(config.model_copy(update={"out": foreign / "notes.txt"}))
    # Hand-edited records: an AttributeError or RecursionError traceback before.
    for text in ("{broken", '{"config": [1]}', '{"config": {"grid": [1]}}', "[" * 50_000):
        (tmp_path / "run" / "campaign.json").write_text(text)
        with pytest.raises(ConfigError, match="unreadable campaign record"):
            cp.prepare_out_dir(config)


def test_damaged_part_is_a_file_format_error(tmp_path):
    config = cs.CampaignConfig(case_kind="cheap", grid=GRID_24, out=tmp_path / "run")
    out = cp.prepare_out_dir(config)
    case = cs.expand_grid(GRID_24)[0]
    path = cp.write_part(out, cp.execute_case(cheap_runner, case.params))
    assert list(cp.read_parts(out)) == [case.case_id]
    leftover = out / "parts" / ".abc.json.123.tmp"
    leftover.write_text("half")
    cp.prepare_out_dir(config)  # a killed run's temporary file is removed on resume
    assert not leftover.exists()
    record = json.loads(path.read_text())
    record["params"]["seed"] = 99
    path.write_text(json.dumps(record))
    with pytest.raises(FileFormatError, match=path.name):
        cp.read_parts(out)
    path.write_text('{"case_id": ')
    # A part cut short says how to get past it, as a damaged one does.
    with pytest.raises(
        FileFormatError, match=r"unreadable campaign part: .*; delete it to run its case again"
    ):
        cp.read_parts(out)


def test_runner_returning_bad_metrics_is_a_type_error():
    params = {"scenario": "s", "noise_scale": 0.0, "method": "bad", "seed": 0}
    with pytest.raises(TypeError, match="metric 'vector' is a list"):
        cp.execute_case(cheap_runner, params)

    def clashing(p: dict) -> dict:
        return {"seed": 1.0}

    with pytest.raises(TypeError, match="clashes"):
        cp.execute_case(clashing, params)
    with pytest.raises(TypeError, match="not a dict"):
        cp.execute_case(lambda p: 3.0, params)


def test_unreachable_scheduler_is_a_config_error(tmp_path):
    config = cs.CampaignConfig(
        case_kind="cheap", grid=GRID_24, out=tmp_path / "run", connect_timeout_s=0.5
    )
    with pytest.raises(
        ConfigError, match=r"cannot connect to Dask scheduler 'tcp://127\.0\.0\.1:1'"
    ):
        cp.run_campaign(config, scheduler="tcp://127.0.0.1:1", progress=False)


# ------------------------------------------------------------------------------------------------
# the registration case (simulator + ICP/GICP)
# ------------------------------------------------------------------------------------------------


def test_seeded_perturbation_has_the_requested_size():
    center = np.array([0.1, -0.2, 1.2])
    T = cc.seeded_perturbation(center, 3.0, 0.02, seed=5)
    assert np.degrees(Rotation.from_matrix(T[:3, :3]).magnitude()) == pytest.approx(3.0)
    moved = T[:3, :3] @ center + T[:3, 3]
    assert np.linalg.norm(moved - center) == pytest.approx(0.02)
    assert np.array_equal(T, cc.seeded_perturbation(center, 3.0, 0.02, seed=5))
    assert not np.allclose(T, cc.seeded_perturbation(center, 3.0, 0.02, seed=6))


LAB_CASE = {"scenario": "lab", "noise_scale": 1.0, "method": "point_to_plane", "seed": 0}


def _without_timing(metrics: dict) -> dict:
    return {k: v for k, v in metrics.items() if not k.startswith("time")}


def test_registration_case_same_seed_same_metrics_other_seed_different():
    first = cc.registration_case(dict(LAB_CASE))
    again = cc.registration_case(dict(reversed(LAB_CASE.items())))
    other = cc.registration_case({**LAB_CASE, "seed": 1})
    assert _without_timing(first) == _without_timing(again)
    for key in ("rotation_error_deg", "translation_error_mm", "inlier_rmse_mm", "n_source"):
        assert first[key] != other[key]
    # ToF noise at 1.2 m is about 1.2 mm along the ray: the residual RMS is of that size.
    assert 1.0 < first["inlier_rmse_mm"] < 2.5


def test_registration_case_noise_free_recovers_the_true_motion():
    # From a 2 deg / 10 mm start, noise-free frames: any slip in composing the true frame-pair
    # transform or the perturbation would leave an error of the order of the perturbation.
    m = cc.registration_case({**LAB_CASE, "noise_scale": 0.0})
    assert m["converged"]
    assert m["fitness"] == 1.0
    assert m["rotation_error_deg"] < 0.01
    assert m["translation_error_mm"] < 0.05


def test_registration_case_orbit_frame_pair():
    # Flash LiDAR at 25 m: ~1000 points 8 cm apart, so no sub-mm truth, but GICP must undo the
    # 2 deg / 100 mm start (REGISTRATION_DEFAULTS) by more than a factor of 10.
    m = cc.registration_case({"scenario": "orbit", "noise_scale": 1.0, "method": "gicp", "seed": 0})
    assert 500 < m["n_source"] < 2000
    assert m["rotation_error_deg"] < 0.2
    assert m["translation_error_mm"] < 10.0


def test_registration_campaign_on_dask_matches_a_direct_call(tmp_path, scheduler):
    grid = {"scenario": ["lab"], "noise_scale": [1.0], "method": ["point_to_plane"], "seed": [0]}
    config = cs.CampaignConfig(name="reg", grid=grid, out=tmp_path / "reg")
    result = cp.run_campaign(config, scheduler=scheduler, progress=False)
    (row,) = result.table.to_pylist()
    direct = _without_timing(cc.registration_case(dict(LAB_CASE)))
    assert {k: row[k] for k in direct} == direct
    assert row["error"] is None
    assert (tmp_path / "reg" / "rotation_error_deg.png").exists()


def test_tracking_runner_scores_a_short_lab_run_against_truth() -> None:
    from spacepose.tools.campaign_cases import get_runner

    params = {"scenario": "lab", "noise_scale": 1.0, "method": "keyframe", "seed": 2, "frames": 5}
    metrics = get_runner("tracking").fn(params)
    assert metrics["n_ok"] + metrics["n_degraded"] + metrics["n_lost"] == 5
    assert metrics["n_lost"] == 0
    # Five frames of 10 mm / 1° steps: sub-millimetre, hundredths-of-a-degree tracking
    # (0.49 mm and 0.064° measured).
    assert 0.0 < metrics["x_mm"] < 1.5 and metrics["yaw_deg"] < 0.1
    assert 0.0 <= metrics["within_3sigma_share"] <= 1.0
    same = get_runner("tracking").fn(params)
    assert {k: v for k, v in same.items() if not k.startswith("time")} == {
        k: v for k, v in metrics.items() if not k.startswith("time")
    }


def test_a_campaign_whose_every_case_failed_says_so_and_exits_1(tmp_path, capsys, scheduler):
    """Its one case failed (a start 1e9 m off finds no correspondence), and the command
    printed "1 cases (1 computed, 0 already done)" with exit code 0: the failure sat in the
    table's error column alone."""
    config = tmp_path / "c.yaml"
    config.write_text(
        "name: huge\ncase_kind: registration\ngrid:\n  scenario: [lab]\n  noise_scale: [0.0]\n"
        "  method: [point_to_point]\n  seed: [0]\n  perturbation_mm: [1e12]\n"
    )
    args = ["campaign", str(config), "--out", str(tmp_path / "o"), "--scheduler", scheduler]
    assert main(args) == 1
    printed = capsys.readouterr()
    assert "1 cases (1 computed, 0 already done, 1 failed (why: the error column))" in " ".join(
        printed.out.split()
    )
    assert f"error: {config}: every case failed (the first: RegistrationError: " in printed.err


def test_a_grid_value_no_scalar_type_takes_is_said_in_one_line(tmp_path, capsys):
    """NaN listed pydantic's four union branches ("grid.noise_scale.0.bool: ...; .int: ...;
    .float: ...; .str: ..."), and so did a list in a list; a folder that cannot be made was
    "/proc/nope: No such file or directory"."""
    head = "name: t\ncase_kind: registration\ngrid:\n  scenario: [lab]\n"
    cases = (
        ("  noise_scale: [.nan]\n  seed: [0]\n", "noise_scale: nan is not a finite number"),
        ("  noise_scale: [1.0]\n  seed: [[0, 1]]\n", "seed: [0, 1] is no single value"),
    )
    path = tmp_path / "c.yaml"
    for axes, said in cases:
        path.write_text(head + "  method: [point_to_point]\n" + axes)
        assert main(["campaign", str(path), "--out", str(tmp_path / "o")]) == 1
        assert f"c.yaml: invalid campaign config: grid: {said}" in capsys.readouterr().err
    path.write_text(head + "  method: [point_to_point]\n  noise_scale: [1.0]\n  seed: [0]\n")
    assert main(["campaign", str(path), "--out", "/proc/nope/c"]) == 1
    assert "cannot create the campaign folder" in capsys.readouterr().err
