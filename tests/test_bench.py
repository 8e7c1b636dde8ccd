"""``spacepose bench``: the JSON it writes, its primitives, the peers and every bad-input path.

Speeds are never asserted: only that every number is there, finite and consistent.
"""

from __future__ import annotations

import contextlib
import io
import json
import math
import re
import sys
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from spacepose.cli import main
from spacepose.core import se3
from spacepose.errors import ConfigError, InputError
from spacepose.tools.bench import (
    QUICK_SIZES,
    REGISTRATIONS,
    STAGES,
    BenchConfig,
    bench_config,
    run_benchmark,
    write_bench,
)
from spacepose.tools.bench_data import registration_error
from spacepose.tools.bench_scaling import SCALING_STAGES, fit_exponent
from spacepose.tools.bench_trials import summarize, time_interleaved

# A frame of 160×120 pixels (about 1.2k points) and small scaling sizes keep the run short.
TINY = {
    "frame_scale": 0.25,
    "scaling_sizes": [500, 1000, 2000],
    "warmup": 0,
    "tracking_warmup_frames": 3,
    "tracking_frames": 2,
    "full_resolutions": [[160, 120]],
    "stream_frames": 2,
}
RAW = ("raw_160x120",)


@pytest.fixture(scope="module")
def tiny_config(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("bench") / "tiny.json"
    path.write_text(json.dumps(TINY))
    return path


@pytest.fixture(scope="module")
def quick_run(tiny_config: Path) -> tuple[int, dict, str]:
    """One CLI run for the whole module: (exit code, the JSON, what it printed)."""
    out = tiny_config.parent / "BENCH.json"
    args = ["bench", "--quick", "--repeats", "2", "--config", str(tiny_config), "--out", str(out)]
    # Module scope has no capsys; rich prints to whatever sys.stdout is at the time.
    printed = io.StringIO()
    with contextlib.redirect_stdout(printed):
        code = main(args)

    def strict(name: str) -> None:
        raise ValueError(f"non-strict JSON constant {name}")

    return code, json.loads(out.read_text(), parse_constant=strict), printed.getvalue()


def _finite_positive(x: float) -> bool:
    return isinstance(x, float) and math.isfinite(x) and x > 0


# ------------------------------------------------------------------------- the whole run


def test_quick_run_has_every_stage_with_positive_times(quick_run: tuple[int, dict, str]) -> None:
    code, result, _ = quick_run
    assert code == 0
    assert list(result["stages"]) == [*STAGES, *RAW]
    for name, stage in result["stages"].items():
        assert stage["repeats"] == 2, name
        for key in ("median_ms", "min_ms", "max_ms"):
            assert _finite_positive(stage[key]), (name, key)
        assert stage["min_ms"] <= stage["median_ms"] <= stage["max_ms"], name
        assert stage["peer"] == {} and stage["ratio"] == {}, name  # no --peers
        assert stage["n_points"] > (0 if name != "ekf_step" else -1), name
    # 160×120 ToF pixels on the mock-up: about a thousand points.
    assert 500 < result["stages"]["icp"]["n_points"] < 2000
    # The raw frame is every pixel: the target and the wall behind it.
    assert result["stages"]["raw_160x120"]["n_points"] > 0.95 * 160 * 120


def test_quick_run_times_the_raw_frame_row(quick_run: tuple[int, dict, str]) -> None:
    raw = quick_run[1]["stages"]["raw_160x120"]
    assert raw["substages"]["status"] in ("ok", "degraded")
    assert raw["substages"]["median_ms"]["preprocess"] > 0
    # The quick run's two timed raw frames per call, after the two untimed ones.
    assert raw["substages"]["frames_per_call"] == 2
    assert _finite_positive(raw["first_frame_ms"]) and _finite_positive(raw["second_frame_ms"])
    stream = quick_run[1]["memory"]["tracker_stream"]
    assert (stream["width"], stream["height"], stream["frames"]) == (160, 120, 2)
    assert len(stream["points"]) == len(stream["status"]) == 2
    assert stream["status"][0] == "ok" and stream["status"][1] in ("ok", "degraded")
    assert 0 < stream["baseline_mb"] <= stream["peak_mb"]


@pytest.mark.parametrize("row", ["tracking_step", "tracking_second_frame"])
def test_quick_run_reports_the_tracker_substages(
    quick_run: tuple[int, dict, str], row: str
) -> None:
    stage = quick_run[1]["stages"][row]
    sub = stage["substages"]
    # Every timed frame of a model-free track is registered, not lost, so fine work is timed.
    assert sub["status"] in ("ok", "degraded")
    assert set(sub["statuses"]) <= {"ok", "degraded"}
    assert sum(sub["statuses"].values()) == 2 * sub["frames_per_call"]  # 2 repeats
    assert sub["frames_per_call"] == (TINY["tracking_frames"] if row == "tracking_step" else 1)
    assert sub["median_ms"]["preprocess"] > 0 and sub["median_ms"]["fine"] > 0
    # Preprocess, coarse, fine and the rest (health, bookkeeping) partition the total.
    assert set(sub["share"]) == {"preprocess", "coarse", "fine", "other"}
    assert sum(sub["share"].values()) == pytest.approx(1.0, abs=1e-9)
    assert sub["share"]["fine"] > sub["share"]["other"]
    # The row is the time per frame of a call; the tracker's own clock runs inside it.
    assert sub["mean_ms"]["total"] <= stage["max_ms"]


def test_quick_run_scores_registrations_against_truth(quick_run: tuple[int, dict, str]) -> None:
    accuracy = quick_run[1]["accuracy"]
    assert set(accuracy) == set(REGISTRATIONS)
    bound = accuracy["icp"]["crlb"]
    # The frame-to-frame bound at about 1 mm noise on ~1k points is sub-mm / sub-0.1°...
    assert 0.1 < bound["translation_mm"] < 5.0 and 0.005 < bound["rotation_deg"] < 0.5
    for stage in REGISTRATIONS:
        assert accuracy[stage]["crlb"] == bound
    # ...and fine registration lands well inside the identity's error (31 mm / 1°): a truth
    # taken the wrong way round would double that instead.
    for stage in ("icp", "gicp"):
        assert accuracy[stage]["ours"]["translation_mm"] < 5.0, stage
        assert accuracy[stage]["ours"]["rotation_deg"] < 0.5, stage
    # The coarse stage is scored too (on ~1k-point frames it is no better than the identity,
    # 31 mm / 1°, so only its presence is checked).
    assert all(math.isfinite(v) for v in accuracy["ransac"]["ours"].values())


def test_quick_run_memory_scaling_environment(quick_run: tuple[int, dict, str]) -> None:
    result = quick_run[1]
    memory = result["memory"]
    assert set(memory["tracemalloc_peak_mb"]) == {*STAGES, *RAW}
    assert memory["pipeline_peak_mb"] == max(memory["tracemalloc_peak_mb"].values())
    assert memory["pipeline_peak_mb"] > 0 and memory["max_rss_mb"] > memory["pipeline_peak_mb"]
    scaling = result["scaling"]
    assert scaling["sizes"] == TINY["scaling_sizes"]
    assert set(scaling["stages"]) == set(SCALING_STAGES)
    for stage, series in scaling["stages"].items():
        ours = series["ours"]
        assert all(_finite_positive(t) for t in ours["median_ms"]), stage
        assert ours["exponent"] == pytest.approx(fit_exponent(scaling["sizes"], ours["median_ms"]))
    # ICP and GICP report their step counts, and the exponent of the time per step.
    for stage in ("icp", "gicp"):
        ours = scaling["stages"][stage]["ours"]
        steps = ours["iterations"]
        assert len(steps) == 3 and all(isinstance(n, int) and n >= 1 for n in steps), stage
        per_step = np.array(ours["median_ms"]) / np.array(steps)
        assert ours["exponent_per_iteration"] == pytest.approx(
            fit_exponent(scaling["sizes"], list(per_step))
        )
    assert "iterations" not in scaling["stages"]["normals"]["ours"]
    # Denser subsets get a proportionally smaller FPFH radius (same neighbours per point).
    r = np.array(scaling["fpfh_radius_m"])
    assert r * np.sqrt(scaling["sizes"]) == pytest.approx(np.full(3, r[0] * np.sqrt(500)))
    env = result["environment"]
    assert env["cpu_count"] >= 1 and env["threads"]["resolved"] == env["cpu_count"]
    assert env["numpy"] == np.__version__
    assert result["config"]["frame_scale"] == 0.25 and result["config"]["repeats"] == 2


def test_quick_run_prints_tables(quick_run: tuple[int, dict, str]) -> None:
    out = quick_run[2]
    for name in (*STAGES, *RAW):
        assert name in out
    assert "tracker on 2 raw 160x120 frames: peak RSS" in out
    assert "CRLB" in out
    assert "scaling gicp: t ~ N^b" in out
    steps = r"\(ours: \d+/\d+/\d+ steps, per step b = -?\d\.\d\d\)"
    assert re.search(r"scaling icp: t ~ N\^b with b = ours -?\d\.\d\d.* " + steps, out)
    assert "wrote " in out and "BENCH.json" in out


# ------------------------------------------------------------------------- primitives


def test_time_interleaved_alternates_contenders_and_leaves_setup_untimed() -> None:
    events: list[str] = []

    def trial(name: str) -> Callable[[], Callable[[], str]]:
        def setup() -> Callable[[], str]:
            events.append(f"setup {name}")

            def call() -> str:
                events.append(f"call {name}")
                return name

            return call

        return setup

    timings = time_interleaved({"a": trial("a"), "b": trial("b")}, repeats=2, warmup=1)
    round_ = ["setup a", "call a", "setup b", "call b"]
    assert events == round_ * 3  # one warm-up round, two timed rounds
    assert [len(t.times_ms) for t in timings.values()] == [2, 2]
    assert timings["a"].outputs == ["a", "a"] and timings["b"].last == "b"


def test_summarize_and_exponent_closed_form() -> None:
    assert summarize([3.0, 1.0, 2.0]) == {
        "median_ms": 2.0,
        "min_ms": 1.0,
        "max_ms": 3.0,
        "repeats": 3,
    }
    sizes = [5000, 10000, 20000, 40000]
    assert fit_exponent(sizes, [2e-3 * n**1.5 for n in sizes]) == pytest.approx(1.5, abs=1e-12)
    assert fit_exponent(sizes, [7.0 * n * np.log(n) for n in sizes]) == pytest.approx(
        1.0 + 1.0 / np.log(np.sqrt(5000 * 40000)), abs=0.01
    )


def test_registration_error_closed_form() -> None:
    T_gt = se3.exp([0.3, -0.2, 0.1, 0.5, 0.2, 1.2])
    rotated = se3.exp([0.0, 0.0, np.radians(0.25), 0.0, 0.0, 0.0]) @ T_gt
    assert registration_error(rotated, T_gt) == pytest.approx(
        {"translation_mm": 0.0, "rotation_deg": 0.25}, abs=1e-9
    )
    shifted = se3.exp([0.0, 0.0, 0.0, 1e-3, 2e-3, -2e-3]) @ T_gt
    assert registration_error(shifted, T_gt) == pytest.approx(
        {"translation_mm": 3.0, "rotation_deg": 0.0}, abs=1e-9
    )


def test_bench_config_file_overrides_only_what_it_sets(tmp_path: Path) -> None:
    path = tmp_path / "b.yaml"
    path.write_text("warmup: 0\nnormals: {k: 12}\n")
    cfg = bench_config(quick=True, path=path)
    assert cfg.warmup == 0 and cfg.normals.k == 12
    assert cfg.frame_scale == 0.5 and cfg.scaling_sizes == QUICK_SIZES  # quick defaults kept
    assert bench_config(quick=False) == BenchConfig()


def test_write_bench_strict_json(tmp_path: Path) -> None:
    path = write_bench({"a": [1.0, float("inf")], "b": {"c": float("nan")}}, tmp_path / "x.json")
    assert json.loads(path.read_text()) == {"a": [1.0, None], "b": {"c": None}}


# ------------------------------------------------------------------------- bad input


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["--repeats", "0"], "repeats must be at least 1"),
        (["--workers", "0"], "workers must be -1"),
    ],
)
def test_cli_rejects_bad_numbers(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], args: list[str], message: str
) -> None:
    assert main(["bench", "--quick", *args, "--out", str(tmp_path / "b.json")]) == 1
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err
    assert not (tmp_path / "b.json").exists()


