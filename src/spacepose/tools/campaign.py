"""Monte Carlo campaigns: a grid of cases (scenario × noise × method × seed × ...) run on Dask.

A campaign is described by a :class:`~spacepose.tools.campaign_spec.CampaignConfig`; its cases
and their ids come from :mod:`spacepose.tools.campaign_spec`, and the *case runner* that computes
one case, picked by the config's ``case_kind``, from :mod:`spacepose.tools.campaign_cases`. This
module runs the cases on Dask, persists each finished one, and consolidates them into one table;
:mod:`spacepose.tools.campaign_summary` reduces the table per grid cell.

Output folder layout::

    out/campaign.json        config, package version (written first, checked on resume)
    out/parts/<case_id>.json one record per finished case, written atomically as it completes
    out/results.parquet      one row per case of the grid, sorted by case_id (params, metrics,
                             error, time_s, case_id); config and version in the schema metadata
    out/summary.json         per grid cell and metric: n, mean, std, median, p95 over seeds
    out/<metric>.png         each metric against noise_scale, one line per method

Killing a run loses at most the cases in flight: a part file appears only through ``os.replace``
of a complete temporary file, and a started-again run skips every case with a part.
"""

from __future__ import annotations

import contextlib
import json
import logging
import numbers
import os
import time
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from spacepose.core.structured_text import load_structured
from spacepose.errors import ConfigError, FileFormatError, InputError, SpaceposeError
from spacepose.tools.campaign_cases import CaseFunction, Metrics, Scalar, get_runner
from spacepose.tools.campaign_spec import (
    NAME_RE,
    RESERVED_COLUMNS,
    CampaignConfig,
    Case,
    case_id,
    expand_grid,
)
from spacepose.tools.campaign_summary import plot_metrics, summarize

CAMPAIGN_FILE = "campaign.json"
PARTS_DIR = "parts"
RESULTS_FILE = "results.parquet"
SUMMARY_FILE = "summary.json"
# Fields of the config that must match for a folder to be resumed (workers, out may change).
_IDENTITY_FIELDS: tuple[str, ...] = ("name", "case_kind")


# --------------------------------------------------------------------------------------------
# One case (runs in a Dask worker)
# --------------------------------------------------------------------------------------------


def execute_case(fn: CaseFunction, params: dict[str, Scalar]) -> dict[str, Any]:
    """Run one case and return its part record (what is stored in ``parts/<case_id>.json``).

    An expected failure (any :class:`SpaceposeError`) is recorded in ``error`` with empty
    metrics; any other exception propagates and stops the campaign. A ``ConfigError`` is one
    too: a grid may combine values no scenario allows (the orbit's standoff before a ToF
    camera, "the sensor sees nothing"), and raised it ended the whole campaign with a Dask
    traceback and no table, and every resume failed the same way.

    Raises
    ------
    TypeError
        If the runner returns something other than a mapping of scalar metrics, or a metric name
        that clashes with an axis or a reserved column.
    """
    start = time.perf_counter()
    error = None
    try:
        raw = fn(dict(params))
    except SpaceposeError as exc:
        raw, error = {}, f"{type(exc).__name__}: {exc}"
    elapsed = time.perf_counter() - start
    return {
        "case_id": case_id(params),
        "params": dict(params),
        "metrics": _clean_metrics(raw, params, getattr(fn, "__name__", repr(fn))),
        "error": error,
        "time_s": elapsed,
    }


def _clean_metrics(raw: Any, params: Mapping[str, Scalar], who: str) -> Metrics:
    if not isinstance(raw, Mapping):
        raise TypeError(f"case runner {who} returned {type(raw).__name__}, not a dict of metrics")
    out: Metrics = {}
    for name, value in raw.items():
        if isinstance(value, np.generic):
            value = value.item()
        problem = _metric_problem(name, value, params)
        if problem is not None:
            raise TypeError(f"case runner {who}: {problem}")
        out[name] = value
    return out


