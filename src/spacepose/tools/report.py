"""One self-contained HTML report of a run folder: tables, and figures embedded as PNG data URIs.

The report discovers what a folder holds rather than asking for it: every sub-folder with a
``scenario.json`` is a simulated run (its trajectories ``*.tum`` are scored against
``groundtruth.tum``, its ``*.health.csv`` drawn as a timeline, its ``nav*.csv`` scored against
``truth.csv``); every folder of experiment, benchmark or campaign output adds its tables and
figures.
The page has no script, so it renders anywhere and leaves the browser console empty.
"""

from __future__ import annotations

import csv
import html
import json
from collections.abc import Iterable, Sequence
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

from spacepose import __version__
from spacepose.core.metrics import ErrorTable, evaluate, navigation_errors, pose_errors
from spacepose.core.mls import MLSConfig, mpp_mls
from spacepose.errors import InputError
from spacepose.tools import plots
from spacepose.tools.cloud_io import read_cloud
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


def _read_csv(path: Path) -> dict[str, list[str]]:
    with path.open(newline="") as fh:
        rows = list(csv.DictReader(fh))
    if not rows:
        raise InputError("CSV file has no data rows", path)
    return {k: [r[k] for r in rows] for k in rows[0]}


def _scenario_section(run: Path) -> str:
    scenario = json.loads((run / "scenario.json").read_text())
    rows = []
    for key, value in sorted(scenario.items()):
        text = json.dumps(value)
        rows.append((key, text if len(text) <= 160 else text[:157] + "..."))
    return _table(("parameter", "value"), rows)


def scenario_name(run: Path) -> str | None:
    """The ``scenario`` entry of a run's scenario.json (``lab``, ``orbit``), if any."""
    return json.loads((run / "scenario.json").read_text()).get("scenario")


def _is_model_free(T_first: np.ndarray) -> bool:
    """A model-free estimate starts at the identity (METHODS §0): score it re-based."""
    return bool(np.allclose(T_first, np.eye(4), atol=1e-9))


def _mls_section(run: Path) -> str:
    """Frame 0 of the run before and after mpp-MLS (Li §2.2); experiment li-l1 quantifies it."""
    frames = sorted((run / "frames").glob("*.ply"))
    if not frames:
        return ""
    raw = read_cloud(frames[0])
    smooth = mpp_mls(raw, MLS_VIEW)
    fig = plots.cloud_views(
        {"raw frame": raw.points, "after mpp-MLS": smooth.points},
        f"{run.name}, frame 0 (voxel {1e3 * MLS_VIEW.voxel_size:g} mm, h {1e3 * MLS_VIEW.h:g} mm)",
    )
    return "<h3>mpp-MLS before / after</h3>" + _figure(plots.figure_png(fig), "mpp-MLS")


def _tracking_section(run: Path) -> str:
    gt_path = run / "groundtruth.tum"
    tracks = sorted(p for p in run.rglob("*.tum") if p != gt_path)
    if not gt_path.exists() or not tracks:
        return ""
    gt = read_tum(gt_path)
    parts, rows, curves, health = [], [], {}, {}
    t = gt.timestamps - gt.timestamps[0]
    for path in tracks:
        est = read_tum(path)
        rebase = _is_model_free(est.poses[0])
        table: ErrorTable = evaluate(est, gt, rebase_first=rebase)
        d = table.to_dict()
        name = path.stem
        rows.append(
            (
                name,
                *(f"{m:.3f} ({s:.3f})" for m, s in _table_cells(d)),
                f"{1e3 * d['ate_translation_rmse']:.3f}",
                f"{d['ate_rotation_rmse']:.4f}",
            )
        )
        gt_eval = gt.rebased_first() if rebase else gt
        if len(est) == len(gt_eval):
            dt, de = pose_errors(est.poses, gt_eval.poses)
            # Columns: x, y, z (mm), then pitch, yaw, roll (deg) as in Li's Table 2.
            curves[name] = np.c_[1e3 * dt, np.degrees(de[:, [1, 0, 2]])]
        health_csv = path.with_name(path.stem + ".health.csv")
        if health_csv.exists():
            health[name] = _read_csv(health_csv)["status"]
    header = ("method", "x mm", "y mm", "z mm", "pitch °", "yaw °", "roll °", "ATE mm", "ATE °")
    parts.append("<p class='muted'>mean (std) of the absolute per-frame errors</p>")
    parts.append(_table(header, rows))
    if curves:
        fig = plots.pose_error_curves(t, curves, f"{run.name}: pose errors")
        parts.append(_figure(plots.figure_png(fig), "per-axis errors against time"))
    if health:
        parts.append(_figure(plots.figure_png(plots.health_timeline(t, health)), "health flags"))
    return "<h3>Tracking</h3>" + "".join(parts)


def _table_cells(d: dict) -> list[tuple[float, float]]:
    keys = ("x_mm", "y_mm", "z_mm", "pitch_deg", "yaw_deg", "roll_deg")
    return [(d["mean"][k], d["std"][k]) for k in keys]


def _navigation_section(run: Path) -> str:
    truth_path = run / "truth.csv"
    navs = sorted(run.rglob("nav*.csv"))
    if not truth_path.exists() or not navs:
        return ""
    truth = {k: np.asarray(v, dtype=float) for k, v in _read_csv(truth_path).items()}
    parts = []
    for nav_path in navs:
        nav = {
            k: np.asarray(v, dtype=float) for k, v in _read_csv(nav_path).items() if k != "status"
        }
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
    return "<h3>Relative navigation</h3>" + "".join(parts)


def _experiments_section(root: Path) -> str:
    parts = []
    for folder in sorted({p.parent for p in root.rglob("*.png")}):
        if (folder / "scenario.json").exists():
            continue
        parts.append(f"<h3>{html.escape(str(folder.relative_to(root)) or folder.name)}</h3>")
        for table_path in sorted(folder.glob("*.json")):
            parts.append(f"<pre class='muted'>{html.escape(_short_json(table_path))}</pre>")
        for png in sorted(folder.glob("*.png")):
            parts.append(_figure(png.read_bytes(), png.stem))
    return "".join(parts)


def _short_json(path: Path, limit: int = 4000) -> str:
    text = json.dumps(json.loads(path.read_text()), indent=1, default=str)
    return text if len(text) <= limit else text[:limit] + "\n..."


def _benchmark_section(root: Path) -> str:
    parts = []
    for path in sorted(root.rglob("bench*.json")):
        data = json.loads(path.read_text())
        stages = data.get("stages", {})
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
        parts.append(f"<h3>{html.escape(path.name)}</h3>")
        parts.append(_table(("stage", "median ms", "min ms", "max ms", "peer / ours"), rows))
    return "".join(parts)


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
    runs = sorted(p.parent for p in root.rglob("scenario.json"))
    body = []
    for run in runs:
        name = html.escape(str(run.relative_to(root)) if run != root else run.name)
        body.append(f"<h2>Run: {name}</h2>")
        body.append(_scenario_section(run))
        if scenario_name(run) == "lab":
            body.append(_mls_section(run))
        body.append(_tracking_section(run))
        body.append(_navigation_section(run))
    experiments = _experiments_section(root)
    if experiments:
        body.append("<h2>Experiments and campaigns</h2>" + experiments)
    bench = _benchmark_section(root)
    if bench:
        body.append("<h2>Benchmark</h2>" + bench)
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
    out_path = Path(out) if out is not None else root / "report.html"
    out_path.parent.mkdir(parents=True, exist_ok=True)
    out_path.write_text(page)
    return out_path
