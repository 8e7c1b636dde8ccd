"""Coarse registration: RANSAC on FPFH correspondences (methods.md §1.4, Li §2.3.1).

Correspondences are nearest neighbours in feature space (optionally mutual). Hypotheses are drawn
and scored in batches: three distinct correspondences per hypothesis, a cheap edge-length test,
a batched Kabsch fit, a test that the three sampled pairs land within the correspondence
distance, inlier counting on the whole correspondence set (at least ``min_inliers``), a few
Kabsch refits of each surviving hypothesis on its own inliers, and then a coverage score
(:mod:`spacepose.core.ransac_scoring`): how many points of a fixed subsample of each cloud land
within the gate of the other cloud (as PCL's SampleConsensusPrerejective validates by inlier
fraction). Hypotheses are ranked by coverage, ties broken by correspondence inliers.
Correspondence inliers alone cannot tell a near-symmetric target from its flip (the lab mock-up
turned 180° about a body axis collects as many feature matches as the true pose), but the flip
leaves part of the observed surface unexplained. Sampling stops at the confidence bound
``k = log(1 − p) / log(1 − w³)`` (w the inlier ratio of the best hypothesis so far) or at the
iteration limit; the best hypothesis is refitted on its inliers with Kabsch.
``ranking="inliers"`` is the paper's plain RANSAC instead: no refits, no coverage, the most
correspondence inliers win. All randomness comes from one seeded generator consumed in a fixed
order, so the result is the same for any ``workers``.
"""

from __future__ import annotations

import math
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import Field
from scipy.spatial import cKDTree

from spacepose.core import se3
from spacepose.core.cloud import PointCloud, as_cloud
from spacepose.core.config import StageConfig, stage_config
from spacepose.core.fpfh import FPFHConfig, compute_fpfh
from spacepose.core.grid import VoxelIndex
from spacepose.core.icp import as_registration_cloud
from spacepose.core.normals import NormalsConfig, estimate_normals
from spacepose.core.ransac_scoring import coverage_counts, evaluate_alignment, squared_residuals
from spacepose.core.registration import RegistrationResult, kabsch
from spacepose.core.scale import rms_radius
from spacepose.core.se3 import check_real
from spacepose.core.threads import thread_count
from spacepose.errors import InputError, RegistrationError

# Most hypotheses a RANSAC may draw: the stop at confidence p needs
# log(1 − p) / log(1 − w³) three-point samples, 6.9·10⁶ at an inlier ratio w of 1 % and
# p = 0.999 (9.2·10⁶ at p = 0.9999); at fewer inliers than 1 % the consensus is noise anyway.
MOST_ITERATIONS = 10_000_000


