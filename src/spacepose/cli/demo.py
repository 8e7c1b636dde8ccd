"""``spacepose demo``: simulate, track, navigate, score and report in one command."""

from __future__ import annotations

from pathlib import Path

import typer

from spacepose.cli.app import app, console


@app.command()
def demo(
    out: Path = typer.Option(Path("runs/demo"), help="Folder for the runs and report.html."),
    orbit_frames: int = typer.Option(600, min=20, help="Frames of the orbit run."),
    seed: int = typer.Option(0, min=0, help="Seed of the simulations and experiments."),
    workers: int = typer.Option(-1, help="Threads for neighbour searches (-1: all cores)."),
) -> None:
    """Run the lab (Li et al.) and orbit (Yu et al.) pipelines end to end and print both tables."""
    from spacepose.tools.demo import li_rich_table, run_demo, yu_rich_table

    result = run_demo(
        out,
        orbit_frames=orbit_frames,
        seed=seed,
        workers=workers,
        log=lambda line: console.print(line, highlight=False),
    )
    console.print(li_rich_table(result.li_table))
    console.print(yu_rich_table(result.yu_table))
    console.print(f"report: {result.report}  ({sum(result.seconds.values()):.0f} s in all)")