def _metric_problem(name: object, value: object, params: Mapping[str, Scalar]) -> str | None:
    """Why ``name: value`` cannot be a metric column of the case ``params`` (None: it can).
    A runner's metrics and a stored part's are held to the same rules."""
    if not isinstance(name, str) or not NAME_RE.match(name):
        return f"metric name {name!r} is not an identifier"
    if name in params or name in RESERVED_COLUMNS:
        return f"metric {name!r} clashes with a column name"
    if not isinstance(value, numbers.Real):  # bool and int are Real too
        return f"metric {name!r} is a {type(value).__name__}, not a scalar"
    return None


def _part_problem(record: Mapping[str, Any]) -> str | None:
    """What a part record (hash already checked) lacks to be consolidated, or None. An
    edited or damaged part (no metrics, a metric that is text, an axis name) ended the
    campaign in a traceback from the table's build, or overwrote that axis' column."""
    metrics = record.get("metrics")
    if not isinstance(metrics, Mapping):
        return f"'metrics' must be a mapping of numbers, got {type(metrics).__name__}"
    for name, value in metrics.items():
        problem = _metric_problem(name, value, record["params"])
        if problem is not None:
            return problem
    if "error" not in record or not isinstance(record["error"], str | None):
        return "'error' must be text, or null for a case that succeeded"
    elapsed = record.get("time_s")
    if isinstance(elapsed, bool) or not isinstance(elapsed, numbers.Real) or not elapsed >= 0:
        return f"'time_s' must be a number of seconds >= 0, got {elapsed!r}"
    return None


# --------------------------------------------------------------------------------------------
# Output folder
# --------------------------------------------------------------------------------------------


def _atomic_write(path: Path, data: bytes) -> None:
    """Write ``data`` to ``path`` so that the file is either absent or complete."""
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    with open(tmp, "wb") as fh:
        fh.write(data)
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)


def _campaign_record(config: CampaignConfig) -> dict[str, Any]:
    from spacepose import __version__

    return {
        "config": config.model_dump(mode="json", exclude={"out"}),
        "spacepose_version": __version__,
    }


def prepare_out_dir(config: CampaignConfig) -> Path:
    """Create (or check, when resuming) the output folder and write ``campaign.json``.

    Raises
    ------
    ConfigError
        If the folder holds another campaign (different name, case kind or grid axes), or is a
        non-empty folder that is not a campaign folder.
    """
    out = Path(config.out)
    record_path = out / CAMPAIGN_FILE
    if out.exists() and not out.is_dir():
        raise ConfigError(f"{out}: campaign output must be a folder, this is a file")
    if record_path.exists():
        try:
            old = load_structured(record_path.read_text(), "json")["config"]
            if not isinstance(old, dict) or not isinstance(old.get("grid", {}), dict):
                raise TypeError("its config is not a mapping with a grid mapping")
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise ConfigError(f"{record_path}: unreadable campaign record: {exc}") from None
        new = config.model_dump(mode="json")
        for field in _IDENTITY_FIELDS:
            if old.get(field) != new[field]:
                raise ConfigError(
                    f"{record_path}: folder holds campaign with {field}={old.get(field)!r}, "
                    f"config has {new[field]!r}; use another --out"
                )
        if sorted(old.get("grid", {})) != sorted(new["grid"]):
            raise ConfigError(
                f"{record_path}: folder holds campaign with axes {sorted(old.get('grid', {}))}, "
                f"config has {sorted(new['grid'])}; use another --out"
            )
    elif out.exists() and any(out.iterdir()):
        raise ConfigError(f"{out}: not empty and not a campaign folder (no {CAMPAIGN_FILE})")
    try:
        (out / PARTS_DIR).mkdir(parents=True, exist_ok=True)
    except OSError as exc:  # "/proc/nope: No such file or directory" did not say what failed
        raise InputError(
            f"cannot create the campaign folder: {exc.strerror or exc}", exc.filename or out
        ) from None
    # Temporary files of a killed run are incomplete by construction: drop them.
    for tmp in (out / PARTS_DIR).glob(".*.tmp"):
        tmp.unlink()
    _atomic_write(record_path, (json.dumps(_campaign_record(config), indent=2) + "\n").encode())
    return out


