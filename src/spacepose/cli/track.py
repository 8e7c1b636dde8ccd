"""``spacepose track INPUT --out EST.tum``: track the target through a sequence of frames."""

from __future__ import annotations

import warnings
from pathlib import Path

import typer
from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

from spacepose.cli.app import app, console
from spacepose.errors import InputError, SpaceposeWarning

# Old method names still accepted, each with a one-line warning.
_DEPRECATED = {"icp": "point_to_plane"}


@app.command()
def track(
    input: Path = typer.Argument(
        ...,
        help="A run folder, a folder of frame files (PLY/PCD/XYZ/NPY, sorted by name) or of "
        "depth images (PNG/TIFF with intrinsics.yaml, or TUM's depth.txt), or a ROS 1/2 bag.",
    ),
    out: Path = typer.Option(..., "--out", help="Estimated trajectory (TUM)."),
    method: str | None = typer.Option(
        None,
        help="Fine registration: point_to_point, point_to_plane, gicp, jicp (Li's J-ICP) or "
        "keyframe (keyframe graph, ours; default: the config's, else keyframe).",
    ),
    model: Path | None = typer.Option(
        None, help="Reference model cloud (target frame): model-based tracking."
    ),
    mls: bool | None = typer.Option(
        None,
        "--mls/--no-mls",
        help="Preprocess by mpp-MLS, or by voxel downsampling (default: the config's, voxels).",
    ),
    background: bool = typer.Option(
        False, "--background", help="Remove the background (walls, turntable) first."
    ),
    config: Path | None = typer.Option(None, help="Tracker config file (YAML or JSON)."),
    workers: int = typer.Option(-1, help="Threads for neighbour searches (-1: all cores)."),
    intrinsics: Path | None = typer.Option(
        None, help="Depth image intrinsics (YAML/JSON: fx, fy, cx, cy, depth_scale, k1..k6, p1, p2)"
    ),
    topic: str | None = typer.Option(
        None, help="Bag topic (PointCloud2, depth Image or CompressedImage)."
    ),
) -> None:
    """Track every frame; writes EST.tum and its .health.csv, .cov.csv, .config.json, .scale.json.

    Without --model the first frame defines the target frame (its pose is the identity).
    """
    from spacepose.tools.outputs import check_spares_inputs
    from spacepose.tools.tracking_io import output_paths, track_folder, tracker_config

    if method in _DEPRECATED:
        new = _DEPRECATED[method]
        warnings.warn(SpaceposeWarning(f"--method {method} is deprecated: use {new}"), stacklevel=1)
        method = new
    cfg = tracker_config(config, method=method, mls=mls, background=background)
    if config is not None:
        # The effective config goes to EST.config.json: given as --config it was replaced.
        check_spares_inputs(output_paths(out), [config])
    with Progress(
        TextColumn("tracking"),
        BarColumn(),
        MofNCompleteColumn(),
        TextColumn("{task.fields[status]}"),
        TimeRemainingColumn(),
        console=console,
        transient=True,
        # Off a terminal rich would still end its (invisible) line: an empty line on stdout.
        disable=not console.is_terminal,
    ) as progress:
        task = progress.add_task("track", total=None, status="")

        def report(done: int, total: int, status: str) -> None:
            progress.update(task, completed=done, total=total, status=status)

        summary = track_folder(
            input,
            out,
            cfg,
            model=model,
            workers=workers,
            progress=report,
            intrinsics=intrinsics,
            topic=topic,
        )
    console.print(
        f"{summary['frames']} frames: {summary['ok']} ok, {summary['degraded']} degraded, "
        f"{summary['lost']} lost; {summary['mean_time_ms']:.1f} ms/frame -> {out}",
        highlight=False,
    )
    if summary["lost"] == summary["frames"]:
        # Rows were written for every frame, but a run with no pose is a failure to report.
        raise InputError(f"every frame was lost ({summary['first_lost']})", input)
    if model is None and summary["frames"] > 1 and summary["lost"] == summary["frames"] - 1:
        # Model-free, the first frame's pose is the identity by definition: nothing was tracked.
        raise InputError(
            f"every frame but the one that sets the target frame was lost "
            f"({summary['first_lost']})",
            input,
        )
