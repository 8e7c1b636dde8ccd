"""The point cloud type every stage takes and returns."""

from __future__ import annotations

import warnings
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree

from spacepose.core import se3
from spacepose.core.se3 import check_real
from spacepose.errors import InputError, SpaceposeWarning

#: A cloud is suspected to be in millimetres when it spans more than this many "metres" (bounding
#: box diagonal) with a median nearest-neighbour spacing above MM_MIN_SPACING. No ToF camera or
#: flash LiDAR samples a scene that wide that coarsely; the same data in millimetres do (a 1 m
#: target sampled every 2 mm reads as 1000 m wide and 2 m apart), while outdoor LiDAR in metres
#: spans 50-200 m at centimetre spacing. Units are the one place an absolute length is needed.
MM_MIN_EXTENT = 50.0
MM_MIN_SPACING = 0.25
_SPACING_PROBES = 1000

#: Largest accepted |coordinate|: sums of squares over any realistic cloud stay finite in float64
#: (sqrt(max float64) / 2**32, about 3e144), so no stage overflows on a finite input.
MAX_ABS_COORDINATE = float(np.sqrt(np.finfo(np.float64).max)) / 2.0**32


@dataclass(frozen=True, eq=False)
class PointCloud:
    """Points with optional normals and per-point noise σ, validated on construction.

    Parameters
    ----------
    points
        (N, 3) coordinates in metres, in the frame the caller says (usually the sensor frame).
    normals
        Optional (N, 3) unit normals in the same frame.
    sigma
        Optional (N,) per-point noise standard deviation in metres.
    source
        Where the data came from (a file name); used in error messages.

    Notes
    -----
    Rows with a non-finite coordinate (or normal, or σ) are dropped and counted in ``n_dropped``
    rather than poisoning every later stage. A cloud with no finite row raises
    :class:`~spacepose.errors.InputError`: an empty cloud is never silently accepted.

    The arrays are read-only and the cloud's own: a caller's writable array (or a view of one)
    is copied, while a read-only array owning its data (another cloud's) is shared.
    """

    points: NDArray[np.float64]
    normals: NDArray[np.float64] | None = None
    sigma: NDArray[np.float64] | None = None
    source: str | None = None
    n_dropped: int = field(default=0)

    def __post_init__(self) -> None:
        pts = _as_rows(self.points, 3, "points", self.source)
        n = len(pts)
        normals = self.normals
        if normals is not None:
            normals = _as_rows(normals, 3, "normals", self.source)
        sigma = None if self.sigma is None else _as_sigma(self.sigma, self.source)
        if normals is not None and len(normals) != n:
            raise InputError(f"{len(normals)} normals for {n} points", self.source)
        if sigma is not None and len(sigma) != n:
            raise InputError(f"{len(sigma)} sigma values for {n} points", self.source)
        if normals is not None:
            _check_directions(normals, self.source)
        if sigma is not None:
            _check_sigma(sigma, self.source)
        values = [pts, normals, sigma]
        given = [self.points, self.normals, self.sigma]
        # NaN when a coordinate is NaN, inf when one is infinite: one pass checks both.
        peak = _peak(pts) if n else float("nan")
        n_keep = n
        if not (np.isfinite(peak) and all(_all_finite(v) for v in values[1:] if v is not None)):
            keep = _finite_rows(pts)
            for v in values[1:]:
                if v is not None:
                    keep &= _finite_rows(v)
            n_keep = int(np.count_nonzero(keep))
            if n_keep == 0:
                what = "is empty" if n == 0 else f"has no finite point (all {n} rows NaN/inf)"
                if n and np.any(_finite_rows(pts)):  # the points are fine: say what is not
                    bad = [k for k, v in (("normals", normals), ("sigma", sigma)) if v is not None]
                    finite = int(np.count_nonzero(_finite_rows(pts)))
                    what = (
                        f"has no row with finite {' and '.join(['points', *bad])} (the points "
                        f"alone are finite on {finite} of {n} rows)"
                    )
                raise InputError(f"point cloud {what}", self.source)
            if n_keep < n:
                # Fresh arrays: the private copies below need not copy them again.
                values = [None if v is None else np.compress(keep, v, axis=0) for v in values]
                given = [None] * 3
            peak = _peak(values[0])
        check_peak(peak, "points", self.source)
        for name, value, raw in zip(("points", "normals", "sigma"), values, given, strict=True):
            object.__setattr__(self, name, None if value is None else _private(value, raw))
        object.__setattr__(self, "n_dropped", self.n_dropped + (n - n_keep))

    def __len__(self) -> int:
        return len(self.points)

    @property
    def has_normals(self) -> bool:
        return self.normals is not None

    def select(self, index: ArrayLike) -> PointCloud:
        """Subset by integer index or boolean mask; normals and σ follow.

        Raises
        ------
        InputError
            An index out of range, not whole numbers, or a mask of another length (numpy's
            IndexError before); a selection of no point (an empty cloud).
        """
        idx = np.asarray(index)
        if idx.dtype == bool and idx.shape == (len(self),):
            idx = np.flatnonzero(idx)
        try:
            rows = [
                None if v is None else _rows(v, idx)
                for v in (self.points, self.normals, self.sigma)
            ]
        except IndexError as exc:
            raise InputError(f"select of {len(self)} points: {exc}", self.source) from None
        return PointCloud(*rows, source=self.source)

    def transformed(self, T_a_b: ArrayLike) -> PointCloud:
        """The cloud mapped from its frame b into frame a by ``T_a_b`` (normals rotated)."""
        T_a_b = se3.as_transform(T_a_b, "T_a_b")
        return PointCloud(
            _frozen(se3.transform_points(T_a_b, self.points)),
            None if self.normals is None else _frozen(se3.rotate_vectors(T_a_b, self.normals)),
            self.sigma,
            source=self.source,
        )

    def with_normals(self, normals: ArrayLike) -> PointCloud:
        """A copy carrying the given (N, 3) normals."""
        return PointCloud(self.points, normals, self.sigma, source=self.source)