def write_part(out_dir: Path, record: Mapping[str, Any]) -> Path:
    """Persist one finished case atomically as ``parts/<case_id>.json``."""
    path = Path(out_dir) / PARTS_DIR / f"{record['case_id']}.json"
    _atomic_write(path, json.dumps(record, sort_keys=True).encode())
    return path


def read_parts(out_dir: str | Path) -> dict[str, dict[str, Any]]:
    """Every finished case in ``out_dir/parts``: case_id -> part record.

    Raises
    ------
    FileFormatError
        If a part cannot be parsed, its parameters do not hash to its name (edited by hand), or
        its metrics, error or time are not what :func:`execute_case` writes.
    """
    parts: dict[str, dict[str, Any]] = {}
    for path in sorted((Path(out_dir) / PARTS_DIR).glob("*.json")):
        try:
            record = json.loads(path.read_text())
            ok = case_id(record["params"]) == path.stem == record["case_id"]
        except (OSError, ValueError, KeyError, TypeError) as exc:
            # A part cut short (a full disk, a killed copy): say how to get past it.
            raise FileFormatError(
                f"unreadable campaign part: {exc}; delete it to run its case again", path
            ) from None
        if not ok:
            raise FileFormatError(
                "part parameters do not match its case_id; delete it to run its case again", path
            )
        problem = _part_problem(record)
        if problem is not None:
            raise FileFormatError(
                f"damaged campaign part: {problem}; delete it to run its case again", path
            )
        parts[path.stem] = record
    return parts


def results_table(
    config: CampaignConfig, cases: Sequence[Case], parts: Mapping[str, Mapping[str, Any]]
) -> Any:
    """One ``pyarrow.Table`` row per case (sorted by case_id), config and version in metadata.

    Columns: the grid axes (config order), the metrics (sorted union over cases; null where a
    case failed), ``error`` (null when it succeeded), ``time_s``, ``case_id``.

    Raises
    ------
    FileFormatError
        A metric is true/false in some parts and a number in others (one was edited).
    """
    import pyarrow as pa

    records = [parts[c.case_id] for c in sorted(cases, key=lambda c: c.case_id)]
    metric_names = sorted({m for r in records for m in r["metrics"]})
    columns: dict[str, Any] = {}
    for axis in config.grid:
        columns[axis] = pa.array([r["params"][axis] for r in records])
    for name in metric_names:
        values = [r["metrics"].get(name) for r in records]
        kinds = {type(v) for v in values if v is not None}
        if bool in kinds and len(kinds) > 1:
            # A part edited by hand (a number where the others hold true/false): pyarrow's
            # ArrowInvalid escaped as a traceback.
            pairs = list(zip(records, values, strict=True))
            flag = next(r for r, v in pairs if isinstance(v, bool))
            other, number = next((r, v) for r, v in pairs if type(v) in kinds - {bool})
            raise FileFormatError(
                f"metric {name!r} is true/false in part {flag['case_id']} and {number!r} in "
                f"part {other['case_id']}: delete the edited one to run its case again",
                Path(config.out) / PARTS_DIR,
            )
        # Mixed int/float (e.g. a metric that is sometimes nan) is stored as float.
        dtype = pa.float64() if (kinds <= {int, float} and float in kinds) or not kinds else None
        columns[name] = pa.array(values, type=dtype)
    columns["error"] = pa.array([r["error"] for r in records], type=pa.string())
    columns["time_s"] = pa.array([r["time_s"] for r in records], type=pa.float64())
    columns["case_id"] = pa.array([r["case_id"] for r in records], type=pa.string())
    record = _campaign_record(config)
    metadata = {
        b"spacepose.campaign": json.dumps(record["config"]).encode(),
        b"spacepose.version": str(record["spacepose_version"]).encode(),
    }
    return pa.table(columns).replace_schema_metadata(metadata)


