"""``spacepose bench``: stage times, registration accuracy, memory and scaling, as JSON."""

from __future__ import annotations

from pathlib import Path

import typer

from spacepose.cli.app import app, console
from spacepose.cli.feedback import working


@app.command()
def bench(
    out: Path = typer.Option(..., help="JSON file to write (BENCH.json)."),
    quick: bool = typer.Option(False, help="320x240 frames, scaling up to 20k points."),
    peers: bool = typer.Option(False, help="Also time Open3D and small_gicp (peers extra)."),
    repeats: int = typer.Option(5, help="Timed calls per stage and contender."),
    seed: int = typer.Option(0, min=0, help="Seed of the simulated frames and of every RANSAC."),
    workers: int = typer.Option(-1, help="Threads for every contender (-1: all cores)."),
    config: Path | None = typer.Option(
        None, help="YAML/JSON file of benchmark options overriding the (--quick) defaults."
    ),
) -> None:
    """Benchmark every stage (interleaved with the peers) on simulated lab frames."""
    from spacepose.tools.bench import (
        accuracy_table,
        bench_config,
        check_bench_output,
        run_benchmark,
        stage_table,
        write_bench,
    )

    options = bench_config(quick, config)
    # Before the benchmark, which takes minutes: a bad --out would throw its result away.
    check_bench_output(out)
    with working("benchmarking"):
        result = run_benchmark(quick, peers, repeats, seed, workers, config=options)
    console.print(stage_table(result))
    console.print(accuracy_table(result))
    memory = result["memory"]
    console.print(
        f"peak traced memory {memory['pipeline_peak_mb']:.1f} MB, "
        f"max RSS {memory['max_rss_mb']:.0f} MB"
    )
    if "tracker_stream" in memory:
        stream = memory["tracker_stream"]
        console.print(
            f"tracker on {stream['frames']} raw {stream['width']}x{stream['height']} frames: "
            f"peak RSS {stream['peak_mb']:.0f} MB (after imports {stream['baseline_mb']:.0f} MB)"
        )
    for stage, series in result["scaling"]["stages"].items():
        exponents = ", ".join(f"{who} {s['exponent']:.2f}" for who, s in series.items())
        ours = series["ours"]
        steps = ""
        if "iterations" in ours:
            counts = "/".join(str(n) for n in ours["iterations"])
            steps = f" (ours: {counts} steps, per step b = {ours['exponent_per_iteration']:.2f})"
        console.print(f"scaling {stage}: t ~ N^b with b = {exponents}{steps}")
    console.print(f"wrote {write_bench(result, out)}")
