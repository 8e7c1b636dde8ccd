"""The depth camera model (core/depth.py): back-projection, z-buffering."""

from __future__ import annotations

import numpy as np
import pytest

from spacepose.core.depth import (
    DepthCamera,
    backproject,
    depth_to_cloud,
    pixel_rays,
    render_depth,
)
from spacepose.core.lens import distort
from spacepose.errors import InputError

PINHOLE = DepthCamera(fx=500.0, fy=480.0, cx=79.5, cy=59.5, depth_scale=0.001)
# The same lens on a 5 x 4 crop: its principal point inside the small test images.
SMALL = PINHOLE.model_copy(update={"cx": 2.0, "cy": 1.5})
# A wide-angle lens with OpenCV's full rational model and tangential terms (|k| as in real
# ToF calibrations: a few pixels to tens of pixels at the corners).
WIDE = PINHOLE.model_copy(
    update={"k1": -0.28, "k2": 0.09, "k3": -0.012, "k4": 0.05, "k5": 0.01, "k6": 0.002}
    | {"p1": 1.2e-3, "p2": -8e-4}
)


def test_pixel_rays_project_back_onto_their_pixels():
    rays = pixel_rays(WIDE, 120, 160)
    assert np.isfinite(rays).all()
    xd, yd = distort(WIDE, rays[..., 0], rays[..., 1])
    v, u = np.mgrid[0:120, 0:160]
    np.testing.assert_allclose(WIDE.fx * xd + WIDE.cx, u, atol=1e-9)
    np.testing.assert_allclose(WIDE.fy * yd + WIDE.cy, v, atol=1e-9)
    assert not rays.flags.writeable


def test_a_distortion_that_folds_most_of_the_image_is_refused_naming_the_file() -> None:
    """k1 = 1e300 (a unit or exponent slip in an intrinsics file) left no pixel invertible:
    every frame came out empty, with overflow warnings and a reason about the frame. The
    camera is now refused in one line naming the image and the coefficients; a strong but
    real barrel (k1 = -5: 3 % of the pixels fold) still back-projects."""
    depth = np.full((120, 160), 1500, dtype=np.uint16)
    broken = PINHOLE.model_copy(update={"k1": 1e300})
    with pytest.raises(InputError, match=r"cannot be inverted at 100 % of its 160x120") as info:
        backproject(depth, broken, source="frame_0001.png")
    assert str(info.value).startswith("frame_0001.png: ") and "k1..k6 1e+300" in str(info.value)
    barrel = backproject(depth, PINHOLE.model_copy(update={"k1": -5.0}))
    assert 0.95 < barrel.valid.mean() < 1.0


def test_pinhole_backprojection_closed_form():
    depth = np.zeros((120, 160), dtype=np.uint16)
    depth[10, 20] = 2000  # 2 m
    depth[100, 150] = 1500
    organised = backproject(depth, PINHOLE)
    assert organised.points.shape == (120, 160, 3)
    assert organised.valid.sum() == 2
    np.testing.assert_allclose(
        organised.points[10, 20], [(20 - 79.5) / 500 * 2, (10 - 59.5) / 480 * 2, 2.0], atol=1e-15
    )
    cloud = depth_to_cloud(depth, PINHOLE)
    np.testing.assert_allclose(cloud.points[:, 2], [2.0, 1.5])  # row-major order
    assert cloud.points[1, 0] > 0 and cloud.points[1, 1] > 0  # bottom right: x right, y down


def test_zero_negative_and_nan_depth_are_no_return():
    depth = np.full((4, 5), 1.25, dtype=np.float32)
    depth[0, 0], depth[1, 1], depth[2, 2] = 0.0, -1.0, np.nan
    camera = SMALL.model_copy(update={"depth_scale": 1.0})
    organised = backproject(depth, camera)
    assert organised.valid.sum() == 17
    assert np.isnan(organised.points[~organised.valid]).all()
    assert len(organised.cloud()) == 17
    with pytest.raises(InputError, match="no return"):
        depth_to_cloud(np.zeros((4, 5), dtype=np.uint16), SMALL, source="empty.png")


