"""``spacepose report RUN_DIR``: one self-contained HTML report."""

from __future__ import annotations

from pathlib import Path

import typer

from spacepose.cli.app import app, console
from spacepose.errors import InputError


@app.command()
def report(
    run_dir: Path = typer.Argument(..., help="A run folder, or a folder of runs (make demo's)."),
    out: Path | None = typer.Option(None, help="HTML file; RUN_DIR/report.html by default."),
) -> None:
    """Write an HTML report (figures embedded) of the runs, tracks, navigation and experiments."""
    from spacepose.tools.report import build_report

    if not run_dir.exists() and not run_dir.is_symlink():
        # "not a folder" sent the user looking at what the path is, not at its spelling.
        raise InputError("not a folder: it does not exist", run_dir)
    console.print(f"report written: {build_report(run_dir, out)}")
