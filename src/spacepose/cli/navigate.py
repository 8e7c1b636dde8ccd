"""``spacepose navigate RUN --out NAV.csv``: rectangle-based relative navigation (Yu et al.)."""

from __future__ import annotations

from pathlib import Path

import typer

from spacepose.cli.app import app, console, err_console
from spacepose.cli.feedback import working


@app.command()
def navigate(
    run: Path = typer.Argument(
        ..., help="Run folder from 'spacepose simulate orbit', or a folder of frame files."
    ),
    out: Path = typer.Option(..., "--out", help="NAV.csv: one row of state, 1-σ and status."),
    config: Path | None = typer.Option(
        None, "--config", help="YAML/JSON NavigationConfig (defaults in code)."
    ),
    scenario: Path | None = typer.Option(
        None, help="YAML/JSON with mean_motion, R_O_C and rectangles (needed for a frame folder)."
    ),
    prior_from_scenario: bool = typer.Option(
        False,
        help="Take the coarse attitude prior from scenario.json (initial_q_I_B: the simulator's "
        "true initial attitude) to resolve equal-size faces and the target's symmetry at start.",
    ),
) -> None:
    """Estimate ρ, ρ̇, attitude, rate, inertia ratios and CoM offset for every frame of RUN."""
    from spacepose.core.config import load_config
    from spacepose.core.navigation import NavigationConfig
    from spacepose.tools.navigation_io import navigate_run

    cfg = None if config is None else load_config(NavigationConfig, config)
    with working("navigating"):
        summary = navigate_run(
            run, out, cfg, scenario=scenario, prior_from_scenario=prior_from_scenario
        )
    if summary.navigated == 0:
        err_console.print(
            "warning: the filter never started (no rectangle told apart without a prediction; "
            "try --prior-from-scenario or prior_q_I_B in the config)"
        )
    console.print(
        f"{summary.frames} frames ({summary.navigated} navigated) -> {summary.nav_csv}; "
        f"config -> {summary.config_json}"
    )
