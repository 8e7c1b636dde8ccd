"""``spacepose campaign CONFIG.yaml``: a Monte Carlo grid of cases run on Dask."""

from __future__ import annotations

from pathlib import Path

import typer

from spacepose.cli.app import app, console


@app.command()
def campaign(
    config: Path = typer.Argument(..., help="Campaign config (YAML or JSON)."),
    scheduler: str | None = typer.Option(
        None, help="Address of a running Dask scheduler; default: a local process cluster."
    ),
    workers: int | None = typer.Option(None, help="Local worker processes (overrides config)."),
    out: Path | None = typer.Option(None, help="Output folder (overrides config)."),
) -> None:
    """Run or resume a campaign: parts/, results.parquet, summary.json and plots go to OUT."""
    from spacepose.errors import ConfigError, InputError
    from spacepose.tools.campaign import RESULTS_FILE, run_campaign
    from spacepose.tools.campaign_spec import load_campaign_config

    if scheduler is not None and workers is not None:
        # The running cluster has its own workers: --workers was dropped without a word.
        raise ConfigError(
            "--workers sets the local cluster's worker processes, and --scheduler uses a "
            "running cluster and its workers: give one of them"
        )
    cfg = load_campaign_config(config, workers=workers, out=out)
    result = run_campaign(cfg, scheduler=scheduler)
    failed = f", {result.n_failed} failed (why: the error column)" if result.n_failed else ""
    console.print(
        f"{result.table.num_rows} cases ({result.n_computed} computed, "
        f"{result.n_skipped} already done{failed}) -> {result.out_dir / RESULTS_FILE}"
    )
    if result.table.num_rows and result.n_failed == result.table.num_rows:
        # A campaign with no result is a failure to report, as a track with no pose is.
        first = result.table.column("error")[0].as_py()
        raise InputError(f"every case failed (the first: {first})", config)
