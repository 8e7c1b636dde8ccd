"""Small text inputs (trajectories, timestamps, transforms, depth lists) read whole.

One reader so that every such file fails the same way: one :class:`FileFormatError` naming the
file for a missing path, a folder, a pipe or device (reading one would wait for a writer for
ever), a read the system refuses, or bytes that are not UTF-8; a byte-order mark is dropped
(it would otherwise hide the first number). Frame times read from such files are checked to
rise and to be seconds (:func:`timing_problem`, :func:`check_timing`). Results are written
as strict JSON (:func:`strict_json`: non-finite numbers as null).
"""

from __future__ import annotations

import json
import math
import os
import warnings
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from spacepose.core.motion import LATEST_S, TIME_UNIT, order_problem
from spacepose.core.structured_text import not_a_file, not_text
from spacepose.errors import FileFormatError, InputError, SpaceposeWarning

__all__ = [
    "as_path",
    "check_timing",
    "json_ready",
    "not_a_file",
    "read_text",
    "strict_json",
    "timing_problem",
]

# Widest median gap (s) between a sequence's frames: no sensor tracks or navigates a target at
# one frame an hour; nanoseconds (3.3e7 at 30 Hz) or microseconds (33,333) are read so.
_WIDEST_STEP_S = 3600.0
# ToF cameras and flash LiDARs frame at 1-100 Hz: a median step of 10 s or more is slower than
# any of them (a frame a minute is a decimated or simulated run), and 10-1000 is the step of
# such a camera's millisecond clock.
_SLOWEST_STEP_S = 10.0
# Narrowest median step (s): a ToF frame integrates its modulated light over several phases
# and a flash LiDAR's pulse needs its energy, neither much faster than a kHz; 0.1 ms a frame
# is times in hours (9.3e-6 at 30 Hz) or days, or seconds converted twice.
_NARROWEST_STEP_S = 1e-4
_MS_CLOCK_STEPS = (10.0, 1000.0)


def as_path(path: str | Path, what: str = "path") -> Path:
    """``path`` as a Path; None, a number or another object ended in pathlib's TypeError."""
    if not isinstance(path, str | os.PathLike):
        raise InputError(f"{what} must be a file name (str or Path), got {path!r:.60}")
    return Path(path)


def read_text(path: str | Path, what: str) -> str:
    """The text of ``path``, UTF-8 with an optional byte-order mark.

    Parameters
    ----------
    path
        The file.
    what
        What it should hold (``"TUM file"``, ``"timestamps"``), for the message.

    Raises
    ------
    FileFormatError
        ``path: no such file`` (a folder, a broken link, a pipe), or
        ``path: cannot read WHAT: problem`` (refused by the system, or not UTF-8 text).
    """
    path = Path(path)
    problem = not_a_file(path)
    if problem is not None:
        raise FileFormatError(problem, path)
    try:
        return path.read_text(encoding="utf-8-sig")
    except OSError as exc:
        raise FileFormatError(f"cannot read {what}: {exc.strerror or exc}", path) from None
    except UnicodeDecodeError as exc:
        raise FileFormatError(f"cannot read {what}: {not_text(exc)}", path) from None


def data_number(text: str) -> float:
    """The number ``text`` of a data file (a time, a coordinate) as ``float`` reads it, but
    for Python's digit separators: ``0_3`` is no number a file means (``float`` read it as 3).

    Raises
    ------
    ValueError
        Not a number.
    """
    if "_" in text:
        raise ValueError(f"not a number: {text!r}")
    return float(text)


def timing_problem(timestamps: ArrayLike) -> str | None:
    """Why a sequence's times cannot be its frames' times in seconds, or None.

    They must increase (:func:`~spacepose.core.motion.order_problem`), and be seconds: a time
    beyond :data:`~spacepose.core.motion.LATEST_S` or a median step beyond
    :data:`_WIDEST_STEP_S` or below :data:`_NARROWEST_STEP_S` is another unit.
    Read as seconds, nanoseconds were tracked a year a frame, and navigation integrated the
    orbit over each of those years (hours a frame, a run that never ended). So is a
    millisecond clock (:func:`_millisecond_clock`): a 30 Hz camera's 0, 33, 67, 100 were
    tracked as a frame every 33 s, its rates read a thousand times too slow, without a word.
    """
    stamps = np.asarray(timestamps, dtype=np.float64).reshape(-1)
    problem = order_problem(stamps)
    if problem is not None or len(stamps) == 0:
        return problem
    latest = float(np.max(np.abs(stamps)))
    if latest > LATEST_S:
        return f"a time of {latest:.4g} s is past the year 5000 {TIME_UNIT}"
    if len(stamps) > 1:
        step = float(np.median(np.diff(stamps)))
        if step > _WIDEST_STEP_S:
            return f"the frames are {step:.4g} s apart (median), more than an hour {TIME_UNIT}"
        if step < _NARROWEST_STEP_S:
            return (
                f"the frames are {step:.4g} s apart (median), faster than any ToF camera or "
                "flash LiDAR frames (10 kHz) (times are seconds; hours or days given, or "
                "seconds converted twice?)"
            )
    return _millisecond_clock(stamps)