def write_results(table: Any, out_dir: Path) -> Path:
    """Write the consolidated table to ``out_dir/results.parquet`` (atomically)."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    sink = pa.BufferOutputStream()
    pq.write_table(table, sink)
    path = Path(out_dir) / RESULTS_FILE
    _atomic_write(path, sink.getvalue().to_pybytes())
    return path


# --------------------------------------------------------------------------------------------
# Running
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class CampaignResult:
    """What :func:`run_campaign` did.

    Attributes
    ----------
    out_dir
        The campaign folder.
    table
        The consolidated ``pyarrow.Table`` (also in ``results.parquet``).
    summary
        :func:`summarize` records (also in ``summary.json``).
    n_computed, n_skipped
        Cases computed by this call, and cases found already finished.
    """

    out_dir: Path
    table: Any
    summary: list[dict[str, Any]]
    n_computed: int
    n_skipped: int

    @property
    def n_failed(self) -> int:
        """Cases of the table whose ``error`` column holds why they failed."""
        if "error" not in self.table.column_names:
            return 0
        return int(self.table.num_rows - self.table.column("error").null_count)


@contextlib.contextmanager
def _dask_client(config: CampaignConfig, scheduler: str | None) -> Iterator[Any]:
    """A client of the given scheduler, or of a fresh local process cluster."""
    from dask.distributed import Client, LocalCluster

    if scheduler is not None:
        try:
            client = Client(scheduler, timeout=f"{config.connect_timeout_s}s")
        except (OSError, ValueError) as exc:
            raise ConfigError(f"cannot connect to Dask scheduler {scheduler!r}: {exc}") from None
        with client:
            yield client
        return
    with (
        LocalCluster(
            n_workers=config.workers,
            threads_per_worker=config.threads_per_worker,
            processes=True,
            # No dashboard, and the scheduler's HTTP endpoint on a free port (not 8787): several
            # campaigns may run side by side without port warnings.
            dashboard_address=":0",
            scheduler_kwargs={"dashboard": False},
            silence_logs=logging.ERROR,
        ) as cluster,
        Client(cluster) as client,
    ):
        yield client


def run_campaign(
    config: CampaignConfig, *, scheduler: str | None = None, progress: bool = True
) -> CampaignResult:
    """Run (or resume) a campaign and consolidate its results.

    Parameters
    ----------
    config
        The campaign; ``config.out`` is the folder.
    scheduler
        Address of a running Dask scheduler (``tcp://host:port``); by default a
        ``LocalCluster`` of ``config.workers`` processes is started and stopped.
    progress
        Show a rich progress bar on stderr.

    Returns
    -------
    CampaignResult
        The table, the summary and how many cases were computed or skipped.

    Raises
    ------
    ConfigError
        Incompatible existing folder, unreachable scheduler.
    """
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TimeRemainingColumn

    runner = get_runner(config.case_kind)
    out = prepare_out_dir(config)
    cases = expand_grid(config.grid)
    done = read_parts(out)
    todo = [c for c in cases if c.case_id not in done]
    if todo:
        with (
            _dask_client(config, scheduler) as client,
            Progress(
                "[progress.description]{task.description}",
                BarColumn(),
                MofNCompleteColumn(),
                TimeRemainingColumn(),
                console=Console(stderr=True),
                disable=not progress,
            ) as bar,
        ):
            from dask.distributed import as_completed

            task = bar.add_task(f"campaign {config.name}", total=len(cases))
            bar.update(task, completed=len(cases) - len(todo))
            futures = [client.submit(execute_case, runner.fn, c.params, pure=False) for c in todo]
            for future in as_completed(futures):
                record = future.result()
                write_part(out, record)
                done[record["case_id"]] = record
                bar.advance(task)
    table = results_table(config, cases, done)
    write_results(table, out)
    group_by = [a for a in config.grid if a != "seed"]
    metrics = [
        n for n in table.column_names if n not in config.grid and n not in ("error", "case_id")
    ]
    summary = summarize(table.to_pylist(), group_by, metrics)
    _atomic_write(out / SUMMARY_FILE, (json.dumps(summary, indent=2) + "\n").encode())
    for metric, png in plot_metrics(summary, group_by).items():
        _atomic_write(out / f"{metric}.png", png)
    return CampaignResult(out, table, summary, len(todo), len(cases) - len(todo))
