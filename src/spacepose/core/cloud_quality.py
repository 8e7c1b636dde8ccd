"""How clean a raw frame is, measured as Li et al. do (methods.md §1.1, Li Eq. 1 and Fig. 5).

The measure is the consistency of neighbouring normals: estimate each point's normal from its
k = 10 nearest neighbours (PCA, oriented towards the sensor), take the angle
``Δθ_ij = arccos(n_i · n_j)`` between the normal of every point i and that of each of its k
nearest neighbours j, and report the share of angles below 20°. On a smooth surface sampled
without noise the share is close to 1; Li et al.'s raw ToF frame has about 20 % (80 % of the
angles between 20° and 160°), their frame after mpp-MLS about 80 %.
"""

from __future__ import annotations

from spacepose.core.cloud import PointCloud
from spacepose.core.normals import (
    NormalConsistency,
    NormalsConfig,
    estimate_normals,
    normal_consistency,
)

# Li et al.'s raw ToF frame: about 20 % of the neighbouring normals within 20° of each other.
PAPER_RAW_SHARE_BELOW_20 = 0.20
# Neighbours for the normals and for the angles, as in the paper's figure.
CONSISTENCY_K = 10


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
