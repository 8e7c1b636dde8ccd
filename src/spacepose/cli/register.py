"""``spacepose register SOURCE TARGET``: align one cloud file onto another."""

from __future__ import annotations

import json
from pathlib import Path

import typer

from spacepose.cli.app import app


@app.command()
def register(
    source: Path = typer.Argument(
        ..., help="Cloud to move (PLY, PCD, XYZ/TXT/CSV, NPY/NPZ, m; or a 16-bit depth image)."
    ),
    target: Path = typer.Argument(..., help="Cloud to align onto, same formats."),
    global_: bool = typer.Option(
        False, "--global", help="FPFH + RANSAC first (for an unknown initial pose)."
    ),
    init: Path | None = typer.Option(
        None, help="Initial T_target_source: 16 numbers, or JSON with T_target_source."
    ),
    method: str = typer.Option("gicp", help="gicp, point_to_plane or point_to_point."),
    robust_kernel: str = typer.Option(
        "geman_mcclure", help="none, huber, cauchy or geman_mcclure (adaptive scale)."
    ),
    voxel: float | None = typer.Option(
        None, help="Voxel size (m); default: derived from the spacing and size of the clouds."
    ),
    out: Path | None = typer.Option(None, help="Write the result as JSON here."),
    intrinsics: Path | None = typer.Option(
        None, help="Camera intrinsics of depth-image inputs (default: intrinsics.yaml beside)."
    ),
    as_json: bool = typer.Option(False, "--json", help="Print the JSON summary instead."),
) -> None:
    """Register SOURCE onto TARGET; print T_target_source, fitness, RMSE, covariance, time."""
    from spacepose.core.config import validate_config
    from spacepose.tools.register import RegisterConfig
    from spacepose.tools.register_io import register_files

    config = validate_config(
        RegisterConfig,
        {
            "method": method,
            "robust_kernel": robust_kernel,
            "voxel_size": voxel,
            "global_registration": global_,
        },
        "command line",
    )
    outcome = register_files(source, target, init, config, out, intrinsics=intrinsics)
    if as_json:
        typer.echo(json.dumps(outcome.to_dict()))
        return
    r = outcome.result
    sigma = outcome.covariance.diagonal() ** 0.5
    typer.echo(f"T_target_source ({source.name} -> {target.name}):")
    for row in r.T_target_source:
        typer.echo("  " + " ".join(f"{v: .6f}" for v in row))
    typer.echo(
        f"fitness {r.fitness:.4f}  inlier RMSE {r.inlier_rmse:.4g} m  iterations "
        f"{outcome.iterations}  time {outcome.time_s:.3f} s  voxel {outcome.voxel_size:.4g} m",
    )
    typer.echo(
        "1-sigma rx ry rz (deg): "
        + " ".join(f"{v:.4g}" for v in 57.29577951308232 * sigma[:3])
        + "   tx ty tz (m): "
        + " ".join(f"{v:.4g}" for v in sigma[3:]),
    )
    if out is not None:
        typer.echo(f"wrote {out}")
