"""Tests of the sensor noise profiles (methods.md §3): the paper-like ToF camera, its artefacts."""

from __future__ import annotations

import numpy as np
import pytest
import trimesh
from scipy import ndimage

from spacepose.core.cloud_quality import PAPER_RAW_SHARE_BELOW_20, frame_normal_consistency
from spacepose.core.sim import LabConfig, sensor_config, simulate_lab
from spacepose.core.sim.grid import grid_scenario
from spacepose.core.sim.sensors import DEFAULT_PROFILES, SENSOR_PRESETS, scan
from spacepose.errors import ConfigError

SMALL_TOF = {"width": 320, "height": 240, "focal_px": 241.8}  # the ToF's field of view, 1/4 rays
# Only the artefact under test: no range noise, dropouts, bias or flying pixels.
QUIET = {
    "sigma_const": 0.0,
    "sigma_quad": 0.0,
    "dropout": 0.0,
    "range_bias": 0.0,
    "multipath_bias": 0.0,
    "flying_probability": 0.0,
}


def _plane(distance: float, tilt_deg: float = 0.0, half: float = 20.0) -> trimesh.Trimesh:
    """A square plate facing the sensor at ``distance``, turned ``tilt_deg`` about sensor y."""
    plate = trimesh.creation.box(bounds=[(-half, -half, 0.0), (half, half, 0.01)])
    turn = trimesh.transformations.rotation_matrix(np.radians(tilt_deg), (0, 1, 0))
    return plate.apply_transform(turn).apply_translation((0.0, 0.0, distance))


def _true_ranges(scene: trimesh.Trimesh, cfg, pixels: np.ndarray) -> np.ndarray:
    clean = scan(scene, cfg.model_copy(update={"noise_scale": 0.0}), None)
    lookup = np.full(cfg.width * cfg.height, np.nan)
    lookup[clean.pixel] = np.linalg.norm(clean.points, axis=1)
    return lookup[pixels]


# --------------------------------------------------------------------------------------------
# Profiles


def test_clean_profiles_stay_the_defaults_and_the_paper_profile_is_selectable() -> None:
    assert DEFAULT_PROFILES == {"tof": "tof-clean", "flash-lidar": "flash-lidar-clean"}
    assert SENSOR_PRESETS["tof"] == SENSOR_PRESETS["tof-clean"] == LabConfig().sensor
    clean = SENSOR_PRESETS["tof-clean"]
    assert (clean.amplitude_exponent, clean.multipath_bias, clean.flying_tail) == (0, 0, 0)
    paper = sensor_config("tof-paper")
    assert paper.amplitude_exponent == 0.5 and paper.multipath_bias > 0 and paper.flying_tail > 0
    assert sensor_config("flash-lidar-edges").flying_tail > 0
    with pytest.raises(ConfigError, match="min_amplitude"):
        sensor_config("tof", amplitude_exponent=0.5)


@pytest.mark.parametrize("distance", [0.8, 2.0, 4.0])
def test_paper_range_noise_and_bias_match_the_model_at_several_ranges(distance: float) -> None:
    # A plate turned 40° from the boresight: the amplitude cos θ varies over the image.
    cfg = sensor_config("tof-paper", dropout=0.0, multipath_bias=0.0, **SMALL_TOF)
    normal = np.array([-np.sin(np.radians(40.0)), 0.0, -np.cos(np.radians(40.0))])
    scene = _plane(distance, 40.0)
    s = scan(scene, cfg, np.random.default_rng(11))
    true_r = _true_ranges(scene, cfg, s.pixel)
    rays = s.points / np.linalg.norm(s.points, axis=1, keepdims=True)
    cos = np.abs(rays @ normal)
    # σ = (c + q r²) / sqrt(albedo · |cos θ|), albedo 1: range and amplitude both count.
    sigma_model = (1.2e-3 + 2.0e-3 * true_r**2) / np.sqrt(cos)
    assert np.allclose(s.sigma, sigma_model, rtol=1e-9)
    # Flying pixels (where the plate leaves the 10 m range) are not range noise.
    surface = ~s.flying
    residual = (np.linalg.norm(s.points, axis=1) - true_r - 1.0e-3)[surface]  # minus the bias
    z = residual / sigma_model[surface]
    assert len(z) > 50_000 and np.ptp(cos[surface]) > 0.3
    assert np.std(z) == pytest.approx(1.0, rel=0.02)
    assert abs(np.mean(z)) < 4 / np.sqrt(len(z))
    # Near the boresight (r ≈ distance, cos θ ≈ cos 40°) the spread is the model's at that range.
    centre = np.all(np.abs(rays[surface, :2]) < 0.03, axis=1)
    expected = (1.2e-3 + 2.0e-3 * distance**2) / np.sqrt(np.cos(np.radians(40.0)))
    assert centre.sum() > 150
    assert np.std(residual[centre]) == pytest.approx(expected, rel=4 / np.sqrt(2 * centre.sum()))


