"""Lab scenarios from the coordinates of the robustness grid (target, range, noise, motion, ...).

:func:`grid_scenario` turns one cell of the grid into a :class:`LabConfig`. The scene is the lab
scene (:mod:`spacepose.core.sim.lab_scene`) scaled to the range: unless told otherwise, the
target spans the same share of the sensor's horizontal field of view as the 0.89 m mock-up does
from 1.2 m in the ToF camera (56 %), the slide steps and the turntable scale with it, and the
wall stands at 5/3 of the range, as in the lab (2 m behind a target at 1.2 m). The sensor is the
ToF camera while the farthest surface of the scene is within its range, the flash LiDAR beyond
(a target at 25 m); either can be named.
"""

from __future__ import annotations

import math
import re
from pathlib import Path

from spacepose.core.config import validate_config
from spacepose.core.sim.lab_scene import LAB_TARGET_EXTENT_M
from spacepose.core.sim.scenarios import LabConfig
from spacepose.core.sim.sensors import SENSOR_PRESETS, sensor_config
from spacepose.errors import ConfigError

MOTIONS = ("constant", "accelerating", "tumbling-2", "tumbling-5", "tumbling-10")
CLUTTERS = ("none", "wall-table", "wall")
LAB_RANGE_M = 1.2  # the lab run's range, where the grid's scene is the lab scene itself
LAB_WALL_M = 2.0  # the lab's wall distance
_TUMBLING = re.compile(r"tumbling-(\d+(?:\.\d+)?)")


def motion_fields(motion: str) -> dict[str, object]:
    """The :class:`LabConfig` fields of a motion name of :data:`MOTIONS` (``tumbling-D``: any D).

    Raises
    ------
    ConfigError
        An unknown motion name.
    """
    tumbling = _TUMBLING.fullmatch(motion)
    if tumbling:
        degrees = float(tumbling.group(1))
        if not 0.0 < degrees <= 90.0:
            # Named as given, not as the scenario's tumble_deg field a user never wrote.
            raise ConfigError(f"motion {motion!r}: D must lie in (0, 90] degrees a frame")
        return {"motion": "tumbling", "tumble_deg": degrees}
    if motion in ("constant", "accelerating"):
        return {"motion": motion}
    raise ConfigError(
        f"unknown motion {motion!r}; choose constant, accelerating or tumbling-D (D deg a frame)"
    )


def scaled_target_size(sensor: str, range_m: float) -> float:
    """Largest target extent (m) spanning the mock-up's share of the ToF view from 1.2 m."""
    tan_half = math.tan(math.radians(0.5 * sensor_config(sensor).fov_deg[0]))
    tan_tof = math.tan(math.radians(0.5 * sensor_config("tof").fov_deg[0]))
    return LAB_TARGET_EXTENT_M * (range_m / LAB_RANGE_M) * (tan_half / tan_tof)


def grid_scenario(
    *,
    target: str = "lab",
    range_m: float = LAB_RANGE_M,
    noise_scale: float = 1.0,
    motion: str = "constant",
    clutter: str = "none",
    seed: int = 0,
    frames: int = 58,
    sensor: str | None = None,
    target_size_m: float | None = None,
) -> LabConfig:
    """The lab config of one grid cell.

    Parameters
    ----------
    target
        ``"lab"`` (the procedural mock-up) or the path of a mesh file.
    range_m
        Distance from the sensor to the target (turntable axis), m.
    noise_scale
        Multiplier of the sensor's range σ.
    motion
        One of :data:`MOTIONS`: ``constant`` (the lab's steps), ``accelerating`` or
        ``tumbling-D`` (D degrees a frame about a precessing axis; any D in (0, 90]).
    clutter
        ``none``, ``wall-table`` (the lab's wall and turntable) or ``wall`` (the wall alone:
        the target floats in front of it).
    seed
        Seed of every random draw.
    frames
        Number of frames.
    sensor
        A sensor preset (:data:`~spacepose.core.sim.sensors.SENSOR_PRESETS`); None: ``tof`` if
        its ``max_range`` reaches the wall, else ``flash-lidar``.
    target_size_m
        Largest extent of the target, m; None: the lab mock-up's share of the field of view at
        this range (0.89 m at 1.2 m in the ToF camera).

    Raises
    ------
    ConfigError
        An unknown motion, clutter or sensor, or an out-of-range value.
    """
    if not (math.isfinite(range_m) and range_m > 0):
        raise ConfigError(f"grid range must be a positive number of metres, got {range_m}")
    wall = LAB_WALL_M * range_m / LAB_RANGE_M
    if sensor is None:
        sensor = "tof" if SENSOR_PRESETS["tof"].max_range >= wall else "flash-lidar"
    if sensor not in SENSOR_PRESETS:
        raise ConfigError(f"unknown sensor {sensor!r}; choose one of: {', '.join(SENSOR_PRESETS)}")
    if clutter not in CLUTTERS:
        raise ConfigError(f"unknown clutter {clutter!r}; choose one of: {', '.join(CLUTTERS)}")
    fields = motion_fields(motion)
    if target_size_m is None:
        target_size_m = scaled_target_size(sensor, range_m)
    scale = target_size_m / LAB_TARGET_EXTENT_M
    if target != "lab":
        fields["model"] = str(Path(target))
    fields |= {
        "frames": frames,
        "seed": seed,
        "range_m": range_m,
        "target_size_m": target_size_m,
        "step_m": LabConfig.model_fields["step_m"].default * scale,
        "background": clutter != "none",
        "turntable": clutter == "wall-table",
        "wall_distance_m": wall,
        "sensor": sensor_config(sensor, noise_scale=noise_scale),
    }
    return validate_config(LabConfig, fields, source="grid scenario")
