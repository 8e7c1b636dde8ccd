"""A timed sequence of rigid poses: what trajectory files hold and what metrics compare."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from spacepose.core import se3
from spacepose.core.cloud import MAX_ABS_COORDINATE
from spacepose.errors import InputError


@dataclass(frozen=True, eq=False)
class Trajectory:
    """Poses ``T_sensor_target`` (or any ``T_a_b``) at given timestamps.

    The timestamps are kept in the given order (not sorted); evaluation pairs poses by time.

    Parameters
    ----------
    timestamps
        (N,) float64 seconds.
    poses
        (N, 4, 4) float64 rigid transforms, one per timestamp.
    source
        Where the data came from (a file name); used in error messages.

    Raises
    ------
    InputError
        If the trajectory is empty, the shapes disagree, a value is not finite or a pose is not a
        proper rigid transform (orthonormal rotation with determinant +1, last row (0, 0, 0, 1)).
    """

    timestamps: NDArray[np.float64]
    poses: NDArray[np.float64]
    source: str | None = None

    def __post_init__(self) -> None:
        se3.check_real(self.timestamps, "timestamps", self.source)
        se3.check_real(self.poses, "poses", self.source)
        try:
            t = np.asarray(self.timestamps, dtype=np.float64).reshape(-1)
            T = np.asarray(self.poses, dtype=np.float64)
        except (TypeError, ValueError) as exc:
            raise InputError(f"trajectory data are not numeric: {exc}", self.source) from None
        if T.ndim != 3 or T.shape[1:] != (4, 4):
            raise InputError(f"poses must have shape (N, 4, 4), got {T.shape}", self.source)
        if len(T) == 0:
            raise InputError("trajectory is empty", self.source)
        if len(t) != len(T):
            raise InputError(f"{len(t)} timestamps for {len(T)} poses", self.source)
        if not np.all(np.isfinite(t)):
            raise InputError("trajectory has non-finite timestamps", self.source)
        bad = ~np.isfinite(T).all(axis=(1, 2))
        if bad.any():
            raise InputError(f"pose {int(np.argmax(bad))} has non-finite entries", self.source)
        # Beyond this a squared error overflows: such a translation is a corrupt value.
        far = np.abs(T[:, :3, 3]).max(axis=1) > MAX_ABS_COORDINATE
        if far.any():
            raise InputError(
                f"pose {int(np.argmax(far))} has a translation beyond {MAX_ABS_COORDINATE:.0e} m",
                self.source,
            )
        bad = se3.non_rigid(T)
        if bad.any():
            raise InputError(f"pose {int(np.argmax(bad))} is not a rigid transform", self.source)
        for name, value in (("timestamps", t), ("poses", T)):
            value = np.array(value, dtype=np.float64, order="C")
            value.setflags(write=False)
            object.__setattr__(self, name, value)

    def __len__(self) -> int:
        return len(self.timestamps)

    @property
    def positions(self) -> NDArray[np.float64]:
        """(N, 3) translation parts of the poses, metres."""
        return self.poses[:, :3, 3]

    def rebased_first(self) -> Trajectory:
        """The trajectory expressed relative to its first pose (methods.md §0, model-free tracking).

        Pose k becomes ``poses[k] @ inv(poses[0])``, so the first pose is the identity and each
        pose is the motion since the first frame, in the frame the poses map into.
        """
        T0_inv = se3.invert(self.poses[0])
        return Trajectory(self.timestamps, self.poses @ T0_inv, source=self.source)
