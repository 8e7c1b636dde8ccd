"""The summary of a campaign: statistics of each metric per grid cell, and their plots.

:func:`summarize` reduces the table's rows to one record per grid cell (every axis but ``seed``)
and metric: n, failures, mean, std, median and p95 of the finite values of the cell's successful
cases. :func:`plot_metrics` draws each metric's mean against ``noise_scale``, one line per method.
:func:`spacepose.tools.campaign.run_campaign` writes them to ``summary.json`` and ``<metric>.png``.
"""

from __future__ import annotations

import warnings
from collections.abc import Mapping, Sequence
from typing import Any

import numpy as np

from spacepose.errors import SpaceposeWarning

# --------------------------------------------------------------------------------------------
# Summary and plots
# --------------------------------------------------------------------------------------------


def summarize(
    rows: Sequence[Mapping[str, Any]],
    group_by: Sequence[str],
    metrics: Sequence[str],
) -> list[dict[str, Any]]:
    """Statistics of each metric per grid cell, in long form (one record per cell and metric).

    Parameters
    ----------
    rows
        One mapping per case (e.g. ``table.to_pylist()``), holding ``group_by`` keys, metrics
        and ``error``.
    group_by
        The axes that define a cell (every axis but ``seed``).
    metrics
        Metric names to summarise.

    Returns
    -------
    Records ``{**cell, "metric", "n", "n_failed", "mean", "std", "median", "p95"}`` sorted by
    cell then metric. Statistics use the finite values of the cell's successful cases; ``std`` is
    the sample standard deviation (ddof=1); ``p95`` the linearly interpolated 95th percentile;
    a statistic that is undefined (no value; std of one value) is ``None``.
    """
    cells: dict[tuple, list[Mapping[str, Any]]] = {}
    for row in rows:
        cells.setdefault(tuple(row[a] for a in group_by), []).append(row)
    out = []
    for key in sorted(cells):
        members = cells[key]
        n_failed = sum(r.get("error") is not None for r in members)
        for metric in metrics:
            v = np.array(
                [float(r[metric]) for r in members if r.get(metric) is not None], dtype=float
            )
            v = v[np.isfinite(v)]
            stats: dict[str, Any] = {"metric": metric, "n": int(v.size), "n_failed": n_failed}
            stats["mean"] = float(np.mean(v)) if v.size else None
            stats["std"] = float(np.std(v, ddof=1)) if v.size > 1 else None
            stats["median"] = float(np.median(v)) if v.size else None
            stats["p95"] = float(np.percentile(v, 95)) if v.size else None
            out.append({**dict(zip(group_by, key, strict=True)), **stats})
    return out


def plot_metrics(summary: Sequence[Mapping[str, Any]], group_by: Sequence[str]) -> dict[str, bytes]:
    """One PNG per metric: its mean (±std bars) against ``noise_scale``, one line per method.

    Scenarios and extra axes that take several values get their own lines too; the label names
    the method and those axes. Returns metric -> PNG bytes.
    """
    import matplotlib.pyplot as plt

    from spacepose.tools.plots import figure_png

    label_axes = [
        a
        for a in group_by
        if a == "method" or (a != "noise_scale" and len({s[a] for s in summary}) > 1)
    ]
    pngs = {}
    for metric in sorted({s["metric"] for s in summary}):
        fig, ax = plt.subplots(figsize=(6.5, 4))
        lines: dict[tuple, list[Mapping[str, Any]]] = {}
        for s in summary:
            if s["metric"] == metric and s["mean"] is not None:
                lines.setdefault(tuple(s[a] for a in label_axes), []).append(s)
        for key, points in sorted(lines.items()):
            points = sorted(points, key=lambda s: s["noise_scale"])
            x = [s["noise_scale"] for s in points]
            y = [s["mean"] for s in points]
            err = [s["std"] or 0.0 for s in points]
            label = ", ".join(f"{a}={v}" for a, v in zip(label_axes, key, strict=True))
            ax.errorbar(x, y, yerr=err, marker="o", capsize=3, label=label)
        ax.set_xlabel("noise_scale")
        ax.set_ylabel(f"{metric} (mean ± std over seeds)")
        ax.grid(alpha=0.3)
        if lines:
            ax.legend(fontsize=7)
        try:
            pngs[metric] = figure_png(fig)
        except (ValueError, OverflowError) as exc:
            # Values no axis can span (a noise_scale of 1e308): the table and summary are
            # written, the figure is not.
            plt.close(fig)
            warnings.warn(SpaceposeWarning(f"{metric}.png not written: {exc}"), stacklevel=2)
    return pngs
