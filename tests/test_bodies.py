"""Two rigid bodies in one object (core/bodies.py, core/clutter_body.py): a support moving
otherwise is split off by motion and then followed, against the known motions and labels of
synthetic boxes; one body, or noise correlated over patches, is never split."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from spacepose.core import se3
from spacepose.core.bodies import MotionSplit, split_trial
from spacepose.core.cloud import PointCloud
from spacepose.core.clutter_body import ClutterBody, subset
from spacepose.core.icp import ICPConfig, icp
from spacepose.core.keyframes import PreparedCloud
from spacepose.core.voxel import voxel_cells
from spacepose.errors import InputError

SIGMA = 0.0005
REACH = 0.03
# About twice the point spacing of the boxes (4000 points over their visible faces).
NEAR = 0.01
TARGET_CENTRE = np.array([0.1, -0.05, 1.2])
SUPPORT_CENTRE = np.array([0.1, 0.27, 1.2])


def split_motion(*args, **kwargs) -> MotionSplit | None:
    """The split alone (:func:`split_trial`)."""
    return split_trial(*args, **kwargs).split


def _visible_box(rng, n, half, centre):
    """(n, 3) points on the three faces of a box that a sensor at the origin sees (the box
    lies at +x, +y, +z), with their normals towards the sensor."""
    axes = rng.integers(0, 3, n)
    p = rng.uniform(-1.0, 1.0, (n, 3)) * half
    normals = np.zeros((n, 3))
    rows = np.arange(n)
    p[rows, axes] = -half[axes]
    normals[rows, axes] = -1.0
    return p + centre, normals


def _visible_disc(rng, n, radius, half_height, centre):
    """(n, 3) points on a disc with its axis along y (a turntable) that a sensor at the origin
    sees: its top face and the near half of its rim, with normals towards the sensor."""
    on_rim = rng.random(n) < 0.5
    phi = rng.uniform(-np.pi / 2, np.pi / 2, n)
    rho, psi = radius * np.sqrt(rng.random(n)), rng.uniform(0.0, 2.0 * np.pi, n)
    rim = np.c_[
        radius * np.sin(phi), rng.uniform(-half_height, half_height, n), -radius * np.cos(phi)
    ]
    top = np.c_[rho * np.cos(psi), np.full(n, -half_height), rho * np.sin(psi)]
    rim_normals = np.c_[np.sin(phi), np.zeros(n), -np.cos(phi)]
    p = np.where(on_rim[:, None], rim, top)
    normals = np.where(on_rim[:, None], rim_normals, [0.0, -1.0, 0.0])
    return p + centre, normals


def _support_box(rng, n):
    return _visible_box(rng, n, np.array([0.2, 0.12, 0.2]), SUPPORT_CENTRE)


def _support_disc(rng, n):
    return _visible_disc(rng, n, 0.25, 0.02, SUPPORT_CENTRE)


def _scene(rng, n_target=4000, n_support=4000, support=_support_box):
    """Target box above a support (a box, or a disc), touching; points, normals, True on the
    target."""
    pt, nt = _visible_box(rng, n_target, np.array([0.15, 0.1, 0.08]), TARGET_CENTRE)
    ps, ns = support(rng, n_support)
    on = np.r_[np.ones(n_target, bool), np.zeros(n_support, bool)]
    return np.vstack([pt, ps]), np.vstack([nt, ns]), on


def _about(centre, rotvec_deg, shift):
    """(4, 4) a turn about ``centre`` then a shift (m), sensor frame."""
    R = Rotation.from_rotvec(np.radians(rotvec_deg)).as_matrix()
    return se3.make_transform(R, centre - R @ centre + np.asarray(shift))


def _frames(seed, M_target, M_support, noise=None, n_support=4000, support=_support_box):
    """The reference (first view, normals) and the frame (second view: each body moved by its
    motion, sampled anew, noise along the normals)."""
    rng = np.random.default_rng(seed)
    p0, n0, _ = _scene(rng, n_support=n_support, support=support)
    p1, n1, on = _scene(rng, n_support=n_support, support=support)
    p1 = p1 + n1 * (rng.normal(0.0, SIGMA, len(p1)) if noise is None else noise(p1))[:, None]
    moved = np.where(
        on[:, None],
        se3.transform_points(M_target, p1),
        se3.transform_points(M_support, p1),
    )
    ref = PreparedCloud(PointCloud(p0, normals=n0))
    return ref, moved, on


def _compromise(ref, frame):
    """The one-motion registration a tracker settles on (robust point-to-plane from rest)."""
    cfg = ICPConfig(
        method="point_to_plane", max_correspondence_distance=REACH, robust_kernel="geman_mcclure"
    )
    return icp(frame, ref.cloud, np.eye(4), cfg).T_target_source


def _error(T, T_true, centre):
    """(deg, m) of ``T`` against ``T_true``: its turn, and how far it moves ``centre``."""
    d = T @ se3.invert(T_true)
    moved = se3.transform_points(d, centre[None])[0]
    turn = Rotation.from_matrix(d[:3, :3]).magnitude()
    return np.degrees(turn), float(np.linalg.norm(moved - centre))


TURNING = _about(TARGET_CENTRE, [1.0, 4.0, 0.5], [0.004, 0.0, 0.0])
SLIDING = _about(SUPPORT_CENTRE, [0.0, 0.0, 0.0], [0.008, 0.0, 0.0])


@pytest.mark.parametrize("seed", range(4))
def test_split_finds_both_motions_and_the_turning_body(seed):
    ref, frame, on = _frames(seed, TURNING, SLIDING)
    split = split_motion(frame, ref, _compromise(ref, frame), SIGMA, REACH, NEAR, workers=1)
    assert split is not None
    # T_ref_frame maps the frame back into the reference: the inverse of each body's motion.
    deg, m = _error(split.T_ref_frame, se3.invert(TURNING), TARGET_CENTRE)
    assert deg < 0.05 and m < 2e-4, (deg, m)
    deg, m = _error(split.T_ref_frame_support, se3.invert(SLIDING), SUPPORT_CENTRE)
    assert deg < 0.05 and m < 2e-4, (deg, m)
    assert np.mean(split.frame_target == on) > 0.97
    # The reference's own labels: its first half is the target box (same layout as the frame).
    assert np.mean(split.ref_target == on) > 0.97
    assert np.mean(split.ref_support == ~on) > 0.97
    assert split.shares[0] == pytest.approx(np.mean(split.frame_target))


def test_the_support_is_the_body_that_moved_less_even_when_it_holds_most_points():
    ref, frame, on = _frames(7, TURNING, SLIDING, n_support=12000)
    split = split_motion(frame, ref, _compromise(ref, frame), SIGMA, REACH, NEAR, workers=1)
    assert split is not None
    assert split.shares[0] < 0.3
    assert np.mean(split.frame_target == on) > 0.97
    deg, _ = _error(split.T_ref_frame, se3.invert(TURNING), TARGET_CENTRE)
    assert deg < 0.05


def test_a_small_support_is_split_off_too():
    """A support holding 13 % of the points (the Hubble kit's turntable holds 12-14 %)."""
    ref, frame, on = _frames(11, TURNING, SLIDING, n_support=600)
    split = split_motion(frame, ref, _compromise(ref, frame), SIGMA, REACH, NEAR, workers=1)
    assert split is not None
    assert np.mean(split.frame_target == on) > 0.97
    deg, _ = _error(split.T_ref_frame, se3.invert(TURNING), TARGET_CENTRE)
    assert deg < 0.05


@pytest.mark.parametrize("seed", range(4))
def test_a_disc_turning_about_its_own_axis_is_a_support(seed):
    """A turntable's disc spinning in itself shows only its slide, but the compromise's turn
    leaves its rigid fit anywhere along that spin: seen from the sensor's origin, 1.2 m off
    the axis, its shift is then metres x radians off the disc's. The pure-shift test must
    start from the shift at the body's own centroid (it returned None on all four seeds when
    it started from the sensor origin's)."""
    spinning = _about(SUPPORT_CENTRE, [0.0, 5.0, 0.0], [0.008, 0.0, 0.0])
    ref, frame, on = _frames(seed, TURNING, spinning, support=_support_disc)
    split = split_motion(frame, ref, _compromise(ref, frame), SIGMA, REACH, NEAR, workers=1)
    assert split is not None
    assert np.mean(split.frame_target == on) > 0.97
    deg, m = _error(split.T_ref_frame, se3.invert(TURNING), TARGET_CENTRE)
    assert deg < 0.05 and m < 2e-4, (deg, m)


def test_a_second_body_that_turns_is_not_taken_for_a_support():
    """Both bodies turn (a part of a tumbling target that new views set apart looks so): the
    support is assumed not to turn, so nothing is split. Without that rule these two bodies
    are split, every point labelled right (measured, seeds 5 and 6)."""
    other = _about(SUPPORT_CENTRE, [0.0, -4.0, 0.0], [0.008, 0.0, 0.0])
    ref, frame, _ = _frames(5, TURNING, other)
    assert split_motion(frame, ref, _compromise(ref, frame), SIGMA, REACH, NEAR, workers=1) is None


@pytest.mark.parametrize("seed", range(5))
def test_one_rigid_body_is_never_split(seed):
    ref, frame, _ = _frames(seed, TURNING, TURNING)
    assert split_motion(frame, ref, _compromise(ref, frame), SIGMA, REACH, NEAR, workers=1) is None


@pytest.mark.parametrize("seed", range(5))
def test_noise_correlated_over_patches_is_not_a_second_motion(seed):
    """Range errors shared over 3 cm patches (2 σ a patch, new each view) give the residuals
    structure, as a real sensor's do; still one motion."""
    rng = np.random.default_rng(100 + seed)

    def patchy(points):
        _, cell = voxel_cells(points, 0.03)
        return rng.normal(0.0, 2 * SIGMA, cell.max() + 1)[cell] + rng.normal(
            0.0, SIGMA, len(points)
        )

    ref, frame, _ = _frames(seed, TURNING, TURNING, noise=patchy)
    assert split_motion(frame, ref, _compromise(ref, frame), SIGMA, REACH, NEAR, workers=1) is None


def _table(rng, n):
    """A table under the target: its top seen from above (normal -y) and, one point in
    eight, its left side (normal -x), the only part that shows the table standing still
    while the target slides over it."""
    side = rng.random(n) < 0.125
    top = np.c_[rng.uniform(-0.5, 0.5, n), np.zeros(n), rng.uniform(-0.5, 0.5, n)]
    left = np.c_[np.full(n, -0.5), rng.uniform(0.0, 0.3, n), rng.uniform(-0.5, 0.5, n)]
    normals = np.where(side[:, None], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0])
    centre = np.array([0.1, 0.03, 1.2])
    return np.where(side[:, None], left, top) + centre, normals


