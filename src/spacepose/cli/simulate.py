"""``spacepose simulate {lab,orbit}``: write a simulated run folder (METHODS §3)."""

from __future__ import annotations

from pathlib import Path

import typer
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn

from spacepose.cli.app import app, console


@app.command()
def simulate(
    scenario: str = typer.Argument(..., help="lab or orbit"),
    out: Path = typer.Option(..., help="Run folder to write."),
    frames: int | None = typer.Option(None, help="Number of frames (default: 58 lab, 600 orbit)."),
    seed: int = typer.Option(0, help="Seed of every random draw."),
    sensor: str | None = typer.Option(
        None, help="tof, flash-lidar or gaussian (default: tof for lab, flash-lidar for orbit)."
    ),
    noise_scale: float | None = typer.Option(None, help="Noise multiplier; 0 = noise-free."),
    model: Path | None = typer.Option(None, help="Mesh file (OBJ/STL/PLY/GLB) as the target."),
    model_scale: float = typer.Option(1.0, help="Scale applied to --model coordinates."),
    background: bool = typer.Option(False, help="lab: add a wall and the turntable."),
) -> None:
    """Simulate the lab or orbit scenario and write frames, ground truth, model and scenario."""
    from spacepose.core.sim import scenario_config
    from spacepose.core.sim import simulate as build
    from spacepose.tools.runs import write_run

    fields: dict[str, object] = {"seed": seed}
    if frames is not None:
        fields["frames"] = frames
    if model is not None:
        fields["model"] = str(model)
        fields["model_scale"] = model_scale
    if background:
        fields["background"] = True
    config = scenario_config(scenario, sensor=sensor, noise_scale=noise_scale, **fields)
    sim = build(config)
    columns = (TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn())
    with Progress(*columns, TimeElapsedColumn(), console=console, transient=True) as bar:
        task = bar.add_task(f"simulating {scenario}", total=len(sim))
        write_run(out, sim, progress=lambda _k: bar.advance(task))
    console.print(f"wrote {len(sim)} {scenario} frames to {out}")
