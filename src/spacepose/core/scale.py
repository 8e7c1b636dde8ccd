"""Lengths from the data: the scale every tracker length is a multiple of (docs/methods.md §5.1).

A tracker tuned in metres works at one range with one sensor. Here the lengths read from a
frame are its *point spacing* ``s`` (median nearest-neighbour distance of the raw points), with
the number of points N the visible area ``A ≈ N s²`` it implies, and its *range noise* σ_r
(:func:`range_noise`). The voxel edge is then

    v = min(max(v_s, 1.5 σ_r), 2 v_s),   v_s = max(s, sqrt(A / n_target))

so that a frame keeps about ``n_target`` points after downsampling whatever its range or
resolution (the time per frame stays bounded), never a voxel finer than the sensor's own
sampling, and none much thinner than the noise. A voxel thinner than the noise slices the noisy
surface instead of averaging it: each centroid's depth is held inside its cell, and two frames'
centroids then match best at zero motion (lab mock-up and satellite_panels at 6 m with three
times the ToF noise, constant and accelerating motion, seeds 0-2: σ_r 52-60 mm against voxels
of 44-60 mm; a fixed 80 mm voxel took the mean rotation error from 0.53 to 0.34° and the frames
beyond 5σ flagged ``ok`` from 34 to 15 of 132). The noise may at most double the voxel (a
quarter of the points kept), and only on a frame denser than ``n_target`` (v_s > s). Gates,
health bounds, keyframe thresholds and the σ floor are multiples of ``v`` or of the target's
RMS radius ``R``
(:class:`spacepose.core.tracker_config.TrackerConfig`). On the lab run at 1.2 m (s = 2.46 mm,
N = 18,277, σ_r = 1.2 mm) this gives v = 6.07 mm; at 2 m 6.1 mm, at 0.6 m 5.6 mm;
on the orbit run's flash-LiDAR frames at 25 m (s = 105 mm, N = 1,025), v = s.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree
from scipy.stats import chi2

from spacepose.core.cloud import as_points
from spacepose.errors import InputError

# Finest angle (rad) between neighbouring returns that a range sensor resolves, with margin: a
# survey scanner's finest step is 0.0005° (9e-6 rad), a ToF camera's pixel about 2e-3 rad.
MIN_SENSOR_ANGLE = 1e-6
# Query points of the spacing estimate: the median of 2,000 nearest-neighbour distances is
# within about 2 % of the full median (its standard error is ~1.25 σ/√n of a narrow spread).
_SPACING_SAMPLES = 2000

# Rays whose ranges measure a frame's noise for the plane search: the orbit run's sparse
# frames (about 1,000 points, an object 30 pixels across) put edges into most larger
# neighbourhoods; with 16 the 1 cm noise read 1.5-2.4 cm, with 6 1.1-1.2 cm (3 cm: 3.1-3.2).
_PLANE_NOISE_NEIGHBOURS = 6
# Median of sqrt(χ²_ν / ν), ν = k − 3: what range_noise reads for σ = 1 (0.888 for k = 6).
_PLANE_NOISE_DOF = _PLANE_NOISE_NEIGHBOURS - 3
_PLANE_NOISE_MEDIAN = math.sqrt(chi2.median(_PLANE_NOISE_DOF) / _PLANE_NOISE_DOF)
# A range noise is taken when its 3σ slab is under a tenth of the frame's RMS radius.
_PLANE_NOISE_SHARE = 30.0
# Neighbours in direction of the range-noise estimate: a plane in three unknowns leaves 13
# degrees of freedom per point.
_NOISE_NEIGHBOURS = 16
# Points indexed in direction at most (a seeded subset of a denser frame).
_NOISE_INDEX_POINTS = 100_000
# The voxel spans at least this many range-noise σ, and the noise grows it by at most this
# factor (a quarter of the points kept: a registration still has hundreds).
NOISE_VOXELS = 1.5
_MAX_NOISE_GROWTH = 2.0
# A frame whose range noise (the spread along neighbouring rays) is this share of the spread of
# all its ranges has no surface: uniform and Gaussian clouds of random points give 0.93-0.99,
# every first frame of the robustness grid and of 141 third-party renders (debris, plates,
# rocket bodies, satellites at 5-40 m, flying pixels) at most 0.82 (a bent plate at 40 m
# in fewer than 100 points), most below 0.3.
SURFACELESS_SPREAD = 0.9


@dataclass(frozen=True)
class DataScale:
    """The lengths a tracker derives from its first frame.

    Attributes
    ----------
    spacing
        Median nearest-neighbour distance of the raw points (m).
    points
        Number of raw points the scale was measured on.
    voxel
        Voxel edge of the downsampling (m).
    radius
        RMS distance of the downsampled points from their centroid (m): the target's size.
    noise
        Range noise σ of the raw points (m, :func:`range_noise`).
    range_spread
        Standard deviation of the raw points' ranges (m); None when not measured.
    """

    spacing: float
    points: int
    voxel: float
    radius: float
    noise: float = 0.0
    range_spread: float | None = None

    @property
    def surfaceless(self) -> bool:
        """Whether the ranges along neighbouring rays spread nearly as much as the ranges of
        the whole frame (:data:`SURFACELESS_SPREAD`): points filling a volume, with no surface
        for a registration to hold on to."""
        spread = self.range_spread
        return spread is not None and self.noise > SURFACELESS_SPREAD * spread > 0.0

    def to_dict(self) -> dict[str, float]:
        return {
            "spacing_m": self.spacing,
            "points": self.points,
            "voxel_m": self.voxel,
            "radius_m": self.radius,
            "range_noise_m": self.noise,
            "range_spread_m": self.range_spread,
        }


def point_spacing(points: ArrayLike, samples: int = _SPACING_SAMPLES, seed: int = 0) -> float:
    """Median distance (m) from a point to its nearest neighbour.

    Parameters
    ----------
    points
        (N, 3) points, N ≥ 2.
    samples
        Query points drawn (seeded, without replacement) when N is larger; each is searched
        against all N points, so the estimate is unbiased.
    seed
        Seed of that draw.

    Raises
    ------
    InputError
        Fewer than two points, every point at one place, or ``samples`` not a whole number
        >= 1 (-1 ended in numpy's 'negative dimensions', 1.5 in a TypeError, NaN was ignored).
    """
    samples = _check_count("samples", samples)
    pts = as_points(points)
    if len(pts) < 2:
        raise InputError(f"{len(pts)} point(s): a spacing needs at least two")
    query = pts
    if len(pts) > samples:
        pick = np.random.default_rng(seed).choice(len(pts), samples, replace=False)
        query = pts[np.sort(pick)]
    # An unbalanced tree builds in about two thirds of the time, the same distances (a 70k-point
    # LiDAR scan: 10 against 15 ms). Not the grid index: a sparse far cluster (an Earth behind
    # the target) took its queries from 7 to 173 ms.
    tree = cKDTree(pts, balanced_tree=False, compact_nodes=False)
    d, _ = tree.query(query, k=2)
    spacing = float(np.median(d[:, 1]))
    if not spacing > 0:
        # Over half the points repeated (a sensor writing each return twice): the distance to
        # the nearest *other* place, among the 8 nearest.
        d, _ = tree.query(query, k=min(8, len(pts)))
        nonzero = np.where(d > 0, d, np.inf).min(axis=1)
        nonzero = nonzero[np.isfinite(nonzero)]
        if not len(nonzero):
            raise InputError("every point is at the same place: no spacing")
        spacing = float(np.median(nonzero))
    return spacing


def range_noise(
    points: ArrayLike, samples: int = _SPACING_SAMPLES, k: int = _NOISE_NEIGHBOURS, seed: int = 0
) -> float:
    """Robust σ (m) of the range noise of a frame in its sensor frame (the sensor at the origin).

    Each sampled point's neighbours are taken *in direction* (the adjacent pixels or beams), and
    a plane is fitted to their ranges over the two angles: the residuals' spread is the noise
    along the rays. Neighbours in space would not do: once the noise is wider than the spacing,
    a neighbourhood is thicker than it is wide and its flattest direction is no longer the
    surface's normal (the lab at 6 m, three times the ToF noise: 16 mm from 16 neighbours in
    space, 52 mm in direction, the simulator's σ 55 mm). Edges and silhouettes give large
    spreads; the median over the samples leaves them out.

    A cloud not seen from its origin (points sampled all over a closed model, a cloud moved into
    another frame) has direction neighbours on several surfaces, and the spread is theirs, not
    the noise's (130 mm for 3 mm of noise on the tests' tumbling model):
    :func:`derive_scale` bounds what the estimate can do to the voxel.

    Parameters
    ----------
    points
        (N, 3) points in the sensor frame; points at the origin (no return) are left out.
    samples, seed
        Points sampled (seeded, without replacement) when there are more.
    k
        Neighbours in direction of each sample (>= 4).

    Returns
    -------
    float
        The median over the samples of ``sqrt(Σ e² / (k − 3))`` (the median of a χ with 13
        degrees of freedom is 0.97 of its σ); 0 with fewer than ``k`` points.
    """
    if k < 4:
        raise InputError(f"range noise needs k >= 4 neighbours (a plane and a residual), got {k}")
    samples = _check_count("samples", samples)
    pts = as_points(points)
    ranges = np.linalg.norm(pts, axis=1)
    keep = ranges > 0
    pts, ranges = pts[keep], ranges[keep]
    if len(pts) < k:
        return 0.0
    rng = np.random.default_rng(seed)
    if len(pts) > _NOISE_INDEX_POINTS:
        # A seeded share of a dense frame: neighbours a few pixels apart instead of adjacent
        # fit the same plane, and the index costs 0.1 s instead of 0.65 on a 1280×720 frame.
        keep = np.sort(rng.choice(len(pts), _NOISE_INDEX_POINTS, replace=False))
        pts, ranges = pts[keep], ranges[keep]
    u = pts / ranges[:, None]
    query = np.arange(len(pts))
    if len(pts) > samples:
        query = np.sort(rng.choice(len(pts), samples, replace=False))
    return _ray_spread(u, ranges, query, k)


def plane_range_sigma(points: ArrayLike) -> float | None:
    """The range noise σ (m) of a frame as the plane search takes it (its slab 3σ thick), or
    None when the frame does not show one.

    :func:`range_noise` over the fewest neighbours that fit a plane with a residual left
    (:data:`_PLANE_NOISE_NEIGHBOURS`), scaled to σ; a σ whose 3σ slab is not under a tenth of
    the frame's RMS radius is a frame of noise or a glitch, which reads as much as its own size
    (a slab as thick as the cloud finds no plane), and 0 is a frame without noise: None.
    """
    pts = as_points(points)
    sigma = plane_noise(pts)
    return sigma if 0 < _PLANE_NOISE_SHARE * sigma < rms_radius(pts) else None


def plane_noise(points: ArrayLike) -> float:
    """The range noise σ (m) :func:`plane_range_sigma` reads, before its test against the
    frame's size: 0 for a frame without noise."""
    return range_noise(as_points(points), k=_PLANE_NOISE_NEIGHBOURS) / _PLANE_NOISE_MEDIAN