class RansacConfig(StageConfig):
    """Parameters of :func:`feature_ransac`.

    Attributes
    ----------
    max_correspondence_distance
        Inlier gate ε (m): a correspondence is an inlier when the hypothesis maps its source
        point within ε of its target point. Typically 1.5× the point spacing.
    mutual_filter
        Keep only correspondences that are nearest neighbours in feature space both ways.
    edge_length_ratio
        Reject a sample when any edge of its source triangle and the matching target edge
        differ by more than this ratio (Open3D's edge-length checker); 0 disables the test.
    max_iterations
        Largest number of hypotheses drawn, at most :data:`MOST_ITERATIONS` (10⁷: the
        confidence bound needs 6.9·10⁶ triples at a 1 % inlier ratio and the default
        ``confidence`` 0.999, 9.2·10⁶ at 0.9999; more draws nothing a stop would use).
    confidence
        Probability p of having drawn at least one all-inlier sample when sampling stops.
    seed
        Seed of the sampling.
    batch_size
        Hypotheses drawn and scored together; memory grows as batch_size × correspondences.
        The result depends on it (sampling stops at a batch boundary), never on ``workers``.
    min_inliers
        Fewest inlier correspondences a hypothesis needs to be scored at all; when none has
        them there is no consensus. Three of them are the sampled pairs themselves, so this
        must exceed 3.
    coverage_points
        Size of the fixed, seeded subsample of each cloud behind the coverage score (all points
        when a cloud is smaller). Hypotheses are ranked by how many subsampled source points
        land within ε of the target cloud plus how many subsampled target points land within ε
        of the moved source cloud; correspondence inliers only break ties and set the stopping
        bound. Cost per batch: two neighbour searches of (hypotheses × coverage_points) points.
    local_refits
        Rounds of Kabsch refit on the hypothesis' own inlier correspondences (and recount)
        before it is scored, as in LO-RANSAC: hypotheses from three noisy pairs can be 10° off
        and under-cover. Each round costs one pass over hypotheses × correspondences.
    ranking
        ``"coverage"`` (ours): local refits, then the coverage score as above;
        ``"inliers"``: the paper's plain RANSAC, hypotheses ranked by their inlier count (the
        smaller sum of squared inlier residuals breaking ties), without refits or coverage.
    """

    max_correspondence_distance: float = Field(default=0.015, gt=0)
    mutual_filter: bool = True
    edge_length_ratio: float = Field(default=0.9, ge=0, lt=1)
    # Bounded: 10¹² ran the first model-based frame for hours without a word.
    max_iterations: int = Field(default=100_000, ge=1, le=MOST_ITERATIONS)
    confidence: float = Field(default=0.999, gt=0, lt=1)
    seed: int = Field(0, ge=0)
    # Bounded: a batch's arrays grow with it (10⁸ ran out of time and memory).
    batch_size: int = Field(default=256, ge=1, le=65536)
    min_inliers: int = Field(default=10, ge=4)
    coverage_points: int = Field(default=300, ge=1)
    ranking: Literal["coverage", "inliers"] = "coverage"
    local_refits: int = Field(default=3, ge=0)


def match_features(
    source_features: ArrayLike,
    target_features: ArrayLike,
    mutual: bool = True,
    workers: int = -1,
) -> NDArray[np.intp]:
    """Nearest-neighbour correspondences in feature space.

    Parameters
    ----------
    source_features, target_features
        (N, D) and (M, D) descriptors (e.g. FPFH, D = 33).
    mutual
        Keep a pair only if each is the other's nearest neighbour.
    workers
        Threads for the searches.

    Returns
    -------
    (K, 2) pairs ``(source index, target index)``, ascending in source index.
    """
    src = _as_features(source_features, "source_features")
    tgt = _as_features(target_features, "target_features")
    if src.shape[1] != tgt.shape[1]:
        raise InputError(
            f"source and target features differ in dimension: {src.shape[1]} vs {tgt.shape[1]}"
        )
    if workers != -1:
        workers = thread_count(workers)  # scipy overflowed on a count past a C long
    _, forward = cKDTree(tgt).query(src, k=1, workers=workers)
    pairs = np.column_stack([np.arange(len(src)), forward])
    if mutual:
        _, backward = cKDTree(src).query(tgt, k=1, workers=workers)
        pairs = pairs[backward[forward] == pairs[:, 0]]
    return pairs


def sample_triples(rng: np.random.Generator, n: int, size: int) -> NDArray[np.intp]:
    """(size, 3) triples of distinct indices in ``0..n-1`` (n >= 3), uniformly drawn."""
    i0 = rng.integers(0, n, size)
    i1 = rng.integers(0, n - 1, size)
    i1 = i1 + (i1 >= i0)
    lo, hi = np.minimum(i0, i1), np.maximum(i0, i1)
    i2 = rng.integers(0, n - 2, size)
    # Skip over the two indices already taken, smallest first, to stay uniform and distinct.
    i2 = i2 + (i2 >= lo)
    i2 = i2 + (i2 >= hi)
    return np.column_stack([i0, i1, i2])