# The target slides 2 cm over the table and turns 3° about the table's normal.
SLIDE_TURN = _about(TARGET_CENTRE, [0.0, 3.0, 0.0], [0.02, 0.0, 0.0])
# A compromise that follows the target but is pulled 0.36° / 2 mm off by the table.
PULLED = _about(TARGET_CENTRE, [0.3, 0.0, 0.2], [0.0, 0.002, 0.0]) @ se3.invert(SLIDE_TURN)


@pytest.mark.parametrize("seed", range(4))
def test_a_support_standing_still_is_split_off_with_its_motion_held(seed):
    ref, frame, on = _frames(seed, SLIDE_TURN, np.eye(4), support=_table)
    split = split_motion(frame, ref, PULLED, SIGMA, REACH, NEAR, workers=1, second=np.eye(4))
    assert split is not None
    np.testing.assert_array_equal(split.T_ref_frame_support, np.eye(4))
    deg, m = _error(split.T_ref_frame, se3.invert(SLIDE_TURN), TARGET_CENTRE)
    # Measured over seeds 0-7: at most 0.029° and 0.09 mm.
    assert deg < 0.05 and m < 2e-4, (deg, m)
    # The table's side goes with the table; its top slides along itself under the target's
    # motion and may go either way.
    side = ~on & (frame[:, 0] < -0.39)
    assert np.mean(~split.frame_target[side]) > 0.97


