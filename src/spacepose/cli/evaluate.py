"""``spacepose evaluate EST GT``: pose errors of an estimated trajectory against ground truth."""

from __future__ import annotations

import json
from pathlib import Path

import typer
from rich.table import Table

from spacepose.cli.app import app, console


@app.command()
def evaluate(
    est: Path = typer.Argument(..., help="Estimated trajectory (TUM or KITTI)."),
    gt: Path = typer.Argument(..., help="Ground-truth trajectory (TUM or KITTI)."),
    rebase_first: bool = typer.Option(
        False, "--rebase-first", help="Express both relative to their first pose (model-free)."
    ),
    as_json: bool = typer.Option(False, "--json", help="Print the numbers as JSON."),
) -> None:
    """Per-axis errors (mean and std of |error|, Li's Table 2) and ATE RMSE (as evo_ape)."""
    from spacepose.core.metrics import evaluate as evaluate_trajectories
    from spacepose.tools.trajectory_io import read_trajectory

    table = evaluate_trajectories(
        read_trajectory(est), read_trajectory(gt), rebase_first=rebase_first
    )
    if as_json:
        console.print_json(json.dumps(table.to_dict()))
        return
    view = Table(title=f"{est.name} vs {gt.name} ({table.n} poses)")
    view.add_column("error")
    view.add_column("mean", justify="right")
    view.add_column("std", justify="right")
    for axis, unit, mean, std in table.rows():
        view.add_row(f"{axis} ({unit})", f"{mean:.4f}", f"{std:.4f}")
    view.add_section()
    view.add_row("ATE translation RMSE (mm)", f"{table.ate_translation_rmse * 1e3:.4f}", "")
    view.add_row("ATE rotation RMSE (deg)", f"{table.ate_rotation_rmse:.4f}", "")
    console.print(view)
