"""The simulator (methods.md §3): targets, range sensors and the lab and orbit scenarios."""

from spacepose.core.sim.grid import grid_scenario
from spacepose.core.sim.mesh_files import load_mesh
from spacepose.core.sim.orbit_truth import mean_motion
from spacepose.core.sim.scenarios import (
    TRUTH_COLUMNS,
    LabConfig,
    OrbitConfig,
    scenario_config,
    simulate,
    simulate_lab,
    simulate_orbit,
)
from spacepose.core.sim.sensors import SENSOR_PRESETS, SensorConfig, sensor_config
from spacepose.core.sim.simulation import Frame, Simulation
from spacepose.core.sim.targets import (
    Rectangle,
    Target,
    lab_target,
    orbit_target,
    sample_surface,
    symmetric_orbit_target,
)

__all__ = [
    "SENSOR_PRESETS",
    "TRUTH_COLUMNS",
    "Frame",
    "LabConfig",
    "OrbitConfig",
    "Rectangle",
    "SensorConfig",
    "Simulation",
    "Target",
    "grid_scenario",
    "lab_target",
    "load_mesh",
    "mean_motion",
    "orbit_target",
    "sample_surface",
    "scenario_config",
    "sensor_config",
    "simulate",
    "simulate_lab",
    "simulate_orbit",
    "symmetric_orbit_target",
]