def _as_sigma(values: ArrayLike, source: str | None) -> NDArray[np.float64]:
    """Per-point σ as a flat float64 array, from (N,) or (N, 1) values (text ended in numpy's
    ValueError; a (100, 3) table of 300 values was read as 300 per-point σ)."""
    check_real(values, "sigma", source)
    try:
        sigma = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"sigma are not numeric: {exc}", source) from None
    if sigma.ndim > 2 or (sigma.ndim == 2 and sigma.shape[1] != 1):
        raise InputError(f"sigma must be one value a point, (N,), got shape {sigma.shape}", source)
    return sigma.reshape(-1)


def _check_directions(normals: NDArray[np.float64], source: str | None) -> None:
    """Refuse normals of zero length: they give no direction, and a point-to-plane residual
    weighed by one is zero whatever the pose (a NaN row is dropped with its point instead).
    Refuse normals not of unit length too: a residual ``n·(p − q)`` scales with the normal,
    and so did every pose and information matrix fitted on them (a length of 10 weighed its
    pair a hundred times; the file readers take such normals as their directions, with a
    warning)."""
    zero = normals[:, 0] == 0.0
    zero &= normals[:, 1] == 0.0
    zero &= normals[:, 2] == 0.0
    if zero.any():
        rows = np.flatnonzero(zero)
        raise InputError(
            f"normals: {len(rows)} of {len(normals)} rows are (0, 0, 0) (first at row {rows[0]}): "
            "a normal needs a direction; leave the normals out to have them estimated",
            source,
        )
    # Squared length within 2e-3 of 1: a length within 1e-3, as the readers take it.
    squared = np.einsum("ij,ij->i", normals, normals)
    # Rows not finite are dropped with their points.
    off = np.isfinite(squared) & (np.abs(squared - 1.0) > 2e-3)
    if off.any():
        rows = np.flatnonzero(off)
        length = float(np.linalg.norm(normals[rows[0]]))
        raise InputError(
            f"normals: {len(rows)} of {len(normals)} rows are not of unit length (row "
            f"{rows[0]}: {length:.6g}); divide them by their lengths, or leave them out",
            source,
        )


def _check_sigma(sigma: NDArray[np.float64], source: str | None) -> None:
    """Refuse a negative noise σ: it is a standard deviation (a NaN row is dropped instead)."""
    negative = sigma < 0.0
    if negative.any():
        rows = np.flatnonzero(negative)
        raise InputError(
            f"sigma: {len(rows)} of {len(sigma)} values are negative (first at row {rows[0]}: "
            f"{sigma[rows[0]]:.6g}): a noise sigma is a standard deviation, >= 0",
            source,
        )


