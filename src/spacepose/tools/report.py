"""One self-contained HTML report of a run folder: tables, and figures embedded as PNG data URIs.

The report discovers what a folder holds rather than asking for it: every sub-folder with a
``scenario.json`` is a simulated run (its trajectories ``*.tum`` are scored against
``groundtruth.tum``, its ``*.health.csv`` drawn as a timeline, its ``nav*.csv`` scored against
``truth.csv``); every folder of experiment, benchmark or campaign output adds its tables and
figures.
The page has no script, so it renders anywhere and leaves the browser console empty.

A file that cannot be read (a corrupt ``scenario.json``, ``bench.json`` or experiment table, a
health CSV without a ``status`` column, a truncated trajectory) does not stop the report: its part
is left out, the page lists it under "Skipped" with the reason, and a
:class:`~spacepose.errors.SpaceposeWarning` names the file.
"""

from __future__ import annotations

import csv
import html
import json
import warnings
from collections.abc import Callable, Iterable, Sequence
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

from spacepose import __version__
from spacepose.core.config import load_structured, not_text, parse_problem
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
from spacepose.errors import FileFormatError, InputError, SpaceposeError, SpaceposeWarning
from spacepose.tools import plots
from spacepose.tools.cloud_io import read_cloud
from spacepose.tools.evaluation import (
    lone_rebased_pose,
    shared_pairings,
    starts_at_identity,
    without_lost_frames,
)
from spacepose.tools.outputs import check_spares_inputs, check_writable
from spacepose.tools.runs import GROUNDTRUTH, TRUTH, read_truth
from spacepose.tools.trajectory_io import read_tum

# The lab experiments' setting (6 mm voxels and smoothing scale, about the ToF noise at 1.2 m).
MLS_VIEW = MLSConfig(voxel_size=0.006, h=0.006)

_CSS = """
body { font-family: system-ui, sans-serif; margin: 2em auto; max-width: 1250px; color: #222; }
h1 { border-bottom: 2px solid #333; } h2 { margin-top: 2em; border-bottom: 1px solid #aaa; }
table { border-collapse: collapse; margin: 0.8em 0; font-size: 0.9em; }
th, td { border: 1px solid #bbb; padding: 0.25em 0.6em; text-align: right; }
th { background: #eee; } td:first-child, th:first-child { text-align: left; }
img { max-width: 100%; display: block; margin: 0.5em 0; }
.muted { color: #666; font-size: 0.9em; }
"""


def shown(name: str) -> str:
    """A file name as text any writer and font takes: bytes that are not UTF-8 (Python holds
    them as surrogates) become backslash escapes."""
    return name.encode("utf-8", "backslashreplace").decode("utf-8")


def _table(header: Sequence[str], rows: Iterable[Sequence[object]]) -> str:
    def cell(v: object) -> str:
        if isinstance(v, float):
            return f"{v:.4g}"
        return html.escape(str(v))

    head = "".join(f"<th>{html.escape(h)}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td>{cell(v)}</td>" for v in r) + "</tr>" for r in rows)
    return f"<table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>"


def _figure(fig_png: bytes, caption: str) -> str:
    uri = plots.png_data_uri(fig_png)
    return (
        f'<figure><img src="{uri}" alt="{html.escape(caption)}"><figcaption class="muted">'
        f"{html.escape(caption)}</figcaption></figure>"
    )


# What a part of the report may fail with when its file is bad: the package's own errors, an
# unreadable file, a value that does not parse, a missing key or column.
_BAD_FILE = (SpaceposeError, OSError, ValueError, KeyError)


class _Skipped:
    """The files left out of the report, with the reason; each is also warned about."""

    def __init__(self) -> None:
        self.files: list[tuple[Path, str]] = []

    def guard(self, path: Path, build: Callable[[], str]) -> str:
        """``build()``, or ``""`` and a record of why ``path`` was skipped."""
        try:
            return build()
        except _BAD_FILE as exc:
            reason = (
                getattr(exc, "reason", None) or " ".join(str(exc).split()) or type(exc).__name__
            )
            if isinstance(exc, KeyError):
                reason = f"missing key or column {exc}"
            elif isinstance(exc, OSError) and exc.strerror:
                reason = exc.strerror  # the path is named once, by the warning
            self.files.append((path, reason))
            warnings.warn(SpaceposeWarning(f"left out of the report: {reason}", path), stacklevel=2)
            return ""

    def section(self, root: Path) -> str:
        if not self.files:
            return ""
        rows = [
            (str(p.relative_to(root)) if p.is_relative_to(root) else str(p), r)
            for p, r in self.files
        ]
        return "<h2>Skipped</h2>" + _table(("file", "why it was left out"), rows)


def _read_json(path: Path) -> object:
    try:
        return load_structured(path.read_text(), "json")
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise FileFormatError(f"not valid JSON: {parse_problem(exc)}", path) from None


