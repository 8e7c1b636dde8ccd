"""The start of a navigation filter (methods.md §2.4, Initialisation): the run's orbit geometry
and the EKF's initial state from one coarse pose.

:func:`scenario_geometry` reads the orbital mean motion n (rad/s) and the constant sensor
(chaser) attitude ``R_O_C`` (3, 3) from a run's scenario description. :func:`start_filter`
initialises a :class:`~spacepose.core.ekf.RelativeNavEKF` at time t (s) from a coarse pose
``T_sensor_model`` (4, 4, model frame B' into sensor frame C, m): ``q_I_B`` from its rotation,
``rho = R_O_C t`` in O (m; the CoM offset Δ starts at 0, so ρ is the B' origin), ``v = 0``, and
ω and the inertia ratios k from the configured priors. Which poses start a filter (a prior's, or
the lost-in-space hypotheses) is decided by :class:`spacepose.core.navigation.RelativeNavigator`.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
from numpy.typing import NDArray
from scipy.spatial.transform import Rotation

from spacepose.core import dynamics, se3
from spacepose.core.config import holds_boolean, holds_text
from spacepose.core.ekf import RelativeNavEKF
from spacepose.core.nav_config import NavigationConfig
from spacepose.core.nav_state import NavState
from spacepose.errors import InputError

__all__ = ["scenario_geometry", "start_filter"]


# The fastest orbit about any body: √(Gρ·4π/3) at its surface is 1.2e-3 rad/s for the Earth
# (ρ 5.5 g/cm³) and below 2e-3 rad/s for iron; a mean motion ten times that is a wrong unit.
_MAX_MEAN_MOTION = 0.02


def scenario_geometry(
    scenario: Mapping[str, Any], source: str = "scenario.json"
) -> tuple[float, NDArray[np.float64]]:
    """Mean motion n (rad/s) and ``R_O_C`` (3, 3) from a run's scenario description.

    Raises
    ------
    InputError
        A key is missing, or ``R_O_C`` is not a rotation matrix, or n is not positive.
    """
    for key in ("mean_motion", "R_O_C"):
        if key not in scenario:
            raise InputError(f"missing key {key!r} (navigation needs an orbit run)", source)
    for key in ("mean_motion", "R_O_C"):
        if holds_boolean(scenario[key]):
            raise InputError(f"{key} holds a yes/no where a number goes", source)
        if holds_text(scenario[key]):
            if _spelt_non_finite(scenario[key]):
                # JSON's NaN and Infinity read as text through YAML.
                raise InputError(f"{key} must be finite, got {scenario[key]!r}", source)
            raise InputError(f"{key} holds text where a number goes (write it unquoted)", source)
    if isinstance(scenario["mean_motion"], list | tuple | dict):
        kind = "a mapping" if isinstance(scenario["mean_motion"], dict) else "a list"
        raise InputError(f"mean_motion must be one number, got {kind}", source)
    try:
        n = float(scenario["mean_motion"])
        R = np.asarray(scenario["R_O_C"], dtype=np.float64)
    except (TypeError, ValueError):
        problem = (
            "mean_motion must be a number"
            if not isinstance(scenario["mean_motion"], int | float)
            else "R_O_C must be a 3x3 rotation matrix of numbers"
        )
        raise InputError(problem, source) from None
    if not np.isfinite(n) or n <= 0:
        raise InputError(f"mean_motion must be positive, got {n}", source)
    if n > _MAX_MEAN_MOTION:
        raise InputError(
            f"mean_motion {n:.4g} rad/s is an orbit of {2 * np.pi / n:.3g} s: no body is dense "
            f"enough (at most {_MAX_MEAN_MOTION} rad/s; rad/s, not rad/min or deg/s?)",
            source,
        )
    try:
        R = se3.typed_rotation(R, "R_O_C")
    except InputError as exc:
        raise InputError(exc.reason, source) from None
    return n, R


def _spelt_non_finite(value: Any) -> bool:
    """Whether ``value`` (text, or lists of it) spells NaN or an infinity somewhere."""
    if isinstance(value, list | tuple):
        return any(_spelt_non_finite(v) for v in value)
    try:
        return isinstance(value, str) and not np.isfinite(float(value))
    except ValueError:
        return False


def start_filter(
    t: float,
    T_sensor_model: NDArray[np.float64],
    mean_motion: float,
    R_O_C: NDArray[np.float64],
    config: NavigationConfig,
) -> RelativeNavEKF:
    """Filter initialised from a coarse pose ``T_sensor_model`` (4, 4) at time ``t`` (Δ = 0,
    so ρ is the B' origin), ω and k from the config's priors."""
    R_I_B = dynamics.R_I_O(mean_motion, t) @ R_O_C @ T_sensor_model[:3, :3]
    initial = NavState(
        t,
        R_O_C @ T_sensor_model[:3, 3],
        np.zeros(3),
        Rotation.from_matrix(R_I_B).as_quat(),
        np.deg2rad(config.init_rate_deg_s),
        np.asarray(config.init_k, dtype=np.float64),
        np.zeros(3),
    )
    return RelativeNavEKF(mean_motion, R_O_C, initial, config.ekf)