def _ray_spread(
    u: NDArray[np.float64], ranges: NDArray[np.float64], query: NDArray[np.intp], k: int
) -> float:
    """Median σ (m) of the ranges about a plane over the two angles, k neighbours in direction
    (``u``: unit directions of the points) of each query point."""
    _, idx = cKDTree(u).query(u[query], k=k)
    # Angular offsets in a tangent basis of each sample's direction: range = a + b·x + c·y.
    u0 = u[query]
    e1 = np.cross(u0, np.where(np.abs(u0[:, :1]) < 0.9, [[1.0, 0.0, 0.0]], [[0.0, 1.0, 0.0]]))
    e1 /= np.linalg.norm(e1, axis=1, keepdims=True)
    e2 = np.cross(u0, e1)
    du = u[idx] - u0[:, None, :]
    X = np.stack(
        [np.ones(idx.shape), np.einsum("skj,sj->sk", du, e1), np.einsum("skj,sj->sk", du, e2)],
        axis=2,
    )
    y = ranges[idx]
    XtX = np.einsum("ski,skj->sij", X, X)
    Xty = np.einsum("ski,sk->si", X, y)
    solvable = np.linalg.cond(XtX) < 1e12
    coef = np.linalg.solve(XtX[solvable], Xty[solvable][..., None])[..., 0]
    e = y[solvable] - np.einsum("ski,si->sk", X[solvable], coef)
    if not len(e):
        return 0.0
    return float(np.median(np.sqrt(np.einsum("sk,sk->s", e, e) / (k - 3))))


