"""``spacepose experiment NAME``: reproduce one of the papers' experiments on the simulator."""

from __future__ import annotations

import json
import time
from pathlib import Path

import typer

from spacepose.cli.app import app
from spacepose.cli.feedback import print_written, working


@app.command()
def experiment(
    name: str = typer.Argument(..., help="li-l1 ... li-l4, li-global, yu-y1 ... yu-y4"),
    out: Path = typer.Option(Path("runs/experiments"), help="Folder; NAME/ is created inside."),
    seed: int = typer.Option(0, help="Seed of every random draw."),
    quick: bool = typer.Option(False, help="Smaller sizes, for a smoke run."),
    workers: int = typer.Option(-1, help="Threads for neighbour searches (-1: all cores)."),
    as_json: bool = typer.Option(False, "--json", help="Also print the result table as JSON."),
) -> None:
    """Run one experiment; tables (JSON) and figures (PNG) go to OUT/NAME/, listed at the end."""
    from spacepose.tools.experiments import ExperimentOptions, run_experiment

    options = ExperimentOptions(seed=seed, quick=quick, workers=workers)
    start = time.time()
    with working(f"experiment {name}"):
        table = run_experiment(name, out / name, options)
    if as_json:
        # Plain print: rich would wrap long lines and break the JSON for a pipe.
        typer.echo(json.dumps(table, default=float, indent=2))
    print_written(out / name, start, stderr=as_json)
