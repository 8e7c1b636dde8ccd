"""The sections of one simulated run in ``spacepose report``: its scenario, frame 0 before and
after mpp-MLS, its tracks scored against the ground truth, its navigation against the truth.

A run is a folder with a ``scenario.json``: :func:`scenario_section` tables its parameters,
:func:`mls_section` draws a lab run's frame 0 raw and smoothed, :func:`tracking_section` scores
every ``*.tum`` against ``groundtruth.tum`` (and draws its ``*.health.csv`` as a timeline), and
:func:`navigation_section` scores every ``nav*.csv`` against ``truth.csv``. A file that cannot be
read leaves its part out through :class:`~spacepose.tools.report_files.Skipped`.
"""

from __future__ import annotations

import html
import json
import warnings
from pathlib import Path

import numpy as np

from spacepose.core.metrics import (
    TIMESTAMP_TOLERANCE,
    ErrorTable,
    associate,
    evaluate,
    navigation_errors,
    pose_errors,
)
from spacepose.core.mls import MLSConfig, mpp_mls
from spacepose.core.sim.scenarios import TRUTH_COLUMNS
from spacepose.errors import FileFormatError, InputError, SpaceposeWarning
from spacepose.tools import plots
from spacepose.tools.cloud_io import read_cloud
from spacepose.tools.evaluation import (
    clock_offset,
    lone_rebased_pose,
    quaternion_order,
    shared_pairings,
    starts_at_identity,
    unit_mismatch,
    without_lost_frames,
)
from spacepose.tools.report_files import Skipped, own_files, read_csv, read_scenario
from spacepose.tools.report_html import html_figure, html_table, shown
from spacepose.tools.runs import GROUNDTRUTH, TRUTH, read_truth
from spacepose.tools.trajectory_io import read_tum

# The lab experiments' setting (6 mm voxels and smoothing scale, about the ToF noise at 1.2 m).
MLS_VIEW = MLSConfig(voxel_size=0.006, h=0.006)


def scenario_section(run: Path) -> str:
    """The table of a run's scenario.json, every parameter and its value (long ones cut).

    Parameters
    ----------
    run
        The run folder.

    Returns
    -------
    The ``<table>`` element.

    Raises
    ------
    FileFormatError
        scenario.json is not valid JSON or not a mapping.
    """
    scenario = read_scenario(run)
    rows = []
    for key, value in sorted(scenario.items()):
        text = json.dumps(value)
        rows.append((key, text if len(text) <= 160 else text[:157] + "..."))
    return html_table(("parameter", "value"), rows)


def mls_section(run: Path) -> str:
    """Frame 0 of the run before and after mpp-MLS (Li §2.2); experiment li-l1 quantifies it.

    Parameters
    ----------
    run
        The run folder (a lab run, smoothed with :data:`MLS_VIEW`).

    Returns
    -------
    The heading and figure, or ``""`` when the run has no frames.
    """
    frames = sorted((run / "frames").glob("*.ply"))
    if not frames:
        return ""
    raw = read_cloud(frames[0])
    smooth = mpp_mls(raw, MLS_VIEW)
    voxel, h = 1e3 * MLS_VIEW.voxel_size, 1e3 * MLS_VIEW.h
    fig = plots.cloud_views(
        {"raw frame": raw.points, "after mpp-MLS": smooth.points},
        f"{shown(run.name)}, frame 0 (voxel {voxel:g} mm, h {h:g} mm)",
    )
    return "<h3>mpp-MLS before / after</h3>" + html_figure(plots.figure_png(fig), "mpp-MLS")


