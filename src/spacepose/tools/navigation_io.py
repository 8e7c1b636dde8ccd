"""Relative navigation of a run folder: read the run, navigate, write NAV.csv and its config."""

from __future__ import annotations

import csv
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import yaml
from numpy.typing import ArrayLike

from spacepose.core.config import dump_config, parse_problem
from spacepose.core.navigation import (
    NavigationConfig,
    NavRow,
    nav_table,
    navigate,
    scenario_geometry,
)
from spacepose.errors import FileFormatError, InputError
from spacepose.tools.catalogue import parse_catalogue
from spacepose.tools.frames import open_frames
from spacepose.tools.runs import SCENARIO, read_run


@dataclass(frozen=True)
class NavigationSummary:
    """What :func:`navigate_run` wrote and how many frames the filter used."""

    nav_csv: Path
    config_json: Path
    frames: int
    navigated: int
    rows: tuple[NavRow, ...]


def write_nav_csv(path: str | Path, rows: Sequence[NavRow]) -> Path:
    """Write one NAV.csv row per frame (columns of :data:`navigation.NAV_COLUMNS`)."""
    path = Path(path)
    columns, values = nav_table(rows)
    path.parent.mkdir(parents=True, exist_ok=True)
    with path.open("w", newline="") as fh:
        writer = csv.writer(fh)
        writer.writerow(columns)
        writer.writerows(
            [f"{v:.17g}" if isinstance(v, float) else v for v in row] for row in values
        )
    return path


def navigate_run(
    input_dir: str | Path,
    out: str | Path,
    config: NavigationConfig | None = None,
    *,
    scenario: str | Path | None = None,
    prior_q_I_B: ArrayLike | None = None,
    prior_from_scenario: bool = False,
) -> NavigationSummary:
    """Navigate every frame of an orbit run; writes ``out`` and ``out``'s ``.config.json``.

    Parameters
    ----------
    input_dir
        A run folder written by ``spacepose simulate orbit`` (its scenario.json gives the orbit,
        the chaser attitude ``R_O_C`` and the rectangle catalogue), or a folder of frame files
        (sorted by name, optional ``timestamps.txt``: seconds since the epoch where I and O
        coincide) together with ``scenario``.
    out
        NAV.csv path.
    config
        Navigation config; defaults in code.
    scenario
        YAML or JSON file with ``mean_motion`` (rad/s), ``R_O_C`` (3×3) and ``rectangles`` (the
        catalogue), optionally ``initial_q_I_B``; overrides a run folder's scenario.json.
    prior_q_I_B
        Coarse attitude prior (x, y, z, w) that picks among the target's symmetric poses at start.
    prior_from_scenario
        Take the prior from the scenario's ``initial_q_I_B`` (the simulator's true start attitude).
    """
    cfg = config or NavigationConfig()
    frames = open_frames(input_dir)
    if scenario is not None:
        source = str(scenario)
        description = _read_mapping(Path(scenario))
    elif (Path(input_dir) / SCENARIO).is_file():
        source = str(Path(input_dir) / SCENARIO)
        description = read_run(input_dir).scenario
    else:
        raise InputError(
            "a folder of frames needs a scenario file (mean_motion, R_O_C, rectangles)", input_dir
        )
    n, R_O_C = scenario_geometry(description, source)
    catalogue = parse_catalogue(description, cfg.rectangle, source)
    if prior_from_scenario:
        if "initial_q_I_B" not in description:
            raise InputError("missing key 'initial_q_I_B' for the attitude prior", source)
        prior_q_I_B = description["initial_q_I_B"]
    if prior_q_I_B is not None:
        prior = tuple(float(v) for v in prior_q_I_B)
        cfg = NavigationConfig.model_validate(cfg.model_dump() | {"prior_q_I_B": prior})
    rows = navigate(((f.timestamp, f.cloud) for f in frames), catalogue, n, R_O_C, cfg)
    nav_csv = write_nav_csv(out, rows)
    config_json = dump_config(cfg, Path(out).with_suffix(".config.json"))
    navigated = sum(r.status != "waiting" for r in rows)
    return NavigationSummary(nav_csv, config_json, len(rows), navigated, tuple(rows))


def _read_mapping(path: Path) -> dict:
    """A YAML or JSON file holding one mapping."""
    try:
        data = yaml.safe_load(path.read_text())
    except OSError as exc:
        raise InputError(f"cannot read: {exc.strerror}", path) from None
    except yaml.YAMLError as exc:
        raise FileFormatError(f"not valid YAML/JSON: {parse_problem(exc)}", path) from None
    if not isinstance(data, dict):
        raise FileFormatError("a scenario file must hold a mapping", path)
    return data
