"""How clean a raw frame is, measured as Li et al. do (methods.md §1.1, Li Eq. 1 and Fig. 5).

The measure is the consistency of neighbouring normals: estimate each point's normal from its
k = 10 nearest neighbours (PCA, oriented towards the sensor), take the angle
``Δθ_ij = arccos(n_i · n_j)`` between the normal of every point i and that of each of its k
nearest neighbours j, and report the share of angles below 20°. On a smooth surface sampled
without noise the share is close to 1; Li et al.'s raw ToF frame has about 20 % (80 % of the
angles between 20° and 160°), their frame after mpp-MLS about 80 %.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from spacepose.core.cloud import PointCloud, as_cloud
from spacepose.core.neighbors import knn
from spacepose.core.normals import NormalsConfig, estimate_normals
from spacepose.errors import InputError

# Li et al.'s raw ToF frame: about 20 % of the neighbouring normals within 20° of each other.
PAPER_RAW_SHARE_BELOW_20 = 0.20
# Neighbours for the normals and for the angles, as in the paper's figure.
CONSISTENCY_K = 10


@dataclass(frozen=True)
class NormalConsistency:
    """Distribution of the angles between the normals of neighbouring points (Li Fig. 5).

    Attributes
    ----------
    angles_deg
        (P,) angle ``arccos(n_i · n_j)`` in degrees for every point i and each of its neighbours
        j, in 0–180° (normals are compared as stored, not folded to 0–90°).
    bin_edges_deg
        (B + 1,) histogram edges in degrees, 0 to 180.
    counts
        (B,) number of angles per bin.
    share_below_20
        Share of the angles below 20°, in [0, 1].
    """

    angles_deg: NDArray[np.float64]
    bin_edges_deg: NDArray[np.float64]
    counts: NDArray[np.int64]
    share_below_20: float

    @property
    def shares(self) -> NDArray[np.float64]:
        """(B,) share of the angles per bin."""
        return self.counts / max(int(self.counts.sum()), 1)


def normal_consistency(
    cloud: PointCloud | ArrayLike, k: int = 10, bin_width_deg: float = 10.0, workers: int = -1
) -> NormalConsistency:
    """Angles between each point's normal and those of its k nearest neighbours.

    Parameters
    ----------
    cloud
        Points with normals (N, 3).
    k
        Number of neighbours per point, the point itself excluded.
    bin_width_deg
        Histogram bin width in degrees; must divide 180.
    workers
        Threads for the neighbour search.
    """
    # An (N, 3) array ended in AttributeError ('has_normals'), a bin width of 0 in
    # ZeroDivisionError and one of NaN in "cannot convert float NaN to integer".
    cloud = as_cloud(cloud, "cloud")
    if not cloud.has_normals:
        raise InputError(
            "normal consistency needs a cloud with normals (run estimate_normals first)",
            cloud.source,
        )
    if isinstance(k, bool) or not isinstance(k, (int, np.integer)) or k < 1:
        raise InputError(f"normal consistency needs k >= 1 neighbours, got {k!r}", cloud.source)
    if len(cloud) < k + 1:
        raise InputError(f"normal consistency with k={k} needs more than {k} points", cloud.source)
    valid = isinstance(bin_width_deg, (int, float, np.integer, np.floating))
    valid = valid and not isinstance(bin_width_deg, bool) and 0 < bin_width_deg <= 180
    n_bins = 180.0 / bin_width_deg if valid else 0.0
    if not valid or abs(n_bins - round(n_bins)) > 1e-9:
        raise InputError(f"bin_width_deg must divide 180, got {bin_width_deg}")
    _, idx = knn(cloud.points, None, k + 1, workers=workers)
    # Drop each point itself (not simply column 0, which a duplicate point may occupy).
    own = idx == np.arange(len(idx))[:, None]
    own[own.sum(axis=1) == 0, -1] = True
    i = np.repeat(np.arange(len(idx)), k)
    j = idx[~own]
    cos = np.einsum("ij,ij->i", cloud.normals[i], cloud.normals[j])
    angles = np.degrees(np.arccos(np.clip(cos, -1.0, 1.0)))
    edges = np.linspace(0.0, 180.0, round(n_bins) + 1)
    counts, _ = np.histogram(angles, bins=edges)
    return NormalConsistency(angles, edges, counts, float(np.mean(angles < 20.0)))


def frame_normal_consistency(
    cloud: PointCloud, k: int = CONSISTENCY_K, workers: int = -1
) -> NormalConsistency:
    """Normal consistency of a raw frame (module notes): normals from k neighbours, then angles.

    Parameters
    ----------
    cloud
        (N, 3) raw points, sensor frame (the normals are oriented towards its origin); any
        normals it carries are replaced.
    k
        Neighbours for the normals and for the angles.
    workers
        Threads for the neighbour searches.

    Returns
    -------
    NormalConsistency
        The angles, their histogram and ``share_below_20``.
    """
    with_normals = estimate_normals(cloud, NormalsConfig(k=k), workers=workers)
    return normal_consistency(with_normals, k=k, workers=workers)
