"""``spacepose experiment fusion --quick``: registration poses in the filter, scored against the
orbit run's truth, and the tracker's covariance scored against its own errors."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.stats import chi2

from spacepose.errors import ConfigError
from spacepose.tools.experiments import ExperimentOptions, available, run_experiment
from spacepose.tools.experiments.fusion import fusion_plan, tracker_errors


def test_tracker_errors_closed_form():
    """A pose off by a turn about the sensor origin: at the target origin the error is the
    turn's displacement of that point; the NEES is the turn's χ² against the covariance."""
    from spacepose.core import se3

    T_true = se3.make_transform(np.eye(3), [0.0, 0.0, 25.0])
    turn = se3.exp([0.0, 1e-3, 0.0, 0.0, 0.0, 0.0])
    cov = np.diag([1e-6] * 3 + [1e-4] * 3)
    e, sigma, nees = tracker_errors(turn @ T_true, cov, T_true)
    np.testing.assert_allclose(e[:3], [0.0, 1e-3, 0.0], atol=1e-12)
    np.testing.assert_allclose(e[3:], [25.0 * np.sin(1e-3), 0.0, 0.0], rtol=1e-6)
    assert abs(nees - 1.0) < 1e-9
    # σ about the target: the rotation's 1e-3 rad at 25 m adds 25 mm to x and y.
    np.testing.assert_allclose(sigma[3:], np.sqrt([1e-4 + 625e-6, 1e-4 + 625e-6, 1e-4]))
    assert chi2.ppf(0.975, 6) > nees


def test_quick_fusion_writes_its_table(tmp_path):
    assert "fusion" in available()
    table = run_experiment("fusion", tmp_path, ExperimentOptions(quick=True))
    assert set(table["runs"]) == {"default / registration", "default / both"}
    saved = json.loads((tmp_path / "fusion.json").read_text())
    assert saved["frames"] == 30 and (tmp_path / "fusion.md").read_text().count("\n") == 4
    for run in table["runs"].values():
        s = run["summary"]
        assert s["frames_navigated"]["mean"] >= 26
        # 30 s in: attitude within 1°, the tracker's poses mostly inside the gate.
        assert max(s["attitude_rms_deg"]["mean"]) < 1.0
        assert s["gate_rejections"]["mean"] <= 8
        # 30 frames fill no 4 batches of 50: the bootstrap says so, and the factor stays 3.
        assert [(t["pose_noise"], t["pose_sigma_scale"]) for t in run["per_seed"]] == [(None, 3.0)]


def test_fusion_plan_names_generated_targets():
    assert fusion_plan(None, quick=False) == {
        "default": ("rectangles", "registration", "both", "model-free"),
        "satellite_panels": ("registration",),
        "hubble": ("registration",),
    }
    # A generated spacecraft has no rectangle catalogue; a repeated name runs once.
    assert fusion_plan("random:3, default,random:3", quick=True) == {
        "random:3": ("registration",),
        "default": ("registration", "both"),
    }
    for bad in ("random:x", "cube", " , "):
        with pytest.raises(ConfigError):
            fusion_plan(bad, quick=False)


def test_quick_fusion_on_a_generated_spacecraft(tmp_path):
    """A spacecraft nothing was tuned on: registration poses against its model in the filter."""
    options = ExperimentOptions(quick=True, targets="random:3")
    table = run_experiment("fusion", tmp_path, options)
    assert set(table["runs"]) == {"random:3 / registration"}
    s = table["runs"]["random:3 / registration"]["summary"]
    # 30 s in (seed 0: 29 frames, attitude 0.012-0.032°, position 12-41 mm while the centre
    # of mass is still being learnt; the tracker within 3σ on every frame and axis).
    assert s["frames_navigated"]["mean"] >= 28
    assert max(s["attitude_rms_deg"]["mean"]) < 0.1
    assert max(s["position_rms_mm"]["mean"]) < 100.0
    assert min(s["tracker_in_3sigma"]["mean"]) >= 0.9


def test_seed_figures_leave_out_the_seeds_that_never_started():
    """A seed whose filter never started has NaN errors: the mean and std over seeds are those
    of the others (numpy's nanmean / nanstd, ddof 1), not NaN for every seed."""
    from spacepose.tools.experiments.fusion import _mean_std

    rng = np.random.default_rng(3)
    values = rng.normal(size=(5, 3))
    values[1] = np.nan  # a seed that never started
    values[3, 2] = np.nan
    got = _mean_std(values)
    np.testing.assert_allclose(got["mean"], np.nanmean(values, axis=0))
    np.testing.assert_allclose(got["std"], np.nanstd(values, axis=0, ddof=1))
    one = _mean_std(np.array([[0.5], [np.nan]]))
    assert one == {"mean": [0.5], "std": [0.0]}
    assert np.isnan(_mean_std(np.array([np.nan, np.nan]))["mean"])


def test_the_table_says_what_no_seed_has_and_no_spread_of_one_seed():
    """A run that navigated nothing read "nan ± nan" in fusion.md, and one seed "± 0"."""
    from spacepose.tools.experiments.fusion import SUMMARY_KEYS, markdown_table

    summary = {k: {"mean": float("nan"), "std": float("nan")} for k in SUMMARY_KEYS}
    summary[SUMMARY_KEYS[0]] = {"mean": [1.25, 2.5, 3.0], "std": [0.0, 0.0, 0.0]}
    runs = {"default / both": {"summary": summary, "per_seed": [{}], "seeds_navigated": 0}}
    row = markdown_table(runs).splitlines()[2]
    assert "nan" not in row and "±" not in row
    assert row.startswith("| default / both | 1.25 / 2.5 / 3 | – |"), row
    runs["default / both"]["per_seed"] = [{}, {}]
    assert "1.25 ± 0 / 2.5 ± 0 / 3 ± 0" in markdown_table(runs)