def tracking_section(run: Path, skipped: Skipped) -> str:
    """The error table and figures of a run's tracks (``*.tum``) against its groundtruth.tum.

    Parameters
    ----------
    run
        The run folder.
    skipped
        Guards each track and its ``*.health.csv``: one that cannot be read is left out.

    Returns
    -------
    The section, or ``""`` when the run has no track (or none could be scored).

    Raises
    ------
    InputError
        The run has tracks but no groundtruth.tum, or it cannot be read.
    """
    gt_path = run / "groundtruth.tum"
    # Any case of the suffix, as `track` writes and the frame readers take it (upper.TUM was
    # left out of the report without a word).
    tracks = [p for p in own_files(run, "*.[tT][uU][mM]") if p.name.lower() != GROUNDTRUTH]
    if not tracks:
        return ""
    if not gt_path.exists():  # the tracks cannot be scored: say so, not leave them out unseen
        raise InputError(
            f"not found, so {', '.join(p.name for p in tracks)} cannot be scored", gt_path
        )
    gt = read_tum(gt_path)
    parts, rows, curves, health, notes = [], [], {}, {}, []
    t = gt.timestamps - gt.timestamps[0]

    def score(path: Path) -> str:
        est = read_tum(path)
        rebase = starts_at_identity(est.poses[0])  # model-free: score it re-based
        # A lost frame's pose is the motion model's guess, not a measurement (as `evaluate`).
        scored, lost, note = without_lost_frames(path, est)
        table: ErrorTable = evaluate(scored, gt, rebase_first=rebase)
        d = table.to_dict()
        i_est, i_gt = associate(est.timestamps, gt.timestamps)
        shared = shared_pairings(i_gt)
        alone = lone_rebased_pose(len(scored), rebase)
        # As `evaluate` warns: a track in millimetres scored its whole distance as error, one
        # written w first 160° of rotation, one on another clock poses that far apart in time.
        units = unit_mismatch(est.poses, gt.poses[i_gt], gt_path.name, rebase)
        paired = (est.poses[i_est], gt.poses[i_gt], gt_path.name, rebase)
        order = quaternion_order(*paired)
        offset = clock_offset(est.timestamps[i_est], gt.timestamps[i_gt], gt_path.name)
        for text in filter(None, (note, shared, alone, order, offset, *units)):
            notes.append(html.escape(f"{shown(path.stem)}: {text}"))
        rows.append(
            (
                path.stem,
                *(f"{m:.3f} ({s:.3f})" for m, s in _table_cells(d)),
                f"{1e3 * d['ate_translation_rmse']:.3f}",
                f"{d['ate_rotation_rmse']:.4f}",
            )
        )
        gt_eval = gt.rebased_first() if rebase else gt
        # Curves pair the k-th estimate with the k-th truth: only when their times do.
        if len(est) == len(gt_eval) and np.array_equal(i_gt, np.arange(len(gt))):
            dt, de = pose_errors(est.poses, gt_eval.poses)
            # Columns: x, y, z (mm), then pitch, yaw, roll (deg) as in Li's Table 2.
            curve = np.c_[1e3 * dt, np.degrees(de[:, [1, 0, 2]])]
            if lost is not None and not lost.all():
                curve[lost] = np.nan  # a gap where the frame was lost
            curves[path.stem] = curve
        return "ok"

    def flags(path: Path) -> str:
        status = read_csv(path, ("status",))["status"]
        other = next((k for k, v in enumerate(status) if v not in plots.STATUS_COLOUR), None)
        if other is not None:
            # Drawn as a black flag of no meaning before.
            raise FileFormatError(
                f"row {other + 1} has status {status[other]!r}, not one of "
                f"{', '.join(plots.STATUS_COLOUR)}",
                path,
            )
        # The timeline is drawn against the ground truth's times, one flag a frame.
        if len(status) != len(t):
            raise FileFormatError(f"{len(status)} rows for {len(t)} ground-truth frames", path)
        health[path.stem] = status
        return "ok"

    for path in tracks:
        if skipped.guard(path, lambda path=path: score(path)):
            health_csv = path.with_name(path.stem + ".health.csv")
            if health_csv.exists():
                skipped.guard(health_csv, lambda path=health_csv: flags(path))
    if not rows:
        return ""
    header = ("method", "x mm", "y mm", "z mm", "pitch °", "yaw °", "roll °", "ATE mm", "ATE °")
    parts.append("<p class='muted'>mean (std) of the absolute per-frame errors</p>")
    parts.append(html_table(header, rows))
    parts.extend(f"<p class='muted'>{n}</p>" for n in notes)
    if curves:
        fig = plots.pose_error_curves(t, curves, f"{shown(run.name)}: pose errors")
        parts.append(html_figure(plots.figure_png(fig), "per-axis errors against time"))
    if health:
        parts.append(
            html_figure(plots.figure_png(plots.health_timeline(t, health)), "health flags")
        )
    return "<h3>Tracking</h3>" + "".join(parts)


def _table_cells(d: dict) -> list[tuple[float, float]]:
    keys = ("x_mm", "y_mm", "z_mm", "pitch_deg", "yaw_deg", "roll_deg")
    return [(d["mean"][k], d["std"][k]) for k in keys]