@pytest.mark.parametrize("seed", range(4))
def test_a_support_standing_still_stands_apart_before_a_slow_target_does(seed):
    """Under three times the noise, a target that has turned 0.15° and slid 1 mm over the
    still table: the table's part already fits the identity clearly better than the target's
    motion, the target's part not yet its own (no split, ``support_apart``); turned 3° and slid
    20 mm, the split stands. Measured over seeds 0-7: apart on all eight, split on seven."""
    sigma = 3.0 * SIGMA
    pull = PULLED @ SLIDE_TURN  # the compromise's error, as in the test above
    for share, splits in ((0.05, False), (1.0, True)):
        M = _about(TARGET_CENTRE, [0.0, 3.0 * share, 0.0], [0.02 * share, 0.0, 0.0])
        draws = np.random.default_rng(100 + seed)
        noise = lambda p, draws=draws: draws.normal(0.0, sigma, len(p))  # noqa: E731
        ref, frame, _ = _frames(seed, M, np.eye(4), noise=noise, support=_table)
        T = pull @ se3.invert(M)
        trial = split_trial(frame, ref, T, sigma, REACH, NEAR, workers=1, second=np.eye(4))
        assert (trial.split is not None) == splits and trial.support_apart != splits


@pytest.mark.parametrize("seed", range(4))
def test_a_support_that_moves_is_not_split_off_as_standing_still(seed):
    """The still hypothesis on frames where nothing stands still: one body, or a support that
    slides (a hand-held sensor sees no part still); nor does a part stand apart."""
    for M_support in (TURNING, SLIDING):
        ref, frame, _ = _frames(seed, TURNING, M_support)
        T = _compromise(ref, frame)
        trial = split_trial(frame, ref, T, SIGMA, REACH, NEAR, workers=1, second=np.eye(4))
        assert trial.split is None and not trial.support_apart


