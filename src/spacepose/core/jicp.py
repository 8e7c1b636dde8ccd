"""J-ICP: joint registration over a sliding window of frames (Li §2.3.2, METHODS §1.6).

Li et al. average, for three frames i (oldest), j, k (newest), the direct estimate ``T_kj`` and
the indirect one through frame i, ``T_ki · T_ji⁻¹`` (Eq. 9), then chain ``T_k0 = ΔT_kj · T_j0``.
:func:`average_three` is that average on SE(3). :class:`JointICP` generalises it to a window of
W frames: the newest frame is registered against every earlier frame of the window and its pose
is solved from all those pairs as a pose graph (:mod:`spacepose.core.posegraph`) weighted by each
pair's information. The poses already output stay fixed, as in the paper's chaining: with W = 3
and equal weights a step reproduces Eq. 9 exactly.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import Field

from spacepose.core import se3
from spacepose.core.cloud import PointCloud
from spacepose.core.config import StageConfig
from spacepose.core.gicp import GICPConfig, compute_covariances, gicp
from spacepose.core.grid import VoxelIndex
from spacepose.core.icp import ICPConfig, as_registration_cloud, icp
from spacepose.core.normals import estimate_normals
from spacepose.core.posegraph import PoseGraphEdge, optimize_pose_graph
from spacepose.core.registration import RegistrationResult


class JICPConfig(StageConfig):
    """Parameters of :class:`JointICP`.

    Attributes
    ----------
    window
        Frames in the window, the newest included (3 is the paper's scheme).
    registration
        Pairwise registration inside the window: ``"icp"`` (with ``icp``) or ``"gicp"``
        (with ``gicp``).
    icp, gicp
        Configs of the pairwise registration.
    weighting
        ``"information"``: each pair weighted by the inverse of its covariance; ``"equal"``:
        every pair weighted alike (Eq. 9 for W = 3).
    """

    window: int = Field(3, ge=2, le=10)
    registration: Literal["icp", "gicp"] = "icp"
    icp: ICPConfig = ICPConfig()
    gicp: GICPConfig = GICPConfig()
    weighting: Literal["information", "equal"] = "information"


def average_three(T_kj: ArrayLike, T_ki: ArrayLike, T_ji: ArrayLike) -> NDArray[np.float64]:
    """Li et al.'s Eq. 9 on SE(3): the average of the direct and indirect estimates of ``T_kj``.

    Parameters
    ----------
    T_kj, T_ki, T_ji
        (4, 4) pairwise registrations; ``T_ba`` maps coordinates in frame a into frame b, frames
        i (oldest), j, k (newest).

    Returns
    -------
    (4, 4) ``ΔT_kj = T_kj · exp(½ · log(T_kj⁻¹ · T_ki · T_ji⁻¹))``: the midpoint of the
    one-parameter curve from ``T_kj`` (direct) to ``T_ki · T_ji⁻¹`` (through frame i), i.e. the
    transform M with ``log(T_kj M⁻¹) = −log(T_ki T_ji⁻¹ M⁻¹)``. Chain ``T_k0 = ΔT_kj · T_j0``.
    """
    T_kj = se3.as_transform(T_kj, "T_kj")
    indirect = se3.as_transform(T_ki, "T_ki") @ se3.invert(se3.as_transform(T_ji, "T_ji"))
    return T_kj @ se3.exp(0.5 * se3.log(se3.invert(T_kj) @ indirect))


@dataclass(frozen=True)
class JointStep:
    """Outcome of one :meth:`JointICP.step`.

    Attributes
    ----------
    index
        Frame number k (0 for the first frame).
    T_k0
        (4, 4) motion from the first frame into frame k (identity for k = 0).
    covariance
        (6, 6) covariance of ``T_k0`` (left perturbation, (omega, v)) given the earlier poses
        of the window, i.e. the uncertainty this step adds; zero for k = 0.
    pairwise
        Registrations of the earlier window frames (oldest first) onto frame k; their
        ``T_target_source`` is ``T_km``.
    """

    index: int
    T_k0: NDArray[np.float64]
    covariance: NDArray[np.float64]
    pairwise: tuple[RegistrationResult, ...]


@dataclass(frozen=True)
class _Frame:
    cloud: PointCloud
    covariances: NDArray[np.float64] | None
    T_k0: NDArray[np.float64]


class JointICP:
    """Sliding-window joint ICP tracker.

    Parameters
    ----------
    config
        Window, pairwise registration and weighting.
    workers
        Threads for neighbour searches (results do not depend on it).

    Examples
    --------
    >>> tracker = JointICP(JICPConfig(window=3))          # doctest: +SKIP
    >>> poses = [tracker.step(cloud).T_k0 for cloud in frames]  # doctest: +SKIP
    """

    def __init__(self, config: JICPConfig = JICPConfig(), workers: int = -1) -> None:
        self.config = config
        self.workers = workers
        self._window: deque[_Frame] = deque(maxlen=config.window - 1)
        self._count = 0

    def step(
        self, frame: PointCloud | ArrayLike, init_T_k_prev: ArrayLike | None = None
    ) -> JointStep:
        """Add the next frame and estimate its pose.

        Parameters
        ----------
        frame
            The new cloud ((N, 3) or :class:`PointCloud`) in the sensor frame.
        init_T_k_prev
            Optional (4, 4) guess of the motion from the previous frame into this one (e.g. a
            coarse registration); by default the previous inter-frame motion is repeated
            (constant velocity), or the identity at the second frame.

        Raises
        ------
        InputError, RegistrationError, DegenerateGeometryError
            From the pairwise registrations; the tracker state is unchanged when one is raised.
        """
        cfg = self.config
        cloud = as_registration_cloud(frame, "frame")
        covs = None
        if cfg.registration == "gicp":
            covs = compute_covariances(cloud, cfg.gicp.k_covariance, cfg.gicp.epsilon, self.workers)
        elif cfg.icp.method == "point_to_plane" and cloud.normals is None:
            # Each frame is the registration target exactly once: estimate its normals once.
            cloud = estimate_normals(cloud, cfg.icp.normals, workers=self.workers)
        k = self._count
        if not self._window:
            self._window.append(_Frame(cloud, covs, np.eye(4)))
            self._count += 1
            return JointStep(0, np.eye(4), np.zeros((6, 6)), ())

        prev = self._window[-1]
        if init_T_k_prev is not None:
            T_k_prev = se3.as_transform(init_T_k_prev, "init_T_k_prev")
        elif len(self._window) >= 2:
            T_k_prev = prev.T_k0 @ se3.invert(self._window[-2].T_k0)
        else:
            T_k_prev = np.eye(4)
        tree = VoxelIndex(cloud.points)
        # Newest pair first: its result seeds the guesses for the older, larger motions.
        X_k = T_k_prev @ prev.T_k0
        results: list[RegistrationResult] = []
        for past in reversed(self._window):
            res = self._register(past, cloud, covs, X_k @ se3.invert(past.T_k0), tree)
            if not results:
                X_k = res.T_target_source @ past.T_k0
            results.append(res)
        results.reverse()

        n = len(self._window)
        edges = [
            PoseGraphEdge(m, n, res.T_target_source, self._edge_information(res))
            for m, res in enumerate(results)
        ]
        poses = np.stack([f.T_k0 for f in self._window] + [X_k])
        graph = optimize_pose_graph(poses, edges, fixed=range(n))
        T_k0 = graph.poses[n]
        self._window.append(_Frame(cloud, covs, T_k0))
        self._count += 1
        return JointStep(k, T_k0, graph.covariances[n], tuple(results))

    def _register(
        self,
        past: _Frame,
        cloud: PointCloud,
        covs: NDArray[np.float64] | None,
        init_T_k_m: NDArray[np.float64],
        tree: VoxelIndex,
    ) -> RegistrationResult:
        """Register an earlier window frame (source) onto the new frame (target)."""
        if self.config.registration == "gicp":
            return gicp(
                past.cloud,
                cloud,
                init_T_k_m,
                self.config.gicp,
                self.workers,
                source_covariances=past.covariances,
                target_covariances=covs,
                target_tree=tree,
            )
        return icp(past.cloud, cloud, init_T_k_m, self.config.icp, self.workers, target_tree=tree)

    def _edge_information(self, result: RegistrationResult) -> NDArray[np.float64]:
        """Weight of a pair in the pose graph: identity, or the inverse of its covariance."""
        if self.config.weighting == "equal":
            return np.eye(6)
        if self.config.registration == "gicp":
            return result.information  # already noise-weighted (see gicp)
        # ICP information is in 1/m²; RegistrationResult.covariance scales it by the inlier RMSE.
        return result.information / max(result.inlier_rmse, np.finfo(float).tiny) ** 2