def _check_count(name: str, value: int) -> int:
    """``value`` as an int: a count of points must be a whole number >= 1 (2000.0 passes)."""
    try:
        whole = not isinstance(value, bool) and float(value).is_integer() and value >= 1
    except (TypeError, ValueError, OverflowError):
        whole = False
    if not whole:
        raise InputError(f"{name} must be a whole number >= 1, got {value!r}")
    return int(value)


def voxel_for(spacing: float, n_points: int, target_points: int) -> float:
    """Voxel edge (m) that leaves about ``target_points`` of a surface sampled at ``spacing``."""
    area = n_points * spacing**2
    return max(spacing, math.sqrt(area / target_points))


def rms_radius(points: NDArray[np.float64]) -> float:
    """RMS distance (m) of (N, 3) points from their centroid."""
    centred = points - points.mean(axis=0)
    return float(np.sqrt((centred**2).sum(axis=1).mean()))


def model_size_ratio(model: ArrayLike, frame: ArrayLike) -> float:
    """RMS radius of a model's points (N, 3) over a frame's returns' (M, 3; rows at the origin
    are no returns), or NaN with fewer than two returns. A view sees part of its target, not a
    fifth of it: five or more says another unit (the model in centimetres); a frame is larger
    than its target's model by its clutter, so below one says little alone."""
    frame = as_points(frame)
    seen = frame[frame.any(axis=1)]
    if len(seen) < 2:
        return float("nan")
    return rms_radius(as_points(model)) / rms_radius(seen)


