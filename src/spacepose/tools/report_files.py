"""The files of a folder as ``spacepose report`` finds and reads them, and those it leaves out.

:func:`read_json` and :func:`read_csv` read a file or raise the package's errors naming it;
:func:`own_files` finds a run's files but those of a run nested in it; :func:`scenario_name`
reads which scenario a run simulated. :class:`Skipped` builds each part of the report under a
guard: a file that cannot be read leaves its part out, is warned about and listed on the page
with the reason.
"""

from __future__ import annotations

import csv
import json
import warnings
from collections.abc import Callable, Sequence
from pathlib import Path

from spacepose.core.structured_text import load_structured, not_a_file, not_text, parse_problem
from spacepose.errors import FileFormatError, InputError, SpaceposeError, SpaceposeWarning
from spacepose.tools.report_html import html_table

# What a part of the report may fail with when its file is bad: the package's own errors, an
# unreadable file, a value that does not parse, a missing key or column.
_BAD_FILE = (SpaceposeError, OSError, ValueError, KeyError)


class Skipped:
    """The files left out of the report, with the reason; each is also warned about.

    Attributes
    ----------
    files
        ``(path, reason)`` of every file left out, in the order they were met.
    """

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
        """The page's "Skipped" section (paths relative to ``root``), or ``""`` if none was."""
        if not self.files:
            return ""
        rows = [
            (str(p.relative_to(root)) if p.is_relative_to(root) else str(p), r)
            for p, r in self.files
        ]
        return "<h2>Skipped</h2>" + html_table(("file", "why it was left out"), rows)


def read_json(path: Path) -> object:
    """The content of a JSON file.

    Parameters
    ----------
    path
        The file.

    Returns
    -------
    Whatever the file holds.

    Raises
    ------
    FileFormatError
        Not valid JSON (or not text), or a pipe or a device.
    """
    try:
        return load_structured(_regular(path).read_text(), "json")
    except (json.JSONDecodeError, UnicodeDecodeError) as exc:
        raise FileFormatError(f"not valid JSON: {parse_problem(exc)}", path) from None


def read_bytes(path: Path) -> bytes:
    """The bytes of a file (a figure).

    Raises
    ------
    FileFormatError
        A pipe or a device.
    """
    return _regular(path).read_bytes()


def _regular(path: Path) -> Path:
    """``path``, refused when a pipe or a device: one named bench.json, EST.health.csv or a
    figure's .png held the report up for ever, waiting for a writer (a folder or a missing
    file is left to the read's own error)."""
    if path.exists() and not (path.is_file() or path.is_dir()):
        raise FileFormatError(str(not_a_file(path)), path)
    return path


def read_csv(path: Path, required: Sequence[str] = ()) -> dict[str, list[str]]:
    """The columns of a CSV file with a header row, blank lines left out.

    Parameters
    ----------
    path
        The file.
    required
        Columns the file must have.

    Returns
    -------
    ``{column: [value of each row]}``, the values as text.

    Raises
    ------
    FileFormatError
        Not text, not CSV, a row of another length than the header, a required column missing,
        or a pipe or a device.
    InputError
        No data rows.
    """
    try:
        with _regular(path).open(newline="") as fh:
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


def read_scenario(run: Path) -> dict:
    """A run's scenario.json.

    Raises
    ------
    FileFormatError
        scenario.json is not valid JSON or not a mapping.
    """
    scenario = read_json(run / "scenario.json")
    if not isinstance(scenario, dict):
        raise FileFormatError("scenario.json must hold a mapping", run / "scenario.json")
    return scenario


def scenario_name(run: Path) -> str | None:
    """The ``scenario`` entry of a run's scenario.json (``lab``, ``orbit``), if any (raises as
    :func:`read_scenario`)."""
    return read_scenario(run).get("scenario")


def own_files(run: Path, pattern: str) -> list[Path]:
    """The files matching ``pattern`` under ``run``, sorted, but for those of a run nested in
    it (a subfolder with its own scenario.json, reported as a run of its own): an outer run
    scored the inner one's tracks, and its groundtruth.tum as a track, against its own truth
    (15 m off, without a word).

    Parameters
    ----------
    run
        The run folder.
    pattern
        A glob pattern, matched in every subfolder (``*.tum``).

    Returns
    -------
    The matching files of ``run`` itself, sorted.
    """
    own = []
    for path in run.rglob(pattern):
        between = list(path.relative_to(run).parents)[:-1]  # the folders below ``run``
        if not any((run / folder / "scenario.json").is_file() for folder in between):
            own.append(path)
    return sorted(own)
