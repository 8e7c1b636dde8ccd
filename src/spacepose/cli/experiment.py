"""``spacepose experiment NAME``: reproduce one of the papers' experiments on the simulator."""

from __future__ import annotations

import json
from pathlib import Path

import typer

from spacepose.cli.app import app, console


@app.command()
def experiment(
    name: str = typer.Argument(..., help="li-l1 ... li-l4, li-global, yu-y1 ... yu-y4"),
    out: Path = typer.Option(Path("runs/experiments"), help="Folder; NAME/ is created inside."),
    seed: int = typer.Option(0, help="Seed of every random draw."),
    quick: bool = typer.Option(False, help="Smaller sizes, for a smoke run."),
    workers: int = typer.Option(-1, help="Threads for neighbour searches (-1: all cores)."),
) -> None:
    """Run one experiment; tables (JSON) and figures (PNG) go to OUT/NAME/."""
    from spacepose.tools.experiments import ExperimentOptions, run_experiment

    options = ExperimentOptions(seed=seed, quick=quick, workers=workers)
    table = run_experiment(name, out / name, options)
    console.print_json(json.dumps(table, default=float))
