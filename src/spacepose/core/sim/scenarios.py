"""The simulated scenarios of methods.md §3: the lab slide-and-turntable run and the orbit run.

Each builds a :class:`~spacepose.core.sim.simulation.Simulation`, the run whose frames are
rendered on demand (:mod:`spacepose.core.sim.simulation`).

Lab (Li et al.): the sensor is fixed and level (sensor −y is up). The target sits on a turntable
carried by a slide; the table frame has the sensor's axes and its origin on the turntable axis at
the target-frame origin. Frame k: slide offset ``x_k`` along sensor x and turntable angle ``θ_k``
about the vertical, both centred on the middle frame so the target stays in view:
``T_sensor_target(k) = Trans(x_k, 0, range) · Rot(−y, θ_k) · R_table_model``. The motion
profiles (constant steps, accelerating, tumbling), the target's size and the clutter are in
:mod:`spacepose.core.sim.lab_scene`; :mod:`spacepose.core.sim.grid` builds a lab config from the
coordinates of the robustness grid.

Orbit (Yu et al., methods.md §2.4): I coincides with O at t = 0, O turns about −y_O at the mean
motion n; ρ = target CoM − chaser CoM in O comes from both spacecraft propagated in inertial
two-body + J2 dynamics (optionally eccentric, optionally drag) and the target's torque-free
attitude from its own integrator (:mod:`spacepose.core.sim.orbit_truth`), not from the filter's
model; the sensor frame C is the chaser frame with a constant ``R_O_C`` whose boresight points
at the initial ρ. A model point x' (in B') sits at ``x_B = x' − Δ``, so
``T_C_B' = [R_C_O R_O_B,  R_C_O (ρ − R_O_B Δ)]``. The scenario hands the filter ``R_O_C`` and
the catalogue with seeded knowledge errors (``R_O_C_true`` and ``rectangles_true`` are exact).
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray
from pydantic import Field, field_validator
from scipy.spatial.transform import Rotation

from spacepose.core import dynamics
from spacepose.core.config import StageConfig, square_stays_finite, validate_config
from spacepose.core.sim.lab_scene import MotionProfile, lab_background, lab_poses, sized_target
from spacepose.core.sim.mesh_files import load_mesh
from spacepose.core.sim.orbit_truth import (
    EARTH_RADIUS,
    ForceModel,
    keplerian_state,
    mean_motion,
    misaligned,
    perturbed_catalogue,
    relative_truth,
    torque_free_attitude,
)
from spacepose.core.sim.process_noise import model_defect
from spacepose.core.sim.random_targets import generated_seed, random_spacecraft
from spacepose.core.sim.sensors import SENSOR_PRESETS, SensorConfig, sensor_config
from spacepose.core.sim.simulation import Simulation
from spacepose.core.sim.targets import Target, lab_target, orbit_target
from spacepose.errors import ConfigError

TRUTH_COLUMNS = (
    "t,rho_x,rho_y,rho_z,v_x,v_y,v_z,qx,qy,qz,qw,w_x,w_y,w_z,k_x,k_y,k_z,com_x,com_y,com_z"
).split(",")
# Boresight z_C along +x_O (the target ahead), y_C towards the Earth (+z_O), x_C = y_C × z_C.
R_O_C_AHEAD = np.array([[0.0, 0.0, 1.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]])
# Farthest a spacecraft's surface lies from its centre (m): the ISS's is 55 m.
_LARGEST_REACH_M = 100.0


class _ScenarioConfig(StageConfig):
    # A million frames (11 days at 1 Hz): larger counts are typos that exhaust memory.
    frames: int = Field(ge=1, le=1_000_000, description="Number of frames.")
    rate_hz: float = Field(1.0, gt=0, description="Frame rate, Hz.")
    seed: int = Field(0, ge=0, description="Seed of every random draw of the run.")
    model: str | None = Field(
        None,
        description="Mesh file replacing the procedural target, or random:K (a generated "
        "spacecraft, core.sim.random_targets).",
    )
    model_scale: float = Field(1.0, gt=0, description="Scale applied to the mesh.")
    model_points: int = Field(20000, ge=100, description="Surface samples in model.ply.")


class LabConfig(_ScenarioConfig):
    """The lab run of methods.md §3 (Li et al.): a ToF camera, a mock-up on slide and turntable."""

    frames: int = Field(58, ge=1, le=1_000_000, description="Number of frames.")
    sensor: SensorConfig = Field(default_factory=lambda: SENSOR_PRESETS["tof"])
    range_m: float = Field(1.2, gt=0, description="Turntable axis distance from the sensor, m.")
    step_m: float = Field(0.010, description="Slide step per frame along sensor x, m.")
    step_deg: float = Field(1.0, description="Turntable step per frame about the vertical, deg.")
    yaw_center_deg: float = Field(
        0.0, description="Turntable angle at the middle frame; 0 = dish facing the sensor."
    )
    tilt_deg: float = Field(
        20.0, description="Mock-up tilt on the table about its wing axis, so its top is seen."
    )
    background: bool = Field(False, description="Add a wall and the turntable to the scene.")
    turntable: bool = Field(
        True, description="With background: the turntable under the target (False: the wall alone)."
    )
    wall_distance_m: float = Field(2.0, gt=0, description="Wall distance along the boresight.")
    motion: MotionProfile = Field(
        "constant", description="constant, accelerating or tumbling (see lab_scene)."
    )
    tumble_deg: float = Field(
        5.0, ge=0, le=90, description="tumbling: rotation angle of every frame step, deg."
    )
    tumble_cone_deg: float = Field(
        30.0, ge=0, lt=90, description="tumbling: spin axis to angular momentum angle, deg."
    )
    target_size_m: float | None = Field(
        None, gt=0, description="Scale the target to this largest extent, m (None: as built)."
    )
    target_albedo: float = Field(1.0, gt=0, le=1, description="Target reflectance.")

    # 1e100 leaked numpy's overflow warnings from the renderer's face normals (a cross product
    # of coordinates, squared) before "the sensor sees nothing".
    _size_squares_finite = field_validator("target_size_m")(square_stays_finite)


class OrbitConfig(_ScenarioConfig):
    """The orbit run of methods.md §3 (Yu et al.): a flash LiDAR 25 m from a tumbling satellite."""

    frames: int = Field(600, ge=1, le=1_000_000, description="Number of frames.")
    sensor: SensorConfig = Field(default_factory=lambda: SENSOR_PRESETS["flash-lidar"])
    altitude_m: float = Field(
        500e3, gt=0, description="Chaser's perigee altitude (the circle's for e = 0), m."
    )
    eccentricity: float = Field(0.0, ge=0, lt=0.5, description="Chaser's orbit eccentricity.")
    inclination_deg: float = Field(51.6, ge=0, le=180, description="Orbit inclination, deg.")
    true_anomaly_deg: float = Field(0.0, description="Chaser's true anomaly at t = 0, deg.")
    j2: bool = Field(True, description="Include the Earth's J2 term in the truth.")
    drag_density: float = Field(0.0, ge=0, description="Air density for drag, kg/m³ (0: none).")
    ballistic_m2_kg: tuple[float, float] = Field(
        (0.01, 0.02), description="C_D A / m of the chaser and the target, m²/kg (drag only)."
    )
    chaser_attitude_sigma_deg: float = Field(
        0.01, ge=0, description="1σ per axis of the chaser attitude R_O_C the filter is given."
    )
    catalogue_sigma_m: float = Field(
        0.002, ge=0, description="1σ of the catalogue centres and sides the filter is given, m."
    )
    standoff_m: float = Field(25.0, gt=0, description="Chaser distance behind the target, m.")
    velocity_perturbation: float = Field(
        0.002,
        ge=0,
        description="Magnitude of the initial relative velocity (seeded random direction), m/s.",
    )
    inertia: tuple[float, float, float] = Field((1200.0, 1000.0, 800.0), description="kg·m².")
    rate_deg_s: tuple[float, float, float] = Field(
        (1.0, -2.0, 1.5), description="Initial angular rate in B, deg/s."
    )
    com_offset: tuple[float, float, float] = Field(
        (0.02, -0.03, 0.05), description="Δ: B' origin → B origin, in B, m."
    )
    attitude_zyx_deg: tuple[float, float, float] = Field(
        (30.0, -20.0, 45.0), description="Initial R_I_B as intrinsic ZYX Euler angles, deg."
    )


def _target(config: LabConfig | OrbitConfig, procedural: Target) -> Target:
    if config.model is None:
        return procedural
    seed = generated_seed(config.model)
    if seed is None:
        return load_mesh(Path(config.model), scale=config.model_scale)
    target = random_spacecraft(seed)
    if config.model_scale == 1.0:
        return target
    return sized_target(target, config.model_scale * float(np.max(target.mesh.extents)))


def simulate_lab(config: LabConfig | None = None) -> Simulation:
    """The lab run (methods.md §3): 58 ToF frames of the mock-up on the slide and turntable."""
    config = config or LabConfig()
    target = _target(config, lab_target())
    target = sized_target(target, config.target_size_m, align=config.model is not None)
    # The target's origin is on the turntable axis, range_m ahead; the slide only moves it aside.
    _check_within_range(config, "a range", config.range_m, target)
    T_sensor_table, T_sensor_target = lab_poses(config)
    background, albedo = (), (config.target_albedo,)
    if config.background:
        _check_wall(config, target, T_sensor_target)
        background, albedo = lab_background(config, target, T_sensor_table)
    return Simulation(
        name="lab",
        config=config,
        target=target,
        timestamps=np.arange(config.frames) / config.rate_hz,
        T_sensor_target=T_sensor_target,
        background=background,
        albedo=albedo,
    )


def _check_wall(config: LabConfig, target: Target, T_sensor_target: NDArray[np.float64]) -> None:
    """Refuse a wall before or through the target: it would hide it from every frame (a lab
    run moved to 3 m kept its wall at 2 m, and every frame saw the wall alone)."""
    hull = target.mesh.convex_hull.vertices
    depths = T_sensor_target[:, 2, :3] @ hull.T + T_sensor_target[:, 2, 3:]
    farthest = float(depths.max())
    if config.wall_distance_m <= farthest:
        raise ConfigError(
            f"the wall at {config.wall_distance_m:g} m stands before or through the target "
            f"(up to {farthest:.3g} m from the sensor): it would hide it; place the wall beyond "
            "it (wall_distance_m; simulate --grid puts it at 5/3 of the range)"
        )


def _check_within_range(
    config: LabConfig | OrbitConfig,
    what: str,
    distance: float,
    target: Target,
    remedy: str = "place it nearer",
) -> None:
    """Refuse a target whose every point lies beyond the sensor's range from ``distance`` (its
    centre's): it would see nothing, and the lab's --range 1e300 leaked numpy's overflow
    warnings from the renderer before saying so."""
    reach = float(np.max(np.linalg.norm(target.mesh.vertices, axis=1)))
    if distance - reach > config.sensor.max_range:
        name = "orbit" if isinstance(config, OrbitConfig) else "lab"
        raise ConfigError(
            f"scenario {name}: {what} of {distance:g} m puts the whole target (reaching "
            f"{reach:.3g} m from its centre) beyond the sensor's {config.sensor.max_range:g} m "
            f"range: it would see nothing; {remedy}"
        )


def orbit_mean_motion(config: OrbitConfig) -> float:
    """The filter's mean motion n (rad/s): that of the chaser's initial osculating orbit."""
    a = (EARTH_RADIUS + config.altitude_m) / (1.0 - config.eccentricity)
    return mean_motion(a - EARTH_RADIUS)


def orbit_truth(config: OrbitConfig) -> NDArray[np.float64]:
    """True states of the orbit run: (N, 20) rows with the columns :data:`TRUTH_COLUMNS`.

    The chaser flies the configured orbit (perigee altitude, e, inclination, true anomaly at
    t = 0; ascending node and perigee on the ECI x axis); the target starts ``standoff_m``
    ahead in the chaser's LVLH, keeping station to first order, plus a seeded velocity
    perturbation of magnitude ``velocity_perturbation``. Both are propagated in two-body + J2
    (+ drag) dynamics and ρ, ρ̇ expressed in the filter's O; q = R_I_B and ω in B from an
    independent torque-free integration; k and Δ constant
    (:mod:`spacepose.core.sim.orbit_truth`).
    """
    rng = np.random.default_rng([config.seed, 2**31])  # a stream apart from the frames' streams
    direction = rng.standard_normal(3)
    v0 = config.velocity_perturbation * direction / np.linalg.norm(direction)
    a = (EARTH_RADIUS + config.altitude_m) / (1.0 - config.eccentricity)
    incl, nu = np.radians([config.inclination_deg, config.true_anomaly_deg])
    r_c, v_c = keplerian_state(a, config.eccentricity, incl, 0.0, 0.0, nu)
    force = ForceModel(config.j2, config.drag_density, *config.ballistic_m2_kg)
    t = np.arange(config.frames) / config.rate_hz
    rel = relative_truth(r_c, v_c, [config.standoff_m, 0.0, 0.0], v0, t, force)
    R_I_B0 = Rotation.from_euler("ZYX", config.attitude_zyx_deg, degrees=True).as_matrix()
    q, w = torque_free_attitude(R_I_B0, np.radians(config.rate_deg_s), config.inertia, t)
    k = dynamics.inertia_ratios(config.inertia)
    ones = np.ones((config.frames, 1))
    return np.hstack([t[:, None], rel.rho_O, rel.v_O, q, w, ones * k, ones * config.com_offset])


def orbit_poses(truth: NDArray[np.float64], R_O_C: NDArray[np.float64], n: float) -> NDArray:
    """``T_C_B'`` (N, 4, 4) from the truth table (see the module notes for the formula)."""
    t, rho, q, com = truth[:, 0], truth[:, 1:4], truth[:, 7:11], truth[:, 17:20]
    R_O_I = Rotation.from_rotvec(np.outer(n * t, [0.0, -1.0, 0.0])).inv()
    R_O_B = (R_O_I * Rotation.from_quat(q)).as_matrix()
    R_C_O = R_O_C.T
    T = np.tile(np.eye(4), (len(t), 1, 1))
    T[:, :3, :3] = R_C_O @ R_O_B
    T[:, :3, 3] = (rho - np.einsum("nij,nj->ni", R_O_B, com)) @ R_C_O.T
    return T