def test_clutter_body_predicts_at_constant_velocity_and_masks_its_points():
    """The support's reference is the reference's support box; it slides one step a second."""
    on_ref = np.r_[np.ones(4000, bool), np.zeros(4000, bool)]
    ref, _, _ = _frames(3, TURNING, SLIDING)
    support = ClutterBody(subset(ref, ~on_ref), [(0.0, np.eye(4))])
    first_step = se3.transform_points(SLIDING, ref.cloud.points[~on_ref])
    assert support.follow(first_step, 1.0, REACH, workers=1)
    step = se3.invert(SLIDING)
    np.testing.assert_allclose(support.predict(2.0), step @ step, atol=2e-4)
    np.testing.assert_allclose(support.predict(1.5)[:3, 3], 1.5 * step[:3, 3], atol=2e-4)
    # A frame two steps on: the support's points go, the target's stay.
    _, frame, on = _frames(3, TURNING @ TURNING, SLIDING @ SLIDING)
    T_ref_frame_target = se3.invert(TURNING @ TURNING)
    keep = support.separate(frame, 2.0, subset(ref, on_ref), T_ref_frame_target, 0.02, workers=1)
    assert np.mean(keep == on) > 0.97


def test_a_support_out_of_view_takes_no_point():
    """A frame of the target alone (the support has left the view): every point stays. (A
    random spacecraft at 1.2 m before a wall and table, turning 10° a frame, ended its run with
    an error on such a frame.)"""
    on_ref = np.r_[np.ones(4000, bool), np.zeros(4000, bool)]
    ref, frame, on = _frames(3, TURNING, SLIDING)
    support = ClutterBody(subset(ref, ~on_ref), [(0.0, np.eye(4))])
    target_only = frame[on]
    keep = support.separate(target_only, 1.0, subset(ref, on_ref), se3.invert(TURNING), NEAR, 1)
    assert keep.shape == (len(target_only),) and keep.all()


def test_arrays_and_clouds_alike_and_bad_inputs():
    ref, frame, _ = _frames(0, TURNING, SLIDING)
    T = _compromise(ref, frame)
    from_cloud = split_motion(PointCloud(frame), ref.cloud, T, SIGMA, REACH, NEAR, workers=1)
    from_arrays = split_motion(frame, ref, T, SIGMA, REACH, NEAR, workers=1)
    np.testing.assert_array_equal(from_cloud.frame_target, from_arrays.frame_target)
    np.testing.assert_array_equal(from_cloud.T_ref_frame, from_arrays.T_ref_frame)
    with pytest.raises(InputError, match="normals"):
        split_motion(frame, PointCloud(ref.cloud.points), T, SIGMA, REACH, NEAR)
    with pytest.raises(InputError, match="sigma"):
        split_motion(frame, ref, T, 0.0, REACH, NEAR)
    with pytest.raises(InputError, match="reach"):
        split_motion(frame, ref, T, SIGMA, np.nan, NEAR)
    bad = frame.copy()
    bad[3] = np.nan
    with pytest.raises(InputError):
        split_motion(bad, ref, T, SIGMA, REACH, NEAR)
    with pytest.raises(InputError, match="finite time"):
        ClutterBody(ref, [(np.nan, np.eye(4))])
