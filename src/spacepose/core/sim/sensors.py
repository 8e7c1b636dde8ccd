"""Range sensors for the simulator (methods.md §3): pinhole ray casting, range noise, artefacts.

One ray per pixel is cast from the sensor origin against a triangle mesh already posed in the
sensor frame (embree through trimesh, first hit per ray). The hit range is then recomputed in
float64 from the hit triangle's plane, because embree works in float32 and a noise-free point
must lie on the surface to ~1e-12 m, not ~1e-7 m. Noise and artefacts are drawn from a generator
the caller seeds, always over every pixel, so a frame depends only on its seed.

Noise profiles. ``tof-clean`` and ``flash-lidar-clean`` are range noise growing with range,
dropouts and (ToF) flying pixels between two returns. ``tof-paper`` is a camera like the one of
Li et al.: its raw lab frame has about as few consistent neighbouring normals as theirs (about
20 % within 20°, :mod:`spacepose.core.cloud_quality`). On top of the clean model it has
amplitude-dependent noise (a return's amplitude is ``albedo·|cos θ|``; σ grows as its inverse
square root, as for shot noise, and returns weaker than ``min_amplitude`` are lost), multipath
excess near concave creases, flying pixels at silhouettes against empty space and a small
systematic range bias (:mod:`spacepose.core.sim.artefacts`). ``flash-lidar-edges`` adds flying
pixels at the silhouettes to the flash LiDAR. ``tof`` and ``flash-lidar`` name the profile each
scenario uses by default (:data:`DEFAULT_PROFILES`).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass
from typing import Literal

import numpy as np
import trimesh
from numpy.typing import NDArray
from pydantic import Field, model_validator
from trimesh.ray.ray_pyembree import RayMeshIntersector

from spacepose.core.config import StageConfig, validate_config
from spacepose.core.crlb import range_sigma_along_normal
from spacepose.core.sim.artefacts import (
    concave_creases,
    correlated_noise,
    flying_pixels,
    multipath_excess,
)
from spacepose.errors import ConfigError

SensorModel = Literal["tof", "flash-lidar", "gaussian"]
# A float64 hit this far outside its triangle (in barycentric units) is a graze, not a hit.
_BARYCENTRIC_TOL = 1e-12
# Largest noise σ (m): a frame's draws stay within 10σ, and its noisy points within float32,
# in which a run's frames are written (a noise_scale of 1e300 failed at frame 0 on "points
# reach |coordinate| 5.4e+297", 1e40 on writing the frame, naming neither the option nor σ).
_LARGEST_SIGMA = float(np.finfo(np.float32).max) / 10


class SensorConfig(StageConfig):
    """A pinhole range sensor; the defaults are the ``tof`` camera of methods.md §3.

    Noise: ``σ(r, a) = noise_scale · (sigma_const + sigma_quad · (r / 1 m)²) · a^−γ`` metres,
    along the ray for ``tof`` and ``flash-lidar``, on each of x, y, z for ``gaussian``; ``a =
    max(albedo·|cos θ|, min_amplitude)`` is the return's relative amplitude and ``γ =
    amplitude_exponent``. ``noise_scale = 0`` gives noise-free frames without dropouts, flying
    pixels, biases or lost weak returns; the biases do not scale with ``noise_scale``.
    """

    model: SensorModel = "tof"
    width: int = Field(640, ge=1, description="Image columns.")
    height: int = Field(480, ge=1, description="Image rows.")
    focal_px: float = Field(483.6, gt=0, description="Focal length, pixels (square pixels).")
    min_range: float = Field(0.3, ge=0, description="Shortest range returned, m.")
    max_range: float = Field(10.0, gt=0, description="Longest range returned, m.")
    sigma_const: float = Field(0.5e-3, ge=0, description="Constant term of σ(r), m.")
    sigma_quad: float = Field(0.5e-3, ge=0, description="Quadratic term of σ(r) at 1 m, m.")
    dropout: float = Field(0.01, ge=0, le=1, description="Share of hit pixels lost.")
    flying_jump: float = Field(0.05, gt=0, description="Depth jump in a 3×3 window, m.")
    flying_jump_pixels: float = Field(
        0.0,
        ge=0,
        description="Depth jump in pixel footprints (r / focal_px), if larger than flying_jump; "
        "an oblique surface of a coarse sensor is not an edge.",
    )
    flying_probability: float = Field(
        0.5, ge=0, le=1, description="Chance an edge pixel mixes the two depths."
    )
    noise_scale: float = Field(1.0, ge=0, description="Multiplier of σ; 0 = noise-free.")
    amplitude_exponent: float = Field(
        0.0, ge=0, description="γ: σ grows as amplitude^−γ (0.5 for shot noise; 0 = off)."
    )
    min_amplitude: float = Field(
        0.0, ge=0, le=1, description="Weakest return kept (albedo·|cos θ|); also σ's floor."
    )
    range_bias: float = Field(0.0, description="Systematic range offset of every return, m.")
    wiggle_amplitude: float = Field(
        0.0,
        ge=0,
        description="Amplitude of a range offset periodic in range (an AMCW ToF camera's "
        "wiggling: its modulation's harmonics), m.",
    )
    wiggle_period: float = Field(1.9, gt=0, description="Period in range of the wiggling, m.")
    multipath_bias: float = Field(0.0, ge=0, description="Range excess at a concave crease, m.")
    multipath_length: float = Field(
        0.01, gt=0, description="Decay length of the multipath excess away from the crease, m."
    )
    flying_tail: float = Field(
        0.0, ge=0, description="Largest range excess of a flying pixel at a bare silhouette, m."
    )
    noise_correlation_px: float = Field(
        0.0,
        ge=0,
        le=50,
        description="Range noise shared over a Gaussian of this many pixels "
        "(a camera's spatial filter); 0: white per pixel.",
    )

    @model_validator(mode="after")
    def _amplitude_floor(self) -> SensorConfig:
        if self.amplitude_exponent > 0 and self.min_amplitude == 0:
            raise ValueError("amplitude_exponent > 0 needs min_amplitude > 0 (σ would be infinite)")
        return self

    @model_validator(mode="after")
    def _noise_stays_finite(self) -> SensorConfig:
        """Refuse a σ (at ``max_range``, on the weakest return) whose noisy points overflow
        float32, in which a run's frames are written."""
        if self.noise_scale == 0:
            return self
        try:
            weakest = self.min_amplitude**-self.amplitude_exponent if self.min_amplitude else 1.0
        except OverflowError:
            weakest = math.inf
        base = self.sigma_const + self.sigma_quad * self.max_range * self.max_range
        sigma = self.noise_scale * base * weakest
        if not sigma <= _LARGEST_SIGMA:  # inf, and NaN of inf * 0, alike
            raise ValueError(
                f"noise_scale {self.noise_scale:g} makes σ {sigma:.3g} m at max_range "
                f"{self.max_range:g} m, beyond {_LARGEST_SIGMA:.3g} m: the noisy points would "
                "overflow float32, in which a run's frames are written"
            )
        return self

    @property
    def fov_deg(self) -> tuple[float, float]:
        """Horizontal and vertical field of view, degrees."""
        return tuple(  # type: ignore[return-value]
            math.degrees(2 * math.atan(0.5 * n / self.focal_px)) for n in (self.width, self.height)
        )