def _read_csv(path: Path, required: Sequence[str] = ()) -> dict[str, list[str]]:
    try:
        with path.open(newline="") as fh:
            reader = csv.reader(fh)
            lines = [(reader.line_num, row) for row in reader]
    except UnicodeDecodeError as exc:
        # Its own ``reason`` ("invalid start byte") would be all the report shows.
        raise FileFormatError(not_text(exc), path) from None
    except csv.Error as exc:
        raise FileFormatError(f"not a readable CSV file: {exc}", path) from None
    lines = [(number, row) for number, row in lines if row]  # blank lines, as DictReader
    if len(lines) < 2:
        raise InputError("CSV file has no data rows", path)
    header = lines[0][1]
    for number, row in lines[1:]:
        if len(row) != len(header):
            # A half-written last row (a run stopped mid-write) was read with its missing
            # fields as None: a status cut to "lo" or none at all was drawn as another flag.
            raise FileFormatError(
                f"line {number} has {len(row)} fields, the header {len(header)}: a half-written "
                "or hand-edited file?",
                path,
            )
    missing = [c for c in required if c not in header]
    if missing:
        raise FileFormatError(f"CSV file has no {', '.join(missing)} column", path)
    return {k: [row[i] for _, row in lines[1:]] for i, k in enumerate(header)}


def _scenario_section(run: Path) -> str:
    scenario = _read_json(run / "scenario.json")
    if not isinstance(scenario, dict):
        raise FileFormatError("scenario.json must hold a mapping", run / "scenario.json")
    rows = []
    for key, value in sorted(scenario.items()):
        text = json.dumps(value)
        rows.append((key, text if len(text) <= 160 else text[:157] + "..."))
    return _table(("parameter", "value"), rows)


def scenario_name(run: Path) -> str | None:
    """The ``scenario`` entry of a run's scenario.json (``lab``, ``orbit``), if any.

    Raises
    ------
    FileFormatError
        scenario.json is not valid JSON or not a mapping.
    """
    scenario = _read_json(run / "scenario.json")
    if not isinstance(scenario, dict):
        raise FileFormatError("scenario.json must hold a mapping", run / "scenario.json")
    return scenario.get("scenario")


def _mls_section(run: Path) -> str:
    """Frame 0 of the run before and after mpp-MLS (Li §2.2); experiment li-l1 quantifies it."""
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
    return "<h3>mpp-MLS before / after</h3>" + _figure(plots.figure_png(fig), "mpp-MLS")


def _tracking_section(run: Path, skipped: _Skipped) -> str:
    gt_path = run / "groundtruth.tum"
    tracks = [p for p in _own_files(run, "*.tum") if p.name != GROUNDTRUTH]
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
        _, i_gt = associate(est.timestamps, gt.timestamps)
        shared = shared_pairings(i_gt)
        alone = lone_rebased_pose(len(scored), rebase)
        for text in filter(None, (note, shared, alone)):
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
        status = _read_csv(path, ("status",))["status"]
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
    parts.append(_table(header, rows))
    parts.extend(f"<p class='muted'>{n}</p>" for n in notes)
    if curves:
        fig = plots.pose_error_curves(t, curves, f"{shown(run.name)}: pose errors")
        parts.append(_figure(plots.figure_png(fig), "per-axis errors against time"))
    if health:
        parts.append(_figure(plots.figure_png(plots.health_timeline(t, health)), "health flags"))
    return "<h3>Tracking</h3>" + "".join(parts)


def _own_files(run: Path, pattern: str) -> list[Path]:
    """The files matching ``pattern`` under ``run``, sorted, but for those of a run nested in
    it (a subfolder with its own scenario.json, reported as a run of its own): an outer run
    scored the inner one's tracks, and its groundtruth.tum as a track, against its own truth
    (15 m off, without a word)."""
    own = []
    for path in run.rglob(pattern):
        between = list(path.relative_to(run).parents)[:-1]  # the folders below ``run``
        if not any((run / folder / "scenario.json").is_file() for folder in between):
            own.append(path)
    return sorted(own)


def _table_cells(d: dict) -> list[tuple[float, float]]:
    keys = ("x_mm", "y_mm", "z_mm", "pitch_deg", "yaw_deg", "roll_deg")
    return [(d["mean"][k], d["std"][k]) for k in keys]