@pytest.mark.parametrize(
    ("text", "names"),
    [
        ("frame_scale: -1\nspeed: 3\n", ("frame_scale", "speed")),
        ("scaling_sizes: [5000]\n", ("scaling_sizes", "at least 2")),
        ("scaling_sizes: [50, 5000]\n", ("scaling_sizes.0", "100")),
    ],
)
def test_cli_rejects_bad_config_file(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], text: str, names: tuple[str, ...]
) -> None:
    cfg = tmp_path / "bad.yaml"
    cfg.write_text(text)
    assert main(["bench", "--config", str(cfg), "--out", str(tmp_path / "b.json")]) == 1
    err = capsys.readouterr().err
    assert "bad.yaml" in err and all(name in err for name in names)


def test_peers_missing_is_one_clear_error(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setitem(sys.modules, "open3d", None)  # import open3d now raises ImportError
    with pytest.raises(ConfigError, match="open3d"):
        run_benchmark(quick=True, peers=True, repeats=1)
    assert main(["bench", "--quick", "--peers", "--out", str(tmp_path / "b.json")]) == 1
    assert "install open3d and small_gicp" in capsys.readouterr().err


def test_write_bench_unwritable_path(tmp_path: Path) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("")
    with pytest.raises(InputError, match="it is a regular file"):
        write_bench({}, blocker / "b.json")


# ------------------------------------------------------------------------- peers


@pytest.mark.peers
def test_peers_interleaved_with_ratios_and_same_answers() -> None:
    pytest.importorskip("open3d")
    pytest.importorskip("small_gicp")
    result = run_benchmark(quick=True, peers=True, repeats=1, config=BenchConfig(**TINY))
    expected = {
        "voxel": {"open3d"},
        "normals": {"open3d", "small_gicp"},
        "fpfh": {"open3d"},
        "ransac": {"open3d"},
        "icp": {"open3d"},
        "gicp": {"open3d", "small_gicp"},
        "tracking_step": {"open3d"},
        "tracking_second_frame": {"open3d"},
        "raw_160x120": {"open3d"},
    }
    for name, stage in result["stages"].items():
        assert set(stage["peer"]) == expected.get(name, set()), name
        for peer, entry in stage["peer"].items():
            assert _finite_positive(entry["median_ms"])
            assert stage["ratio"][peer] == pytest.approx(entry["median_ms"] / stage["median_ms"])
    threads = result["environment"]["threads"]
    assert threads["open3d_set_max_threads"] == threads["small_gicp_num_threads"] > 0
    # The compiled searches ran, on a thread pool that takes concurrent callers.
    assert threads["numba_threading_layer"] in ("omp", "tbb")
    acc = result["accuracy"]
    # Same inputs, same gate and criteria: Open3D's point-to-plane ICP and small_gicp's GICP
    # land where ours does (to far below the registration error itself).
    for stage, peer in (("icp", "open3d"), ("gicp", "small_gicp")):
        ours, theirs = acc[stage]["ours"], acc[stage][peer]
        assert theirs["translation_mm"] == pytest.approx(ours["translation_mm"], abs=0.02)
        assert theirs["rotation_deg"] == pytest.approx(ours["rotation_deg"], abs=2e-3)
    assert set(result["scaling"]["stages"]["gicp"]) == {"ours", "open3d", "small_gicp"}
