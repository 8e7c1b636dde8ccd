"""What a navigation run is configured by, read and checked where its file is known: the
``--config`` file (a navigation config, or the fusion config a fused run writes), the scenario
(the orbit, the chaser's attitude, the catalogue, the target model) and the attitude prior.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import yaml
from numpy.typing import ArrayLike

from spacepose.core.cloud import PointCloud
from spacepose.core.config import read_mapping, validate_config
from spacepose.core.fused_navigation import FusionConfig, Measurements
from spacepose.core.lost_in_space import with_sensor_fov
from spacepose.core.navigation import NavigationConfig
from spacepose.core.sim.sensors import SensorConfig, sigma_at
from spacepose.core.structured_text import load_structured, parse_problem
from spacepose.errors import ConfigError, FileFormatError, InputError, SpaceposeWarning
from spacepose.tools.cloud_io import read_cloud
from spacepose.tools.runs import SCENARIO, read_run
from spacepose.tools.text_io import read_text

# How far from 1 a prior quaternion's norm may be before its normalisation is warned of: four
# numbers written to 3 decimals are within it, a norm of 2 (or 0.5) is not.
_PRIOR_NORM_TOLERANCE = 0.01

# What navigation reads from a scenario file (the orbit, the chaser's attitude, the catalogue,
# a model, the sensor's field of view, the debugging prior), and the rest of what a simulated
# orbit run's scenario.json holds (a test keeps these in step with the simulator).
NAVIGATION_KEYS = ("mean_motion", "R_O_C", "rectangles", "model", "sensor_fov_deg")
SCENARIO_KEYS = frozenset(
    {
        *NAVIGATION_KEYS, "initial_q_I_B", "R_O_C_true", "com_offset", "config", "frames",
        "inertia", "inertia_ratios", "initial_state", "process_noise", "rate_rad_s",
        "rectangles_true", "scenario", "seed", "spacepose_version", "target",
    }
)  # fmt: skip


def load_navigation_config(
    path: str | Path, measurements: Measurements
) -> tuple[NavigationConfig, FusionConfig | None]:
    """A ``--config`` file: a :class:`NavigationConfig`, or the :class:`FusionConfig` that
    ``navigate --measurements registration|both`` writes as NAV.config.json (the filter's
    config and the fusion's).

    Raises
    ------
    ConfigError
        Not a valid config of either kind, or a fusion config whose ``measurements`` are not
        those of ``--measurements``.
    """
    data = read_mapping(path) or {}
    # NAV.config.json of a fused run: refused as eleven "Extra inputs" though navigate wrote it.
    if "navigation" not in data and "tracker" not in data:
        return _with_checked_prior(validate_config(NavigationConfig, data, path), path), None
    fusion = validate_config(FusionConfig, data, path)
    fusion = fusion.model_copy(update={"navigation": _with_checked_prior(fusion.navigation, path)})
    if fusion.measurements != measurements:
        raise ConfigError(
            f"{path}: a fusion config for --measurements {fusion.measurements}, given with "
            f"--measurements {measurements}: give --measurements {fusion.measurements}, or a "
            "navigation config"
        )
    return fusion.navigation, fusion


def _with_checked_prior(config: NavigationConfig, path: str | Path) -> NavigationConfig:
    """``config`` with its ``prior_q_I_B`` checked and normalised here, where the file is known
    (checked later, its error named the key alone, not the file)."""
    if config.prior_q_I_B is None:
        return config
    prior = prior_quaternion(config.prior_q_I_B, f"{path}: prior_q_I_B")
    return config.model_copy(update={"prior_q_I_B": prior})


def prior_quaternion(values: ArrayLike, name: str) -> tuple[float, float, float, float]:
    """``values`` as a unit attitude prior ``(qx, qy, qz, qw)``.

    Parameters
    ----------
    values
        The quaternion, scalar last; any non-zero norm.
    name
        What the values came from (``--prior``, a file's key), named by the error.

    Raises
    ------
    ConfigError
        Not four finite numbers, or a zero norm: no rotation (scipy would fail on it mid-run).

    Warns
    -----
    SpaceposeWarning
        The norm is more than 0.01 from 1 (it is normalised, as before, but no longer silently).
    """
    try:
        q = np.asarray(values, dtype=np.float64)
    except (TypeError, ValueError):
        q = np.empty(0)
    if q.shape != (4,) or not np.all(np.isfinite(q)) or not np.any(q):
        got = " ".join(repr(values).split())  # an array's repr may span lines
        raise ConfigError(
            f"{name}: the quaternion must be four finite numbers with a non-zero norm, got {got}"
        )
    # Scaled first: the norm of 1e-200s underflows to 0 and that of 1e308s overflows.
    largest = float(np.max(np.abs(q)))
    q = q / largest
    norm = float(np.linalg.norm(q)) * largest  # inf past 1.8e308, and warned of as such
    q /= np.linalg.norm(q)
    if not abs(norm - 1.0) <= _PRIOR_NORM_TOLERANCE:
        # Accepted (its direction is the rotation), but a norm of 2 is a typo or a scaled
        # vector more often than a deliberate choice: it was normalised without a word.
        warnings.warn(
            SpaceposeWarning(f"{name}: the quaternion has norm {norm:.6g}, not 1; normalised"),
            stacklevel=2,
        )
    return (float(q[0]), float(q[1]), float(q[2]), float(q[3]))


def read_scenario(input_dir: str | Path, scenario: str | Path | None) -> tuple[dict, str]:
    """What a navigation run's scenario holds (the orbit, the chaser's attitude, the catalogue),
    from ``scenario``, else the run folder's scenario.json.

    Parameters
    ----------
    input_dir
        A run folder written by ``spacepose simulate orbit``, or a folder of frames.
    scenario
        YAML or JSON file with the scenario's keys (:data:`NAVIGATION_KEYS`); overrides a run
        folder's scenario.json.

    Returns
    -------
    description, source
        The scenario's mapping, and the file its errors and warnings name.

    Raises
    ------
    InputError
        A folder of frames without a scenario file.
    ConfigError
        ``scenario`` is a navigation config, not a scenario.
    FileFormatError
        ``scenario`` is not YAML / JSON holding a mapping.

    Warns
    -----
    SpaceposeWarning
        Keys no scenario holds (a misspelt optional key would be ignored without a word).
    """
    if scenario is not None:
        source = str(scenario)
        description = _read_mapping(Path(scenario))
        _refuse_a_config(description, source)
        _warn_unknown_keys(description, source)
    elif (Path(input_dir) / SCENARIO).is_file():
        source = str(Path(input_dir) / SCENARIO)
        description = read_run(input_dir).scenario
        if description.get("scenario") == "orbit":  # an edited run's misspelt key, as above
            _warn_unknown_keys(description, source)
    else:
        raise InputError(
            "a folder of frames needs a scenario file (mean_motion, R_O_C, rectangles)", input_dir
        )
    return description, source


def with_scenario_noise(
    config: NavigationConfig, description: dict, source: str
) -> NavigationConfig:
    """``config`` with the filter noise a simulated run's scenario gives, for each setting
    ``config.ekf`` does not set itself: the translational process noise measured from what CW
    misses on the run (``process_noise.sigma_accel``) and the σ of the chaser attitude the
    filter is told (``config.chaser_attitude_sigma_deg``, a star tracker's specification).
    ``spacepose navigate`` had kept the defaults (3e-8 against the 1.25e-6 measured on the
    orbit run, 2.8e-5 on an eccentric one): NEES above its bounds on every frame of the second
    half, the position 9.7σ off along the line of sight.

    Raises
    ------
    ConfigError
        A value that is not a valid setting, or ``process_noise`` or ``config`` that is no
        mapping (an edited scenario).
    """
    for key, holds in (("process_noise", "sigma_accel"), ("config", "chaser_attitude_sigma_deg")):
        value = description.get(key)
        if value is not None and not isinstance(value, dict):
            # "process_noise: 1.25e-6" was passed over without a word: the default noise used.
            raise ConfigError(
                f"{source}: {key} must be a mapping (such as {holds}: value), got {value!r}"
            )
    given = config.ekf.model_fields_set
    ekf: dict[str, object] = {}
    noise = description.get("process_noise")
    if isinstance(noise, dict) and "sigma_accel" in noise and "sigma_accel" not in given:
        ekf["sigma_accel"] = noise["sigma_accel"]
    settings = description.get("config")
    chaser = settings.get("chaser_attitude_sigma_deg") if isinstance(settings, dict) else None
    if chaser is not None and "sigma_chaser_attitude_deg" not in given:
        ekf["sigma_chaser_attitude_deg"] = chaser
    if not ekf:
        return config
    merged = validate_config(type(config.ekf), config.ekf.model_dump() | ekf, source)
    return config.model_copy(update={"ekf": merged})


def scenario_range_sigma(description: dict, source: str) -> float | None:
    """The range noise σ (m) of a simulated run's sensor at its standoff (amplitude 1), or
    None when the scenario does not describe its sensor (a hand-written one).

    Raises
    ------
    ConfigError
        A sensor or standoff that is not a valid setting (an edited scenario).
    """
    settings = description.get("config")
    if not isinstance(settings, dict) or not isinstance(settings.get("sensor"), dict):
        return None
    sensor = validate_config(SensorConfig, settings["sensor"], f"{source}: config.sensor")
    standoff = settings.get("standoff_m")
    if isinstance(standoff, bool) or not isinstance(standoff, int | float) or not standoff > 0:
        raise ConfigError(f"{source}: config.standoff_m must be a distance > 0, got {standoff!r}")
    sigma = float(sigma_at(sensor, np.array([float(standoff)]))[0])
    return sigma if sigma > 0 else None


def with_run_settings(
    config: NavigationConfig,
    description: dict,
    source: str,
    prior_q_I_B: ArrayLike | None,
    debug_prior_from_truth: bool,
) -> NavigationConfig:
    """``config`` with what the run adds: the scenario's sensor field of view and filter noise
    (:func:`with_scenario_noise`), each unless ``config`` sets its own, and the attitude prior.

    Parameters
    ----------
    config
        The navigation config (defaults, or a ``--config`` file's).
    description, source
        What the scenario holds and the file it came from (:func:`read_scenario`).
    prior_q_I_B
        The attitude prior given (``--prior``), or None: ``config``'s own, if any.
    debug_prior_from_truth
        DEBUGGING ONLY: take the prior from the scenario's ``initial_q_I_B``.

    Raises
    ------
    InputError
        ``debug_prior_from_truth`` and no ``initial_q_I_B`` in the scenario.
    ConfigError
        The sensor field of view is not two angles, or the prior is not a rotation
        (:func:`prior_quaternion`).
    """
    if config.lost_in_space.fov_deg is None and "sensor_fov_deg" in description:
        fov = with_sensor_fov(config.lost_in_space, description["sensor_fov_deg"], source)
        config = config.model_copy(update={"lost_in_space": fov})
    config = with_scenario_noise(config, description, source)
    if config.range_sigma is None:
        sigma = scenario_range_sigma(description, source)
        config = config if sigma is None else config.with_range_sigma(sigma)
    prior_name = "prior_q_I_B"
    if debug_prior_from_truth:
        if "initial_q_I_B" not in description:
            raise InputError("missing key 'initial_q_I_B' for the attitude prior", source)
        prior_q_I_B, prior_name = description["initial_q_I_B"], f"{source}: initial_q_I_B"
    if prior_q_I_B is None:
        prior_q_I_B = config.prior_q_I_B  # from a config file, if any
    if prior_q_I_B is not None:
        prior = prior_quaternion(prior_q_I_B, prior_name)
        config = NavigationConfig.model_validate(config.model_dump() | {"prior_q_I_B": prior})
    return config


def scenario_model(
    input_dir: str | Path, scenario: str | Path | None, description: dict
) -> PointCloud | None:
    """The target's surface samples: the scenario's ``model`` file (``null``: none given), else
    a run's model.ply.

    Parameters
    ----------
    input_dir
        The run folder, or a folder of frames.
    scenario
        The scenario file given, or None (the run's scenario.json).
    description
        What the scenario holds (:func:`read_scenario`).

    Returns
    -------
    PointCloud or None
        The model (frame B'), or None: none given and no run's model.ply.

    Raises
    ------
    InputError
        The scenario's ``model`` is not a file name (a number, a list, empty text): read as
        one it named a file "5" or "None", or the scenario's folder, not the scenario's key.
    """
    name = description.get("model") if scenario is not None else None
    if name is not None:
        if not isinstance(name, str) or not name.strip():
            raise InputError(
                f"model must name a cloud file (relative to the scenario), got {name!r}",
                scenario,
            )
        return read_cloud(Path(scenario).parent / name)
    if (Path(input_dir) / SCENARIO).is_file() and (Path(input_dir) / "model.ply").is_file():
        return read_run(input_dir).model
    return None


def _refuse_a_config(description: dict, source: str) -> None:
    """Refuse a navigation or fusion config given as the scenario (NAV.config.json): its
    fourteen keys were warned of as unknown, then "missing key 'mean_motion'" ended the run.

    Raises
    ------
    ConfigError
        ``description`` holds no orbit key and a config's own sections.
    """
    sections = {"ekf", "plane", "rectangle", "lost_in_space", "navigation", "tracker"}
    if not set(description) & {"mean_motion", "R_O_C"} and set(description) & sections:
        raise ConfigError(
            f"{source}: a navigation config (--config), not a scenario (mean_motion, R_O_C, "
            "rectangles)"
        )


def _warn_unknown_keys(description: dict, source: str) -> None:
    """Warn, naming ``source``, of a scenario file's keys no scenario holds: a misspelt
    optional key (``rectangle`` for ``rectangles``) would otherwise be ignored without a
    word."""
    unknown = sorted(set(description) - SCENARIO_KEYS)
    if unknown:
        problem = (
            f"unknown keys {unknown} ignored (misspelt? navigation reads "
            f"{', '.join(NAVIGATION_KEYS)})"
        )
        warnings.warn(SpaceposeWarning(problem, source), stacklevel=4)


def _read_mapping(path: Path) -> dict:
    """A YAML or JSON file holding one mapping."""
    text = read_text(path, "the scenario")
    try:
        data = load_structured(text, "yaml")
    except yaml.YAMLError as exc:
        raise FileFormatError(f"not valid YAML/JSON: {parse_problem(exc)}", path) from None
    if not isinstance(data, dict):
        raise FileFormatError("a scenario file must hold a mapping", path)
    return data