def edge_lengths_agree(
    source_triples: NDArray[np.float64], target_triples: NDArray[np.float64], ratio: float
) -> NDArray[np.bool_]:
    """Whether every edge of each source triangle matches its target edge within ``ratio``.

    Parameters
    ----------
    source_triples, target_triples
        (B, 3, 3) sampled points (three per hypothesis) in their own frames.
    ratio
        Smallest accepted ratio of the shorter to the longer of two matching edges.
    """
    a, b = [0, 1, 0], [1, 2, 2]
    ls = np.linalg.norm(source_triples[:, a] - source_triples[:, b], axis=2)
    lt = np.linalg.norm(target_triples[:, a] - target_triples[:, b], axis=2)
    return np.all((ls >= ratio * lt) & (lt >= ratio * ls), axis=1)


def iteration_bound(inlier_ratio: float, confidence: float) -> float:
    """Hypotheses needed to draw an all-inlier triple with probability ``confidence``."""
    if inlier_ratio <= 0.0:
        return math.inf
    miss = 1.0 - inlier_ratio**3
    if miss <= 0.0:
        return 0.0
    if miss >= 1.0:  # inliers too rare for the triple's probability to show in float64
        return math.inf
    return math.log(1.0 - confidence) / math.log(miss)


def ransac_correspondences(
    source: PointCloud | ArrayLike,
    target: PointCloud | ArrayLike,
    correspondences: ArrayLike,
    config: RansacConfig = RansacConfig(),
    workers: int = -1,
) -> RegistrationResult:
    """RANSAC rigid fit on given point correspondences.

    Parameters
    ----------
    source, target
        Clouds ((N, 3) arrays or :class:`PointCloud`), each in its own frame.
    correspondences
        (K, 2) putative pairs ``(source index, target index)``, K >= 3.
    config
        Gate, sampling, coverage and stopping parameters.
    workers
        Threads for the coverage and final neighbour searches (the result does not depend on
        it).

    Returns
    -------
    RegistrationResult
        ``T_target_source`` of the best-covering (refitted) hypothesis, refitted once more on
        its inlier correspondences; ``fitness`` (the coverage of the whole source cloud),
        ``inlier_rmse``, ``information`` (point-to-point ``Σ JᵀJ``, 1/m²) and
        ``n_correspondences`` from the nearest target point within ε of every mapped source
        point; ``iterations`` is the number of hypotheses drawn; ``converged`` says the
        confidence bound was reached.

    Raises
    ------
    InputError
        Clouds with fewer than 3 points, malformed or out-of-range correspondences.
    RegistrationError
        Fewer than 3 correspondences, or no hypothesis with ``min_inliers`` inliers.
    """
    src = as_registration_cloud(source, "source")
    tgt = as_registration_cloud(target, "target")
    pairs = np.asarray(correspondences)
    if pairs.ndim != 2 or pairs.shape[1] != 2 or not np.issubdtype(pairs.dtype, np.integer):
        raise InputError(f"correspondences must be a (K, 2) integer array, got {pairs.shape}")
    if len(pairs) and (
        pairs.min() < 0 or pairs[:, 0].max() >= len(src) or pairs[:, 1].max() >= len(tgt)
    ):
        raise InputError("correspondences index outside the source or target cloud")
    if len(pairs) < 3:
        raise RegistrationError(f"RANSAC needs at least 3 correspondences, got {len(pairs)}")
    src_c, tgt_c = src.points[pairs[:, 0]], tgt.points[pairs[:, 1]]
    gate = config.max_correspondence_distance
    eps2 = gate**2
    rng = np.random.default_rng(config.seed)
    # Fixed subsamples for the coverage score, drawn before any hypothesis so that they do not
    # depend on how many batches run.
    src_sub = src.points[_subsample(rng, len(src), config.coverage_points)]
    tgt_sub = tgt.points[_subsample(rng, len(tgt), config.coverage_points)]
    src_tree, tgt_tree = VoxelIndex(src.points), VoxelIndex(tgt.points)

    best_T, best_key, best_count, most = None, (-1, -1, -math.inf), 0, 0
    drawn, bound = 0, math.inf
    while drawn < min(bound, config.max_iterations):
        size = min(config.batch_size, config.max_iterations - drawn)
        sample = sample_triples(rng, len(pairs), size)
        drawn += size
        S, D = src_c[sample], tgt_c[sample]
        ok = edge_lengths_agree(S, D, config.edge_length_ratio)
        if not ok.any():
            continue
        T = kabsch(S[ok], D[ok])
        moved = np.einsum("hij,hkj->hki", T[:, :3, :3], S[ok]) + T[:, None, :3, 3]
        T = T[np.all(np.sum((moved - D[ok]) ** 2, axis=2) < eps2, axis=1)]
        if len(T) == 0:
            continue
        r2 = squared_residuals(T, src_c, tgt_c)
        inl = r2 < eps2
        most = max(most, int(inl.sum(axis=1).max()))
        # Score each hypothesis where refits on its own inliers take it: a fit to three noisy
        # pairs can be 10° off, and a flip would then out-cover a true pose sampled less
        # exactly. Too few inliers (at any round) is no consensus, whatever the coverage.
        keep = inl.sum(axis=1) >= config.min_inliers
        plain = config.ranking == "inliers"
        for _ in range(0 if plain else config.local_refits):
            T, inl = T[keep], inl[keep]
            shape = (len(T), *src_c.shape)
            T = kabsch(np.broadcast_to(src_c, shape), np.broadcast_to(tgt_c, shape), inl)
            r2 = squared_residuals(T, src_c, tgt_c)
            inl = r2 < eps2
            keep = inl.sum(axis=1) >= config.min_inliers
        if not keep.any():
            continue
        T, inl, r2 = T[keep], inl[keep], r2[keep]
        count = inl.sum(axis=1)
        sq = np.where(inl, r2, 0.0).sum(axis=1)
        # Both directions: a partial view registered to a whole model (either way round) is
        # judged by how much of the view the model explains, and a flip loses on both.
        cover = np.zeros(len(T), dtype=np.int64)
        if not plain:
            cover = coverage_counts(T, src_sub, tgt_tree, gate, workers) + coverage_counts(
                se3.invert(T), tgt_sub, src_tree, gate, workers
            )
        # Best coverage, then most inliers, then smallest squared error; lexsort keeps the
        # first on a full tie, and so does the strict comparison across batches.
        h = np.lexsort((sq, -count, -cover))[0]
        key = (int(cover[h]), int(count[h]), -float(sq[h]))
        if key > best_key:
            best_T, best_key, best_count = T[h], key, int(count[h])
            bound = iteration_bound(best_count / len(pairs), config.confidence)

    if best_T is None:
        raise RegistrationError(
            f"RANSAC found no consensus: best hypothesis has {most} of {len(pairs)} "
            f"correspondences within {gate:.3g} m after {drawn} hypotheses "
            f"(need {config.min_inliers})"
        )
    inliers = np.sum((se3.transform_points(best_T, src_c) - tgt_c) ** 2, axis=1) < eps2
    T_target_source = kabsch(src_c[inliers], tgt_c[inliers])
    return evaluate_alignment(src, tgt, T_target_source, config, drawn, drawn >= bound, workers)


