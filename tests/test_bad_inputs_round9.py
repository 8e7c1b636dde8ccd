"""Bad inputs found by a ninth hostile round: each ends in one line naming the file (or the
parameter) and the problem, never a traceback or a silently wrong result."""

from __future__ import annotations

import warnings

import numpy as np
import pytest

from spacepose.core.depth import DepthCamera, distort, pixel_rays, undistort
from spacepose.errors import InputError

_WIDE = DepthCamera(fx=500.0, fy=500.0, cx=2.0, cy=2.0, k1=0.1)


# -- pixel_rays of an image without pixels ---------------------------------------------------------


@pytest.mark.parametrize("camera", [_WIDE, DepthCamera(fx=500.0, fy=500.0, cx=2.0, cy=2.0)])
@pytest.mark.parametrize(("height", "width", "name"), [(0, 5, "height"), (5, 0, "width")])
def test_pixel_rays_of_no_pixels_is_an_input_error(camera, height, width, name):
    """0 rows or columns gave numpy's 'Mean of empty slice' warnings and an empty array."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(InputError) as exc:
            pixel_rays(camera, height, width)
    assert str(exc.value) == f"pixel_rays: {name} must be a whole number >= 1, got 0"


def test_pixel_rays_of_a_fractional_size_is_an_input_error():
    """A height of 2.5 gave the rays of 3 rows."""
    with pytest.raises(InputError) as exc:
        pixel_rays(_WIDE, 2.5, 5)
    assert str(exc.value) == "pixel_rays: height must be a whole number >= 1, got 2.5"
    assert pixel_rays(_WIDE, 4.0, 5).shape == (4, 5, 2)


# -- distort / undistort of x and y of different lengths ------------------------------------------


@pytest.mark.parametrize("function", [distort, undistort])
def test_distort_of_unequal_coordinates_is_an_input_error(function):
    """x of 3 and y of 2 values ended in numpy's 'operands could not be broadcast together'."""
    name = function.__name__
    x, y = ("x", "y") if name == "distort" else ("xd", "yd")
    with pytest.raises(InputError) as exc:
        function(_WIDE, [0.1, 0.2, 0.3], [0.1, 0.2])
    assert str(exc.value) == f"{name}: {x} and {y} must have the same shape, got (3,) and (2,)"
    xd, yd = distort(_WIDE, [[0.1, 0.2]], [[0.0, 0.1]])
    assert xd.shape == yd.shape == (1, 2)
    np.testing.assert_allclose(undistort(_WIDE, xd, yd)[0], [[0.1, 0.2]], atol=1e-9)
