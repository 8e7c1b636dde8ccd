"""Small text inputs (trajectories, timestamps, transforms, depth lists) read whole.

One reader so that every such file fails the same way: one :class:`FileFormatError` naming the
file for a missing path, a folder, a pipe or device (reading one would wait for a writer for
ever), a read the system refuses, or bytes that are not UTF-8; a byte-order mark is dropped
(it would otherwise hide the first number). Frame times read from such files are checked to
rise and to be seconds (:func:`timing_problem`).
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike

from spacepose.core.config import not_a_file, not_text
from spacepose.core.motion import order_problem
from spacepose.errors import FileFormatError

__all__ = ["not_a_file", "read_text", "timing_problem"]

# Latest time read as seconds since the Unix epoch: 1e11 s is the year 5138, so a larger time
# counts milliseconds, microseconds or nanoseconds (1.7e12, 1.7e15, 1.7e18 in 2024).
_LATEST_S = 1e11
# Widest median gap (s) between a sequence's frames: no sensor tracks or navigates a target at
# one frame an hour; nanoseconds (3.3e7 at 30 Hz) or microseconds (33,333) are read so.
_WIDEST_STEP_S = 3600.0


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


def timing_problem(timestamps: ArrayLike) -> str | None:
    """Why a sequence's times cannot be its frames' times in seconds, or None.

    They must increase (:func:`~spacepose.core.motion.order_problem`), and be seconds: a time
    beyond :data:`_LATEST_S` or a median step beyond :data:`_WIDEST_STEP_S` is another unit.
    Read as seconds, nanoseconds were tracked a year a frame, and navigation integrated the
    orbit over each of those years (hours a frame, a run that never ended).
    """
    stamps = np.asarray(timestamps, dtype=np.float64).reshape(-1)
    problem = order_problem(stamps)
    if problem is not None or len(stamps) == 0:
        return problem
    unit = "(times are seconds; milliseconds, microseconds or nanoseconds given?)"
    latest = float(np.max(np.abs(stamps)))
    if latest > _LATEST_S:
        return f"a time of {latest:.4g} s is past the year 5000 {unit}"
    if len(stamps) > 1:
        step = float(np.median(np.diff(stamps)))
        if step > _WIDEST_STEP_S:
            return f"the frames are {step:.4g} s apart (median), more than an hour {unit}"
    return None