def feature_ransac(
    source: PointCloud | ArrayLike,
    target: PointCloud | ArrayLike,
    source_features: ArrayLike,
    target_features: ArrayLike,
    config: RansacConfig = RansacConfig(),
    workers: int = -1,
) -> RegistrationResult:
    """Coarse ``T_target_source`` from feature correspondences by RANSAC.

    Parameters
    ----------
    source, target
        Clouds ((N, 3), (M, 3)), each in its own frame.
    source_features, target_features
        (N, D) and (M, D) descriptors, one row per point.
    config
        Matching, gate, sampling and stopping parameters.
    workers
        Threads for the searches (the result does not depend on it).

    Raises
    ------
    InputError
        A feature count that differs from the point count, mismatched dimensions, NaNs, or
        fewer than 3 points.
    RegistrationError
        Fewer than 3 correspondences (after the mutual filter) or no consensus.
    """
    config = stage_config(config, RansacConfig)
    src = as_registration_cloud(source, "source")
    tgt = as_registration_cloud(target, "target")
    for name, cloud, feats in (
        ("source", src, source_features),
        ("target", tgt, target_features),
    ):
        n_feat = len(_as_features(feats, f"{name}_features"))
        if n_feat != len(cloud):
            raise InputError(f"{n_feat} {name} features for {len(cloud)} {name} points")
    pairs = match_features(source_features, target_features, config.mutual_filter, workers)
    return ransac_correspondences(src, tgt, pairs, config, workers)