def _focal_for_fov(pixels: int, fov_deg: float) -> float:
    return 0.5 * pixels / math.tan(math.radians(0.5 * fov_deg))


_TOF_CLEAN = SensorConfig()
_FLASH_CLEAN = SensorConfig(
    model="flash-lidar",
    width=160,
    height=160,
    focal_px=_focal_for_fov(160, 30.0),
    min_range=0.5,
    max_range=200.0,
    sigma_const=0.01,
    sigma_quad=0.0,
    dropout=0.0,
    flying_probability=0.0,
)
# The profile each sensor kind means by default; switching the lab to the paper-like camera is
# changing "tof-clean" to "tof-paper" here.
DEFAULT_PROFILES = {"tof": "tof-clean", "flash-lidar": "flash-lidar-clean"}
_PROFILES: dict[str, SensorConfig] = {
    "tof-clean": _TOF_CLEAN,
    # Li et al.'s camera: σ = 4.1 mm / sqrt(a) at 1.2 m (set so that the raw lab frame's
    # normal consistency is near the paper's), multipath at inner corners, silhouette tails;
    # a depth edge is a jump of 5 cm or 12 pixel footprints, whichever is larger.
    "tof-paper": _TOF_CLEAN.model_copy(
        update={
            "sigma_const": 1.2e-3,
            "sigma_quad": 2.0e-3,
            "amplitude_exponent": 0.5,
            "min_amplitude": 0.05,
            "range_bias": 1.0e-3,
            "multipath_bias": 5.0e-3,
            "multipath_length": 0.015,
            "flying_tail": 0.10,
            "flying_jump_pixels": 12.0,
        }
    ),
    "flash-lidar-clean": _FLASH_CLEAN,
    # A partly covered pixel at the silhouette returns a weak echo placed up to 0.4 m farther.
    "flash-lidar-edges": _FLASH_CLEAN.model_copy(
        update={"flying_probability": 0.5, "flying_tail": 0.4, "flying_jump_pixels": 12.0}
    ),
    "gaussian": SensorConfig(
        model="gaussian", sigma_const=1e-3, sigma_quad=0.0, dropout=0.0, flying_probability=0.0
    ),
}
SENSOR_PRESETS: dict[str, SensorConfig] = {
    **{kind: _PROFILES[profile] for kind, profile in DEFAULT_PROFILES.items()},
    **_PROFILES,
}


