"""``spacepose simulate {lab,orbit}``: write a simulated run folder (methods.md §3)."""

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
    seed: int = typer.Option(0, min=0, help="Seed of every random draw."),
    sensor: str | None = typer.Option(
        None,
        help="tof, tof-clean, tof-paper, flash-lidar, flash-lidar-clean, flash-lidar-edges or "
        "gaussian (default: tof for lab, flash-lidar for orbit).",
    ),
    noise_scale: float | None = typer.Option(None, help="Noise multiplier; 0 = noise-free."),
    model: Path | None = typer.Option(
        None, help="Mesh file (OBJ/STL/PLY/GLB) as the target, or random:K (a generated one)."
    ),
    model_scale: float | None = typer.Option(
        None, help="Scale applied to --model coordinates (default 1)."
    ),
    background: bool = typer.Option(False, help="lab: add a wall and the turntable."),
    turntable: bool = typer.Option(
        True, help="lab, with --background: the turntable under the target (off: the wall alone)."
    ),
    motion: str | None = typer.Option(
        None, help="lab: constant (default), accelerating or tumbling-D (D degrees a frame)."
    ),
    range_m: float | None = typer.Option(
        None,
        "--range",
        help="lab: target distance, m (default 1.2); orbit: the chaser's standoff (default 25).",
    ),
    target_size: float | None = typer.Option(
        None, help="lab: scale the target to this largest extent, m."
    ),
    grid: bool = typer.Option(
        False,
        help="lab: build the scene as the robustness grid does: scaled to --range (target, "
        "slide, turntable), the wall at 5/3 of the range, the sensor chosen by range.",
    ),
) -> None:
    """Simulate the lab or orbit scenario and write frames, ground truth, model and scenario."""
    from spacepose.core.sim import scenario_config
    from spacepose.core.sim import simulate as build
    from spacepose.core.sim.grid import grid_scenario, motion_fields
    from spacepose.errors import ConfigError
    from spacepose.tools.runs import check_run_out, write_run
    from spacepose.tools.simulate_checks import warn_if_model_moved, warn_if_no_catalogue

    check_run_out(out)  # before the scene is built
    if model is not None:
        _check_not_a_folder(model)
    if grid and scenario != "lab":
        raise ConfigError(f"--grid builds lab scenes only, not {scenario!r}")
    if model_scale is not None and (model is None or grid or target_size is not None):
        why = "the grid scales its target by --range" if grid else "no --model is given"
        if model is not None and not grid:
            # --target-size sizes the target whatever its scale: --model-scale was lost.
            why = "--target-size sets the target's size whatever its scale: give one of them"
        raise ConfigError(f"--model-scale applies to a --model's coordinates, and {why}")
    if not turntable and not background:
        # The turntable is part of --background's scene: without it the option was ignored.
        raise ConfigError(
            "--no-turntable leaves the turntable out of --background's scene, and --background "
            "is not given: add --background (a wall alone), or leave out --no-turntable"
        )
    # Named, not truthy: --target-size 0 is given (0.0 == False would hide it).
    lab_only = {"--background": background or None, "--motion": motion}
    lab_only["--target-size"] = target_size
    given_lab = [name for name, value in lab_only.items() if value is not None]
    if scenario == "orbit" and given_lab:
        raise ConfigError(
            f"{given_lab[0]} applies to the lab scenario only; the orbit run's target tumbles "
            "torque-free from its inertia and rates"
        )
    if grid:
        given = {
            "target": None if model is None else str(model),
            "range_m": range_m,
            "noise_scale": noise_scale,
            "motion": motion,
            "frames": frames,
            "sensor": sensor,
            "target_size_m": target_size,
        }
        config = grid_scenario(
            seed=seed,
            clutter=("wall-table" if turntable else "wall") if background else "none",
            **{name: value for name, value in given.items() if value is not None},
        )
    else:
        fields: dict[str, object] = {"seed": seed}
        if frames is not None:
            fields["frames"] = frames
        if model is not None:
            fields["model"] = str(model)
            fields["model_scale"] = 1.0 if model_scale is None else model_scale
        if background:
            fields |= {"background": True, "turntable": turntable}
        if motion is not None:
            fields |= motion_fields(motion)
        if range_m is not None:
            fields["range_m" if scenario == "lab" else "standoff_m"] = range_m
        if target_size is not None:
            fields["target_size_m"] = target_size
        config = scenario_config(scenario, sensor=sensor, noise_scale=noise_scale, **fields)
    sim = build(config)
    if model is not None:
        warn_if_model_moved(model, sim.target.mesh, 1.0 if model_scale is None else model_scale)
    warn_if_no_catalogue(sim, out)
    columns = (TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn())
    shown = console.is_terminal  # off a terminal rich would still print an empty line
    with Progress(
        *columns, TimeElapsedColumn(), console=console, transient=True, disable=not shown
    ) as bar:
        task = bar.add_task(f"simulating {scenario}", total=len(sim))
        write_run(out, sim, progress=lambda _k: bar.advance(task))
    console.print(f"wrote {len(sim)} {scenario} frames to {out}")


def _check_not_a_folder(model: Path) -> None:
    """Refuse a folder given as ``--model``: it was called an unknown mesh extension ('') or,
    named ``*.obj``, no such mesh file, though the user sees it there.

    Raises
    ------
    FileFormatError
        ``model`` is a folder; the message names its mesh files, if it holds any.
    """
    from spacepose.core.sim.mesh_files import MESH_SUFFIXES
    from spacepose.errors import FileFormatError

    if not model.is_dir():
        return
    meshes = sorted(p.name for p in model.iterdir() if p.suffix.lower() in MESH_SUFFIXES)
    if meshes:
        shown = ", ".join(meshes[:3]) + (", ..." if len(meshes) > 3 else "")
        hint = f"give one of its meshes ({shown})"
    else:
        hint = f"it holds no mesh ({', '.join(MESH_SUFFIXES)})"
    raise FileFormatError(f"--model is a folder, not a mesh file: {hint}", model)
