"""``spacepose evaluate EST GT``: pose errors of an estimated trajectory against ground truth."""

from __future__ import annotations

import json
from pathlib import Path

import typer
from rich.table import Table

from spacepose.cli.app import app, console
from spacepose.core.metrics import TIMESTAMP_TOLERANCE


@app.command()
def evaluate(
    est: Path = typer.Argument(..., help="Estimated trajectory (TUM or KITTI)."),
    gt: Path = typer.Argument(..., help="Ground-truth trajectory (TUM or KITTI)."),
    rebase_first: bool = typer.Option(
        False, "--rebase-first", help="Express both relative to their first pose (model-free)."
    ),
    gt_sensor_poses: bool = typer.Option(
        False,
        "--gt-sensor-poses",
        help="GT holds the sensor's pose in a world frame (T_world_sensor, as TUM RGB-D's "
        "groundtruth.txt): scored as its inverses, the still scene's pose in the sensor frame.",
    ),
    max_dt: float = typer.Option(
        TIMESTAMP_TOLERANCE,
        "--max-dt",
        min=0.0,
        help="Largest time difference (s) of an estimated pose and the ground-truth pose it is "
        "scored against, the nearest in time (TUM RGB-D's 100 Hz ground truth: 0.01, as evo's "
        "t_max_diff).",
    ),
    as_json: bool = typer.Option(False, "--json", help="Print the numbers as JSON."),
) -> None:
    """Per-axis errors (mean and std of |error|, Li's Table 2) and ATE RMSE (as evo_ape).

    Warns when the two files differ in length, when estimates share a ground-truth pose, when
    estimates outside the ground truth's times are left out, and when a model-free track (first
    pose the identity) is compared without --rebase-first.
    """
    from spacepose.tools.evaluation import compare_trajectory_files

    result = compare_trajectory_files(
        est, gt, rebase_first=rebase_first, tolerance=max_dt, gt_sensor_poses=gt_sensor_poses
    )
    table = result.table
    if as_json:
        # Plain print: rich would wrap long lines and break the JSON for a pipe.
        typer.echo(json.dumps(result.to_dict(), indent=2))
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