def test_weak_returns_are_noisier_or_lost() -> None:
    cfg = sensor_config("tof-paper", dropout=0.0, range_bias=0.0, **SMALL_TOF)
    scene = _plane(1.5)
    faces = len(scene.faces)
    bright = scan(scene, cfg, np.random.default_rng(3), np.ones(faces))
    dark = scan(scene, cfg, np.random.default_rng(3), np.full(faces, 0.25))
    # Same pixels, a quarter of the amplitude: twice the σ (shot noise, γ = 1/2).
    assert np.array_equal(bright.pixel, dark.pixel)
    assert np.allclose(dark.sigma, 2.0 * bright.sigma, rtol=1e-12)
    true_r = _true_ranges(scene, cfg, dark.pixel)
    errors = [np.linalg.norm(x.points, axis=1) - true_r for x in (bright, dark)]
    assert np.allclose(errors[1], 2.0 * errors[0], atol=1e-12)  # same draws, twice the σ
    assert np.std(errors[1] / dark.sigma) == pytest.approx(1.0, rel=0.02)
    # Below min_amplitude (0.05) nothing comes back.
    assert len(scan(scene, cfg, np.random.default_rng(3), np.full(faces, 0.04)).points) == 0


# --------------------------------------------------------------------------------------------
# Flying pixels


def _plate_scene(distance: float) -> trimesh.Trimesh:
    """A 1 m square plate at ``distance`` with nothing behind it."""
    return trimesh.creation.box(bounds=[(-0.5, -0.5, distance), (0.5, 0.5, distance + 0.1)])


@pytest.mark.parametrize(
    ("preset", "tail", "distance", "extra"),
    [("tof-paper", 0.10, 1.5, SMALL_TOF), ("flash-lidar-edges", 0.4, 3.0, {})],
)
def test_flying_pixels_trail_behind_silhouettes_against_no_return(
    preset, tail, distance, extra
) -> None:
    cfg = sensor_config(preset, **{**QUIET, "flying_probability": 0.5}, **extra)
    scene = _plate_scene(distance)
    s = scan(scene, cfg, np.random.default_rng(4))
    true_r = _true_ranges(scene, cfg, s.pixel)
    excess = np.linalg.norm(s.points, axis=1) - true_r
    assert np.all(np.abs(excess[~s.flying]) < 1e-12)  # the rest lie on the plate
    assert np.all((excess[s.flying] >= 0) & (excess[s.flying] < tail))
    assert np.mean(excess[s.flying]) == pytest.approx(0.5 * tail, rel=0.2)
    # Flying pixels are exactly the returns next to a pixel without return, about half of them.
    clean = scan(scene, cfg.model_copy(update={"noise_scale": 0.0}), None)
    missing = np.ones(cfg.width * cfg.height, dtype=bool)
    missing[clean.pixel] = False
    image = missing.reshape(cfg.height, cfg.width)
    silhouette = ndimage.maximum_filter(image, 3, mode="nearest").ravel() & ~missing
    assert np.all(silhouette[s.pixel[s.flying]])
    n_edge = int(silhouette.sum())
    assert n_edge > 100
    assert abs(s.flying.sum() - 0.5 * n_edge) < 4 * np.sqrt(0.25 * n_edge)
    assert s.flying.sum() < 0.05 * len(s.points)


def test_clean_flash_lidar_has_no_flying_pixels_at_silhouettes() -> None:
    s = scan(_plate_scene(3.0), sensor_config("flash-lidar"), np.random.default_rng(4))
    assert len(s.points) > 1000 and not s.flying.any()


def test_an_oblique_surface_is_no_depth_edge_for_a_coarse_sensor() -> None:
    # At 25 m a flash-LiDAR pixel is 8 cm wide: a wall at 60° steps ~30 cm across a 3×3 window,
    # more than the 5 cm jump, less than the 12 pixel footprints of flying_jump_pixels.
    scene = _plane(25.0, 60.0, half=200.0)
    edges = sensor_config("flash-lidar-edges", **{**QUIET, "flying_probability": 0.5})
    assert not scan(scene, edges, np.random.default_rng(6)).flying.any()
    absolute = edges.model_copy(update={"flying_jump_pixels": 0.0})
    assert scan(scene, absolute, np.random.default_rng(6)).flying.mean() > 0.3


# --------------------------------------------------------------------------------------------
# Multipath


def _step_scene() -> trimesh.Trimesh:
    """A floor 0.3 m below the sensor and a 0.2 m high box on it, its front face at z = 1.5.

    Concave crease: where the box's front face meets the floor (its side faces turn away from
    the sensor, so their creases are hidden). Convex edge: the box's top front edge (y = 0.1).
    """
    floor = trimesh.creation.box(bounds=[(-3.0, 0.3, 0.5), (3.0, 0.35, 4.0)])
    box = trimesh.creation.box(bounds=[(-0.3, 0.1, 1.5), (0.3, 0.3, 2.0)])
    return trimesh.util.concatenate([floor, box])


def _distance_to_segment(p: np.ndarray, a, b) -> np.ndarray:
    a, b = np.asarray(a, float), np.asarray(b, float)
    t = np.clip((p - a) @ (b - a) / np.dot(b - a, b - a), 0.0, 1.0)
    return np.linalg.norm(p - (a + t[:, None] * (b - a)), axis=1)