def _navigation_section(run: Path, skipped: _Skipped) -> str:
    truth_path = run / TRUTH
    # NAV.csv itself, not its companions (NAV.candidates.csv, NAV.health.csv).
    # Any case: the README writes NAV.csv, the demo nav.csv.
    navs = [
        p
        for p in _own_files(run, "*.csv")
        if p.stem.lower().startswith("nav") and "." not in p.stem
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
    table = _read_csv(nav_path)
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
    parts.append(_table(("state (RMS over the second half)", "x", "y", "z"), rows))
    for name, (unit, cols, err, sig) in errors.groups.items():
        fig = plots.error_with_envelope(
            errors.t,
            err,
            sig,
            [f"{c} ({unit})" for c in cols],
            f"{nav_path.stem}: {name} error",
        )
        parts.append(_figure(plots.figure_png(fig), f"{name} error with ±3σ"))
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


def _experiments_section(root: Path, skipped: _Skipped) -> str:
    parts = []
    for folder in sorted({p.parent for p in root.rglob("*.png")}):
        if (folder / "scenario.json").exists():
            continue
        parts.append(f"<h3>{html.escape(str(folder.relative_to(root)) or folder.name)}</h3>")
        for table_path in sorted(folder.glob("*.json")):
            text = skipped.guard(table_path, lambda p=table_path: _short_json(p))
            if text:
                parts.append(f"<pre class='muted'>{html.escape(text)}</pre>")
        for png in sorted(folder.glob("*.png")):
            # A folder or a broken link named as a figure: left out, not the whole report.
            parts.append(skipped.guard(png, lambda p=png: _figure(p.read_bytes(), p.stem)))
    return "".join(parts)


def _short_json(path: Path, limit: int = 4000) -> str:
    text = json.dumps(_read_json(path), indent=1, default=str)
    return text if len(text) <= limit else text[:limit] + "\n..."


def _benchmark_section(root: Path, skipped: _Skipped) -> str:
    return "".join(
        skipped.guard(path, lambda p=path: _bench_file(p))
        for path in sorted(root.rglob("bench*.json"))
    )


def _bench_file(path: Path) -> str:
    """The stage-time table of one ``spacepose bench`` output."""
    data = _read_json(path)
    stages = data.get("stages", {}) if isinstance(data, dict) else None
    if not isinstance(stages, dict) or not all(isinstance(s, dict) for s in stages.values()):
        raise FileFormatError("not a spacepose bench output (no 'stages' mapping)", path)
    rows = [
        (
            name,
            s.get("median_ms", float("nan")),
            s.get("min_ms", float("nan")),
            s.get("max_ms", float("nan")),
            s.get("peer_ratio", ""),
        )
        for name, s in stages.items()
    ]
    header = ("stage", "median ms", "min ms", "max ms", "peer / ours")
    return f"<h3>{html.escape(path.name)}</h3>" + _table(header, rows)


def build_report(run_dir: str | Path, out: str | Path | None = None) -> Path:
    """Write the HTML report of everything found under ``run_dir``.

    Parameters
    ----------
    run_dir
        A run folder from ``spacepose simulate`` (with tracks / navigation beside it), or a folder
        of several such runs plus experiment, benchmark and campaign outputs (``make demo``'s).
    out
        The HTML file; ``run_dir/report.html`` by default.

    Returns
    -------
    The path written.
    """
    root = Path(run_dir)
    if not root.is_dir():
        raise InputError("not a folder", root)
    out_path = Path(out) if out is not None else root / "report.html"
    check_writable(out_path)
    # The report reads the folder's files (a run's groundtruth.tum, a track): written onto one
    # it would destroy it. A page written before (report.html) is no input.
    check_spares_inputs(
        [out_path], (p for p in root.rglob("*") if p.suffix.lower() not in (".html", ".htm"))
    )
    runs = sorted(p.parent for p in root.rglob("scenario.json"))
    skipped = _Skipped()
    body = []
    for run in runs:
        name = html.escape(str(run.relative_to(root)) if run != root else run.name)
        body.append(f"<h2>Run: {name}</h2>")
        scenario = skipped.guard(run / "scenario.json", lambda run=run: _scenario_section(run))
        body.append(scenario)
        if scenario and scenario_name(run) == "lab":
            body.append(skipped.guard(run / "frames", lambda run=run: _mls_section(run)))
        body.append(
            skipped.guard(run / "groundtruth.tum", lambda run=run: _tracking_section(run, skipped))
        )
        body.append(
            skipped.guard(run / "truth.csv", lambda run=run: _navigation_section(run, skipped))
        )
    experiments = _experiments_section(root, skipped)
    if experiments:
        body.append("<h2>Experiments and campaigns</h2>" + experiments)
    bench = _benchmark_section(root, skipped)
    if bench:
        body.append("<h2>Benchmark</h2>" + bench)
    body.append(skipped.section(root))
    if not any(body):
        raise InputError("nothing to report: no run, experiment or benchmark output found", root)
    stamp = datetime.now(UTC).strftime("%Y-%m-%d %H:%M UTC")
    page = (
        "<!DOCTYPE html><html lang='en'><head><meta charset='utf-8'>"
        f"<title>spacepose report: {html.escape(root.name)}</title><style>{_CSS}</style></head>"
        f"<body><h1>spacepose report: {html.escape(root.name)}</h1>"
        f"<p class='muted'>spacepose {__version__}, written {stamp}</p>"
        f"{''.join(body)}</body></html>"
    )
    out_path.parent.mkdir(parents=True, exist_ok=True)
    out_path.write_text(page, encoding="utf-8", errors="backslashreplace")
    return out_path