def simulate_orbit(config: OrbitConfig | None = None) -> Simulation:
    """The orbit run (methods.md §3): flash-LiDAR frames of the tumbling satellite from 25 m.

    ``extras`` hold what the filter is given (``mean_motion``, ``R_O_C`` and ``rectangles``
    with their knowledge errors, ``process_noise`` measured by
    :func:`~spacepose.core.sim.process_noise.model_defect`) beside the exact ``R_O_C_true`` and
    ``rectangles_true``.
    """
    config = config or OrbitConfig()
    n = orbit_mean_motion(config)
    target = _target(config, orbit_target())
    # Within the tumbling target's reach the chaser would sit inside it and render its faces
    # from within, a run of frames that looks like any other (--range 1e-9 did).
    reach = float(np.max(np.linalg.norm(target.mesh.vertices, axis=1)))
    if config.standoff_m <= reach:
        # The largest spacecraft (the ISS) reaches 55 m from its centre: 866 m is millimetres.
        millimetres = reach > _LARGEST_REACH_M
        remedy = "a model in millimetres? give it in metres" if millimetres else "stand off farther"
        raise ConfigError(
            f"scenario orbit: a standoff of {config.standoff_m:g} m puts the chaser within the "
            f"target's reach ({reach:.3g} m from its centre); {remedy}"
        )
    # Checked before the truth is integrated: --range 1e300 ran for ever in it.
    _check_within_range(config, "a standoff", config.standoff_m, target, "stand off nearer")
    truth = orbit_truth(config)
    R_O_C_known = misaligned(
        R_O_C_AHEAD,
        np.radians(config.chaser_attitude_sigma_deg),
        np.random.default_rng([config.seed, 2**31 + 1]),
    )
    known = perturbed_catalogue(
        target.rectangles, config.catalogue_sigma_m, np.random.default_rng([config.seed, 2**31 + 2])
    )
    return Simulation(
        name="orbit",
        config=config,
        target=target,
        timestamps=truth[:, 0].copy(),
        T_sensor_target=orbit_poses(truth, R_O_C_AHEAD, n),
        truth=truth,
        extras={
            "mean_motion": n,
            "R_O_C": R_O_C_known.tolist(),
            "R_O_C_true": R_O_C_AHEAD.tolist(),
            "rectangles": [r.to_dict() for r in known],
            "rectangles_true": [r.to_dict() for r in target.rectangles],
            "process_noise": None if len(truth) < 2 else model_defect(truth, n).to_dict(),
            "inertia": list(config.inertia),
            "inertia_ratios": truth[0, 14:17].tolist(),
            "rate_rad_s": np.radians(config.rate_deg_s).tolist(),
            "com_offset": list(config.com_offset),
            "initial_state": truth[0, 1:7].tolist(),
            "initial_q_I_B": truth[0, 7:11].tolist(),
        },
    )


