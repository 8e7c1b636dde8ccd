"""Bad inputs found by an eighth hostile round: each ends in one line naming the file (or the
parameter) and the problem, never a traceback or a silently wrong result."""

from __future__ import annotations

import numpy as np
import pytest

from spacepose.core.clusters import cluster_labels, main_cluster_group
from spacepose.errors import InputError


def _plane(n: int = 400, seed: int = 0) -> np.ndarray:
    """``n`` points on a 0.4 m square plate 1 m in front of the sensor, slightly noisy."""
    rng = np.random.default_rng(seed)
    xy = rng.uniform(-0.2, 0.2, (n, 2))
    return np.column_stack([xy, 1.0 + 1e-4 * rng.normal(size=n)])


# -- cluster_labels: a link length of 0, < 0, NaN or inf ------------------------------------------


@pytest.mark.parametrize("distance", [0.0, -0.02, float("nan"), float("inf")])
def test_cluster_labels_of_no_link_length_is_an_input_error(distance):
    """0 and NaN left every point its own cluster, -0.02 and inf put all in one: no error."""
    points = _plane(50)
    with pytest.raises(InputError) as exc:
        cluster_labels(points, distance)
    assert str(exc.value) == (
        f"distance must be a positive, finite number of metres, got {distance!r}"
    )
    with pytest.raises(InputError, match=r"^merge_distance must be a positive, finite"):
        main_cluster_group(points, 0.02, distance, 0.1)


def test_cluster_labels_of_bad_points_is_an_input_error():
    """(N, 2) points were clustered in the plane without a word; NaN ended in scipy's
    'data must be finite'."""
    points = _plane(50)
    with pytest.raises(InputError) as exc:
        cluster_labels(points[:, :2], 0.02)
    assert str(exc.value) == "cluster_labels: points must have shape (N, 3), got (50, 2)"
    points[7, 2] = np.nan
    with pytest.raises(InputError) as exc:
        cluster_labels(points, 0.02)
    assert str(exc.value) == "cluster_labels: points have non-finite entries (NaN or inf)"
    assert len(cluster_labels(np.zeros((0, 3)), 0.02)) == 0
