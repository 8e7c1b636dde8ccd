"""Range-camera artefacts for the simulator (methods.md §3): flying pixels, multipath and noise
shared between neighbouring pixels.

Both work on the organised image of true ranges a sensor sees before noise (row-major, one entry
per pixel, ``inf`` where a pixel has no return).

- **Flying pixels.** A pixel whose footprint straddles a depth edge returns a mix of the two
  depths. An edge pixel is a return whose 3×3 window of returns spans more than ``jump``
  (target in front of a farther surface), or, when ``tail > 0``, a return next to a pixel with
  no return at all (a silhouette against empty space). With probability ``probability`` it
  flies: in the first case its range becomes ``w·near + (1 − w)·far`` of its window, in the
  second ``r + w·tail`` (a partly covered pixel returns a weaker echo that the camera places
  farther along the same ray), ``w`` uniform in [0, 1).
- **Multipath.** Light that reaches a surface after bouncing off another surface facing it
  travels farther, so a ToF camera reads a longer range near concave creases (inner corners).
  A pixel lies on a concave crease when a neighbouring pixel on the same surface patch has a
  normal turned towards it: ``(n_j − n_i)·(p_j − p_i) < −t·|p_j − p_i|`` with ``t =
  CREASE_TURN`` (creases sharper than about 6°; coplanar neighbours give exactly 0, convex edges
  a positive value). Neighbours are on the same patch when their 3D gap is below
  ``CREASE_GAP_PIXELS`` pixel footprints (``r / f``), so a surface seen past an occluding edge
  (a depth step) is not a crease. Every return at 3D distance ``d`` from the nearest crease point
  reads ``bias·exp(−d / length)`` longer.
- **Spatially correlated noise.** Many depth cameras filter their depth maps before output
  (bilateral or median filters, phase unwrapping over a neighbourhood), so neighbouring pixels'
  errors are shared: :func:`correlated_noise` draws the pixels' standard normal noise as white
  noise smoothed by a Gaussian of ``correlation_px`` pixels (standard deviation), rescaled to
  unit variance per pixel; each return's noise is then ``σ`` times its pixel's value.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray
from scipy import ndimage
from scipy.spatial import cKDTree

# Minimum turn of the normal towards a neighbour, per unit of separation, for a concave crease.
CREASE_TURN = 0.1
# Largest gap between neighbouring pixels on one surface patch, in pixel footprints (a diagonal
# neighbour on a surface seen at up to 60° from its normal).
CREASE_GAP_PIXELS = 6.0
# Multipath excess is cut where exp(−d / length) < e^-8 (3e-4 of the edge value).
_MULTIPATH_CUTOFF = 8.0
# Neighbour offsets (row, column) that cover each pair of 8-connected pixels once.
_OFFSETS = ((0, 1), (1, 0), (1, 1), (1, -1))


@dataclass(frozen=True, eq=False)
class FlyingPixels:
    """Outcome of :func:`flying_pixels` for the returns of one frame.

    Attributes
    ----------
    ranges
        (N,) ranges of the returns after mixing, m (unchanged where a pixel does not fly).
    flying
        (N,) True where the pixel flies.
    """

    ranges: NDArray[np.float64]
    flying: NDArray[np.bool_]


def flying_pixels(
    true_range: NDArray[np.float64],
    idx: NDArray[np.int64],
    shape: tuple[int, int],
    jump: float | NDArray[np.float64],
    tail: float,
    probability: float,
    rng: np.random.Generator,
) -> FlyingPixels:
    """Mix the ranges of pixels at depth edges and silhouettes (see the module notes).

    Parameters
    ----------
    true_range
        (H·W,) true range per pixel, m; ``inf`` for a pixel without a return.
    idx
        (N,) row-major indices of the returns (where ``true_range`` is finite).
    shape
        ``(H, W)`` of the image.
    jump
        Depth span of a 3×3 window of returns that marks a depth edge, m: one number, or (N,)
        one per return.
    tail
        Largest range excess of a pixel next to a pixel without return, m; 0 = such a pixel does
        not fly.
    probability
        Chance that an edge pixel flies.
    rng
        Seeded generator; draws two uniforms per edge pixel, edge pixels in index order.
    """
    r = true_range[idx]
    img = np.full(true_range.shape, np.inf)
    img[idx] = r
    near = ndimage.minimum_filter(img.reshape(shape), 3).ravel()[idx]
    img[idx] = -r  # the maximum of the returns is minus the minimum of their negatives
    far = -ndimage.minimum_filter(img.reshape(shape), 3).ravel()[idx]
    depth_edge = far - near > jump
    edge_mask = depth_edge.copy()
    if tail > 0:
        missing = ~np.isfinite(true_range).reshape(shape)
        silhouette = ndimage.maximum_filter(missing, 3, mode="nearest").ravel()[idx]
        edge_mask |= silhouette
    edge = np.flatnonzero(edge_mask)
    u_fly, w_fly = rng.random((2, len(edge)))
    chosen = u_fly < probability
    fly, w = edge[chosen], w_fly[chosen]
    mixed = np.where(depth_edge[fly], w * near[fly] + (1.0 - w) * far[fly], r[fly] + w * tail)
    flying = np.zeros(len(idx), dtype=bool)
    flying[fly] = True
    ranges = r.copy()
    ranges[fly] = mixed
    return FlyingPixels(ranges, flying)


def concave_creases(
    points: NDArray[np.float64],
    normals: NDArray[np.float64],
    face: NDArray[np.int64],
    shape: tuple[int, int],
    focal_px: float,
) -> NDArray[np.bool_]:
    """Pixels on a concave crease of the true surface (see the module notes).

    Parameters
    ----------
    points
        (H·W, 3) true surface point per pixel, sensor frame, m; NaN without a return.
    normals
        (H·W, 3) unit surface normal per pixel, sensor frame; NaN without a return.
    face
        (H·W,) scene face hit per pixel (−1 without a return): only neighbours on different
        faces can straddle a crease, so only those pairs are tested.
    shape
        ``(H, W)`` of the image.
    focal_px
        Focal length, pixels: a pixel's footprint at range r is ``r / focal_px``.

    Returns
    -------
    (H·W,) True on a concave crease.
    """
    h, w = shape
    pixel = np.arange(h * w).reshape(h, w)
    crease = np.zeros(h * w, dtype=bool)
    for dv, du in _OFFSETS:
        ia = pixel[0 : h - dv, max(0, -du) : w - max(du, 0)].ravel()
        ib = pixel[dv:h, max(du, 0) : w - max(0, -du)].ravel()
        other = face[ia] != face[ib]
        ia, ib = ia[other], ib[other]
        dp, dn = points[ib] - points[ia], normals[ib] - normals[ia]
        gap = np.linalg.norm(dp, axis=1)
        max_gap = CREASE_GAP_PIXELS / focal_px * np.linalg.norm(points[ia], axis=1)
        with np.errstate(invalid="ignore"):
            pair = (np.einsum("ij,ij->i", dn, dp) < -CREASE_TURN * gap) & (gap < max_gap)
        crease[ia[pair]] = True
        crease[ib[pair]] = True
    return crease


def multipath_excess(
    points: NDArray[np.float64],
    crease_points: NDArray[np.float64],
    bias: float,
    length: float,
) -> NDArray[np.float64]:
    """Range excess ``bias·exp(−d / length)`` of each point, d its distance to the nearest crease.

    Parameters
    ----------
    points
        (N, 3) true surface points of the returns, m.
    crease_points
        (M, 3) true surface points of the concave-crease pixels, m (may be empty).
    bias, length
        Excess at the crease and its decay length, m.

    Returns
    -------
    (N,) non-negative range excess, m (0 beyond ``8·length`` from every crease).
    """
    excess = np.zeros(len(points))
    if len(crease_points) == 0 or bias == 0:
        return excess
    reach = _MULTIPATH_CUTOFF * length
    lo, hi = crease_points.min(axis=0) - reach, crease_points.max(axis=0) + reach
    near = np.flatnonzero(np.all((points >= lo) & (points <= hi), axis=1))
    d, _ = cKDTree(crease_points).query(points[near], distance_upper_bound=reach)
    excess[near] = np.where(np.isfinite(d), bias * np.exp(-d / length), 0.0)
    return excess


def correlated_noise(
    shape: tuple[int, int], correlation_px: float, rng: np.random.Generator
) -> NDArray[np.float64]:
    """(H·W,) standard normal noise per pixel (row-major), shared between neighbours over a
    Gaussian of ``correlation_px`` pixels (standard deviation; 0: white).

    The white image is smoothed and divided by the kernel's root sum of squares, so that every
    pixel's variance is 1 away from the border (reflected there).
    """
    white = rng.standard_normal(shape)
    if correlation_px <= 0:
        return white.ravel()
    impulse = np.zeros((int(8 * correlation_px) + 1,) * 2)
    impulse[len(impulse) // 2, len(impulse) // 2] = 1.0
    kernel = ndimage.gaussian_filter(impulse, correlation_px, mode="constant")
    smooth = ndimage.gaussian_filter(white, correlation_px, mode="reflect")
    return (smooth / np.sqrt(np.sum(kernel**2))).ravel()
