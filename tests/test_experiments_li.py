"""Experiments L1–L4 (tools/experiments/li.py, li_tracking.py): quick runs check the outputs and
the numbers the experiments exist to show; the slow tests are on the full 58-frame lab run."""

from __future__ import annotations

import json

import numpy as np
import pytest

from spacepose.core import se3
from spacepose.core.sim.scenarios import LabConfig, simulate_lab
from spacepose.tools.experiments import ExperimentOptions, available, run_experiment
from spacepose.tools.experiments.li import AXES, METHODS, PAPER_TABLE2
from spacepose.tools.experiments.li_tracking import (
    crlb_column,
    l3_summary,
    method_configs,
    run_methods,
)

QUICK = ExperimentOptions(seed=0, quick=True, workers=2)


def test_registered():
    assert {"li-l1", "li-l2", "li-l3", "li-l4"} <= set(available())


def test_l1_mls_makes_normals_consistent(tmp_path):
    table = run_experiment("li-l1", tmp_path, QUICK)
    assert (tmp_path / "li-l1.json").is_file() and (tmp_path / "li-l1.png").is_file()
    share = {k: v["mean"] for k, v in table["share_below_20deg"].items()}
    # Li Fig. 5: about 20 % of the raw frame's neighbour angles below 20°, 80 % after mpp-MLS.
    # The paper-like profile's raw frame is within 10 points of it (measured 20.3 % on 10
    # seeds); the clean profile is far cleaner (74 %).
    assert abs(share["tof-paper raw"] - 0.2) < 0.1
    assert share["tof-clean raw"] > 0.6
    for profile in ("tof-clean", "tof-paper"):
        assert share[f"{profile} mpp-MLS"] > share[f"{profile} raw"]
    assert share["tof-clean mpp-MLS"] > 0.8
    assert table["improvement_points"]["tof-paper"]["mean"] == pytest.approx(
        100 * (share["tof-paper mpp-MLS"] - share["tof-paper raw"])
    )
    assert sum(table["histogram_counts"]["tof-paper raw"]) > 0


def test_l2_writes_rows_per_noise_and_variant(tmp_path):
    table = run_experiment("li-l2", tmp_path, QUICK)
    assert len(table["rows"]) == 8  # quick: (3 σ + the paper-like profile) × (raw, mpp-MLS)
    assert "L / 10" in table["sigma_scaling"]
    low = [r for r in table["rows"] if r["sigma_paper"] == 0.01]
    # At the lowest noise the coarse registration lands within a few mm / degrees.
    assert all(r["failures"] == 0 for r in low)
    assert all(r["position_error_mm_median"] < 20 for r in low)  # measured 4 mm (quick)
    assert all(r["rotation_angle_error_deg_median"] < 5 for r in low)  # measured 2.6°
    # A pose more than 5° or 5 cm off is a failure, never an error beside "failures: 0".
    for r in table["rows"]:
        if r["rotation_angle_error_deg_mean"] is not None:
            assert r["rotation_angle_error_deg_mean"] <= 5.0 and r["position_error_mm_mean"] <= 50
        else:
            assert r["failures"] == r["trials"]
    assert {r["noise"] for r in table["rows"]} == {"gaussian", "tof-paper"}
    assert (tmp_path / "li-l2.png").is_file()


def test_l3_quick_table_layout(tmp_path):
    table = run_experiment("li-l3", tmp_path, QUICK)
    saved = json.loads((tmp_path / "li-l3.json").read_text())
    assert saved["seeds"] == [0, 1]  # quick: 2 seeds
    assert (
        set(saved["methods"])
        == set(METHODS)
        == {
            "point_to_point",
            "point_to_plane",
            "gicp",
            "jicp",
            "keyframe",
        }
    )
    assert set(saved["variants"]) == {"tof-clean", "tof-paper+mls"}
    clean = saved["variants"]["tof-clean"]
    assert clean["table"].keys() == set(AXES)
    assert set(clean["table"]["x_mm"]) == set(METHODS)
    assert set(clean["table"]["x_mm"]["jicp"]) == {"mean", "seed_std", "frame_std"}
    assert saved["paper"]["jicp"]["roll_deg"] == [0.019, 0.013]
    assert saved["paper"]["point_to_point"]["x_mm"] == [2.06, 1.50]
    assert all(v > 0 for v in clean["crlb_frame_to_frame"].values())
    for variant in saved["variants"]:
        assert (tmp_path / f"li-l3_{variant}.png").is_file()
        assert (tmp_path / f"li-l3_{variant}_health.png").is_file()
    # The keyframe graph keeps every frame of both seeds ok on the clean run, but the second,
    # which no velocity confirms yet, and the third, whose motion model is untested (degraded).
    assert table["frames"] == 5
    assert table["variants"]["tof-clean"]["status_counts"]["keyframe"] == {
        "ok": 6,
        "degraded": 4,
        "lost": 0,
    }


