"""Li et al.'s J-ICP (Li §2.3.2, Eqs. 8–9; docs/methods.md §1.6), exactly, for any length.

Li registers three consecutive frames i (oldest), j, k (newest) pairwise by ICP, with the newer
frame as the reference of each pair (Eq. 8 with P_r the newer frame): ``T_ji``, ``T_ki`` and
``T_kj``, where ``T_ba`` maps frame a into frame b. The motion from j to k is the average of the
direct estimate ``T_kj`` and the indirect one through frame i, ``T_ki · T_ji⁻¹`` (Eq. 9), and
the poses are chained, ``T_k0 = ΔT_kj · T_j0``. ``T_ji`` is the registration made when frame j
was the newest; every pose is projected back onto SE(3) as it is chained, so that rounding cannot
grow along a run of any length.

:func:`average_three` is Eq. 9 on SE(3), :func:`average_three_covariance` its first-order
covariance, :class:`JointICP` the scheme over a sequence. The tracker runs the same step with its
health checks as method ``jicp`` (:mod:`spacepose.core.frame_registration`).
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from spacepose.core import se3
from spacepose.core.cloud import PointCloud
from spacepose.core.config import StageConfig
from spacepose.core.gicp import GICPConfig, gicp
from spacepose.core.gicp_covariances import compute_covariances
from spacepose.core.grid import VoxelIndex
from spacepose.core.icp import ICPConfig, as_registration_cloud, icp
from spacepose.core.motion import rigid
from spacepose.core.normals import estimate_normals
from spacepose.core.registration import RegistrationResult
from spacepose.errors import InputError


class JICPConfig(StageConfig):
    """Parameters of :class:`JointICP` (and of the tracker's method ``jicp``).

    Attributes
    ----------
    registration
        Pairwise registration of the frames: ``"icp"`` (with ``icp``; Li's Eq. 6 is
        point-to-point, the default) or ``"gicp"`` (with ``gicp``).
    icp, gicp
        Configs of the pairwise registration.
    """

    registration: Literal["icp", "gicp"] = "icp"
    icp: ICPConfig = ICPConfig(method="point_to_point")
    gicp: GICPConfig = GICPConfig()


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
    transform M with ``log(T_kj M⁻¹) = −log(T_ki T_ji⁻¹ M⁻¹)``; to first order its twist is Li's
    ``½((ξ_ki − ξ_ji) + ξ_kj)``. Chain ``T_k0 = ΔT_kj · T_j0``.
    """
    T_kj = se3.as_transform(T_kj, "T_kj")
    indirect = se3.as_transform(T_ki, "T_ki") @ se3.invert(se3.as_transform(T_ji, "T_ji"))
    return rigid(T_kj @ se3.exp(0.5 * se3.log(se3.invert(T_kj) @ indirect)))


def average_three_covariance(
    T_ki: ArrayLike,
    T_ji: ArrayLike,
    cov_kj: ArrayLike,
    cov_ki: ArrayLike,
    cov_ji: ArrayLike,
) -> NDArray[np.float64]:
    """First-order covariance (6, 6) of :func:`average_three`'s ``ΔT_kj``.

    Parameters
    ----------
    T_ki, T_ji
        (4, 4) the registrations through frame i.
    cov_kj, cov_ki, cov_ji
        (6, 6) covariances of ``T_kj``, ``T_ki`` and ``T_ji``, each a left perturbation in the
        frame it maps into (k, k and j), twist (omega, v); the three taken as independent.

    Returns
    -------
    ``¼ (C_kj + C_ki + Ad C_ji Adᵀ)`` with ``Ad`` the adjoint of ``T_ki T_ji⁻¹``: the indirect
    estimate's error is ``δ_ki − Ad δ_ji`` and the midpoint halves the sum of the two errors.
    """
    T_ki, T_ji = se3.as_transform(T_ki, "T_ki"), se3.as_transform(T_ji, "T_ji")
    C_kj, C_ki, C_ji = (
        _covariance6(c, name)
        for c, name in ((cov_kj, "cov_kj"), (cov_ki, "cov_ki"), (cov_ji, "cov_ji"))
    )
    Ad = se3.adjoint(T_ki @ se3.invert(T_ji))
    return 0.25 * (C_kj + C_ki + Ad @ C_ji @ Ad.T)


def _covariance6(values: ArrayLike, name: str) -> NDArray[np.float64]:
    """A finite, symmetric, positive semi-definite (6, 6) covariance (a 5×5 one ended in
    numpy's broadcast error, text in a UFuncTypeError, NaN in a NaN covariance, and a negative
    or lopsided one came out as a "covariance" with a negative eigenvalue or two different
    off-diagonal entries)."""
    C = se3.real_array(values, name)
    if C.shape != (6, 6) or not np.isfinite(C).all():
        raise InputError(f"{name} must be a finite 6x6 covariance, got shape {C.shape}")
    scale = float(np.abs(C).max())
    if np.abs(C - C.T).max() > 1e-9 * scale:
        raise InputError(f"{name} must be symmetric, as a covariance is")
    eig = np.linalg.eigvalsh(C)
    if eig[0] < -1e-9 * scale:
        raise InputError(f"{name} must be positive semi-definite, got eigenvalue {eig[0]:.3g}")
    return C


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
        (6, 6) covariance of ``T_k0`` (left perturbation in frame k, (omega, v)): the pairwise
        registrations' covariances carried along the chain; zero for k = 0.
    pairwise
        The registrations of the earlier frames onto frame k, oldest first (``T_ki``, ``T_kj``;
        only ``T_10`` at k = 1); their ``T_target_source`` is ``T_km``.
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
    cov_k0: NDArray[np.float64]
    # This frame's direct registration onto the frame before it (T_jm, its covariance).
    direct: tuple[NDArray[np.float64], NDArray[np.float64]] | None


class JointICP:
    """Li's J-ICP over a sequence: each frame against its two predecessors, Eq. 9, chained.

    Parameters
    ----------
    config
        Pairwise registration.
    workers
        Threads for neighbour searches (results do not depend on it).

    Examples
    --------
    >>> tracker = JointICP(JICPConfig())                      # doctest: +SKIP
    >>> poses = [tracker.step(cloud).T_k0 for cloud in frames]  # doctest: +SKIP
    """

    def __init__(self, config: JICPConfig = JICPConfig(), workers: int = -1) -> None:
        self.config = config
        self.workers = workers
        self._window: deque[_Frame] = deque(maxlen=2)
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
            self._window.append(_Frame(cloud, covs, np.eye(4), np.zeros((6, 6)), None))
            self._count += 1
            return JointStep(0, np.eye(4), np.zeros((6, 6)), ())

        j = self._window[-1]
        if init_T_k_prev is not None:
            T_k_prev = se3.as_transform(init_T_k_prev, "init_T_k_prev")
        elif len(self._window) == 2:
            T_k_prev = rigid(j.T_k0 @ se3.invert(self._window[0].T_k0))
        else:
            T_k_prev = np.eye(4)
        tree = VoxelIndex(cloud.points)
        # Frame j onto k (direct), then frame i onto k, started from the direct estimate.
        res_kj = self._register(j, cloud, covs, T_k_prev, tree)
        T_kj, cov_kj = res_kj.T_target_source, self._covariance(res_kj)
        delta, cov_delta, pairwise = T_kj, cov_kj, (res_kj,)
        if len(self._window) == 2:
            i = self._window[0]
            T_ji, cov_ji = j.direct
            res_ki = self._register(i, cloud, covs, T_kj @ T_ji, tree)
            T_ki = res_ki.T_target_source
            delta = average_three(T_kj, T_ki, T_ji)
            cov_delta = average_three_covariance(
                T_ki, T_ji, cov_kj, self._covariance(res_ki), cov_ji
            )
            pairwise = (res_ki, res_kj)
        T_k0 = rigid(delta @ j.T_k0)
        Ad = se3.adjoint(delta)
        cov_k0 = cov_delta + Ad @ j.cov_k0 @ Ad.T
        self._window.append(_Frame(cloud, covs, T_k0, cov_k0, (T_kj, cov_kj)))
        self._count += 1
        return JointStep(k, T_k0, cov_k0, pairwise)

    def _register(
        self,
        past: _Frame,
        cloud: PointCloud,
        covs: NDArray[np.float64] | None,
        init_T_k_m: NDArray[np.float64],
        tree: VoxelIndex,
    ) -> RegistrationResult:
        """Register an earlier frame (source) onto the new frame (target, Li's reference)."""
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

    def _covariance(self, result: RegistrationResult) -> NDArray[np.float64]:
        """Covariance of a pair (left perturbation in the newer frame); GICP's is noise-weighted."""
        return result.covariance(1.0) if self.config.registration == "gicp" else result.covariance()