def navigation_section(run: Path, skipped: Skipped) -> str:
    """The RMS tables and error figures of a run's navigation outputs (``nav*.csv``, any
    case) against its truth.csv.

    Parameters
    ----------
    run
        The run folder.
    skipped
        Guards each navigation output: one that cannot be read or scored is left out.

    Returns
    -------
    The section, or ``""`` when the run has no navigation output (or none could be scored).

    Raises
    ------
    InputError
        The run has navigation outputs but no truth.csv, or it (or the frames' times in
        groundtruth.tum) cannot be read.
    """
    truth_path = run / TRUTH
    # NAV.csv itself, not its companions (NAV.candidates.csv, NAV.health.csv).
    # Any case: the README writes NAV.csv, the demo nav.csv.
    navs = [
        p for p in own_files(run, "*.csv") if p.stem.lower().startswith("nav") and "." not in p.stem
    ]
    if not navs:
        return ""
    if not truth_path.exists():  # as tracks without groundtruth.tum: said, not left out unseen
        raise InputError(
            f"not found, so {', '.join(p.name for p in navs)} cannot be scored", truth_path
        )
    # Checked as navigate reads it (read_run): a truth row at another time than its frame
    # scored every navigation against the wrong frame's state without a word.
    gt_path = run / GROUNDTRUTH
    times = None  # no frame times to check against: the table itself is checked
    if gt_path.exists():
        try:
            times = read_tum(gt_path).timestamps
        except InputError as exc:  # the section is left out under truth.csv: say whose fault
            raise InputError(f"its frames' times cannot be read: {exc}", truth_path) from None
    truth = dict(zip(TRUTH_COLUMNS, read_truth(truth_path, times).T, strict=True))
    parts = [skipped.guard(nav_path, lambda p=nav_path: _nav_file(p, truth)) for nav_path in navs]
    return "<h3>Relative navigation</h3>" + "".join(parts) if any(parts) else ""


def _nav_file(nav_path: Path, truth: dict[str, np.ndarray]) -> str:
    """The RMS table and error figures of one navigation output against truth."""
    parts = []
    table = read_csv(nav_path)
    nav = {k: np.asarray(v, dtype=float) for k, v in table.items() if k != "status"}
    if "t" in nav and "t" in truth:
        # Rows pair line by line: a table of other times would score other frames' states.
        n = min(len(nav["t"]), len(truth["t"]))
        apart = np.flatnonzero(np.abs(nav["t"][:n] - truth["t"][:n]) > TIMESTAMP_TOLERANCE)
        if len(apart):
            k = apart[0]
            raise InputError(
                f"row {k + 1} is at t = {nav['t'][k]:.9g} s, truth.csv's at {truth['t'][k]:.9g} s: "
                "a navigation of other frames, which scored line by line would pair other states"
            )
    if "qw" in nav and not np.any(np.isfinite(nav["qw"])):
        # Its error curves were all NaN: numpy's bare warnings and matplotlib's "Axis limits
        # cannot be NaN or Inf" as the reason.
        raise InputError("no frame navigated (no row holds a state): nothing to score")
    _warn_if_partial(nav_path, nav, table.get("status"), len(truth.get("t", ())))
    errors = navigation_errors(nav, truth)
    rms = errors.rms(0.5)
    rows = [(f"{name} ({unit})", *rms[name]) for name, (unit, *_) in errors.groups.items()]
    parts.append(f"<h4>{html.escape(nav_path.name)}</h4>")
    parts.append(html_table(("state (RMS over the second half)", "x", "y", "z"), rows))
    for name, (unit, cols, err, sig) in errors.groups.items():
        fig = plots.error_with_envelope(
            errors.t,
            err,
            sig,
            [f"{c} ({unit})" for c in cols],
            f"{nav_path.stem}: {name} error",
        )
        parts.append(html_figure(plots.figure_png(fig), f"{name} error with ±3σ"))
    return "".join(parts)


def _warn_if_partial(
    nav_path: Path, nav: dict[str, np.ndarray], status: object, frames: int
) -> None:
    """Warn of a navigation table scored on less than the run: fewer rows than the run's
    frames ("the second half" was then of those rows), or a row the filter updated that holds
    NaN (it was left out of the RMS without a word)."""
    rows = len(nav.get("t", ()))
    if frames and rows < frames:
        problem = f"{rows} rows for the run's {frames} frames: scored over those rows only"
        warnings.warn(SpaceposeWarning(problem, nav_path), stacklevel=3)
    if status is None:
        return
    state = [nav[k] for k in ("rho_x", "rho_y", "rho_z", "qw") if k in nav]
    updated = np.asarray(status) == "update"
    holes = np.flatnonzero(updated & ~np.all(np.isfinite(state), axis=0)) if state else []
    if len(holes):
        problem = (
            f"row {holes[0] + 1} holds NaN though its status is update ({len(holes)} such rows, "
            "left out of the RMS)"
        )
        warnings.warn(SpaceposeWarning(problem, nav_path), stacklevel=3)
