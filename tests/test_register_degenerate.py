"""``spacepose register`` on surfaces that leave the pose partly free: flagged, σ widened."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from spacepose.cli import main
from spacepose.core.cloud import PointCloud
from spacepose.core.tracker_config import HealthConfig
from spacepose.tools.cloud_io import read_cloud, write_cloud
from spacepose.tools.register import RegisterConfig, register

PAIR = Path(__file__).resolve().parents[1] / "data" / "real" / "small_gicp"


def noisy_plane(seed: int, noise: float = 0.001) -> np.ndarray:
    """A 0.5 m square at z = 1.2 m sampled every 3 mm, with ``noise`` (m) along its normal."""
    u, v = np.meshgrid(np.arange(-0.25, 0.25, 0.003), np.arange(-0.25, 0.25, 0.003))
    base = np.c_[u.ravel(), v.ravel(), np.full(u.size, 1.2)]
    return base + np.random.default_rng(seed).normal(0, noise, base.shape) * [0, 0, 1]


@pytest.mark.parametrize("method", ["gicp", "point_to_plane", "point_to_point"])
def test_a_noisy_plane_onto_itself_is_degenerate_and_says_so(method: str) -> None:
    """Two 1 mm-noise scans of one plane: x, y and the rotation about z are free. The methods'
    own σ claimed 0.005-0.09° about z and 0.14-0.34 mm along x and y; the coarse condition is
    infinite (no row leans on those directions; the bound is 1e4), and those σ become 1 rad and
    the cloud's radius (0.2 m), the rest stays."""
    out = register(noisy_plane(1), noisy_plane(2), config=RegisterConfig(method=method), workers=2)
    d = out.degeneracy
    assert d.degenerate and d.condition > HealthConfig().lost_condition
    names = d.names()
    assert names[0].startswith("rotation about [0.00 0.00 1.00] through ["), names
    assert names[0].endswith(" 1.200] m"), names  # through the plane's centre
    assert len(names) == 3 and all(n.startswith("translation along") for n in names[1:])
    assert all(n.endswith("0.00]") for n in names[1:]), names  # in the plane
    sigma = np.sqrt(np.diag(out.covariance))
    assert np.degrees(sigma[2]) > 50 and np.all(sigma[3:5] > 0.15), sigma
    # What the plane does fix stays as tight as the registration said: tilts and depth.
    assert np.all(np.degrees(sigma[:2]) < 0.05) and sigma[5] < 1e-4, sigma
    summary = out.to_dict()
    assert summary["degenerate"] is True and summary["unconstrained"] == names


def test_well_conditioned_pairs_are_not_flagged_and_keep_their_covariance() -> None:
    """The real LiDAR pair scores 8.5-8.7 and the lab target 7.1 (the tracker's ok bound is
    1e3): not flagged, and the covariance is the registration's own, never narrower and only
    as much wider as its cluster-robust form asks (σ 1.8-6.3 times the information's on the
    real pair; on the lab target the point-to-point information is the wider), not widened
    along a free direction (a widening adds the radius squared, metres²: σ thousands of times
    the information's)."""
    from spacepose.core.sim.targets import sample_surface
    from test_icp import asymmetric_target

    shape = asymmetric_target()
    lab = (sample_surface(shape, 6000, seed=2).points, sample_surface(shape, 6000, seed=1).points)
    real = (read_cloud(PAIR / "source.ply"), read_cloud(PAIR / "target.ply"))
    for pair, method in ((real, "gicp"), (real, "point_to_plane"), (lab, "point_to_point")):
        out = register(*pair, config=RegisterConfig(method=method), workers=2)
        assert not out.degeneracy.degenerate, (method, out.degeneracy.condition)
        assert out.degeneracy.condition < HealthConfig().ok_condition
        own = out.result.covariance(sigma=1.0 if method == "gicp" else None)
        assert np.linalg.eigvalsh(out.covariance - own).min() > -1e-12 * np.abs(own).max()
        ratio = np.sqrt(np.diag(out.covariance) / np.diag(own))
        assert np.all(ratio < 10.0), (method, ratio)
        summary = out.to_dict()
        assert summary["degenerate"] is False and summary["unconstrained"] == []


def test_command_line_warns_about_a_plane_registered_onto_itself(tmp_path: Path, capsys) -> None:
    """The fuzzed case: one plane file onto itself claimed σ of 1e-6° and 1e-8 m (GICP). Now
    one warning line names the pair and the free directions, and the JSON carries the flag."""
    plane = tmp_path / "plane.npy"
    write_cloud(plane, PointCloud(noisy_plane(3)))
    out = tmp_path / "r.json"
    assert main(["register", str(plane), str(plane), "--out", str(out)]) == 0
    captured = capsys.readouterr()
    err = captured.err.strip()
    assert err.count("\n") == 0 and err.startswith(f"warning: {plane} onto {plane}: degenerate")
    assert "rotation about [0.00 0.00 1.00] through [" in err and "unconstrained" in err
    # Strict JSON: the infinite condition (no row leans on the free directions) is null, not
    # the Infinity that json.dumps writes by default.
    result = json.loads(out.read_text(), parse_constant=lambda name: pytest.fail(name))
    assert result["degenerate"] is True and len(result["unconstrained"]) == 3
    assert result["condition_number"] is None
    sigma = np.sqrt(np.diag(result["covariance"]))
    assert np.degrees(sigma[2]) > 50 and np.all(sigma[3:5] > 0.15), sigma
