"""The lens distortion model (core/lens.py): the forward model and its inverse, camera matrices."""

from __future__ import annotations

import numpy as np
import pytest

from spacepose.core.depth import DepthCamera
from spacepose.core.lens import distort, undistort

PINHOLE = DepthCamera(fx=500.0, fy=480.0, cx=79.5, cy=59.5, depth_scale=0.001)
# A wide-angle lens with OpenCV's full rational model and tangential terms (|k| as in real
# ToF calibrations: a few pixels to tens of pixels at the corners).
WIDE = PINHOLE.model_copy(
    update={"k1": -0.28, "k2": 0.09, "k3": -0.012, "k4": 0.05, "k5": 0.01, "k6": 0.002}
    | {"p1": 1.2e-3, "p2": -8e-4}
)


def test_undistort_inverts_the_forward_model():
    rng = np.random.default_rng(7)
    x, y = rng.uniform(-0.25, 0.25, (2, 5000))
    xd, yd = distort(WIDE, x, y)
    assert np.max(np.hypot(xd - x, yd - y)) > 1e-3  # the distortion is not negligible
    xu, yu = undistort(WIDE, xd, yd)
    np.testing.assert_allclose(xu, x, atol=1e-13)
    np.testing.assert_allclose(yu, y, atol=1e-13)


def test_a_camera_matrix_with_nan_or_the_wrong_size_says_which():
    """'needs 9 finite numbers, got 9' named the count, not the NaN."""
    from spacepose.core.lens import matrix_fields
    from spacepose.errors import InputError

    K = [[500.0, 0, 320], [0, 500.0, 240], [0, 0, 1]]
    with pytest.raises(InputError, match="holds non-finite numbers"):
        matrix_fields([[np.nan, 0, 320], *K[1:]], [0, 0, 0, 0])
    with pytest.raises(InputError, match="needs 9 numbers, got 8"):
        matrix_fields(np.ravel(K)[:8], [0, 0, 0, 0])