def test_multipath_bias_is_positive_and_only_near_concave_creases() -> None:
    bias, length = 5e-3, 0.02
    cfg = sensor_config(
        "tof-paper", **{**QUIET, "multipath_bias": bias, "multipath_length": length}, **SMALL_TOF
    )
    scene = _step_scene()
    s = scan(scene, cfg, np.random.default_rng(5))
    true_r = _true_ranges(scene, cfg, s.pixel)
    surface = s.points / np.linalg.norm(s.points, axis=1, keepdims=True) * true_r[:, None]
    # The measured range is the true range plus the reported bias (no noise here).
    assert np.allclose(np.linalg.norm(s.points, axis=1) - true_r, s.bias, atol=1e-12)
    assert np.all(s.bias >= 0) and s.bias.max() == pytest.approx(bias, rel=1e-9)
    to_crease = _distance_to_segment(surface, (-0.3, 0.3, 1.5), (0.3, 0.3, 1.5))
    footprint = true_r / cfg.focal_px
    biased = s.bias > 0
    assert biased.sum() > 500
    # Only near the creases (8 decay lengths, plus a pixel for the crease pixels' offset)...
    assert np.all(to_crease[biased] <= 8 * length + 2 * footprint[biased])
    # ... every return there, decaying with distance as the model says, the full bias on them.
    near = to_crease < 6 * length
    assert np.mean(biased[near]) > 0.98
    on = to_crease < footprint  # the pixels next to the crease line
    assert on.sum() > 50 and np.all(s.bias[on] > bias * np.exp(-2.0 * footprint[on] / length))
    model = bias * np.exp(-to_crease / length)
    inner = near & (to_crease > 3 * footprint)
    assert np.allclose(s.bias[inner], model[inner], atol=0.15 * bias)
    # The convex top edge of the box, far from every crease, gets none.
    convex = _distance_to_segment(surface, (-0.3, 0.1, 1.5), (0.3, 0.1, 1.5)) < 0.02
    assert convex.sum() > 50 and np.all(s.bias[convex & (to_crease > 8 * length + 0.01)] == 0)


# --------------------------------------------------------------------------------------------
# The raw lab frame


def test_paper_profile_raw_lab_frame_has_the_papers_normal_consistency() -> None:
    shares = {}
    for profile in ("tof-clean", "tof-paper"):
        frame = simulate_lab(LabConfig(frames=1, sensor=sensor_config(profile))).frame(0)
        shares[profile] = frame_normal_consistency(frame.cloud).share_below_20
    # Li et al.'s raw frame: about 20 % within 20°; five seeds gave 0.204 ± 0.003 here.
    assert shares["tof-paper"] == pytest.approx(PAPER_RAW_SHARE_BELOW_20, abs=0.03)
    assert shares["tof-clean"] > 0.7


def test_same_seed_same_frames_with_every_artefact() -> None:
    def frame(seed: int, k: int):
        config = grid_scenario(
            motion="tumbling-5", clutter="wall-table", seed=seed, frames=3, sensor="tof-paper"
        ).model_copy(update={"sensor": sensor_config("tof-paper", **SMALL_TOF)})
        return simulate_lab(config).frame(k)

    a, b, c = frame(2, 1), frame(2, 1), frame(3, 1)
    assert np.array_equal(a.cloud.points, b.cloud.points) and np.array_equal(a.flying, b.flying)
    assert a.flying.any() and a.on_target.any() and not a.on_target.all()
    assert a.cloud.points.shape != c.cloud.points.shape or not np.array_equal(
        a.cloud.points, c.cloud.points
    )


def test_noise_shared_between_pixels_keeps_its_sigma_and_has_a_gaussians_correlation() -> None:
    """A camera that filters its depth: the range noise is white noise smoothed by a Gaussian
    of s pixels, rescaled to the profile's σ per pixel. Its correlation between pixels d apart
    is then exp(−d² / (4 s²)) (the autocorrelation of a Gaussian of s is one of s√2): 0.939
    at 1 pixel, 0.570 at 3 for s = 2."""
    cfg = sensor_config("tof", dropout=0.0, flying_probability=0.0, noise_correlation_px=2.0)
    scene = _plane(1.2)
    s = scan(scene, cfg, np.random.default_rng(5))
    true_r = _true_ranges(scene, cfg, s.pixel)
    z = np.full(cfg.width * cfg.height, np.nan)
    z[s.pixel] = (np.linalg.norm(s.points, axis=1) - true_r) / s.sigma
    image = z.reshape(cfg.height, cfg.width)[20:-20, 20:-20]
    assert np.nanstd(image) == pytest.approx(1.0, rel=0.05)
    for d, expected in ((1, np.exp(-1 / 16)), (3, np.exp(-9 / 16))):
        a, b = image[:, :-d].ravel(), image[:, d:].ravel()
        assert np.corrcoef(a, b)[0, 1] == pytest.approx(expected, abs=0.03)
