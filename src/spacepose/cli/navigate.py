"""``spacepose navigate RUN --out NAV.csv``: relative navigation from rectangles (Yu et al.),
registration poses of the model-based tracker, or both in one filter."""

from __future__ import annotations

from pathlib import Path

import typer

from spacepose.cli.app import app, console, err_console
from spacepose.cli.feedback import working


@app.command()
def navigate(
    run: Path = typer.Argument(
        ...,
        help="Run folder from 'spacepose simulate orbit', a folder of frame files or depth "
        "images, or a ROS 1/2 bag.",
    ),
    out: Path = typer.Option(..., "--out", help="NAV.csv: one row of state, 1-σ and status."),
    config: Path | None = typer.Option(
        None, "--config", help="YAML/JSON NavigationConfig (defaults in code)."
    ),
    scenario: Path | None = typer.Option(
        None, help="YAML/JSON with mean_motion, R_O_C and rectangles (needed for a frame folder)."
    ),
    prior: str | None = typer.Option(
        None,
        help="Coarse attitude prior 'qx,qy,qz,qw' (q_I_B at t = 0) that picks among the "
        "target's symmetric poses at start. Without it the navigator starts lost in space.",
    ),
    debug_prior_from_truth: bool = typer.Option(
        False,
        help="DEBUGGING ONLY: take the prior from the simulator's TRUE initial attitude "
        "(scenario.json initial_q_I_B). No real run has it.",
    ),
    intrinsics: Path | None = typer.Option(
        None, help="Depth image intrinsics (YAML/JSON: fx, fy, cx, cy, depth_scale, k1..k6, p1, p2)"
    ),
    topic: str | None = typer.Option(None, help="Bag topic (PointCloud2 or depth Image)."),
    measurements: str = typer.Option(
        "rectangles",
        help="rectangles (Yu's faces), registration (the model-based tracker's pose and "
        "covariance each frame) or both, fused in one filter.",
    ),
    model: Path | None = typer.Option(
        None,
        help="Target surface samples (cloud file, model frame) for registration; default: "
        "the scenario's model or the run's model.ply.",
    ),
) -> None:
    """Estimate ρ, ρ̇, attitude, rate, inertia ratios and CoM offset for every frame of RUN."""
    from spacepose.tools.navigation_config_io import load_navigation_config
    from spacepose.tools.navigation_io import navigate_run, output_paths
    from spacepose.tools.outputs import check_spares_inputs

    if measurements not in ("rectangles", "registration", "both"):
        from spacepose.errors import ConfigError

        raise ConfigError(
            f"--measurements must be rectangles, registration or both, got {measurements!r}"
        )
    cfg, fusion = (None, None) if config is None else load_navigation_config(config, measurements)
    if config is not None:
        # The effective config goes to NAV.config.json: given as --config it was replaced.
        check_spares_inputs(output_paths(out, measurements), [config])
    with working("navigating"):
        summary = navigate_run(
            run,
            out,
            cfg,
            scenario=scenario,
            prior_q_I_B=None if prior is None else _quaternion(prior),
            debug_prior_from_truth=debug_prior_from_truth,
            intrinsics=intrinsics,
            topic=topic,
            measurements=measurements,
            model=model,
            fusion=fusion,
        )
    if summary.ambiguous:
        err_console.print(
            f"{summary.ambiguous} frames ambiguous (several candidate poses), candidates -> "
            f"{summary.candidates_csv}",
            markup=False,
        )
    health = "" if summary.health_csv is None else f"; tracker health -> {summary.health_csv}"
    if summary.pose_noise_json is not None:
        health += f"; poses' σ factor measured -> {summary.pose_noise_json}"
    console.print(
        f"{summary.frames} frames ({summary.navigated} navigated) -> {summary.nav_csv}; "
        f"config -> {summary.config_json}{health}"
    )


def _quaternion(text: str) -> tuple[float, ...]:
    """``qx,qy,qz,qw`` as four floats of a rotation; ConfigError otherwise."""
    from spacepose.errors import ConfigError
    from spacepose.tools.navigation_config_io import prior_quaternion

    try:
        q = tuple(float(v) for v in text.replace(" ", ",").split(",") if v)
    except ValueError:
        q = ()
    if len(q) != 4:
        raise ConfigError(f"--prior must be four numbers qx,qy,qz,qw, got {text!r}")
    return prior_quaternion(q, "--prior")