def sensor_config(name: str, **overrides: object) -> SensorConfig:
    """The preset ``name`` with fields overridden.

    Presets: ``tof-clean``, ``tof-paper``, ``flash-lidar-clean``, ``flash-lidar-edges``,
    ``gaussian``; ``tof`` and ``flash-lidar`` are the profiles of :data:`DEFAULT_PROFILES`.

    Raises
    ------
    ConfigError
        Unknown sensor name or an invalid override.
    """
    if name not in SENSOR_PRESETS:
        raise ConfigError(f"unknown sensor {name!r}; choose one of: {', '.join(SENSOR_PRESETS)}")
    data = SENSOR_PRESETS[name].model_dump() | overrides
    return validate_config(SensorConfig, data, source=f"sensor {name}")


def sigma_at(
    config: SensorConfig,
    ranges: NDArray[np.float64],
    amplitude: NDArray[np.float64] | None = None,
) -> NDArray[np.float64]:
    """Noise σ (m) at the given ranges (m), noise_scale included.

    ``amplitude`` (same shape, ``albedo·|cos θ|``) enters only when ``amplitude_exponent > 0``;
    it is floored at ``min_amplitude``.
    """
    sigma = config.noise_scale * (config.sigma_const + config.sigma_quad * np.square(ranges))
    if config.amplitude_exponent > 0 and amplitude is not None:
        a = np.maximum(amplitude, config.min_amplitude)
        sigma = sigma * a ** (-config.amplitude_exponent)
    return sigma


def pixel_directions(config: SensorConfig) -> NDArray[np.float64]:
    """Unit ray directions (H·W, 3) in the sensor frame, row-major (row v, then column u).

    Pinhole model with the principal point at the image centre; z is the boresight, x right,
    y down (methods.md §0). Read-only and cached: every frame of a run casts the same rays.
    """
    return _pixel_directions(config.width, config.height, config.focal_px)


@functools.lru_cache(maxsize=4)
def _pixel_directions(width: int, height: int, focal_px: float) -> NDArray[np.float64]:
    u = np.arange(width) - 0.5 * (width - 1)
    v = np.arange(height) - 0.5 * (height - 1)
    uu, vv = np.meshgrid(u, v)
    d = np.column_stack([uu.ravel(), vv.ravel(), np.full(uu.size, focal_px)])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    d.setflags(write=False)
    return d