def _as_rows(values: ArrayLike, width: int, name: str, source: str | None) -> NDArray[np.float64]:
    check_real(values, name, source)
    try:
        arr = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name} are not numeric: {exc}", source) from None
    if arr.ndim != 2 or arr.shape[1] != width:
        raise InputError(f"{name} must have shape (N, {width}), got {arr.shape}", source)
    return arr


def as_points(
    values: PointCloud | ArrayLike,
    name: str = "points",
    source: str | None = None,
    min_points: int = 1,
) -> NDArray[np.float64]:
    """Validate a non-empty, finite (N, 3) float64 array (or take a PointCloud's points).

    The one check behind every stage that accepts raw arrays, so that bad input fails here with
    the package's own error rather than deep inside numpy or scipy.

    Raises
    ------
    InputError
        Not numeric, not (N, 3), fewer than ``min_points`` rows (an empty array included), or
        holding NaN / inf; the message names ``name`` and ``source``.
    """
    cloud = isinstance(values, PointCloud)
    if cloud:
        arr = values.points
        source = values.source if source is None else source
    else:
        arr = _as_rows(values, 3, name, source)
    if len(arr) < max(min_points, 1):
        raise InputError(
            f"{name}: need at least {max(min_points, 1)} point(s) in a non-empty (N, 3) array, "
            f"got {len(arr)}",
            source,
        )
    if cloud:
        # Checked when the cloud was made, and read-only since: a second pass over a 900k-point
        # frame costs a millisecond.
        return arr
    peak = _peak(arr)
    if not np.isfinite(peak):
        raise InputError(f"{name} have non-finite entries (NaN or inf)", source)
    check_peak(peak, name, source)
    return arr


def as_cloud(
    values: PointCloud | ArrayLike,
    name: str = "points",
    min_points: int = 1,
    say_dropped: bool = True,
) -> PointCloud:
    """A :class:`PointCloud` as it is, or an (N, 3) array wrapped in one (validated).

    The one coercion behind every one-call function that takes "a cloud": a caller may pass the
    raw (N, 3) array of points (frame as the caller says) instead of building a PointCloud.

    Raises
    ------
    InputError
        Not (N, 3), no finite row, coordinates out of range, or fewer than ``min_points`` rows;
        the message names ``name`` (or the cloud's source).

    Warns
    -----
    SpaceposeWarning
        An array's rows holding NaN or inf were left out (unless ``say_dropped`` is False: a
        tracker's frame, whose NaN rows are pixels without a return).
    """
    cloud = values if isinstance(values, PointCloud) else PointCloud(values, source=name)
    if say_dropped and cloud is not values and cloud.n_dropped:
        # The rows of what comes back (normals, features, correspondence indices) are the
        # kept rows: one NaN row first shifted every index by one against the caller's array.
        problem = (
            f"{cloud.n_dropped} of {cloud.n_dropped + len(cloud)} rows hold NaN or inf and are "
            "left out: rows and indices of the result refer to the rows kept (drop them first, "
            "or pass a PointCloud, to keep the numbering)"
        )
        warnings.warn(SpaceposeWarning(problem, name), stacklevel=3)
    if len(cloud) < min_points:
        raise InputError(f"need at least {min_points} points, got {len(cloud)}", cloud.source)
    return cloud


def _peak(points: NDArray[np.float64]) -> float:
    """Largest |coordinate| of a non-empty array: NaN if any entry is NaN, inf if any is
    infinite (max and min propagate both), so one pass is also the finite check."""
    return float(max(points.max(), -points.min()))


def check_peak(peak: float, name: str, source: str | None = None) -> None:
    """Refuse coordinates whose squares would overflow float64 in a covariance or a distance
    (``peak``: their largest magnitude; ``name`` the plural they are named by)."""
    if peak > MAX_ABS_COORDINATE:
        raise InputError(
            f"{name} reach |coordinate| {peak:.3g}, beyond {MAX_ABS_COORDINATE:.3g}: their squares "
            "overflow float64 (wrong units or a corrupt file?)",
            source,
        )


def _all_finite(values: NDArray[np.float64]) -> bool:
    return bool(np.isfinite(values).all())


def _finite_rows(values: NDArray[np.float64]) -> NDArray[np.bool_]:
    """(N,) True where the row of an (N,) or (N, k) array is finite: column by column, as
    numpy's ``all(axis=1)`` over (N, 3) is about 6x slower."""
    finite = np.isfinite(values)
    if finite.ndim == 1:
        return finite
    keep = finite[:, 0].copy()
    for column in finite.T[1:]:
        keep &= column
    return keep