def test_l3_summary_is_over_seeds():
    """Mean and std over seeds of each run's mean error; the frame std is averaged."""
    runs = []
    for k in range(3):
        run = {}
        for n, m in enumerate(METHODS):
            mean = {a: float(k + n + 1) for a in AXES}
            std = {a: 0.5 * (k + 1) for a in AXES}
            run[m] = {
                "table": {"mean": mean, "std": std},
                "status": ["ok"] * 4,
                "time_ms": np.ones(4),
            }
        runs.append(run)
    summary = l3_summary(runs)
    cell = summary["table"]["y_mm"]["gicp"]  # means 3, 4, 5
    assert cell == pytest.approx({"mean": 4.0, "seed_std": np.std([3, 4, 5]), "frame_std": 1.0})
    # keyframe (means 5, 6, 7) against point_to_point (1, 2, 3): 1 − 6 / 2 on every axis.
    assert summary["reduction_vs"]["keyframe"]["point_to_point"] == pytest.approx(-2.0)
    assert summary["status_counts"]["jicp"] == {"ok": 12, "degraded": 0, "lost": 0}


def test_crlb_column_matches_the_simulator_bound():
    sim = simulate_lab(LabConfig(frames=3))
    col = crlb_column(sim)
    std = np.mean([sim.frame(k).crlb(frame_to_frame=True).std for k in (1, 2)], axis=0)
    assert col["roll_deg"] == pytest.approx(np.degrees(std[0]))
    assert col["z_mm"] == pytest.approx(1e3 * std[5])


def test_l4_times_every_method(tmp_path):
    table = run_experiment("li-l4", tmp_path, QUICK)
    assert set(table["rows"]) == set(method_configs()) | {f"{m}+mls" for m in METHODS}
    assert all(r["median_ms"] > 0 for r in table["rows"].values())
    assert table["paper"]["jicp_ms"] == 98.0 and table["sensor"] == "tof-paper"


@pytest.mark.slow
def test_l3_acceptance_on_the_default_lab_run():
    """58 frames, clean ToF noise, model-free, seed 0: the keyframe graph's translation below
    point-to-point ICP's and within 1.5× the paper's J-ICP on every axis. One seed is an
    anecdote (seed 0 gives yaw 0.059° against the paper's 0.046°): over 10 seeds the means are
    0.46 / 0.47 / 0.17 mm and 0.027 / 0.059 / 0.023° (pitch / yaw / roll), at or below the
    paper but for yaw and roll, the README's table."""
    sim = simulate_lab(LabConfig())
    runs = run_methods(sim, ExperimentOptions(seed=0, workers=2))
    summary = l3_summary([runs])
    mean = {m: runs[m]["table"]["mean"] for m in runs}
    print(json.dumps(summary, indent=1, default=float))
    # Measured x / y / z: keyframe 0.50 / 0.43 / 0.15 mm, point-to-point 1.72 / 0.98 / 0.22.
    for a in ("x_mm", "y_mm", "z_mm"):
        assert mean["keyframe"][a] < mean["point_to_point"][a], a
    for a in AXES:
        assert mean["keyframe"][a] <= 1.5 * PAPER_TABLE2["jicp"][a][0], a
    # Every frame ok but the second (no velocity yet to confirm it) and the third (the motion
    # model not yet tested).
    assert summary["status_counts"]["keyframe"] == {"ok": len(sim) - 2, "degraded": 2, "lost": 0}
    # Li's J-ICP tracks every frame (none lost).
    assert summary["status_counts"]["jicp"]["lost"] == 0


@pytest.mark.slow
def test_sigma_covers_the_error_on_the_default_lab_run():
    from scipy.spatial.transform import Rotation

    from spacepose.core.tracker import TrackerConfig, track_sequence

    sim = simulate_lab(LabConfig())
    out = track_sequence([f.cloud for f in sim.frames()], sim.timestamps, TrackerConfig(), None, 2)
    D = out.trajectory.poses @ se3.invert(sim.groundtruth.rebased_first().poses)
    err = np.c_[Rotation.from_matrix(D[:, :3, :3]).as_rotvec(), D[:, :3, 3]]
    sigma = np.array([r.sigma for r in out.results])
    within = (np.abs(err[1:]) <= 3 * sigma[1:]).all(axis=1)
    assert within.mean() >= 0.95  # measured 100 %
