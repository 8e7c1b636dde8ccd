"""The per-frame tables of a track, beside its trajectory: ``EST.health.csv`` (status, fitness,
RMSE, σ, residual structure and the reasons a frame is not ``ok``) and ``EST.cov.csv`` (each
frame's 6×6 covariance to the bit), written and read back."""

from __future__ import annotations

import csv
from collections.abc import Sequence
from pathlib import Path
from typing import TextIO

import numpy as np
from numpy.typing import NDArray

from spacepose.core.track_result import TrackResult
from spacepose.errors import FileFormatError

HEALTH_COLUMNS: tuple[str, ...] = (
    "frame",
    "timestamp",
    "status",
    "fitness",
    "rmse",
    "iterations",
    "time_ms",
    "sig_rx",
    "sig_ry",
    "sig_rz",
    "sig_tx",
    "sig_ty",
    "sig_tz",
    "structure",
    "reasons",
)


# The covariance table: each frame's 6×6 covariance of T_sensor_target (twist rx ry rz tx ty tz,
# left perturbation in the sensor frame; rad², rad·m, m²) as its upper triangle, row by row.
_AXES = ("rx", "ry", "rz", "tx", "ty", "tz")
_UPPER = np.triu_indices(6)
COVARIANCE_COLUMNS: tuple[str, ...] = (
    "frame",
    "timestamp",
    *(f"c_{_AXES[i]}_{_AXES[j]}" for i, j in zip(*_UPPER, strict=True)),
)


def covariance_row(result: TrackResult) -> dict[str, object]:
    """One row of :data:`COVARIANCE_COLUMNS`: the frame, its time, and the upper triangle of
    its covariance to the bit (``repr``), so that a filter reading it gets what the tracker
    gave."""
    upper = np.asarray(result.covariance, dtype=np.float64)[_UPPER]
    return {
        "frame": result.index,
        "timestamp": repr(result.timestamp),
        **{c: repr(float(v)) for c, v in zip(COVARIANCE_COLUMNS[2:], upper, strict=True)},
    }


def read_covariance_csv(path: str | Path) -> NDArray[np.float64]:
    """The (N, 6, 6) covariances of a :data:`COVARIANCE_COLUMNS` table, in its row order.

    Raises
    ------
    FileFormatError
        Not such a table (other columns, a value that is not a number).
    """
    path = Path(path)
    with path.open(newline="", encoding="utf-8") as fh:
        reader = csv.DictReader(fh)
        if tuple(reader.fieldnames or ()) != COVARIANCE_COLUMNS:
            raise FileFormatError("not a covariance table of spacepose track", path)
        try:
            upper = np.array([[float(row[c]) for c in COVARIANCE_COLUMNS[2:]] for row in reader])
        except (TypeError, ValueError) as exc:
            raise FileFormatError(f"a value that is not a number: {exc}", path) from None
    out = np.zeros((len(upper), 6, 6))
    out[:, _UPPER[0], _UPPER[1]] = upper.reshape(-1, 21)
    out[:, _UPPER[1], _UPPER[0]] = upper.reshape(-1, 21)
    return out


def health_row(result: TrackResult) -> dict[str, object]:
    """One row of :data:`HEALTH_COLUMNS` (σ in rad and m, RMSE in m, time in ms, the residual
    structure unit-free; the reasons a frame is not ``ok`` joined by ``; ``)."""
    return {
        "frame": result.index,
        "timestamp": repr(result.timestamp),
        "status": result.status,
        "fitness": f"{result.fitness:.6g}",
        "rmse": f"{result.rmse:.6g}",
        "iterations": result.iterations,
        "time_ms": f"{result.time_ms.get('total', float('nan')):.3f}",
        **{c: f"{v:.6g}" for c, v in zip(HEALTH_COLUMNS[7:13], result.sigma, strict=True)},
        "structure": f"{result.structure:.4g}",
        "reasons": "; ".join(result.reasons),
    }


def open_table(path: Path) -> TextIO:
    """A CSV table opened for writing as UTF-8. A reason quotes a frame's file name, which on
    Linux need not be UTF-8 (Python holds such bytes as surrogates): those are written as
    backslash escapes, not a UnicodeEncodeError that ends the run."""
    return path.open("w", newline="", encoding="utf-8", errors="backslashreplace")


def write_health_csv(path: str | Path, results: Sequence[TrackResult]) -> Path:
    """Write the per-frame health table (:data:`HEALTH_COLUMNS`) as CSV."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    with open_table(path) as fh:
        writer = csv.DictWriter(fh, fieldnames=HEALTH_COLUMNS)
        writer.writeheader()
        writer.writerows(health_row(r) for r in results)
    return path