def _ray_triangle(
    tri: NDArray[np.float64], d: NDArray[np.float64]
) -> tuple[NDArray[np.float64], NDArray[np.bool_]]:
    """Möller–Trumbore for rays from the origin, float64, broadcast over leading axes.

    ``tri`` (..., 3, 3) and ``d`` (..., 3) broadcast together; returns the range along each ray
    (NaN for a ray parallel to its triangle) and whether the hit lies in the triangle, ahead.
    """
    e1, e2 = tri[..., 1, :] - tri[..., 0, :], tri[..., 2, :] - tri[..., 0, :]
    pvec = np.cross(d, e2)
    det = np.einsum("...i,...i->...", e1, pvec)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv = 1.0 / det
        tvec = -tri[..., 0, :]
        u = np.einsum("...i,...i->...", tvec, pvec) * inv
        qvec = np.cross(tvec, e1)
        v = np.einsum("...i,...i->...", d, qvec) * inv
        t = np.einsum("...i,...i->...", e2, qvec) * inv
        tol = _BARYCENTRIC_TOL
        inside = (u >= -tol) & (v >= -tol) & (u + v <= 1 + tol) & (t > 0) & np.isfinite(t)
    return t, inside


def cast_rays(
    mesh_sensor: trimesh.Trimesh, directions: NDArray[np.float64]
) -> tuple[NDArray[np.int64], NDArray[np.float64], NDArray[np.float64]]:
    """First hit of rays from the sensor origin on a mesh given in the sensor frame.

    Embree (float32) finds the hit face; the range is recomputed in float64 on that face. A ray
    that embree puts on a face it misses in float64 (it grazes an edge) is re-cast exactly
    against every face, so every returned point lies on the mesh to rounding error.

    Parameters
    ----------
    mesh_sensor
        The scene, sensor frame.
    directions
        (P, 3) unit ray directions, sensor frame.

    Returns
    -------
    face, ranges, normals
        (P,) hit face index or −1; (P,) exact range along the ray (inf on a miss); (P, 3) unit
        normal of the hit face turned towards the sensor (NaN on a miss).
    """
    face = RayMeshIntersector(mesh_sensor).intersects_first(np.zeros_like(directions), directions)
    face = np.asarray(face, dtype=np.int64)
    triangles = mesh_sensor.triangles
    ranges = np.full(len(directions), np.inf)
    hit = np.flatnonzero(face >= 0)
    t, inside = _ray_triangle(triangles[face[hit]], directions[hit])
    ranges[hit[inside]] = t[inside]
    graze = hit[~inside]
    # Few rays (edge pixels): test them against every face, in batches bounded in memory.
    batch = max(1, 2_000_000 // len(triangles))
    for start in range(0, len(graze), batch):
        rays = graze[start : start + batch]
        t_all, ok = _ray_triangle(triangles[None], directions[rays, None, :])
        t_all = np.where(ok, t_all, np.inf)
        best = np.argmin(t_all, axis=1)
        ranges[rays] = t_all[np.arange(len(rays)), best]
        face[rays] = np.where(np.isfinite(ranges[rays]), best, -1)
    hit = np.flatnonzero(np.isfinite(ranges))
    n = mesh_sensor.face_normals[face[hit]]
    normals = np.full(directions.shape, np.nan)
    normals[hit] = n * -np.sign(np.einsum("ij,ij->i", n, directions[hit]))[:, None]
    return np.where(np.isfinite(ranges), face, -1), ranges, normals


@dataclass(frozen=True, eq=False)
class Scan:
    """Raw output of one simulated sensor frame, before the scenario labels it.

    Attributes
    ----------
    points
        (N, 3) measured points, sensor frame.
    true_normals
        (N, 3) unit normals of the surfaces hit, towards the sensor, sensor frame.
    face
        (N,) index of the scene face each ray hit.
    sigma
        (N,) noise σ of each point (along the ray for range sensors, per axis for gaussian), m.
    sigma_normal
        (N,) noise σ along the true normal, ``σ·|cos θ|`` for range sensors, m.
    flying
        (N,) True for flying pixels (a mix of two depths: not on any surface).
    pixel
        (N,) row-major pixel index of each point.
    bias
        (N,) systematic range offset of each point (``range_bias``, the wiggling and the
        multipath excess; 0 on flying pixels' multipath), m; the measured range is true (or
        mixed) range + bias + noise.
    """

    points: NDArray[np.float64]
    true_normals: NDArray[np.float64]
    face: NDArray[np.int64]
    sigma: NDArray[np.float64]
    sigma_normal: NDArray[np.float64]
    flying: NDArray[np.bool_]
    pixel: NDArray[np.int64]
    bias: NDArray[np.float64]


def scan(
    mesh_sensor: trimesh.Trimesh,
    config: SensorConfig,
    rng: np.random.Generator | None,
    albedo: NDArray[np.float64] | None = None,
) -> Scan:
    """Simulate one frame of ``config`` looking at ``mesh_sensor`` (sensor frame).

    Steps: first hit per pixel; returns outside ``[min_range, max_range]`` and, for a noisy
    sensor, returns weaker than ``min_amplitude`` are lost; flying pixels at depth edges and
    silhouettes (:func:`~spacepose.core.sim.artefacts.flying_pixels`; only returns count as
    depths, so a pixel next to empty space flies only when ``flying_tail > 0``); the systematic
    range bias, the wiggling (of the true or mixed range) and the multipath excess near concave
    creases; range (or xyz) noise, σ evaluated at the true range and amplitude; dropouts. Missed
    and dropped rays are left out, so the output is not organised; ``Scan.pixel`` says where
    each point came from.

    Parameters
    ----------
    mesh_sensor
        The scene, sensor frame.
    config
        The sensor.
    rng
        Seeded generator; may be None only for a noise-free sensor.
    albedo
        (F,) reflectance of each face of ``mesh_sensor`` in (0, 1]; None = 1 everywhere.
    """
    if rng is None and config.noise_scale > 0:
        raise ConfigError("a noisy sensor needs a seeded random generator")
    directions = pixel_directions(config)
    face, true_range, normals = cast_rays(mesh_sensor, directions)
    hit = np.isfinite(true_range) & (true_range >= config.min_range)
    hit &= true_range <= config.max_range
    amplitude = np.abs(np.einsum("ij,ij->i", normals, directions))
    if albedo is not None:
        amplitude *= np.asarray(albedo, dtype=np.float64)[face]
    noisy = config.noise_scale > 0
    if noisy and config.min_amplitude > 0:
        hit &= amplitude >= config.min_amplitude
    returned = np.where(hit, true_range, np.inf)
    idx = np.flatnonzero(hit)
    r = true_range[idx]
    flying = np.zeros(len(idx), dtype=bool)
    shape = (config.height, config.width)
    # Draws only for the pixels that need them, in a fixed order: flying, dropout, noise.
    if noisy and config.flying_probability > 0:
        mixed = flying_pixels(
            returned,
            idx,
            shape,
            np.maximum(config.flying_jump, config.flying_jump_pixels / config.focal_px * r),
            config.flying_tail,
            config.flying_probability,
            rng,
        )
        r, flying = mixed.ranges, mixed.flying
    bias = np.zeros(len(idx))
    if noisy:
        bias += config.range_bias
        bias += config.wiggle_amplitude * np.sin(2 * np.pi * r / config.wiggle_period)
        if config.multipath_bias > 0:
            surface = directions * np.where(hit, true_range, np.nan)[:, None]
            crease = concave_creases(
                surface,
                np.where(hit[:, None], normals, np.nan),
                np.where(hit, face, -1),
                shape,
                config.focal_px,
            )
            excess = multipath_excess(
                surface[idx], surface[crease], config.multipath_bias, config.multipath_length
            )
            bias += np.where(flying, 0.0, excess)
    r = r + bias
    keep = rng.random(len(idx)) >= config.dropout if noisy else np.ones(len(idx), dtype=bool)
    idx, r, flying, bias = idx[keep], r[keep], flying[keep], bias[keep]
    d, n = directions[idx], normals[idx]
    sigma = sigma_at(config, true_range[idx], amplitude[idx])
    if config.model == "gaussian":
        points = d * r[:, None]
        if noisy:
            points += sigma[:, None] * rng.standard_normal((len(idx), 3))
        sigma_normal = sigma
    else:
        if noisy and config.noise_correlation_px > 0:
            r = r + sigma * correlated_noise(shape, config.noise_correlation_px, rng)[idx]
        elif noisy:
            r = r + sigma * rng.standard_normal(len(idx))
        points = d * r[:, None]
        sigma_normal = range_sigma_along_normal(sigma, d, n) if len(idx) else np.zeros(0)
    return Scan(points, n, face[idx], sigma, sigma_normal, flying, idx, bias)
