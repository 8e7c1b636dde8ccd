"""What the rectangle navigation reports (methods.md §2.4): a :class:`NavRow` per frame, the
:class:`Candidate` filters while the pose is ambiguous, and the NAV.csv table.

A row holds the :class:`~spacepose.core.nav_state.NavState` after the frame's updates, in the
filter's frames and SI units: ``t`` (s), ``rho`` and ``v`` in O (m, m/s), ``q_I_B`` (B -> I,
scalar last), ``omega_B`` (rad/s, in B), the inertia ratios ``k`` and the CoM offset ``com`` in B
(m); then 1-σ per block (``att`` a rotation vector, rad), the number of rectangles used and a
status. :data:`NAV_COLUMNS` names the 40 columns in that order (``sig_<block>_<axis>`` for the
σ's); :func:`nav_table` turns rows into one list of values each, NaN before initialisation and
while ambiguous.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from spacepose.core.nav_state import NavState

__all__ = ["NAV_COLUMNS", "Candidate", "NavRow", "nav_table"]

STATE_COLUMNS = (
    "t,rho_x,rho_y,rho_z,v_x,v_y,v_z,qx,qy,qz,qw,w_x,w_y,w_z,k_x,k_y,k_z,com_x,com_y,com_z"
).split(",")
SIGMA_COLUMNS = [
    f"sig_{name}_{axis}" for name in ("rho", "v", "att", "w", "k", "com") for axis in "xyz"
]
NAV_COLUMNS = [*STATE_COLUMNS, *SIGMA_COLUMNS, "n_rect", "status"]


@dataclass(frozen=True, eq=False)
class Candidate:
    """One candidate filter's estimate while the target's pose is ambiguous.

    Attributes
    ----------
    state
        The candidate filter's estimate after the frame.
    explained
        Share of the frame its pose explains (:func:`lost_in_space.explained_share`), in [0, 1].
    """

    state: NavState
    explained: float


@dataclass(frozen=True, eq=False)
class NavRow:
    """The navigation output of one frame.

    Attributes
    ----------
    state
        The estimate after the frame's updates; None before initialisation and while ambiguous.
    sigmas
        1-σ per block (``rho, v, att, omega, k, com``), None when ``state`` is.
    n_rect
        Rectangles recognised and used in this frame (by the best candidate while ambiguous).
    status
        ``waiting`` (no filter yet), ``ambiguous`` (several candidate filters explain the data
        equally well: no state, see ``candidates``), ``init`` (first frame with a state),
        ``update`` (at least one measurement used) or ``predict`` (prediction only).
    coarse_T_sensor_model
        Coarse pose of the frame from its rectangles after the 4-fold fix (4, 4), or None.
    raw_T_sensor_model
        Coarse pose from the largest rectangle's raw eigenvector frame (no 4-fold fix), or None;
        kept for the ablation of the fix.
    candidates
        The candidate filters' estimates when ``status`` is ``ambiguous``, best first.
    problem
        What went wrong in the frame, or None: the plane search refused its points (it is then
        a prediction-only step), or a gap before it too long to predict across (the filter
        starts again).
    """

    t: float
    state: NavState | None
    sigmas: dict[str, NDArray[np.float64]] | None
    n_rect: int
    status: str
    coarse_T_sensor_model: NDArray[np.float64] | None = None
    raw_T_sensor_model: NDArray[np.float64] | None = None
    candidates: tuple[Candidate, ...] = ()
    problem: str | None = None

    def values(self) -> list[float | int | str]:
        """The row in the order of :data:`NAV_COLUMNS` (NaN before initialisation)."""
        if self.state is None or self.sigmas is None:
            numbers = [self.t] + [float("nan")] * (len(STATE_COLUMNS) + len(SIGMA_COLUMNS) - 1)
        else:
            s = self.state
            numbers = [s.t, *s.rho, *s.v, *s.q_I_B, *s.omega_B, *s.k, *s.com]
            numbers += [float(v) for key in ("rho", "v", "att", "omega", "k", "com")
                        for v in self.sigmas[key]]  # fmt: skip
        return [*numbers, self.n_rect, self.status]


def nav_table(rows: Sequence[NavRow]) -> tuple[list[str], list[list[float | int | str]]]:
    """Column names (:data:`NAV_COLUMNS`) and one list of values per row."""
    return list(NAV_COLUMNS), [row.values() for row in rows]
