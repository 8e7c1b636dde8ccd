"""``spacepose experiment NAME``: reproduce one of the papers' experiments on the simulator."""

from __future__ import annotations

import time
from pathlib import Path

import typer

from spacepose.cli.app import app
from spacepose.cli.feedback import print_written, working


@app.command()
def experiment(
    name: str = typer.Argument(
        ..., help="li-l1 ... li-l4, li-global, yu-y1 ... yu-y4, robustness, fusion, room"
    ),
    out: Path = typer.Option(Path("runs/experiments"), help="Folder; NAME/ is created inside."),
    seed: int = typer.Option(0, min=0, help="Seed of every random draw."),
    quick: bool = typer.Option(False, help="Smaller sizes, for a smoke run."),
    workers: int = typer.Option(-1, help="Threads for neighbour searches (-1: all cores)."),
    seeds: int = typer.Option(
        None, min=1, help="li-l1, li-l3, fusion, room: seeds from --seed on (li: 10, room: 5)."
    ),
    as_json: bool = typer.Option(False, "--json", help="Also print the result table as JSON."),
    cells: str = typer.Option(
        None, help="robustness: cells, e.g. 'target=lab,range=1.2+25,seed=0', or a YAML/JSON file."
    ),
    frames: int = typer.Option(None, min=2, help="robustness, room, fusion: frames per run."),
    frames_csv: bool = typer.Option(False, help="robustness: write every frame's scores."),
    jobs: int = typer.Option(1, min=1, help="robustness: processes running cells."),
    tracker: Path = typer.Option(
        None, help="robustness: a tracker config file (YAML/JSON) instead of the defaults."
    ),
    targets: str = typer.Option(
        None, help="fusion: targets, e.g. 'default,random:3' (random:K: a generated spacecraft)."
    ),
) -> None:
    """Run one experiment; tables (JSON) and figures (PNG) go to OUT/NAME/, listed at the end."""
    from spacepose.tools.experiments import ExperimentOptions, run_experiment
    from spacepose.tools.text_io import strict_json

    options = ExperimentOptions(
        seed=seed,
        quick=quick,
        workers=workers,
        seeds=seeds,
        cells=cells,
        frames=frames,
        frames_csv=frames_csv,
        jobs=jobs,
        tracker=None if tracker is None else str(tracker),
        targets=targets,
    )
    start = time.time()
    with working(f"experiment {name}"):
        table = run_experiment(name, out / name, options)
    if as_json:
        # Plain print: rich would wrap long lines and break the JSON for a pipe.
        typer.echo(strict_json(table, default=float, indent=2))
    print_written(out / name, start, stderr=as_json)