def _millisecond_clock(stamps: np.ndarray) -> str | None:
    """Why ``stamps`` (increasing) count a camera's milliseconds, or None.

    Whole numbers a median of 10-1000 apart whose steps jitter by a unit or two about it
    (33, 34, 33: a period that is no whole number of units, rounded by the clock) are a
    1-100 Hz camera's milliseconds; as seconds they would be a frame every half minute,
    slower than any ToF camera or flash LiDAR frames, on a clock that ticks in whole seconds.
    Steps all equal but for whole missed frames (a simulated run at a frame every 10 s: 0, 10,
    20, 40) tell nothing and are left to :func:`check_timing`.
    """
    steps = np.diff(stamps)
    if len(steps) < 2 or not np.all(stamps == np.round(stamps)):
        return None
    step = float(np.median(steps))
    low, high = _MS_CLOCK_STEPS
    jitter = steps[np.abs(steps - step) <= 2]
    if not (low <= step <= high) or np.all(jitter == step):
        return None
    return (
        f"whole-number times {step:g} apart (median) whose steps vary "
        f"({np.min(jitter):g} to {np.max(jitter):g}): a {1e3 / np.mean(steps):.3g} Hz camera's "
        f"milliseconds, read as seconds a frame every {step:g} s {TIME_UNIT}"
    )


def check_timing(timestamps: ArrayLike, path: str | Path) -> None:
    """Refuse a file's frame times that cannot be seconds (:func:`timing_problem`), and warn
    when they are slower than any ToF camera or flash LiDAR frames (a median step of 10 s or
    more): milliseconds with fractions (0, 33.3, 66.7) cannot be told from such a run, and
    were tracked a thousand times too slow without a word.

    Raises
    ------
    InputError
        ``path: problem``.

    Warns
    -----
    SpaceposeWarning
        The frames are 10 s or more apart (median), naming ``path``.
    """
    stamps = np.asarray(timestamps, dtype=np.float64).reshape(-1)
    problem = timing_problem(stamps)
    if problem is not None:
        raise InputError(problem, path)
    step = float(np.median(np.diff(stamps))) if len(stamps) > 1 else 0.0
    if step >= _SLOWEST_STEP_S:
        warnings.warn(
            SpaceposeWarning(
                f"the frames are {step:.4g} s apart (median), slower than a ToF camera or "
                f"flash LiDAR frames (1-100 Hz) {TIME_UNIT}",
                path,
            ),
            stacklevel=3,
        )


def json_ready(value: Any) -> Any:
    """A copy of ``value`` that strict JSON can hold: NumPy scalars and arrays as Python numbers
    and lists, non-finite floats (NaN, inf) as None (``json.dumps`` writes them as the bare
    tokens ``NaN`` and ``Infinity``, which strict parsers refuse)."""
    if isinstance(value, dict):
        return {k: json_ready(v) for k, v in value.items()}
    if isinstance(value, np.ndarray):
        return json_ready(value.tolist())
    if isinstance(value, list | tuple):
        return [json_ready(v) for v in value]
    if isinstance(value, np.generic):
        value = value.item()
    if isinstance(value, float) and not math.isfinite(value):
        return None
    return value


def strict_json(value: Any, **kwargs: Any) -> str:
    """``json.dumps`` of :func:`json_ready` ``(value)``: strict JSON, non-finite numbers null.

    Parameters
    ----------
    value
        Dicts, lists, tuples, numbers (NumPy's too), text, booleans and None.
    **kwargs
        Passed to ``json.dumps`` (``indent``, ``sort_keys``, ``default``).

    Raises
    ------
    ValueError
        A ``default`` that returns a non-finite float (never written as a bare ``NaN``).
    """
    return json.dumps(json_ready(value), allow_nan=False, **kwargs)