SCENARIOS = {"lab": (LabConfig, simulate_lab), "orbit": (OrbitConfig, simulate_orbit)}


def scenario_config(
    name: str,
    *,
    sensor: str | None = None,
    noise_scale: float | None = None,
    **fields: Any,
) -> LabConfig | OrbitConfig:
    """Config of scenario ``name`` with the given fields and an optional sensor preset/noise.

    Raises
    ------
    ConfigError
        Unknown scenario or sensor, or an invalid field (e.g. ``background`` for ``orbit``).
    """
    if name not in SCENARIOS:
        raise ConfigError(f"unknown scenario {name!r}; choose one of: {', '.join(SCENARIOS)}")
    model, _ = SCENARIOS[name]
    # None is the scenario's own sensor; an empty name is a mistake, not a request for it.
    sensor_name = ("tof" if name == "lab" else "flash-lidar") if sensor is None else sensor
    overrides = {} if noise_scale is None else {"noise_scale": noise_scale}
    fields["sensor"] = sensor_config(sensor_name, **overrides)
    return validate_config(model, fields, source=f"scenario {name}")


def simulate(config: LabConfig | OrbitConfig) -> Simulation:
    """Build the run described by ``config`` (a :class:`LabConfig` or :class:`OrbitConfig`).

    Raises
    ------
    ConfigError
        ``config`` is neither (None or a dict ran the default orbit run without a word).
    """
    if isinstance(config, LabConfig):
        return simulate_lab(config)
    if isinstance(config, OrbitConfig):
        return simulate_orbit(config)
    raise ConfigError(
        f"simulate needs a LabConfig or an OrbitConfig (scenario_config builds one), got "
        f"{type(config).__name__}"
    )