def sensor_frame_problem(points: ArrayLike, spacing: float) -> str:
    """Why ``points`` (N, 3) cannot have been measured by a sensor at their frame's origin, or
    "" when they can: neighbours ``spacing`` (m) apart at their median range subtend an angle
    finer than any range sensor resolves (:data:`MIN_SENSOR_ANGLE`). A frame moved 10 km out
    (a world frame) lost every frame after the first ("the pose graph edges leave a free node
    unconstrained"), which named neither the cause nor the frame."""
    r = float(np.median(np.linalg.norm(as_points(points), axis=1)))
    if not r > 0 or spacing / r >= MIN_SENSOR_ANGLE:
        return ""
    return (
        f"the points are {r:.3g} m from the origin yet {spacing:.2g} m apart ({spacing / r:.1g} "
        "rad, finer than any range sensor resolves): the tracker takes the origin as the "
        "sensor; give the clouds in the sensor's frame"
    )


def derive_scale(
    points: ArrayLike, target_points: int, voxel_size: float | None = None
) -> DataScale:
    """The scale of a frame: its spacing, range noise, the voxel edge (the module's rule) and
    (after downsampling) its radius.

    Parameters
    ----------
    points
        (N, 3) raw points of the frame (sensor frame, m).
    target_points
        Points a frame should keep after downsampling (``n_target`` above).
    voxel_size
        A voxel edge (m) to use instead of the derived one.

    Raises
    ------
    InputError
        ``target_points`` is not a whole number >= 1 (0 ended in ZeroDivisionError, a negative
        count in 'math domain error', NaN gave the spacing as the voxel without a word), or as
        :func:`point_spacing` and :func:`~spacepose.core.voxel.voxel_cells`; a ``voxel_size``
        wider than the frame.
    """
    from spacepose.core.voxel import voxel_cells

    target_points = _check_count("target_points", target_points)
    pts = as_points(points)
    spacing = point_spacing(pts)
    noise = range_noise(pts)
    voxel = voxel_size
    if voxel is not None and voxel > (extent := float(np.max(np.ptp(pts, axis=0)))):
        # One voxel would hold the whole frame: said so, not as "4 points after preprocessing".
        raise InputError(
            f"the configured voxel_size {voxel:g} m is wider than the frame ({extent:.3g} m "
            "across)",
            getattr(points, "source", None),
        )
    if voxel is None:
        voxel = voxel_for(spacing, len(pts), target_points)
        if voxel > spacing:
            # Only where voxels average several points: a frame sparser than ``target_points``
            # keeps its spacing (and a voxel grown there would leave too few points).
            voxel = min(max(voxel, NOISE_VOXELS * noise), _MAX_NOISE_GROWTH * voxel)
    centroids, _ = voxel_cells(pts, voxel)
    ranges = np.linalg.norm(pts, axis=1)
    spread = float(ranges[ranges > 0].std()) if np.any(ranges > 0) else 0.0
    return DataScale(spacing, len(pts), voxel, rms_radius(centroids), noise, spread)
