"""``spacepose planes FILE``: extract planes, measure them as rectangles, recognise them."""

from __future__ import annotations

import json
import warnings
from pathlib import Path

import typer
from rich.table import Table

from spacepose.cli.app import app, console
from spacepose.errors import SpaceposeWarning


@app.command()
def planes(
    file: Path = typer.Argument(..., help="Point cloud (PLY, PCD, XYZ/TXT/CSV, NPY/NPZ), metres."),
    sigma: float = typer.Option(0.0, help="Point noise σ (m) removed from the eigenvalues."),
    catalogue: Path | None = typer.Option(
        None, help="Rectangle catalogue: a run's scenario.json or a YAML/JSON list."
    ),
    focal_px: float | None = typer.Option(
        None, help="Focal length (px) of the camera that took FILE: enables the fill check."
    ),
    cluster_radius: float | None = typer.Option(
        None, help="Keep each plane's largest group of inliers closer than this (m)."
    ),
    threshold: float | None = typer.Option(
        None,
        help="Plane thickness d (m) for RANSAC inliers [default: 3 σ, σ given by --sigma or "
        "measured along FILE's rays; 0.005 for a frame without noise].",
    ),
    min_inliers: int = typer.Option(50, help="Stop when a plane has fewer inliers."),
    max_planes: int = typer.Option(10, help="Largest number of planes to extract."),
    seed: int = typer.Option(0, min=0, help="Seed of the RANSAC sampling."),
    as_json: bool = typer.Option(False, "--json", help="Print a JSON list instead of a table."),
) -> None:
    """List the planes of FILE with centroid, normal, eigenvalues, sides and recognised name.

    With a catalogue a rectangle is named when its sides match one entry only; when they match
    several (faces of equal size) it is left unnamed and ``candidates`` lists them all.
    """
    from spacepose.core.config import validate_config
    from spacepose.core.planes import PlaneConfig, slab_thickness, why_no_planes
    from spacepose.core.rectangle_search import find_rectangles
    from spacepose.core.rectangles import RectangleConfig, candidates
    from spacepose.tools.catalogue import load_catalogue
    from spacepose.tools.cloud_io import read_sensor_cloud

    settings = {
        "min_inliers": min_inliers,
        "max_planes": max_planes,
        "seed": seed,
        "cluster_radius": cluster_radius,
    }
    validate_config(PlaneConfig, settings, "command line")  # refused before the file is read
    rect_config = validate_config(
        RectangleConfig, {"sigma": sigma, "focal_px": focal_px}, "command line"
    )
    entries = [] if catalogue is None else load_catalogue(catalogue, rect_config)
    cloud = read_sensor_cloud(file)
    if threshold is None:
        threshold = slab_thickness(cloud, sigma)  # the cloud: its warning names the file
    settings = {**settings, "distance_threshold": threshold}
    plane_config = validate_config(PlaneConfig, settings, "command line")
    found = find_rectangles(cloud, entries, plane_config, rect_config)
    if not found:
        reason = why_no_planes(cloud, plane_config)
        warnings.warn(SpaceposeWarning(f"{file}: no plane found: {reason}"), stacklevel=1)
    rows = [
        {
            "centroid": f.measurement.centroid.tolist(),
            "normal": f.plane.normal.tolist(),
            "eigenvalues": f.measurement.eigenvalues.tolist(),
            "a": f.measurement.a,
            "b": f.measurement.b,
            "n_inliers": f.plane.n_inliers,
            "rectangle": f.name,
            "candidates": [e.name for e in candidates(f.measurement, entries, rect_config)],
        }
        for f in found
    ]
    if as_json:
        # Plain print: rich would wrap long lines and break the JSON for a pipe.
        typer.echo(json.dumps(rows))
        return
    table = Table(title=f"{len(rows)} planes in {file}")
    for column in ("#", "inliers", "centroid (m)", "normal", "a x b (m)", "rectangle"):
        table.add_column(column)
    for i, row in enumerate(rows):
        table.add_row(
            str(i),
            str(row["n_inliers"]),
            " ".join(f"{v:.3f}" for v in row["centroid"]),
            " ".join(f"{v:.3f}" for v in row["normal"]),
            f"{row['a']:.3f} x {row['b']:.3f}",
            row["rectangle"] or _unnamed(row["candidates"]),
        )
    console.print(table)


def _unnamed(names: list[str]) -> str:
    """What the table says of a rectangle its sides do not name."""
    return "ambiguous: " + " | ".join(names) if len(names) > 1 else "-"
