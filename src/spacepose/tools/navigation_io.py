"""Relative navigation of a run folder: read the run, navigate, write NAV.csv and its config."""

from __future__ import annotations

import csv
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

from numpy.typing import ArrayLike

from spacepose.core.config import dump_config
from spacepose.core.navigation import (
    NavigationConfig,
    NavRow,
    nav_table,
    navigate,
    scenario_geometry,
)
from spacepose.errors import InputError
from spacepose.tools.catalogue import parse_catalogue
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
    run_dir: str | Path,
    out: str | Path,
    config: NavigationConfig | None = None,
    *,
    prior_q_I_B: ArrayLike | None = None,
    prior_from_scenario: bool = False,
) -> NavigationSummary:
    """Navigate every frame of an orbit run folder; writes ``out`` and ``out``'s ``.config.json``.

    Parameters
    ----------
    run_dir
        Folder written by ``spacepose simulate orbit`` (frames, scenario.json with the orbit,
        the chaser attitude ``R_O_C`` and the rectangle catalogue).
    out
        NAV.csv path.
    config
        Navigation config; defaults in code.
    prior_q_I_B
        Coarse attitude prior (x, y, z, w) that picks among the target's symmetric poses at start.
    prior_from_scenario
        Take the prior from the scenario's ``initial_q_I_B`` (the simulator's true start attitude).
    """
    cfg = config or NavigationConfig()
    run = read_run(run_dir)
    source = str(run.path / SCENARIO)
    n, R_O_C = scenario_geometry(run.scenario, source)
    catalogue = parse_catalogue(run.scenario, cfg.rectangle, source)
    if prior_from_scenario:
        if "initial_q_I_B" not in run.scenario:
            raise InputError("missing key 'initial_q_I_B' for the attitude prior", source)
        prior_q_I_B = run.scenario["initial_q_I_B"]
    if prior_q_I_B is not None:
        prior = tuple(float(v) for v in prior_q_I_B)
        cfg = NavigationConfig.model_validate(cfg.model_dump() | {"prior_q_I_B": prior})
    rows = navigate(zip(run.timestamps, run.frames(), strict=True), catalogue, n, R_O_C, cfg)
    nav_csv = write_nav_csv(out, rows)
    config_json = dump_config(cfg, Path(out).with_suffix(".config.json"))
    navigated = sum(r.status != "waiting" for r in rows)
    return NavigationSummary(nav_csv, config_json, len(rows), navigated, tuple(rows))
