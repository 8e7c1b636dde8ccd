"""Small text inputs (trajectories, timestamps, transforms, depth lists) read whole.

One reader so that every such file fails the same way: one :class:`FileFormatError` naming the
file for a missing path, a folder, a pipe or device (reading one would wait for a writer for
ever), a read the system refuses, or bytes that are not UTF-8; a byte-order mark is dropped
(it would otherwise hide the first number).
"""

from __future__ import annotations

from pathlib import Path

from spacepose.core.config import not_a_file, not_text
from spacepose.errors import FileFormatError

__all__ = ["not_a_file", "read_text"]


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