def global_registration(
    source: PointCloud | ArrayLike,
    target: PointCloud | ArrayLike,
    voxel_size: float,
    ransac: RansacConfig | None = None,
    normals: NormalsConfig | None = None,
    fpfh: FPFHConfig | None = None,
    viewpoint: ArrayLike = (0.0, 0.0, 0.0),
    workers: int = -1,
) -> RegistrationResult:
    """Normals → FPFH → RANSAC in one call, scales derived from the point spacing.

    Parameters
    ----------
    source, target
        Clouds (:class:`PointCloud` or (N, 3) arrays) with a roughly even spacing ``voxel_size``
        (e.g. mpp-MLS output). Normals they carry are used as they are; missing ones are
        estimated and turned towards ``viewpoint`` (both clouds in sensor frames: the sensor
        origin).
    voxel_size
        Point spacing (m). Defaults follow Open3D's global-registration recipe: normals within
        2×, FPFH within 5× (at most 100 neighbours), inlier gate 1.5× the spacing.
    ransac, normals, fpfh
        Override the derived configs.
    viewpoint
        (3,) position the estimated normals face.
    workers
        Threads for the neighbour searches.
    """
    # Text or None ended in numpy's "ufunc 'isfinite' not supported" TypeError.
    number = isinstance(voxel_size, (int, float, np.integer, np.floating))
    if isinstance(voxel_size, bool) or not number or not np.isfinite(voxel_size) or voxel_size <= 0:
        raise InputError(f"voxel_size must be a positive number of metres, got {voxel_size!r}")
    # None derives a config; an empty dict was taken for None, and any other dict ended in
    # AttributeError.
    normals = (
        NormalsConfig(k=30, radius=2.0 * voxel_size)
        if normals is None
        else stage_config(normals, NormalsConfig, "normals")
    )
    fpfh = (
        FPFHConfig(radius=5.0 * voxel_size, max_nn=100)
        if fpfh is None
        else stage_config(fpfh, FPFHConfig, "fpfh")
    )
    ransac = (
        RansacConfig(max_correspondence_distance=1.5 * voxel_size)
        if ransac is None
        else stage_config(ransac, RansacConfig, "ransac")
    )
    given = (as_cloud(source, "source"), as_cloud(target, "target"))
    for name, cloud in zip(("source", "target"), given, strict=True):
        radius = rms_radius(cloud.points)
        if voxel_size > radius:
            # Every feature would span the whole cloud, and every point its neighbour: slow,
            # and a "fit" of a few centroids.
            raise InputError(
                f"voxel_size {voxel_size:.4g} m is wider than the {name} cloud "
                f"(RMS radius {radius:.4g} m): give the point spacing"
            )
    clouds = [
        c if c.has_normals else estimate_normals(c, normals, viewpoint, workers) for c in given
    ]
    features = [compute_fpfh(c, fpfh, workers) for c in clouds]
    return feature_ransac(clouds[0], clouds[1], features[0], features[1], ransac, workers)


def _subsample(rng: np.random.Generator, n: int, m: int) -> NDArray[np.intp]:
    """``min(m, n)`` distinct indices of ``0..n-1`` in ascending order (all of them if m >= n)."""
    if m >= n:
        return np.arange(n)
    return np.sort(rng.choice(n, m, replace=False))


def _as_features(values: ArrayLike, name: str) -> NDArray[np.float64]:
    check_real(values, name)
    try:
        arr = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError) as exc:
        raise InputError(f"{name} are not numeric: {exc}") from None
    if arr.ndim != 2 or arr.shape[0] == 0 or arr.shape[1] == 0:
        raise InputError(f"{name} must be a non-empty (N, D) array, got shape {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise InputError(f"{name} contain NaN or inf")
    return arr
