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

The sections of one run come from :mod:`spacepose.tools.report_runs`, and the files are found,
read and left out by :mod:`spacepose.tools.report_files`; this module adds the experiment and
benchmark sections and writes the page.
"""

from __future__ import annotations

import html
import json
import warnings
from datetime import UTC, datetime
from pathlib import Path

from spacepose import __version__
from spacepose.errors import FileFormatError, InputError, SpaceposeWarning
from spacepose.tools.outputs import check_spares_inputs, check_writable
from spacepose.tools.report_files import Skipped, read_bytes, read_json, scenario_name
from spacepose.tools.report_html import html_figure, html_table
from spacepose.tools.report_runs import (
    mls_section,
    navigation_section,
    scenario_section,
    tracking_section,
)

_CSS = """
body { font-family: system-ui, sans-serif; margin: 2em auto; max-width: 1250px; color: #222; }
h1 { border-bottom: 2px solid #333; } h2 { margin-top: 2em; border-bottom: 1px solid #aaa; }
table { border-collapse: collapse; margin: 0.8em 0; font-size: 0.9em; }
th, td { border: 1px solid #bbb; padding: 0.25em 0.6em; text-align: right; }
th { background: #eee; } td:first-child, th:first-child { text-align: left; }
img { max-width: 100%; display: block; margin: 0.5em 0; }
.muted { color: #666; font-size: 0.9em; }
"""


def _experiments_section(root: Path, skipped: Skipped) -> str:
    parts = []
    for folder in sorted({p.parent for p in root.rglob("*.png")}):
        if (folder / "scenario.json").exists():
            continue
        # The root itself is "." relative to itself: its own name heads its figures.
        heading = folder.name if folder == root else str(folder.relative_to(root))
        parts.append(f"<h3>{html.escape(heading)}</h3>")
        # A bench output is the benchmark section's table, not a JSON dump here as well.
        for table_path in sorted(
            p for p in folder.glob("*.json") if not p.name.startswith("bench")
        ):
            text = skipped.guard(table_path, lambda p=table_path: _short_json(p))
            if text:
                parts.append(f"<pre class='muted'>{html.escape(text)}</pre>")
        for png in sorted(folder.glob("*.png")):
            # A folder or a broken link named as a figure: left out, not the whole report.
            parts.append(skipped.guard(png, lambda p=png: html_figure(read_bytes(p), p.stem)))
    return "".join(parts)


def _short_json(path: Path, limit: int = 4000) -> str:
    text = json.dumps(read_json(path), indent=1, default=str)
    return text if len(text) <= limit else text[:limit] + "\n..."


def _benchmark_section(root: Path, skipped: Skipped) -> str:
    return "".join(
        skipped.guard(path, lambda p=path: _bench_file(p))
        for path in sorted(root.rglob("bench*.json"))
    )


def _bench_file(path: Path) -> str:
    """The stage-time table of one ``spacepose bench`` output."""
    data = read_json(path)
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
    return f"<h3>{html.escape(path.name)}</h3>" + html_table(header, rows)


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

    Warns
    -----
    SpaceposeWarning
        ``out`` is not named ``.html`` (or ``.htm``).
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
    if out_path.suffix.lower() not in (".html", ".htm"):
        # Written all the same; opened by its name, a browser shows a .txt page as its source.
        problem = "not named .html: the report is an HTML page, which a browser shows as text"
        warnings.warn(SpaceposeWarning(problem, out_path), stacklevel=2)
    runs = sorted(p.parent for p in root.rglob("scenario.json"))
    skipped = Skipped()
    body = []
    for run in runs:
        name = html.escape(str(run.relative_to(root)) if run != root else run.name)
        body.append(f"<h2>Run: {name}</h2>")
        scenario = skipped.guard(run / "scenario.json", lambda run=run: scenario_section(run))
        body.append(scenario)
        if scenario and scenario_name(run) == "lab":
            body.append(skipped.guard(run / "frames", lambda run=run: mls_section(run)))
        body.append(
            skipped.guard(run / "groundtruth.tum", lambda run=run: tracking_section(run, skipped))
        )
        body.append(
            skipped.guard(run / "truth.csv", lambda run=run: navigation_section(run, skipped))
        )
    experiments = _experiments_section(root, skipped)
    if experiments:
        body.append("<h2>Experiments and campaigns</h2>" + experiments)
    bench = _benchmark_section(root, skipped)
    if bench:
        body.append("<h2>Benchmark</h2>" + bench)
    body.append(skipped.section(root))
    if not any(body):
        # Tracks of a folder with no scenario.json are no run's: say so, not that none exist.
        found = sorted(p.relative_to(root).as_posix() for p in root.rglob("*.[tT][uU][mM]"))
        if found:
            raise InputError(
                f"nothing to report: {', '.join(found[:3])}{' ...' if found[3:] else ''} "
                "found, but no scenario.json: the report reads run folders as `spacepose "
                "simulate` writes them (scenario.json, groundtruth.tum, tracks)",
                root,
            )
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
