"""Li's normal-consistency measure against theory: a plane, and uniform random normals."""

from __future__ import annotations

import numpy as np
import pytest

from spacepose.core.cloud import PointCloud
from spacepose.core.cloud_quality import normal_consistency
from spacepose.errors import InputError


def test_consistency_plane_and_random_normals():
    rng = np.random.default_rng(5)
    pts = rng.uniform(-1, 1, (2000, 3))
    plane = PointCloud(pts, np.tile([0.0, 0.0, 1.0], (2000, 1)))
    c = normal_consistency(plane, k=8)
    assert c.share_below_20 == 1.0
    assert c.angles_deg.shape == (2000 * 8,)
    assert c.counts[0] == 2000 * 8 and c.counts.sum() == 2000 * 8
    # Independent uniform unit normals: P(angle < 20°) = (1 − cos 20°) / 2 = 0.0302.
    d = rng.normal(size=(2000, 3))
    rand = PointCloud(pts, d / np.linalg.norm(d, axis=1, keepdims=True))
    c = normal_consistency(rand, k=10, bin_width_deg=20.0)
    assert c.share_below_20 == pytest.approx((1 - np.cos(np.radians(20))) / 2, abs=0.005)
    assert len(c.counts) == 9 and c.bin_edges_deg[-1] == 180.0
    # Uniform directions: the angle density is sin(θ)/2, so the 80–100° bin holds ~0.174.
    assert c.shares[4] == pytest.approx(np.cos(np.radians(80)), abs=0.01)


def test_consistency_of_bad_clouds_is_an_input_error():
    with pytest.raises(InputError, match="needs a cloud with normals"):
        normal_consistency(PointCloud(np.random.default_rng(0).uniform(size=(20, 3))))
    up = np.array([0.0, 0.0, 1.0])
    with pytest.raises(InputError, match="more than 10"):
        normal_consistency(PointCloud(np.zeros((5, 3)), np.tile(up, (5, 1))))
    with pytest.raises(InputError, match="divide 180"):
        normal_consistency(PointCloud(np.zeros((50, 3)), np.tile(up, (50, 1))), bin_width_deg=7.0)