def _frozen(values: NDArray[np.float64]) -> NDArray[np.float64]:
    """A fresh array made read-only, so that a new cloud takes it as its own without a copy."""
    values.setflags(write=False)
    return values


def _rows(values: NDArray[np.float64], index: NDArray) -> NDArray[np.float64]:
    """``values[index]``, frozen: the new cloud's own array, no second copy. A 1-D integer
    index goes through ``np.take`` (3-6x faster on (N, 3) rows); any other index is numpy's,
    with numpy's errors."""
    if index.ndim == 1 and index.dtype.kind in "iu":
        return _frozen(np.take(values, index, axis=0))
    return _frozen(values[index])


def _private(value: NDArray[np.float64], given: object) -> NDArray[np.float64]:
    """The cloud's own read-only, C-ordered float64 copy of ``value`` (validated from ``given``).

    No copy when ``value`` is already private: an array made here (``given`` None), converted
    from a list or from an array of another dtype (no memory shared with it), or a read-only
    array owning its data (a cloud's own, or :func:`_frozen`): nobody can write it through a
    view. Any other array is copied: freezing the caller's own array would break their later
    writes, and a view of a writable buffer could change under the cloud.
    """
    fresh = given is None or isinstance(given, list | tuple)
    if isinstance(given, np.ndarray):
        fresh = not np.may_share_memory(value, given)
    base = value
    while isinstance(base.base, np.ndarray):
        base = base.base
    frozen = not value.flags.writeable and not base.flags.writeable and base.flags.owndata
    if not (fresh or frozen):
        value = np.array(value, dtype=np.float64, order="C", copy=True)
    elif not value.flags.c_contiguous:
        value = np.ascontiguousarray(value)
    value.setflags(write=False)
    return value


def check_rows(name: str, *arrays: ArrayLike, shapes: tuple[tuple[int, ...], ...] = ()) -> None:
    """Raise :class:`InputError` unless the arrays share one row count M and are each (M, 3),
    or (M, *shape) for the ``shapes`` given: the check before a compiled kernel that indexes
    several arrays by the same row without bounds checks."""
    shapes = shapes or ((3,),) * len(arrays)
    rows = {np.shape(a)[0] if np.ndim(a) else None for a in arrays}
    if len(rows) != 1 or any(
        np.shape(a)[1:] != shape for a, shape in zip(arrays, shapes, strict=True)
    ):
        got = ", ".join(str(np.shape(a)) for a in arrays)
        raise InputError(f"{name} needs arrays of one row count shaped {shapes}, got {got}")


@dataclass(frozen=True)
class ScaleCheck:
    """Extent and spacing of a cloud, and whether they look like millimetres read as metres.

    Attributes
    ----------
    extent
        Bounding-box diagonal, in the cloud's units (m if it is in metres).
    spacing
        Median distance from a point to its nearest neighbour (same units); NaN when the extent
        alone rules millimetres out (it is not computed).
    millimetres
        ``extent > MM_MIN_EXTENT and spacing > MM_MIN_SPACING``.
    """

    extent: float
    spacing: float
    millimetres: bool


def check_scale(points: ArrayLike, seed: int = 0) -> ScaleCheck:
    """Whether an (N, 3) cloud looks like millimetres taken for metres.

    The median nearest-neighbour spacing is measured on at most 1000 points drawn with
    ``numpy.random.default_rng(seed)`` (against the whole cloud), and only when the extent
    already exceeds ``MM_MIN_EXTENT``: a cloud of ordinary size costs one min/max.
    """
    pts = as_points(points)
    # Column by column: numpy reduces an (N, 3) array along axis 0 about 50x slower.
    extent = float(np.linalg.norm([pts[:, i].max() - pts[:, i].min() for i in range(3)]))
    if extent <= MM_MIN_EXTENT or len(pts) < 2:
        return ScaleCheck(extent, float("nan"), False)
    rng = np.random.default_rng(seed)
    probes = pts[rng.choice(len(pts), min(len(pts), _SPACING_PROBES), replace=False)]
    distance, _ = cKDTree(pts).query(probes, k=2)
    spacing = float(np.median(distance[:, 1]))
    return ScaleCheck(extent, spacing, spacing > MM_MIN_SPACING)