def test_the_integer_no_return_code_and_the_far_plane_are_no_return():
    depth = np.full((4, 5), 1500, dtype=np.uint16)
    depth[0, 0] = 65535  # a camera's no-return / saturation code, a renderer's background
    depth[1, 1] = 9000  # 9 m: beyond a far plane at 8 m
    assert backproject(depth, SMALL).valid.sum() == 19
    far = SMALL.model_copy(update={"max_depth": 8.0})
    organised = backproject(depth, far)
    assert organised.valid.sum() == 18 and not organised.valid[1, 1]
    # A float image has no such code: its largest finite values are depths like any other.
    metres = depth.astype(np.float32) / 1000
    assert backproject(metres, SMALL.model_copy(update={"depth_scale": 1.0})).valid.sum() == 20


def test_a_range_image_puts_each_point_at_its_range_along_the_ray():
    # A flat wall at z = 2 m seen as ranges bends unless read as ranges.
    u, v = np.meshgrid(np.arange(160.0), np.arange(120.0))
    x, y = (u - 79.5) / 500, (v - 59.5) / 480
    ranges_m = 2.0 * np.sqrt(1 + x**2 + y**2)
    camera = PINHOLE.model_copy(update={"depth_scale": 1.0, "depth_kind": "range"})
    points = backproject(ranges_m, camera).points
    np.testing.assert_allclose(points[..., 2], 2.0, atol=1e-12)
    np.testing.assert_allclose(np.linalg.norm(points, axis=-1), ranges_m, rtol=1e-12)
    as_z = backproject(ranges_m, camera.model_copy(update={"depth_kind": "z"})).points
    assert as_z[0, 0, 2] - 2.0 > 0.04  # the corner pixel 4.6 cm behind the wall


def test_stride_keeps_every_other_pixel():
    depth = np.arange(1, 121 * 161 + 1, dtype=np.float64).reshape(121, 161) % 5000 + 100
    organised = backproject(depth, PINHOLE)
    strided = organised.cloud(stride=2)
    np.testing.assert_array_equal(strided.points, organised.points[::2, ::2].reshape(-1, 3))
    with pytest.raises(InputError, match="stride"):
        organised.cloud(stride=0)


def test_size_and_shape_are_checked():
    sized = PINHOLE.model_copy(update={"width": 160, "height": 120})
    with pytest.raises(InputError, match="640x480, the intrinsics say 160x120"):
        backproject(np.ones((480, 640)), sized, source="big.png")
    with pytest.raises(InputError, match="one numeric channel"):
        backproject(np.ones((4, 5, 3)), PINHOLE)
    # Intrinsics of the full 160 x 120 sensor on a 64 x 48 binned image: refused, not bent.
    with pytest.raises(InputError, match=r"principal point \(79.5, 59.5\) lies outside the 64x48"):
        backproject(np.ones((48, 64)), PINHOLE, source="binned.png")


def test_render_then_backproject_round_trip_with_distortion():
    rng = np.random.default_rng(3)
    # Points on the rays of random pixels, at random depths: rendering must find those pixels.
    rays = pixel_rays(WIDE, 120, 160)
    v, u = np.divmod(rng.choice(120 * 160, 300, replace=False), 160)
    z = rng.uniform(0.5, 3.0, 300)
    points = np.column_stack([rays[v, u, 0] * z, rays[v, u, 1] * z, z])
    image = render_depth(np.vstack([points, points * 1.5]), WIDE, 120, 160)  # behind: hidden
    organised = backproject(image, WIDE.model_copy(update={"depth_scale": 1.0}))
    np.testing.assert_allclose(organised.points[v, u], points, atol=1e-12)
    assert organised.valid.sum() == 300
