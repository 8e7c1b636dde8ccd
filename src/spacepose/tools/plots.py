"""Figures shared by the experiments and the report (matplotlib, Agg backend, no display)."""

from __future__ import annotations

import base64
import io
from collections.abc import Mapping, Sequence

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.figure import Figure
from numpy.typing import NDArray

POSE_AXES = ("x (mm)", "y (mm)", "z (mm)", "pitch (deg)", "yaw (deg)", "roll (deg)")

STATUS_COLOUR = {"ok": "tab:green", "degraded": "tab:orange", "lost": "tab:red"}


def figure_png(fig: Figure, dpi: int = 110) -> bytes:
    """Render a figure to PNG bytes and close it."""
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=dpi, bbox_inches="tight")
    plt.close(fig)
    return buf.getvalue()


def png_data_uri(png: bytes) -> str:
    """A ``data:`` URI embedding PNG bytes, so an HTML page needs no side files."""
    return "data:image/png;base64," + base64.b64encode(png).decode("ascii")


def pose_error_curves(
    t: NDArray[np.float64], errors: Mapping[str, NDArray[np.float64]], title: str = ""
) -> Figure:
    """Per-axis pose errors against time, one line per method (Li et al. Figs. 11–12 style).

    Parameters
    ----------
    t
        (N,) timestamps, s.
    errors
        Method name -> (N, 6) signed errors: translation x, y, z in mm, then pitch, yaw, roll in
        degrees.
    """
    fig, axes = plt.subplots(2, 3, figsize=(13, 6), sharex=True)
    for name, err in errors.items():
        for i, ax in enumerate(axes.flat):
            ax.plot(t, err[:, i], lw=1.2, label=name)
    for i, ax in enumerate(axes.flat):
        ax.set_title(POSE_AXES[i])
        ax.axhline(0.0, color="0.6", lw=0.8)
        ax.grid(alpha=0.3)
    for ax in axes[1]:
        ax.set_xlabel("time (s)")
    axes[0, 0].legend()
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    return fig


def health_timeline(t: NDArray[np.float64], status: Mapping[str, Sequence[str]]) -> Figure:
    """Tracker status per frame for each method: green ok, orange degraded, red lost."""
    fig, ax = plt.subplots(figsize=(13, 0.6 + 0.5 * len(status)))
    for row, flags in enumerate(status.values()):
        colours = [STATUS_COLOUR.get(s, "black") for s in flags]
        ax.scatter(t[: len(flags)], np.full(len(flags), row), c=colours, marker="s", s=30)
    ax.set_yticks(range(len(status)), list(status))
    ax.set_xlabel("time (s)")
    ax.set_ylim(-0.7, len(status) - 0.3)
    ax.set_title("tracker health (green ok, orange degraded, red lost)")
    fig.tight_layout()
    return fig


def error_with_envelope(
    t: NDArray[np.float64],
    error: NDArray[np.float64],
    sigma: NDArray[np.float64],
    labels: Sequence[str],
    title: str,
) -> Figure:
    """Estimation errors with their ±3σ envelopes, one panel per component (Yu et al. Figs. 8–16).

    Parameters
    ----------
    t
        (N,) time, s.
    error, sigma
        (N, k) signed error and the filter's 1-σ of each component, in display units.
    labels
        k panel titles, units included.
    """
    k = error.shape[1]
    fig, axes = plt.subplots(1, k, figsize=(4.3 * k, 3.2), squeeze=False)
    for i, ax in enumerate(axes[0]):
        ax.fill_between(
            t, -3 * sigma[:, i], 3 * sigma[:, i], color="tab:blue", alpha=0.2, label="±3σ"
        )
        ax.plot(t, error[:, i], color="tab:red", lw=1.0, label="error")
        ax.set_title(labels[i])
        ax.set_xlabel("time (s)")
        ax.grid(alpha=0.3)
        # Show the converged part: the first seconds' large σ would flatten everything else.
        tail = slice(len(t) // 10, None)
        lim = 4 * max(np.nanmax(np.abs(error[tail, i])), np.nanmax(3 * sigma[tail, i]), 1e-12)
        ax.set_ylim(-lim, lim)
    axes[0, 0].legend(loc="upper right")
    fig.suptitle(title)
    fig.tight_layout()
    return fig


def histogram_comparison(
    edges: NDArray[np.float64], counts: Mapping[str, NDArray[np.float64]], xlabel: str, title: str
) -> Figure:
    """Normalised histograms of the same quantity under several conditions, as step lines."""
    fig, ax = plt.subplots(figsize=(7, 3.5))
    for name, c in counts.items():
        share = np.asarray(c, dtype=float) / max(float(np.sum(c)), 1.0)
        ax.stairs(100 * share, edges, label=name, lw=1.5)
    ax.set_xlabel(xlabel)
    ax.set_ylabel("share (%)")
    ax.set_title(title)
    ax.legend()
    ax.grid(alpha=0.3)
    fig.tight_layout()
    return fig


def cloud_views(clouds: Mapping[str, NDArray[np.float64]], title: str) -> Figure:
    """Side-by-side views of point clouds (x–y and x–z projections), e.g. before/after mpp-MLS."""
    fig, axes = plt.subplots(2, len(clouds), figsize=(5 * len(clouds), 7.5), squeeze=False)
    for col, (name, pts) in enumerate(clouds.items()):
        for row, (i, j, lab) in enumerate(((0, 1, "y"), (0, 2, "z"))):
            ax = axes[row, col]
            ax.scatter(pts[:, i], pts[:, j], s=0.3, c=pts[:, 2], cmap="viridis")
            ax.set_aspect("equal")
            ax.set_xlabel("x (m)")
            ax.set_ylabel(f"{lab} (m)")
            if row == 0:
                ax.set_title(f"{name} ({len(pts)} points)")
    fig.suptitle(title)
    fig.tight_layout()
    return fig
